#!/usr/bin/env bash
# Sets up a fresh Debian 12 machine (dependencies from Debian packages), builds
# aggscan in Debug and runs the whole test suite with CTest; ends with the list
# of skipped tests and their reasons (scripts/skipped-tests.py).
#   scripts/run-tests.sh [extra ctest args]
# Environment: BUILD_DIR (default build), JOBS (default 2), SANITIZE=1 for ASan+UBSan.
set -euo pipefail
cd "$(dirname "$0")/.."
root=$(pwd)
BUILD_DIR=${BUILD_DIR:-build}
JOBS=${JOBS:-2}

bash scripts/install-deps.sh

san=()
if [ "${SANITIZE:-0}" = 1 ]; then san=(-DAGGSCAN_ASAN=ON -DAGGSCAN_UBSAN=ON); fi
cmake -S . -B "$BUILD_DIR" -DCMAKE_BUILD_TYPE=Debug -DAGGSCAN_BUILD_BENCH=OFF "${san[@]}"
cmake --build "$BUILD_DIR" -j"$JOBS"
cd "$BUILD_DIR"
rc=0
ctest --output-on-failure -j"$JOBS" --output-junit ctest-junit.xml "$@" || rc=$?
# Last: every skipped test with its reason, so a green run cannot hide one.
python3 "$root/scripts/skipped-tests.py" ctest-junit.xml || true
exit "$rc"
