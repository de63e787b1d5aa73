#!/usr/bin/env bash
# Idempotent development setup: venv + locked wheels + haptic_topology_msgs + haptic_topology.
#
# Each step runs only when its inputs changed (sha256 stamps inside the venv), so a second run
# with nothing changed takes a second or two. Safe with no stdin (CI).
#
#   scripts/setup.sh              what `make setup` and `make demo` need (steps 1-6): no browser,
#                                 no Node.js, no root
#   scripts/setup.sh --for-tests  the same, then what `make test` adds (steps 7-8)
#   scripts/setup.sh --robots     the same, plus the optional extra "robots" (step 2b: what
#                                 `make robots` runs; combines with --for-tests)
#
#   1. <venv> from python3.11, if missing
#   2. pip install --no-deps -r requirements.lock                (stamp: hash of the lock)
#   2b. --robots: pip install --no-deps -r requirements-robots.lock: example-robot-data, the
#      robots by name (131 MB; never installed otherwise)      (stamp: both locks)
#   3. build msg_schemas/ with cmake, install into the venv prefix (stamp: msg_schemas/ + lock)
#      + msg_schemas/third_party/<pkg> (tf2_msgs) the same way, only where the wheels lack it
#        (`import <pkg>.msg` fails)                (stamp: its files + lock)
#   4. pip install -e . (editable: Python edits need no reinstall)  (stamp: packaging files)
#      + share/haptic_topology/{package.xml,config} as symlinks, ament index marker
#   5. <site-packages>/haptic_topology_env.pth: AMENT_PREFIX_PATH for every venv process
#   6. the loop's compiled functions into numba's cache (haptic_topology/*/__pycache__)
#      + the OpenHaptics emulator: emulators/openhaptics/hd.c -> <venv>/lib/haptic_topology/
#        libHD.so with gcc (backend openhaptics, `library: emulator`)   (stamp: its source)
#      + the Force Dimension emulator (emulators/forcedimension, gcc) into <venv>/fdsdk-emulator,
#        an SDK-like tree for FDSDK                      (stamp: its sources)
#   7. --for-tests: unshare present; chromium (apt-get), if missing: the docs tests render the
#      site headless
#   8. --for-tests: test/foxglove_client/: npm ci (the @foxglove/ws-protocol client of the
#      live-view test); needs Node.js >= 20 with npm   (stamp: package.json + package-lock.json)
#
# Environment: HAPTIC_VENV (default <repo>/.venv), PYTHON (default python3.11).
set -euo pipefail

for_tests=0
robots=0
for arg in "$@"; do
  case $arg in
    --for-tests) for_tests=1 ;;
    --robots) robots=1 ;;
    -h|--help) sed -n '2,/^set -euo/p' "${BASH_SOURCE[0]}" | sed -e '$d' -e 's/^# \{0,1\}//'; exit 0 ;;
    *) printf 'setup: ERROR: unknown argument %s (expected --for-tests or --robots)\n' "$arg" >&2; exit 2 ;;
  esac
done

root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
venv=${HAPTIC_VENV:-$root/.venv}
python=${PYTHON:-python3.11}
t0=$(date +%s.%N)

say() { printf 'setup: %s\n' "$*"; }
die() { printf 'setup: ERROR: %s\n' "$*" >&2; exit 1; }

# --- prerequisites ---------------------------------------------------------------------------
command -v "$python" >/dev/null 2>&1 \
  || die "$python not found. Install CPython 3.11 (the ROS 2 Jazzy wheels are cp311 only)."
"$python" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))' \
  || die "$python is $("$python" -V 2>&1), need Python 3.11 (the ROS 2 Jazzy wheels are cp311)."
for tool in cmake gcc g++ make; do
  command -v "$tool" >/dev/null 2>&1 \
    || die "$tool not found; it builds msg_schemas/ (apt-get install cmake build-essential)."
done
hash_files() { # sha256 over the names and contents of the given files, in sorted order
  local f
  printf '%s\n' "$@" | LC_ALL=C sort | while IFS= read -r f; do
    printf '%s\n' "${f#"$root"/}"
    sha256sum < "$f"
  done | sha256sum | cut -d' ' -f1
}
stamp_ok() { [[ -f "$venv/.stamp-$1" && "$(cat "$venv/.stamp-$1")" == "$2" ]]; }
stamp_set() { printf '%s\n' "$2" > "$venv/.stamp-$1"; }

# --- 1. venv ---------------------------------------------------------------------------------
if [[ ! -x "$venv/bin/python" ]]; then
  say "creating $venv with $("$python" -V 2>&1)"
  "$python" -m venv "$venv"
fi
vpy="$venv/bin/python"
"$vpy" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))' \
  || die "$venv is not a Python 3.11 venv; remove it (make clean) and run again."

# --- 2. locked wheels ------------------------------------------------------------------------
lock_hash=$(hash_files "$root/requirements.lock")
if ! stamp_ok lock "$lock_hash"; then
  say "installing requirements.lock (exact pins, no resolver)"
  export PIP_DISABLE_PIP_VERSION_CHECK=1 PIP_NO_INPUT=1
  # pip first, alone: the lock's pip version is the one that installs the rest.
  pip_pin=$(grep -E '^pip==' "$root/requirements.lock")
  "$vpy" -m pip install -qq "$pip_pin"
  "$vpy" -m pip install -qq --no-deps -r "$root/requirements.lock"
  "$vpy" -m pip check
  # wheels changed: their cmake files need the include fix again, the messages a rebuild
  rm -f "$venv/.stamp-msgs"
  for f in "$venv"/.stamp-iface-*; do
    if [[ -f "$f" ]]; then printf 'rebuild\n' > "$f"; fi
  done
  stamp_set lock "$lock_hash"
fi

# --- 2b. the optional extra "robots" (--robots) -----------------------------------------------
if ((robots)); then
  robots_hash=$(hash_files "$root/requirements.lock" "$root/requirements-robots.lock")
  if ! stamp_ok robots "$robots_hash"; then
    say "installing requirements-robots.lock (example-robot-data, 131 MB)"
    "$vpy" -m pip install -qq --no-deps -r "$root/requirements-robots.lock"
    "$vpy" -m pip check
    stamp_set robots "$robots_hash"
  fi
fi

# --- 3. haptic_topology_msgs (and stand-ins for interface packages the wheels lack) ----------
fix_wheel_cmake() {
  # The wheels' exported CMake files carry their build machine's Python and numpy include dirs
  # (/opt/python/cp311-cp311/...); cmake then fails with "Imported target ... includes
  # non-existent path". Point them at this venv's dirs (a no-op once done).
  local py_inc np_inc bogus=/opt/python/cp311-cp311 bad
  read -r py_inc np_inc < <("$vpy" -c \
    'import sysconfig, numpy; print(sysconfig.get_paths()["include"], numpy.get_include())')
  mapfile -t bad < <(grep -rl --include='*.cmake' "$bogus" "$venv/share" || true)
  if ((${#bad[@]})); then
    say "fixing build-machine include paths in ${#bad[@]} wheel cmake files"
    sed -i -e "s|$bogus/lib/python3.11/site-packages/numpy/_core/include|$np_inc|g" \
           -e "s|$bogus/include/python3.11|$py_inc|g" "${bad[@]}"
  fi
}
build_interfaces() { # build_interfaces NAME SOURCE_DIR: cmake build + install into the venv
  local name=$1 src=$2 build="$venv/build/$1"
  fix_wheel_cmake
  say "building ${src#"$root"/} ($name) in $build"
  rm -rf "$build" && mkdir -p "$build"
  AMENT_PREFIX_PATH="$venv" cmake -S "$src" -B "$build" \
    -DCMAKE_BUILD_TYPE=Release \
    -DCMAKE_INSTALL_PREFIX="$venv" \
    -DCMAKE_PREFIX_PATH="$venv" \
    -DPython3_EXECUTABLE="$vpy" \
    -DBUILD_TESTING=OFF > "$build.configure.log" 2>&1 \
    || { tail -40 "$build.configure.log" >&2; die "cmake configure failed (log: $build.configure.log)"; }
  AMENT_PREFIX_PATH="$venv" cmake --build "$build" -j "$(nproc)" > "$build.build.log" 2>&1 \
    || { tail -40 "$build.build.log" >&2; die "msg build failed (log: $build.build.log)"; }
  cmake --install "$build" > "$build.install.log" 2>&1 \
    || { tail -40 "$build.install.log" >&2; die "msg install failed (log: $build.install.log)"; }
  "$vpy" -c "import $name.msg" || die "$name built but does not import"
}

# msg_schemas/ without third_party/ (its packages have stamps of their own, below).
mapfile -t msg_files < <(find "$root/msg_schemas" -path "$root/msg_schemas/third_party" -prune \
  -o -type f -print)
msgs_hash=$(hash_files "${msg_files[@]}" "$root/requirements.lock")
if ! stamp_ok msgs "$msgs_hash"; then
  build_interfaces haptic_topology_msgs "$root/msg_schemas"
  stamp_set msgs "$msgs_hash"
fi

# msg_schemas/third_party/<pkg>: upstream definitions of interface packages the wheels lack
# (tf2_msgs for /tf). Built only where `import <pkg>.msg` fails and no earlier run of this
# script built it; rebuilt when its files or the lock change.
for src in "$root"/msg_schemas/third_party/*/; do
  src=${src%/}
  name=$(basename "$src")
  [[ -f "$src/package.xml" ]] || continue
  mapfile -t pkg_files < <(find "$src" -type f)
  pkg_hash=$(hash_files "${pkg_files[@]}" "$root/requirements.lock")
  stamp_ok "iface-$name" "$pkg_hash" && continue
  if [[ ! -f "$venv/.stamp-iface-$name" ]] && "$vpy" -c "import $name.msg" 2>/dev/null; then
    continue  # the wheels (or the system) provide it: use theirs
  fi
  build_interfaces "$name" "$src"
  stamp_set "iface-$name" "$pkg_hash"
done

# --- 4. haptic_topology itself ---------------------------------------------------------------
pkg_hash=$(hash_files "$root/setup.py" "$root/setup.cfg" "$root/pyproject.toml" \
  "$root/requirements.lock")
if ! stamp_ok pkg "$pkg_hash"; then
  say "installing haptic_topology (editable)"
  # --no-build-isolation: build with the locked setuptools/wheel from the venv, fetch nothing.
  "$vpy" -m pip install -qq --no-deps --no-build-isolation -e "$root"
  stamp_set pkg "$pkg_hash"
fi
# An editable (PEP 660) install does not install setup.py's data_files, so lay out the share
# tree that `colcon build --symlink-install` would make: the ament index marker plus symlinks to
# package.xml and config/ (config edits and new files show up with no reinstall).
share="$venv/share/haptic_topology"
index="$venv/share/ament_index/resource_index/packages"
mkdir -p "$share" "$index"
[[ -f "$index/haptic_topology" ]] || : > "$index/haptic_topology"
for item in package.xml config; do
  [[ "$(readlink "$share/$item" 2>/dev/null)" == "$root/$item" ]] || ln -sfn "$root/$item" "$share/$item"
done

# --- 5. environment hook for every process of the venv ---------------------------------------
site=$("$vpy" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')
pth="$site/haptic_topology_env.pth"
# One line (a .pth runs lines that start with "import"): put the venv prefix first on
# AMENT_PREFIX_PATH so ament_index finds haptic_topology(_msgs) with no sourced setup file.
line="import os, sys; _p = os.environ.get('AMENT_PREFIX_PATH', ''); sys.prefix in _p.split(os.pathsep) or os.environ.__setitem__('AMENT_PREFIX_PATH', os.pathsep.join(x for x in (sys.prefix, _p) if x))"
if [[ ! -f "$pth" || "$(cat "$pth")" != "$line" ]]; then
  printf '%s\n' "$line" > "$pth"
fi

# --- 6. the loop's compiled arithmetic into numba's cache -------------------------------------
# Importing the modules compiles each function once per machine (a few seconds; then cached in
# their __pycache__ and loaded in about 1 s), so no node's first activation waits for it.
"$vpy" -c 'import haptic_topology.control.compiled, haptic_topology.device.compiled' \
  || die "compiling haptic_topology's loop arithmetic (numba) failed"
# The emulator of OpenHaptics' libHD.so (a simulated Touch) that the openhaptics backend's tests
# and `library: emulator` load; soname libHD.so, as pyOpenHaptics loads it by that name.
emu_src="$root/emulators/openhaptics/hd.c"
emu_lib="$venv/lib/haptic_topology/libHD.so"
emu_hash=$(hash_files "$emu_src")
if ! stamp_ok libhd "$emu_hash" || [[ ! -f "$emu_lib" ]]; then
  say "building the OpenHaptics emulator $emu_lib"
  mkdir -p "$(dirname "$emu_lib")"
  gcc -O2 -Wall -fPIC -shared -pthread -Wl,-soname,libHD.so -o "$emu_lib" "$emu_src" -lm \
    || die "building the OpenHaptics emulator ($emu_src) failed"
  stamp_set libhd "$emu_hash"
fi

# The Force Dimension emulator: a libdrd for forcedimension-core without the vendor's SDK
# (the forcedimension backend's tests, FDSDK=<venv>/fdsdk-emulator; docs/devices.md).
mapfile -t emu_files < <(find "$root/emulators/forcedimension" -type f)
emu_hash=$(hash_files "${emu_files[@]}")
if ! stamp_ok fdemu "$emu_hash" || [[ ! -d "$venv/fdsdk-emulator" ]]; then
  say "building the Force Dimension emulator into $venv/fdsdk-emulator"
  rm -rf "$venv/fdsdk-emulator"
  bash "$root/emulators/forcedimension/build.sh" "$venv/fdsdk-emulator" \
    || die "building the Force Dimension emulator (gcc) failed"
  stamp_set fdemu "$emu_hash"
fi

# --- 7. unshare and chromium (--for-tests) ----------------------------------------------------
if ((for_tests)); then
  command -v unshare >/dev/null 2>&1 \
    || die "unshare not found; the tests run the loop process without real-time privileges in a user namespace (apt-get install util-linux)."
fi
# The docs tests render the built site in a headless browser (test/docs). Installed with apt only
# when missing, so a machine that has it is left alone.
if ((for_tests)) && ! command -v chromium >/dev/null 2>&1; then
  if [[ $(id -u) -eq 0 ]]; then
    apt=(apt-get)
  elif command -v sudo >/dev/null 2>&1 && sudo -n true 2>/dev/null; then
    apt=(sudo apt-get)
  else
    die "chromium not found and no root to install it; make test needs it for the docs tests (apt-get install chromium). make demo and make setup do not."
  fi
  command -v apt-get >/dev/null 2>&1 || die "chromium not found and no apt-get; install Chromium (the docs tests of make test need it)."
  say "installing chromium with apt-get (the docs tests render the site headless)"
  export DEBIAN_FRONTEND=noninteractive
  "${apt[@]}" update -qq > /dev/null || die "apt-get update failed; install chromium by hand."
  "${apt[@]}" install -y -qq --no-install-recommends chromium > /dev/null \
    || die "apt-get install chromium failed; install it by hand."
  command -v chromium >/dev/null 2>&1 || die "apt-get installed chromium but it is not on PATH."
fi

# --- 8. the Node client of test/graph/test_foxglove_clients.py (--for-tests) ------------------
# Exact versions from package-lock.json; the tests themselves never use the network.
client="$root/test/foxglove_client"
if ((for_tests)); then
  if ! command -v node >/dev/null 2>&1 || ! command -v npm >/dev/null 2>&1; then
    die "node/npm not found; make test needs Node.js >= 20 with npm for the live-view test (test/foxglove_client). make demo and make setup do not."
  fi
  npm_hash=$(hash_files "$client/package.json" "$client/package-lock.json")
  if ! stamp_ok npm "$npm_hash" || [[ ! -d "$client/node_modules" ]]; then
    say "installing test/foxglove_client (npm ci, exact versions of package-lock.json)"
    (cd "$client" && npm ci --ignore-scripts --no-audit --no-fund --loglevel=error > /dev/null) \
      || die "npm ci failed in test/foxglove_client (needs the npm registry once)"
    stamp_set npm "$npm_hash"
  fi
fi

say "ready: $venv ($(awk "BEGIN { printf \"%.1f\", $(date +%s.%N) - $t0 }") s)"
