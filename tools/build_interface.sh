#!/usr/bin/env bash
# Build one interface package (interfaces/PKG) with plain cmake into the venv prefix.
# Usage: tools/build_interface.sh PKG VENV_DIR
set -euo pipefail
pkg=$1
venv=$(cd "$2" && pwd)
src=$(cd "$(dirname "$0")/../interfaces/$pkg" && pwd)
build=$(dirname "$0")/../build/$pkg
rm -rf "$build" && mkdir -p "$build" && cd "$build"
# shellcheck disable=SC1091
source "$venv/bin/activate"
cmake "$src" -DCMAKE_INSTALL_PREFIX="$venv" -DCMAKE_PREFIX_PATH="$venv" \
  -DPython3_EXECUTABLE="$venv/bin/python" -DBUILD_TESTING=OFF >cmake.log \
  || { tail -30 cmake.log; exit 1; }
make -j2 >build.log || { tail -30 build.log; exit 1; }
make install >install.log
echo "built $pkg into $venv"
