#!/usr/bin/env bash
# colcon from PyPI builds this repository in a workspace, against the ROS 2 wheels; checked.
#
# What a user with a ROS 2 install does, reproduced with the wheels: a workspace
# ws/src/haptic_topology holding (a copy of) this working tree, colcon-common-extensions
# (exact pins: scripts/colcon_requirements.txt) in a venv of its own that has the locked wheels
# (requirements.lock) but neither haptic_topology nor haptic_topology_msgs. Then:
#
#   1. plain `colcon build --symlink-install`: colcon's crawl stops at the repository root's
#      package.xml, so it builds haptic_topology only (checked: if it ever builds both, the
#      check says so and goes on with 4); every node and console script of that install must
#      then stop with ONE line (exit status != 0, no traceback) naming the colcon command;
#   2. that command, taken from the line, run in the workspace root: both packages are built,
#      haptic_topology_msgs first;
#   3. the README's form of it (`--base-paths . src/haptic_topology/msg_schemas`) finds both;
#   4. from the install space (`source install/setup.bash`): ve_sim runs and a probe receives
#      its LmiUpdate, deserialised with the haptic_topology_msgs built in the workspace; the
#      node stops cleanly on SIGINT.
#
# The venv is kept between runs in $COLCON_CHECK_DIR/venv (default build/colcon_check; made
# again when the lock, the pins or msg_schemas/third_party change: 1-2 min); the workspace is
# made anew each run.
# Prints `colcon check: ok (N s)` and exits 0, or `colcon check: FAILED: ...` and exits 1.
set -euo pipefail

root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
dir=${COLCON_CHECK_DIR:-$root/build/colcon_check}
venv=$dir/venv
ws=$dir/ws
pins=$root/scripts/colcon_requirements.txt
lock=$root/requirements.lock
python=${PYTHON:-python3.11}
readme_cmd='colcon build --symlink-install --base-paths . src/haptic_topology/msg_schemas'
t0=$(date +%s)

say() { printf 'colcon check: %s\n' "$*"; }
die() { printf 'colcon check: FAILED: %s\n' "$*" >&2; exit 1; }

# --- a clean environment: the check venv's ROS, nothing from the caller's venv ---------------
# (Run from the development venv, the caller's LD_LIBRARY_PATH, PYTHONPATH and the wheels'
# bootstrap guard would point into .venv, where haptic_topology_msgs is installed.)
clean_env=(env -u PYTHONPATH -u PYTHONHOME -u LD_LIBRARY_PATH -u VIRTUAL_ENV
           -u _ROS_WHEELS_BOOTSTRAP_COMPLETE -u COLCON_PREFIX_PATH -u CMAKE_PREFIX_PATH
           -u AMENT_CURRENT_PREFIX -u HAPTIC_VENV
           "PATH=$venv/bin:/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin"
           "AMENT_PREFIX_PATH=$venv" "ROS_DOMAIN_ID=${ROS_DOMAIN_ID:-$((RANDOM % 100 + 1))}")
in_ws() { (cd "$ws" && "${clean_env[@]}" bash -c "$1"); }
# shellcheck disable=SC2016  # expanded by the inner shell
in_install() { in_ws 'set +u; source install/setup.bash; set -u; '"$1"; }

# --- the check's venv: locked wheels + colcon, nothing built from this repository -----------
third_party=$root/msg_schemas/third_party
mapfile -t tp_files < <(find "$third_party" -type f 2>/dev/null | LC_ALL=C sort)
stamp=$(cat "$lock" "$pins" "${tp_files[@]}" | sha256sum | cut -d' ' -f1)
if [[ ! -f "$venv/.stamp" || "$(cat "$venv/.stamp")" != "$stamp" ]]; then
  say "creating $venv (locked wheels + colcon)"
  rm -rf "$venv"
  mkdir -p "$dir"
  "$python" -m venv "$venv"
  export PIP_DISABLE_PIP_VERSION_CHECK=1 PIP_NO_INPUT=1
  "$venv/bin/python" -m pip install -qq "$(grep -E '^pip==' "$lock")"
  "$venv/bin/python" -m pip install -qq --no-deps -r "$lock" -r "$pins"
  "$venv/bin/python" -m pip check
  # The wheels' CMake files name their build machine's include dirs (as scripts/setup.sh).
  read -r py_inc np_inc < <("$venv/bin/python" -c \
    'import sysconfig, numpy; print(sysconfig.get_paths()["include"], numpy.get_include())')
  bogus=/opt/python/cp311-cp311
  mapfile -t bad < <(grep -rl --include='*.cmake' "$bogus" "$venv/share" || true)
  if ((${#bad[@]})); then
    sed -i -e "s|$bogus/lib/python3.11/site-packages/numpy/_core/include|$np_inc|g" \
           -e "s|$bogus/include/python3.11|$py_inc|g" "${bad[@]}"
  fi
  # What a ROS install has and the wheels lack (tf2_msgs): msg_schemas/third_party/<pkg>,
  # built into the venv as scripts/setup.sh builds it into .venv (COLCON_IGNORE keeps it out
  # of the workspace build: on a ROS install it comes from the distribution).
  for src in "$third_party"/*/; do
    src=${src%/}
    name=$(basename "$src")
    [[ -f "$src/package.xml" ]] || continue
    "${clean_env[@]}" python -c "import $name.msg" 2>/dev/null && continue
    say "building ${src#"$root"/} ($name) into the venv"
    build=$dir/build-$name
    rm -rf "$build"
    { "${clean_env[@]}" cmake -S "$src" -B "$build" -DCMAKE_BUILD_TYPE=Release \
        -DCMAKE_INSTALL_PREFIX="$venv" -DCMAKE_PREFIX_PATH="$venv" \
        -DPython3_EXECUTABLE="$venv/bin/python" -DBUILD_TESTING=OFF \
      && "${clean_env[@]}" cmake --build "$build" -j "$(nproc)" \
      && "${clean_env[@]}" cmake --install "$build"; } > "$build.log" 2>&1 \
      || { tail -30 "$build.log" >&2; die "building $name into the venv failed"; }
    "${clean_env[@]}" python -c "import $name.msg" || die "$name built but does not import"
  done
  printf '%s\n' "$stamp" > "$venv/.stamp"
fi

# --- the workspace: ws/src/haptic_topology = this working tree (tracked + untracked files) ----
rm -rf "$ws"
mkdir -p "$ws/src/haptic_topology"
(cd "$root" && git ls-files -z --cached --others --exclude-standard \
   | xargs -0 -I{} sh -c 'test -e "{}" && printf "%s\0" "{}"' \
   | tar --null -T - -cf -) | tar -xf - -C "$ws/src/haptic_topology"
log=$dir/log
mkdir -p "$log"

# The venv has ROS (rclpy imports) and neither of this repository's packages.
in_ws 'python -c "
import importlib.util as u, rclpy
found = [n for n in (\"haptic_topology\", \"haptic_topology_msgs\") if u.find_spec(n)]
assert not found, f\"{found} installed in the check venv: the check would prove nothing\""' \
  || die "$venv is not a venv with ROS and without this repository's packages"

built() { # the packages colcon reports finished in the build output $1, in order
  grep -oE '^Finished <<< [A-Za-z0-9_]+' "$1" | awk '{print $3}' | paste -sd' ' -
}
check_both() { # $1: build output; both packages, the messages finished before the other starts
  local out=$1
  [[ "$(built "$out")" == 'haptic_topology_msgs haptic_topology' ]] \
    || die "expected both packages built, messages first; colcon built: '$(built "$out")' (log: $out)"
  local msgs_done node_start
  msgs_done=$(grep -nE '^Finished <<< haptic_topology_msgs' "$out" | cut -d: -f1)
  node_start=$(grep -nE '^Starting >>> haptic_topology$' "$out" | cut -d: -f1)
  ((msgs_done < node_start)) \
    || die "haptic_topology started before haptic_topology_msgs finished (log: $out)"
}

# --- 1. the plain build ----------------------------------------------------------------------
say "1. plain \`colcon build --symlink-install\` in $ws"
in_ws 'colcon build --symlink-install' > "$log/plain.txt" 2>&1 \
  || { tail -30 "$log/plain.txt" >&2; die 'plain colcon build failed'; }
plain=$(built "$log/plain.txt")
command=''
if [[ "$plain" == 'haptic_topology' ]]; then
  say "   built haptic_topology only (the crawl stops at the repository root's package.xml)"
  lib=install/haptic_topology/lib/haptic_topology
  ros='--ros-args -p scenario:=fig8'
  runs=("$lib/device_driver $ros" "$lib/lmi_controller $ros" "$lib/ve_sim $ros"
        "$lib/recorder $ros" "$lib/foxglove_bridge $ros" "$lib/haptic-topology run fig8"
        "python -m haptic_topology.nodes.ve_sim $ros")
  line=''
  for run in "${runs[@]}"; do
    rc=0
    out=$(in_install "$run </dev/null" 2>&1) || rc=$?
    lines=$(printf '%s\n' "$out" | grep -c . || true)
    ((rc != 0)) || die "\`$run\` exited 0 without the messages: $out"
    [[ "$lines" == 1 && "$out" != *Traceback* ]] \
      || die "\`$run\` printed $lines lines, not one:"$'\n'"$out"
    [[ -z "$line" || "$out" == "$line" ]] || die "\`$run\` printed another line: $out"
    line=$out
    say "   \`${run#"$lib/"}\` -> exit $rc"
  done
  say "   each printed: $line"
  command=$(printf '%s\n' "$line" | grep -oE '`colcon build --[^`]*`' | head -1 | tr -d '`')
  [[ -n "$command" ]] || die "no \`colcon build ...\` command in: $line"
elif [[ "$plain" == 'haptic_topology_msgs haptic_topology' ]]; then
  say '   the plain build built both packages'
  check_both "$log/plain.txt"
else
  die "plain build: unexpected packages '$plain' (log: $log/plain.txt)"
fi

# --- 2. the command the line names -------------------------------------------------------------
if [[ -n "$command" ]]; then
  say "2. the named command: $command"
  rm -rf "$ws/build" "$ws/install" "$ws/log"
  in_ws "$command" > "$log/named.txt" 2>&1 \
    || { tail -30 "$log/named.txt" >&2; die "\`$command\` failed"; }
  check_both "$log/named.txt"
  say '   built haptic_topology_msgs, then haptic_topology'

  # --- 3. the README's form (relative paths) finds the same two packages -----------------------
  say "3. the README's command: $readme_cmd"
  in_ws "$readme_cmd" > "$log/readme.txt" 2>&1 \
    || { tail -30 "$log/readme.txt" >&2; die "\`$readme_cmd\` failed"; }
  check_both "$log/readme.txt"
fi

# --- 4. a node from the install space publishes the workspace's messages -----------------------
say '4. ve_sim from the install space; a probe takes one LmiUpdate'
probe=$(cat <<'EOF'
import sys, time
import rclpy
import os
import haptic_topology, haptic_topology_msgs
from haptic_topology.vocabulary import TOPIC_LMI
from haptic_topology.nodes.qos import QOS_LMI
from haptic_topology.nodes.dds_env import localhost_discovery_default
from haptic_topology_msgs.msg import LmiUpdate
ws, pid = sys.argv[1], int(sys.argv[2])
localhost_discovery_default(os.environ)   # DDS set up as the nodes set it up
assert haptic_topology_msgs.__file__.startswith(ws + '/install/'), haptic_topology_msgs.__file__
assert haptic_topology.__file__.startswith(ws + '/'), haptic_topology.__file__
rclpy.init()
node = rclpy.create_node('colcon_check_probe')
got = []
node.create_subscription(LmiUpdate, TOPIC_LMI, got.append, QOS_LMI)
deadline = time.monotonic() + 60.0
def alive():
    try:
        with open(f'/proc/{pid}/stat') as f:
            return f.read().rsplit(')', 1)[1].split()[0] != 'Z'
    except OSError:
        return False
while not got and time.monotonic() < deadline:
    assert alive(), 've_sim exited'
    rclpy.spin_once(node, timeout_sec=0.1)
assert got, 'no LmiUpdate from ve_sim within 60 s'
msg = got[0]
assert msg.dof == 3 and len(msg.mass_matrix) == 9, (msg.dof, len(msg.mass_matrix))
print(f'LmiUpdate seq {msg.seq}, dof {msg.dof}, from {haptic_topology_msgs.__file__}')
EOF
)
printf '%s\n' "$probe" > "$log/probe.py"
# shellcheck disable=SC2016
in_install 've_sim=install/haptic_topology/lib/haptic_topology/ve_sim
  "$ve_sim" --ros-args -p scenario:=fig8 > "'"$log"'/ve_sim.txt" 2>&1 &
  pid=$!
  status=0
  python "'"$log"'/probe.py" "$PWD" "$pid" || status=$?
  kill -INT "$pid" 2>/dev/null || true
  node=0
  wait "$pid" || node=$?
  if ((status == 0 && node != 0)); then
    echo "ve_sim exited with $node after SIGINT:"; tail -5 "'"$log"'/ve_sim.txt"; exit 1
  fi
  exit "$status"' || { tail -20 "$log/ve_sim.txt" >&2; die 've_sim from the install space'; }

say "ok ($(($(date +%s) - t0)) s)"
