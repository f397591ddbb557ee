#!/usr/bin/env bash
# Every C++ source and header of the tree is as clang-format 14 lays it out
# (.clang-format at the root): exit 1 naming the files that are not, with the
# command that fixes them. Files generated into a build directory are not
# looked at.
#   scripts/check-format.sh [SOURCE_DIR]
set -euo pipefail
cd "${1:-$(dirname "$0")/..}"
CF=${CLANG_FORMAT:-clang-format-14}
command -v "$CF" > /dev/null || { echo "$CF not found (apt-get install clang-format-14)"; exit 1; }
mapfile -t files < <(find common config daemon drivers pipeline cli store tests bench \
  -name build -prune -o \( -name '*.cpp' -o -name '*.h' \) -type f -print | sort)
# One run over every file (one process per file costs ~20x more); the
# warnings name the files.
out=$("$CF" --dry-run -Werror "${files[@]}" 2>&1) && rc=0 || rc=$?
echo "${#files[@]} files checked with $("$CF" --version | head -1)"
if [ "$rc" -ne 0 ]; then
  mapfile -t bad < <(printf '%s\n' "$out" | sed -n 's/^\([^:]*\):[0-9]*:[0-9]*: error:.*/\1/p' | sort -u)
  [ "${#bad[@]}" -gt 0 ] || { printf '%s\n' "$out"; exit 1; }
  printf 'not formatted: %s\n' "${bad[@]}"
  echo "fix: $CF -i ${bad[*]}"
  exit 1
fi
