#!/usr/bin/env bash
# The main job on a fresh Debian 12 machine: installs the dependencies, builds
# aggscan, starts aggscand on the simulated rig (config/sim.toml, with the
# printed calibration board for the sim camera to draw) and aggscan-worker,
# calibrates the rig as an operator does (the board on the disc, arm a
# calibration capture, START; the worker solves it), captures a two-side sample of a simulated rock through the
# CLI exactly as an operator would (arm, press, flip, press), lets the worker
# reconstruct the rock (a closed metric mesh) and prints its 3D morphology.
#   scripts/run-sim-demo.sh [SAMPLE_ID]
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=$(pwd)
BUILD_DIR=${BUILD_DIR:-build-release}
SAMPLE=${1:-demo-$(date +%Y%m%d-%H%M%S)}

bash scripts/install-deps.sh
cmake -S . -B "$BUILD_DIR" -DCMAKE_BUILD_TYPE=Release -DAGGSCAN_BUILD_TESTS=OFF -DAGGSCAN_BUILD_BENCH=OFF >/dev/null
cmake --build "$BUILD_DIR" -j"${JOBS:-2}"

AGGSCAND="$BUILD_DIR/daemon/aggscand"
WORKER="$BUILD_DIR/pipeline/aggscan-worker"
CLI="$BUILD_DIR/cli/aggscan"
CONFIG=config/sim.toml
STATE_DIR=$("$AGGSCAND" --config "$CONFIG" --print-config | sed -n 's/^state_dir *= *"\(.*\)".*/\1/p' | head -1)
PORT=$("$AGGSCAND" --config "$CONFIG" --print-config | sed -n 's/^listen_port *= *\([0-9]*\).*/\1/p' | head -1)
export AGGSCAN_URL="http://127.0.0.1:${PORT}"
mkdir -p "$STATE_DIR"

# The printed ChArUco board of [calibration], for the sim camera to draw
# when a calibration capture is armed (sim.board_image).
"$CLI" calibrate board --config "$CONFIG" --out "$STATE_DIR/board.pgm" --margin-mm 0 >/dev/null
sed "s|^board_image = \"\"|board_image = \"$STATE_DIR/board.pgm\"|" "$CONFIG" > "$STATE_DIR/sim-demo.toml"
CONFIG="$STATE_DIR/sim-demo.toml"

"$AGGSCAND" --config "$CONFIG" 2> "$STATE_DIR/aggscand.log" &
DAEMON=$!
"$WORKER" --state-dir "$STATE_DIR" --config "$CONFIG" 2> "$STATE_DIR/worker.log" &
WORKER_PID=$!
trap 'kill $DAEMON $WORKER_PID 2>/dev/null || true; wait 2>/dev/null || true' EXIT

for _ in $(seq 100); do "$CLI" status >/dev/null 2>&1 && break; sleep 0.1; done
wait_state() {  # wait_state STATE...: poll until the daemon reports one of them
  for _ in $(seq 1200); do
    s=$("$CLI" --json status | python3 -c 'import json, sys; print(json.load(sys.stdin)["state"])')
    for want in "$@"; do [ "$s" = "$want" ] && return 0; done
    [ "$s" = faulted ] && { "$CLI" status; exit 1; }
    sleep 0.1
  done
  echo "timed out waiting for $*" >&2; exit 1
}

echo "== the operator's console: open $AGGSCAN_URL/ in a browser on this machine to watch"
# Rig calibration, as an operator does it once per set-up: the board lying on
# the disc, a calibration capture (one side), solved by the worker into
# STATE_DIR/calibration.json, which every later sample copies.
echo "== calibrating the rig: the ChArUco board on the turntable"
"$CLI" arm-calibration
"$CLI" press
wait_state idle
for _ in $(seq 600); do  # up to 2 min
  c=$("$CLI" --json status | python3 -c 'import json, sys; c = json.load(sys.stdin)["calibration_capture"] or {}; print(c.get("state", ""))')
  [ "$c" = done ] && break
  [ "$c" = failed ] && { "$CLI" --json status; echo "the calibration failed; see $STATE_DIR/worker.log" >&2; exit 1; }
  sleep 0.2
done
[ "$c" = done ] || { echo "no calibration after 2 min; see $STATE_DIR/worker.log" >&2; exit 1; }
"$CLI" --json status | python3 -c 'import json, sys; r = json.load(sys.stdin)["calibration_capture"]["result"]; print("calibrated: RMS %.3f px from %d of %d views, fx %.1f px, camera %.1f mm from the axis" % (r["reprojection_rms_px"], r["views_used"], r["views_total"], r["fx_px"], r["camera_distance_mm"]))'

echo "== arming sample $SAMPLE on the simulated rig"
"$CLI" arm "$SAMPLE"
echo "== pressing start: side 1"
"$CLI" press
wait_state awaiting_pose
"$CLI" status
echo "== the simulated operator flipped the rock; pressing start: side 2"
"$CLI" press
wait_state idle
echo "== waiting for the worker (masks, markers, stitching, surface, morphology)"
RES="$STATE_DIR/samples/$SAMPLE/results"
for _ in $(seq 3000); do  # up to 10 min
  [ -f "$RES/morphology.json" ] && break
  if ! kill -0 $WORKER_PID 2>/dev/null; then echo "the worker stopped; see $STATE_DIR/worker.log" >&2; exit 1; fi
  sleep 0.2
done
[ -f "$RES/morphology.json" ] || { echo "no results after 10 min; see $STATE_DIR/worker.log" >&2; exit 1; }
"$CLI" show "$SAMPLE"
echo "== 3D morphology and quality (GET /api/v1/samples/$SAMPLE/results)"
curl -fsS "$AGGSCAN_URL/api/v1/samples/$SAMPLE/results" | python3 -c '
import json, sys
m = json.load(sys.stdin)
d = m["morphology_3d"]
print("volume %.1f cm3, area %.1f cm2, a/b/c %.1f/%.1f/%.1f mm, FER %.2f, sphericity %.3f, watertight %s" % (
    d["volume_mm3"] / 1e3, d["surface_area_mm2"] / 1e2, d["a_mm"], d["b_mm"], d["c_mm"], d["fer_3d"],
    d["sphericity"], d["watertight"]))
print("quality:", json.dumps(m["quality"]))
print("methods:", json.dumps(m["methods"]), " total %.1f s" % m["timings_s"]["total"])'
echo "== the rock's QA report (GET /api/v1/samples/$SAMPLE/report.pdf, made by aggscan report)"
curl -fsS -o "$STATE_DIR/$SAMPLE-report.pdf" "$AGGSCAN_URL/api/v1/samples/$SAMPLE/report.pdf"
echo "report: $STATE_DIR/$SAMPLE-report.pdf ($(stat -c %s "$STATE_DIR/$SAMPLE-report.pdf") bytes)"
echo "mesh: $RES/mesh.ply (also mesh.obj, mesh.stl); library: $STATE_DIR/library.csv"
echo "sample directory: $STATE_DIR/samples/$SAMPLE"
