#!/usr/bin/env bash
# The two poses paths side by side on one capture: a two-side sim capture in
# the paper profile (2 x 30 views, 30 deg steps, 2016 x 1512 by default), the
# rig calibrated from a ChArUco capture first (not timed), reconstructed by
#   sfm           full SfM through COLMAP (intrinsics fixed from the calibration)
#   turntable+ba  the calibrated turntable, angles refined by bundle adjustment
# on two copies of the same photos, both from the poses stage on (the masks
# computed once, before). Prints per path: wall time, the poses stage per side, and the
# volume, area and a/b/c errors against the sim's truth.
#   bench/sfm_vs_turntable.sh [BUILD_DIR] [SEED]   (default build-release, seed 1)
# WIDTH/HEIGHT (default 2016/1512) set the photo size; CORES (default "0,1")
# pins the runs with taskset. Needs /usr/bin/colmap.
set -euo pipefail
cd "$(dirname "$0")/.."
BUILD_DIR=${1:-build-release}
SEED=${2:-1}
CORES=${CORES:-0,1}
WIDTH=${WIDTH:-2016}
HEIGHT=${HEIGHT:-1512}
CLI="$BUILD_DIR/cli/aggscan"
[ -x "$CLI" ] || { echo "build $BUILD_DIR first (Release)"; exit 1; }
[ -x /usr/bin/colmap ] || { echo "needs Debian's colmap (apt-get install colmap)"; exit 1; }
WORK=$(mktemp -d /tmp/aggscan-sfmbench-XXXXXX)
trap 'rm -rf "$WORK"' EXIT
printf '[camera]\nwidth = %d\nheight = %d\n' "$WIDTH" "$HEIGHT" > "$WORK/cfg.toml"

"$CLI" sim capture --scene charuco --config "$WORK/cfg.toml" --out "$WORK/board" > /dev/null 2>&1
"$CLI" calibrate "$WORK/board" --out "$WORK/calibration.json" > /dev/null
"$CLI" sim capture --seed "$SEED" --config "$WORK/cfg.toml" --calibration "$WORK/calibration.json" \
  --out "$WORK/turntable/rock" > /dev/null 2>&1
echo "sample: seed $SEED, 2 x $(ls "$WORK"/turntable/rock/side1/*.jpg | wc -l) views at ${WIDTH}x$HEIGHT, cores $CORES"
# Masks and the 2D figures once (not timed); both paths then start at the poses.
"$CLI" reconstruct "$WORK/turntable/rock" > /dev/null 2> "$WORK/log" || { cat "$WORK/log"; exit 1; }
mkdir -p "$WORK/sfm"
cp -r "$WORK/turntable/rock" "$WORK/sfm/rock"

for path in turntable+ba sfm; do
  dir="$WORK/${path%%+*}/rock"
  t0=$(date +%s.%N)
  taskset -c "$CORES" "$CLI" reconstruct "$dir" --poses "$path" --from poses > "$WORK/out.json" \
    2> "$WORK/log" || { cat "$WORK/log"; exit 1; }
  t1=$(date +%s.%N)
  /usr/bin/python3 - "$dir" "$path" "$t0" "$t1" <<'PY'
import json, sys
d, path, t0, t1 = sys.argv[1], sys.argv[2], float(sys.argv[3]), float(sys.argv[4])
m = json.load(open(d + "/results/morphology.json"))
t = json.load(open(d + "/truth.json"))
rel = lambda k: 100 * (m["morphology_3d"][k] / t[k] - 1)
print("%-13s wall %6.1f s; V %+.2f %% A %+.2f %% a %+.2f %% b %+.2f %% c %+.2f %%" % (
    path, t1 - t0, rel("volume_mm3"), rel("surface_area_mm2"), rel("a_mm"), rel("b_mm"), rel("c_mm")))
for side in (1, 2):
    p = json.load(open("%s/results/poses_side%d.json" % (d, side)))
    print("  side %d: %s, poses stage %.1f s%s" % (side, p["method"], p.get("stage_seconds", 0),
          (", SfM " + json.dumps(p["sfm"].get("timings_s", {}))) if "sfm" in p else ""))
PY
done
