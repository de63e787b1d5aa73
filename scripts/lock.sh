#!/usr/bin/env bash
# Regenerate requirements.lock from requirements.in in a throw-away venv, so the lock holds the
# resolver's answer for the direct requirements and nothing that happened to be in .venv; then
# the optional extra's lock, requirements-robots.lock (requirements-robots.in resolved with
# the new lock as constraints: only what the extra adds).
#
#   scripts/lock.sh [--keep-pins] [OUT]     (the extra's lock: beside OUT, requirements-robots.lock)
#
# --keep-pins: resolve with the current requirements.lock as constraints (pip -c), so every
# distribution already locked keeps its version and only what requirements.in adds is
# resolved anew (adding one package then changes the lock by that package and its new
# dependencies only; check with `git diff requirements.lock`). Without it, everything moves
# to the newest versions requirements.in allows.
set -euo pipefail
root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
keep=0
if [[ "${1:-}" == --keep-pins ]]; then
  keep=1
  shift
fi
out=${1:-$root/requirements.lock}
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
# Read before OUT may be overwritten (OUT can be the lock itself).
cp "$root/requirements.lock" "$tmp/constraints.txt"
python3.11 -m venv "$tmp/venv"
if ((keep)); then
  "$tmp/venv/bin/python" -m pip install -qq "$(grep -E '^pip==' "$tmp/constraints.txt")"
  "$tmp/venv/bin/python" -m pip install -qq -r "$root/requirements.in" -c "$tmp/constraints.txt"
else
  "$tmp/venv/bin/python" -m pip install -qq --upgrade pip
  "$tmp/venv/bin/python" -m pip install -qq -r "$root/requirements.in"
fi
"$tmp/venv/bin/python" -m pip check
"$tmp/venv/bin/python" "$root/scripts/freeze_lock.py" > "$out"
echo "wrote $out"
robots_out=$(dirname "$out")/requirements-robots.lock
"$tmp/venv/bin/python" -m pip install -qq -r "$root/requirements-robots.in" -c "$out"
"$tmp/venv/bin/python" -m pip check
"$tmp/venv/bin/python" "$root/scripts/freeze_lock.py" --extra robots "$out" > "$robots_out"
echo "wrote $robots_out"
