#!/usr/bin/env bash
# Run the test suite (the pytest part of `make test`) N times on the current checkout, some of
# the runs beside a CPU hog pinned to one core, to shake out timing-dependent failures of the
# node-graph tests.
#
#   scripts/stress_tests.sh N [--busy K] [-- PYTEST_ARGS...]
#
#   N        number of runs (>= 1)
#   --busy K how many of the runs get a busy process (a pure-Python loop pinned with
#            `taskset -c $STRESS_BUSY_CPU`, default core 0) beside them; default N/2 rounded
#            down. The busy runs are spread evenly over the N runs.
#   -- ...   extra arguments for `python -m pytest`, e.g. -- -m "not graph" -q -x test/foo.py
#
# Prints one line per run (number, busy or idle, PASS/FAIL, pytest's summary line, wall time),
# keeps each run's full output in a log directory (STRESS_LOG_DIR, default a new directory
# under ${TMPDIR:-/tmp}) and ends with "P of N passed, mean wall time S s". Exit status 0 only
# if every run passed. Runs on the venv as it is (HAPTIC_VENV, default .venv): `make setup` first.
set -euo pipefail

root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
venv=${HAPTIC_VENV:-$root/.venv}
busy_cpu=${STRESS_BUSY_CPU:-0}

usage() { # usage [STATUS]: 2 (bad arguments, to stderr) unless asked for with -h
  local status=${1:-2}
  ((status == 0)) || exec >&2
  cat <<EOF
usage: scripts/stress_tests.sh N [--busy K] [-- PYTEST_ARGS...]
  N          number of test runs (a positive integer)
  --busy K   runs beside a busy process pinned to CPU $busy_cpu (0..N; default N/2 rounded down)
  -- ARGS    extra pytest arguments, e.g.: scripts/stress_tests.sh 4 -- -m "not graph" -q
EOF
  exit "$status"
}
is_count() { [[ $1 =~ ^[0-9]{1,6}$ ]]; }

# --- arguments -------------------------------------------------------------------------------
(($# >= 1)) || usage
case $1 in -h | --help) usage 0 ;; esac
is_count "$1" && ((10#$1 >= 1)) || { echo "stress_tests: N must be a positive integer, got '$1'" >&2; usage; }
runs=$((10#$1))
shift
busy=$((runs / 2))
pytest_args=()
while (($#)); do
  case $1 in
    --busy)
      (($# >= 2)) || { echo 'stress_tests: --busy needs a number' >&2; usage; }
      is_count "$2" || { echo "stress_tests: --busy K must be an integer >= 0, got '$2'" >&2; usage; }
      busy=$((10#$2))
      shift 2
      ;;
    --busy=*)
      is_count "${1#--busy=}" || { echo "stress_tests: bad $1" >&2; usage; }
      busy=$((10#${1#--busy=}))
      shift
      ;;
    --)
      shift
      pytest_args=("$@")
      break
      ;;
    -h | --help) usage 0 ;;
    *)
      echo "stress_tests: unknown argument '$1' (pytest arguments go after --)" >&2
      usage
      ;;
  esac
done
((busy <= runs)) || { echo "stress_tests: --busy $busy is more than N=$runs" >&2; usage; }
if ((busy > 0)) && ! command -v taskset >/dev/null 2>&1; then
  echo 'stress_tests: taskset not found (util-linux); it pins the busy process' >&2
  exit 2
fi

# --- the busy process, always cleaned up -----------------------------------------------------
busy_pid=
stop_busy() {
  if [[ -n $busy_pid ]]; then
    kill "$busy_pid" 2>/dev/null || true
    wait "$busy_pid" 2>/dev/null || true
    busy_pid=
  fi
}
start_busy() {
  # A background job of a non-interactive shell ignores SIGINT, so the traps below end it; and
  # should this script be SIGKILLed, the loop sees its parent change and ends by itself.
  taskset -c "$busy_cpu" "$venv/bin/python" -c '
import os, sys
parent = int(sys.argv[1])
while os.getppid() == parent:
    for _ in range(200_000):
        pass
' "$$" &
  busy_pid=$!
}
# pytest runs in the foreground, so a Ctrl-C at the terminal reaches it too (its fixtures stop
# the node processes); the traps run once it has returned.
trap stop_busy EXIT
trap 'stop_busy; echo; echo "stress_tests: interrupted" >&2; trap - INT; kill -INT $$' INT
trap 'stop_busy; trap - TERM; kill -TERM $$' TERM
trap 'stop_busy; trap - HUP; kill -HUP $$' HUP

# --- runs ------------------------------------------------------------------------------------
cd "$root"
# No setup here: every run must test the same venv, and a rebuild of the shared venv under
# other test runs would race with them. Bring it up to date first with `make setup`.
[[ -x $venv/bin/python ]] || { echo "stress_tests: no venv at $venv; run make setup first" >&2; exit 1; }

if [[ -n ${STRESS_LOG_DIR:-} ]]; then
  logs=$STRESS_LOG_DIR
  mkdir -p "$logs"
else
  logs=$(mktemp -d "${TMPDIR:-/tmp}/haptic-stress.$(date +%Y%m%d-%H%M%S).XXXX")
fi
summary=$logs/summary.txt
say() { printf '%s\n' "$*" | tee -a "$summary"; }

say "stress_tests: $runs runs ($busy beside a busy process on CPU $busy_cpu) of:"
say "  $venv/bin/python -m pytest ${pytest_args[*]@Q}"
say "  logs: $logs"

passed=0
total_wall=0
for ((i = 1; i <= runs; i++)); do
  # Run i is busy when floor(i*K/N) steps up: K busy runs spread evenly over the N.
  if ((i * busy / runs > (i - 1) * busy / runs)); then kind=busy; else kind=idle; fi
  log=$(printf '%s/run-%03d-%s.log' "$logs" "$i" "$kind")
  [[ $kind == busy ]] && start_busy
  t0=$(date +%s.%N)
  rc=0
  "$venv/bin/python" -m pytest "${pytest_args[@]}" >"$log" 2>&1 || rc=$?
  t1=$(date +%s.%N)
  stop_busy
  wall=$(awk -v a="$t0" -v b="$t1" 'BEGIN { printf "%.1f", b - a }')
  total_wall=$(awk -v a="$total_wall" -v b="$wall" 'BEGIN { print a + b }')
  # pytest's summary: "=== 3 passed in 1.2s ===" (or without the = signs under -q).
  line=$(sed -e 's/\x1b\[[0-9;]*m//g' "$log" \
    | grep -E '(passed|failed|error|errors|skipped|deselected|xfailed|xpassed|no tests ran).* in [0-9.]+s' \
    | tail -n 1 | sed -E 's/^=+ //; s/ =+$//' || true)
  [[ -n $line ]] || line="(no summary line; see $log)"
  if ((rc == 0)); then
    verdict=PASS
    passed=$((passed + 1))
  else
    verdict="FAIL (exit $rc)"
  fi
  say "$(printf 'run %d/%d  %s  %-15s %s  [%s s]' "$i" "$runs" "$kind" "$verdict" "$line" "$wall")"
done

mean=$(awk -v t="$total_wall" -v n="$runs" 'BEGIN { printf "%.1f", t / n }')
say "logs: $logs"
say "$passed of $runs passed, mean wall time $mean s"
((passed == runs))
