#!/usr/bin/env bash
# Builds the libFuzzer targets (tests/fuzz/) with clang in their own build
# directory and runs each for a while on a copy of its seed corpus.
#   scripts/run-fuzzers.sh [SECONDS_PER_TARGET]      (default 60)
# Environment:
#   FUZZ_BUILD_DIR  build directory (default build-fuzz)
#   FUZZ_TARGETS    names to run, space-separated (default: every target in build-fuzz/fuzzers.txt)
#   FUZZ_RSS_MB     memory limit per target process, MB (default 2048)
#   FUZZ_TIMEOUT_S  one input taking longer than this is a finding (default 10)
#   FUZZ_JOBS       build jobs (default 2)
#   FUZZ_NO_BUILD=1 run what is built
#   FUZZ_RUN_DIR    where the corpus copies, logs and reproducers go (default $FUZZ_BUILD_DIR/fuzz-run)
#   FUZZ_KEEP_GOING=1  go on after a crash (libFuzzer's fork mode), collecting
#                   every reproducer for the whole time: for long runs
# Each target stops at its first crash (or leak, timeout, out-of-memory); the
# others still run. One line per target: executions, exec/s, crashes. Exit 1
# when any target crashed, with the reproducer's path. Inputs the run finds
# new coverage with stay in $FUZZ_BUILD_DIR/fuzz-run/<name>/corpus: the
# committed corpus is never written.
set -euo pipefail
cd "$(dirname "$0")/.."
SECONDS_PER_TARGET=${1:-60}
BUILD_DIR=${FUZZ_BUILD_DIR:-build-fuzz}
RSS_MB=${FUZZ_RSS_MB:-2048}
TIMEOUT_S=${FUZZ_TIMEOUT_S:-10}
JOBS=${FUZZ_JOBS:-2}
SRC=$(pwd)

CC_BIN=$(command -v clang-14 || command -v clang || true)
CXX_BIN=$(command -v clang++-14 || command -v clang++ || true)
if [ -z "$CC_BIN" ] || [ -z "$CXX_BIN" ]; then
  echo "run-fuzzers: clang is missing: apt-get install clang-14 libclang-rt-14-dev (scripts/install-deps.sh does)" >&2
  exit 2
fi

if [ "${FUZZ_NO_BUILD:-0}" != 1 ]; then
  launcher=()
  if command -v ccache >/dev/null; then
    launcher=(-DCMAKE_C_COMPILER_LAUNCHER=ccache -DCMAKE_CXX_COMPILER_LAUNCHER=ccache)
  fi
  t0=$(date +%s)
  # -O1 -g without NDEBUG: assertions stay on, stacks stay readable.
  cmake -S . -B "$BUILD_DIR" -DAGGSCAN_FUZZ=ON -DCMAKE_C_COMPILER="$CC_BIN" -DCMAKE_CXX_COMPILER="$CXX_BIN" \
    -DCMAKE_BUILD_TYPE=RelWithDebInfo -DCMAKE_C_FLAGS_RELWITHDEBINFO="-O1 -g" \
    -DCMAKE_CXX_FLAGS_RELWITHDEBINFO="-O1 -g" "${launcher[@]}" >/dev/null
  cmake --build "$BUILD_DIR" -j"$JOBS" --target aggscan_fuzzers
  echo "run-fuzzers: build $(($(date +%s) - t0)) s"
fi

read -r -a targets <<<"${FUZZ_TARGETS:-$(tr '\n' ' ' <"$BUILD_DIR/fuzzers.txt")}"
RUN_DIR=${FUZZ_RUN_DIR:-$(realpath "$BUILD_DIR")/fuzz-run}
# The targets' scratch files: memory-backed where possible (the store's
# writes fsync every file).
scratch_root=/tmp
if [ -d /dev/shm ] && [ -w /dev/shm ]; then scratch_root=/dev/shm; fi

export ASAN_OPTIONS=${ASAN_OPTIONS:-abort_on_error=1:detect_leaks=1:symbolize=1}
export UBSAN_OPTIONS=${UBSAN_OPTIONS:-print_stacktrace=1:halt_on_error=1}

summary=()
crashed=0
start_all=$(date +%s)
for t in "${targets[@]}"; do
  bin="$BUILD_DIR/tests/fuzz/${t}_fuzzer"
  seeds="$SRC/tests/fuzz/corpus/$t"
  [ -x "$bin" ] || { echo "run-fuzzers: $bin is not built" >&2; exit 2; }
  [ -d "$seeds" ] || { echo "run-fuzzers: no seed corpus $seeds" >&2; exit 2; }
  work="$RUN_DIR/$t"
  rm -rf "$work"
  mkdir -p "$work/corpus" "$work/artifacts"
  cp -r "$seeds/." "$work/corpus/"
  dict=()
  mode=()
  if [ "${FUZZ_KEEP_GOING:-0}" = 1 ]; then mode=(-fork=1 -ignore_crashes=1 -ignore_ooms=1 -ignore_timeouts=1); fi
  [ -f "$SRC/tests/fuzz/$t.dict" ] && dict=(-dict="$SRC/tests/fuzz/$t.dict")
  scratch=$(mktemp -d "$scratch_root/aggscan-fuzz-$t.XXXXXX")
  echo "run-fuzzers: $t for ${SECONDS_PER_TARGET} s (log: $work/log.txt)"
  rc=0
  # The outer timeout only guards against a hang of libFuzzer itself.
  TMPDIR="$scratch" nice -n 10 timeout --kill-after=30 $((SECONDS_PER_TARGET + 5 * TIMEOUT_S + 60)) \
    "$bin" "$work/corpus" -max_total_time="$SECONDS_PER_TARGET" -rss_limit_mb="$RSS_MB" -timeout="$TIMEOUT_S" \
    -artifact_prefix="$work/artifacts/" -print_final_stats=1 "${dict[@]}" "${mode[@]}" >"$work/log.txt" 2>&1 || rc=$?
  rm -rf "$scratch"
  execs=$(sed -n 's/^stat::number_of_executed_units: *//p' "$work/log.txt" | tail -1)
  rate=$(sed -n 's/^stat::average_exec_per_sec: *//p' "$work/log.txt" | tail -1)
  if [ -z "$execs" ]; then  # fork mode: "#N: cov: ... exec/s R ..." lines
    last=$(grep -E '^#[0-9]+: cov:' "$work/log.txt" | tail -1 || true)
    execs=$(sed -n 's/^#\([0-9]*\):.*/\1/p' <<<"$last")
    rate=$(sed -n 's/.*exec\/s:\? \([0-9]*\).*/\1/p' <<<"$last")
  fi
  mapfile -t found < <(find "$work/artifacts" -type f | sort)
  line=$(printf '%-18s executions %-9s exec/s %-6s crashes %d' "$t" "${execs:-?}" "${rate:-?}" "${#found[@]}")
  if [ "${#found[@]}" -gt 0 ] || [ "$rc" -ne 0 ]; then
    crashed=1
    what=$(grep -m1 -E "what\(\): |runtime error|^==[0-9]+== ?ERROR|timeout after|out-of-memory" "$work/log.txt" || true)
    line+="  FAILED (exit $rc): ${what:-see the log}"
    for f in "${found[@]}"; do line+=$'\n'"    reproducer: $f  (re-run: $bin $f)"; done
    line+=$'\n'"    log: $work/log.txt"
  fi
  summary+=("$line")
  echo "$line"
done

echo "run-fuzzers: summary (${SECONDS_PER_TARGET} s a target, $(($(date +%s) - start_all)) s in all)"
printf '%s\n' "${summary[@]}"
if [ "$crashed" -ne 0 ]; then
  echo "run-fuzzers: FAILED: a target found a crash; each reproducer is listed above" >&2
  exit 1
fi
