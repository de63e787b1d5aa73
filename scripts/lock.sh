#!/usr/bin/env bash
# Regenerate requirements.lock from requirements.in in a throw-away venv, so the lock holds the
# resolver's answer for the direct requirements and nothing that happened to be in .venv.
set -euo pipefail
root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
python3.11 -m venv "$tmp/venv"
"$tmp/venv/bin/python" -m pip install -qq --upgrade pip
"$tmp/venv/bin/python" -m pip install -qq -r "$root/requirements.in"
"$tmp/venv/bin/python" -m pip check
out=${1:-$root/requirements.lock}
"$tmp/venv/bin/python" "$root/scripts/freeze_lock.py" > "$out"
echo "wrote $out"
