#!/usr/bin/env bash
# Benchmark of the whole worker on one rock: a two-side sim
# capture at 2016x1512 (the default paper profile, 2 x 30 views), the rig
# calibrated from a ChArUco capture first (not timed), then
#   1. aggscan-worker --sample on it: wall time, CPU time, peak RSS, and the
#      per-stage times from results/morphology.json and the side results;
#   2. the same 60 photos through COLMAP's own sparse pipeline
#      (feature_extractor with the masks, exhaustive_matcher, mapper), CPU,
#      timed side by side.
# Targets: <= 15 s per rock on the fast path and peak RSS <= 512 MB (a two-minute
# capture stays ahead of its reconstruction on an ARM board several times slower).
#   bench/worker_bench.sh [BUILD_DIR] [SEED]   (a Release build; default build-release, seed 1)
# CORES (default "0,1") pins both runs to two cores with taskset; COLMAP=0 skips the comparison.
set -euo pipefail
cd "$(dirname "$0")/.."
BUILD_DIR=${1:-build-release}
SEED=${2:-1}
CORES=${CORES:-0,1}
CLI="$BUILD_DIR/cli/aggscan"
WORKER="$BUILD_DIR/pipeline/aggscan-worker"
[ -x "$WORKER" ] && [ -x "$CLI" ] || { echo "build $BUILD_DIR first (Release)"; exit 1; }
WORK=$(mktemp -d /tmp/aggscan-wbench-XXXXXX)
trap 'rm -rf "$WORK"' EXIT
printf '[camera]\nwidth = 2016\nheight = 1512\n' > "$WORK/cfg.toml"

"$CLI" sim capture --scene charuco --config "$WORK/cfg.toml" --out "$WORK/board" > /dev/null 2>&1
"$CLI" calibrate "$WORK/board" --out "$WORK/calibration.json" > /dev/null
"$CLI" sim capture --seed "$SEED" --config "$WORK/cfg.toml" --calibration "$WORK/calibration.json" \
  --out "$WORK/rock" > /dev/null 2>&1
echo "sample: seed $SEED, $(ls "$WORK"/rock/side1/*.jpg | wc -l) + $(ls "$WORK"/rock/side2/*.jpg | wc -l) views at 2016x1512, cores $CORES"

/usr/bin/time -f "%e %U %S %M" -o "$WORK/time" taskset -c "$CORES" \
  "$WORKER" --sample "$WORK/rock" --log-level warning 2> "$WORK/worker.log" || { cat "$WORK/worker.log"; exit 1; }
read -r wall user sys rss_kb < "$WORK/time"
python3 - "$WORK/rock" "$wall" "$user" "$sys" "$rss_kb" <<'PY'
import json, sys, glob
d, wall, user, sys_s, rss = sys.argv[1], *map(float, sys.argv[2:])
m = json.load(open(d + "/results/morphology.json"))
t = m["timings_s"]
side = []
for p in sorted(glob.glob(d + "/results/side*_morph2d.json")):
    j = json.load(open(p))
    side.append("%s %.1f s" % (p.split("/")[-1].split("_")[0], j.get("timing_ms", 0.0) / 1e3))
print("aggscan-worker: wall %.1f s, CPU %.1f s (user %.1f + sys %.1f), peak RSS %.0f MB" % (wall, user + sys_s, user, sys_s, rss / 1024))
print("  masks + 2D (per side): " + (", ".join(side) if side else "see worker log"))
for k in ("calibration_s", "poses_side1_s", "poses_side2_s", "stitch_s", "surface_s", "morphology_s", "total", "this_run_wall"):
    if k in t: print("  %-16s %7.2f s" % (k, t[k]))
if "surface_detail_s" in t: print("  surface detail:", json.dumps(t["surface_detail_s"]))
d3 = m["morphology_3d"]
print("  result: V %.0f mm3, a/b/c %.1f/%.1f/%.1f mm, methods %s" % (d3["volume_mm3"], d3["a_mm"], d3["b_mm"], d3["c_mm"], json.dumps(m["methods"])))
print("  targets: <= 15 s per rock: %s; peak RSS <= 512 MB: %s" % ("PASS" if wall <= 15 else "FAIL", "PASS" if rss <= 512 * 1024 else "FAIL"))
PY

# COLMAP's own sparse pipeline on the same photos (CPU), for comparison.
[ "${COLMAP:-1}" = 0 ] && exit 0
C="$WORK/colmap"; mkdir -p "$C/images" "$C/masks" "$C/sparse"
for s in 1 2; do
  for f in "$WORK"/rock/side$s/view_*.jpg; do
    b=$(basename "$f" .jpg); ln -s "$f" "$C/images/s${s}_$b.jpg"
    cp "$WORK/rock/results/masks/side$s/$b.png" "$C/masks/s${s}_$b.jpg.png"
  done
done
# COLMAP gets the rig's calibrated lens, as the worker does, and keeps it fixed
# (OPENCV fx, fy, cx, cy, k1, k2, p1, p2; COLMAP puts pixel centres at +0.5).
# The rock fills a few % of the frame, so lens distortion is unobservable: with
# the mapper's default refinement of k1, k2, p1, p2 no third image registered
# after any initial pair (0 of 60, though a 30 deg pair has ~180 inliers).
CAM=$(python3 -c 'import json, sys; c = json.load(open(sys.argv[1]))["camera"]; print(",".join("%.9g" % v for v in (c["fx"], c["fy"], c["cx"] + 0.5, c["cy"] + 0.5, c["k1"], c["k2"], c["p1"], c["p2"])))' "$WORK/calibration.json")
t0=$(date +%s.%N)
taskset -c "$CORES" colmap feature_extractor --database_path "$C/db.db" --image_path "$C/images" \
  --ImageReader.mask_path "$C/masks" --ImageReader.camera_model OPENCV --ImageReader.single_camera_per_folder 0 \
  --ImageReader.single_camera 1 --ImageReader.camera_params "$CAM" \
  --SiftExtraction.use_gpu 0 --SiftExtraction.num_threads 2 > "$C/log" 2>&1
t1=$(date +%s.%N)
taskset -c "$CORES" colmap exhaustive_matcher --database_path "$C/db.db" --SiftMatching.use_gpu 0 \
  --SiftMatching.num_threads 2 >> "$C/log" 2>&1
t2=$(date +%s.%N)
taskset -c "$CORES" colmap mapper --database_path "$C/db.db" --image_path "$C/images" --output_path "$C/sparse" \
  --Mapper.num_threads 2 --Mapper.ba_refine_focal_length 0 --Mapper.ba_refine_extra_params 0 >> "$C/log" 2>&1 || true
t3=$(date +%s.%N)
# Registered images in the largest model, and the size of every model (the mapper
# writes one per connected part, e.g. one per side when the sides do not match).
reg=0 models=""
for m in "$C"/sparse/*/; do
  [ -f "$m/images.bin" ] || continue
  colmap model_converter --input_path "$m" --output_path "$m" --output_type TXT >> "$C/log" 2>&1
  n=$(awk '!/^#/ { n++ } END { print int(n / 2) }' "$m/images.txt")
  models="$models${models:+ + }$n"
  if [ "$n" -gt "$reg" ]; then reg=$n; fi
done
python3 -c "import sys; a=list(map(float,sys.argv[1:5])); print('colmap sparse (same 60 photos, masks, 2 cores): extract %.1f s, exhaustive match %.1f s, mapper %.1f s, total %.1f s; %s of 60 registered in the largest model (models: %s), lens fixed from the calibration (sparse only: no dense surface on CPU)' % (a[1]-a[0], a[2]-a[1], a[3]-a[2], a[3]-a[0], sys.argv[5], sys.argv[6] or 'none'))" "$t0" "$t1" "$t2" "$t3" "$reg" "$models"
