#!/usr/bin/env bash
# clang-tidy (.clang-tidy at the root) over the product's sources in a
# build's compile_commands.json; exit 1 when it reports anything.
#   scripts/run-clang-tidy.sh [BUILD_DIR] [PATH_REGEX]
# BUILD_DIR defaults to build; PATH_REGEX (default: every product directory)
# narrows it, e.g. 'pipeline/' or 'daemon/http_api'. JOBS (default 2).
set -euo pipefail
cd "$(dirname "$0")/.."
BUILD_DIR=${1:-build}
REGEX=${2:-'/(common|config|store|drivers|daemon|pipeline|cli)/'}
[ -f "$BUILD_DIR/compile_commands.json" ] || { echo "no $BUILD_DIR/compile_commands.json: configure with cmake first"; exit 1; }
out=$(run-clang-tidy-14 -p "$BUILD_DIR" -j "${JOBS:-2}" -quiet "$REGEX" 2>&1) || true
findings=$(printf '%s\n' "$out" | sed 's/\x1b\[[0-9;]*m//g' | grep -E '^/.*: (warning|error):' | sort -u || true)
if [ -n "$findings" ]; then
  printf '%s\n' "$findings"
  echo "clang-tidy: $(printf '%s\n' "$findings" | wc -l) findings"
  exit 1
fi
echo "clang-tidy: clean ($REGEX)"
