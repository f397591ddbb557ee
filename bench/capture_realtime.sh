#!/usr/bin/env bash
# Benchmark: one side captured in REAL time (time_scale 1, 30 views, one shot
# every 2 s, 2016x1512 sim frames) by the real aggscand.
# Reports the schedule error of the view timestamps (p50 / p99 / max, ms)
# and the daemon's peak RSS (VmHWM). Targets: p99 <= 20 ms, RSS <= 60 MB + one frame.
#   bench/capture_realtime.sh [BUILD_DIR]   (a Release build; default build-release)
set -euo pipefail
cd "$(dirname "$0")/.."
BUILD_DIR=${1:-build-release}
AGGSCAND="$BUILD_DIR/daemon/aggscand"
CLI="$BUILD_DIR/cli/aggscan"
[ -x "$AGGSCAND" ] || { echo "build $BUILD_DIR first (Release)"; exit 1; }
WORK=$(mktemp -d /tmp/aggscan-bench-XXXXXX)
trap 'kill $DAEMON 2>/dev/null || true; rm -rf "$WORK"' EXIT
cat > "$WORK/bench.toml" <<TOML
[daemon]
state_dir = "$WORK/state"
listen_port = 0
time_scale = 1.0
[capture]
profile = "custom"
sides = 1
views_per_side = ${VIEWS:-30}
step_deg = 30.0
interval = "2s"
[camera]
width = 2016
height = 1512
TOML
"$AGGSCAND" --config "$WORK/bench.toml" --port-file "$WORK/port" 2> "$WORK/daemon.log" &
DAEMON=$!
for _ in $(seq 100); do [ -s "$WORK/port" ] && break; sleep 0.1; done
export AGGSCAN_URL="http://127.0.0.1:$(cat "$WORK/port")"
"$CLI" arm bench-1 >/dev/null
start=$(date +%s.%N)
"$CLI" press >/dev/null
for _ in $(seq 1200); do
  s=$("$CLI" --json status | python3 -c 'import json, sys; print(json.load(sys.stdin)["state"])')
  [ "$s" = idle ] && break
  [ "$s" = faulted ] && { "$CLI" status; exit 1; }
  sleep 0.2
done
end=$(date +%s.%N)
hwm_kb=$(awk '/VmHWM/ {print $2}' /proc/$DAEMON/status)
frame_kb=$(( 2016 * 1512 * 3 / 1024 ))
python3 - "$WORK/state/samples/bench-1/side1" "$hwm_kb" "$frame_kb" "$start" "$end" <<'PY'
import json, glob, sys, statistics
d, hwm, frame, t0, t1 = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), float(sys.argv[4]), float(sys.argv[5])
errs = sorted(abs(json.load(open(f))["schedule_error_ms"]) for f in glob.glob(d + "/view_*.json"))
n = len(errs)
p = lambda q: errs[min(n - 1, int(round(q * (n - 1))))]
print(f"views: {n}  wall: {t1 - t0:.1f} s")
print(f"schedule error |ms|: p50 {p(0.5):.2f}  p99 {p(0.99):.2f}  max {errs[-1]:.2f}  mean {statistics.mean(errs):.2f}")
print(f"daemon peak RSS (VmHWM): {hwm/1024:.1f} MiB  (target 60 MiB + one RGB frame {frame/1024:.1f} MiB = {60+frame/1024:.1f} MiB)")
PY
