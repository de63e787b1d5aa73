#!/usr/bin/env bash
# Build the Force Dimension emulator into an SDK-like tree:
#   emulators/forcedimension/build.sh DIR  ->  DIR/lib/release/lin-<machine>-gcc/libdrd.so.3.16.0
# forcedimension-core then finds it with FDSDK=DIR (scripts/setup.sh builds it into
# <venv>/fdsdk-emulator).
set -euo pipefail
here=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
out=${1:?usage: build.sh DIR}
lib="$out/lib/release/lin-$(uname -m)-gcc"
mkdir -p "$lib"
gcc -std=c11 -O2 -g -fPIC -shared -fvisibility=hidden -Wall -Wextra -Werror \
  -Wl,-soname,libdrd.so.3 -o "$lib/libdrd.so.3.16.0.tmp" \
  "$here/fd_emulator.c" "$here/fd_stubs.c" -lm
mv "$lib/libdrd.so.3.16.0.tmp" "$lib/libdrd.so.3.16.0"
