#!/usr/bin/env bash
# The SfM poses path against COLMAP's default sparse pipeline, on the same
# photos and masks, one path per call so an outside timer can pair them:
#   bench/sfm_speed.sh prepare DIR [BUILD_DIR] [SEED]
#       a two-side sim capture in the paper profile (2 x 30 views, 30 deg
#       steps, 2016 x 1512), the rig calibrated from a ChArUco capture, the
#       masks and 2D figures computed (not timed); written to DIR/rock
#   bench/sfm_speed.sh run DIR PATH [BUILD_DIR]
#       PATH is one of
#         sfm              aggscan reconstruct --poses sfm --from poses: SIFT on
#                          the masks' window, pairs from the capture order and
#                          the plan's angles, the lens fixed from the calibration
#         sfm-whole-frame  the same with SIFT on the whole photos
#         colmap-defaults  per side: colmap feature_extractor (the masks, the
#                          calibrated lens held fixed, otherwise defaults),
#                          exhaustive_matcher, mapper (defaults)
#       on a fresh copy of DIR/rock (the copy is timed with the run); prints
#       the wall time and, for the aggscan paths, the errors against the sim's
#       truth, for colmap-defaults the registered views per side.
# Without arguments: prepare in a temporary directory, then the three paths.
# CORES (default "0,1") pins the runs with taskset. Needs /usr/bin/colmap.
set -euo pipefail
cd "$(dirname "$0")/.."
CORES=${CORES:-0,1}
[ -x /usr/bin/colmap ] || { echo "needs Debian's colmap (apt-get install colmap)"; exit 1; }

prepare() {
  local dir=$1 build=${2:-build-release} seed=${3:-1}
  local cli="$build/cli/aggscan"
  [ -x "$cli" ] || { echo "build $build first (Release)"; exit 1; }
  mkdir -p "$dir"
  printf '[camera]\nwidth = 2016\nheight = 1512\n' > "$dir/cfg.toml"
  "$cli" sim capture --scene charuco --config "$dir/cfg.toml" --out "$dir/board" > /dev/null 2>&1
  "$cli" calibrate "$dir/board" --out "$dir/calibration.json" > /dev/null
  "$cli" sim capture --seed "$seed" --config "$dir/cfg.toml" --calibration "$dir/calibration.json" \
    --out "$dir/rock" > /dev/null 2>&1
  # Masks and 2D figures once (the turntable path reconstructs it; the runs
  # start again at the poses).
  "$cli" reconstruct "$dir/rock" > /dev/null 2> "$dir/log" || { cat "$dir/log"; exit 1; }
  echo "prepared $dir/rock: seed $seed, $(ls "$dir"/rock/side1/*.jpg | wc -l) + $(ls "$dir"/rock/side2/*.jpg | wc -l) views at 2016x1512"
}

colmap_defaults() {
  local rock=$1 calib=$2
  # The calibrated lens, held fixed, as the worker has it (OPENCV fx, fy, cx,
  # cy, k1, k2, p1, p2; COLMAP puts pixel centres at +0.5): COLMAP's own guess
  # from the image size, refined, registers no third view on a rock that
  # fills a few per cent of the frame.
  local cam
  cam=$(/usr/bin/python3 -c 'import json, sys; c = json.load(open(sys.argv[1]))["camera"]; print(",".join("%.9g" % v for v in (c["fx"], c["fy"], c["cx"] + 0.5, c["cy"] + 0.5, c["k1"], c["k2"], c["p1"], c["p2"])))' "$calib")
  local out=""
  for s in 1 2; do
    local c="$rock/colmap$s"
    mkdir -p "$c/images" "$c/masks" "$c/sparse"
    for f in "$rock"/side$s/view_*.jpg; do
      local b
      b=$(basename "$f" .jpg)
      ln -s "$f" "$c/images/$b.jpg"
      cp "$rock/results/masks/side$s/$b.png" "$c/masks/$b.jpg.png"
    done
    taskset -c "$CORES" colmap feature_extractor --database_path "$c/db.db" --image_path "$c/images" \
      --ImageReader.mask_path "$c/masks" --ImageReader.camera_model OPENCV \
      --ImageReader.single_camera 1 --ImageReader.camera_params "$cam" \
      --SiftExtraction.use_gpu 0 > "$c/log" 2>&1
    taskset -c "$CORES" colmap exhaustive_matcher --database_path "$c/db.db" \
      --SiftMatching.use_gpu 0 >> "$c/log" 2>&1
    taskset -c "$CORES" colmap mapper --database_path "$c/db.db" --image_path "$c/images" \
      --output_path "$c/sparse" --Mapper.ba_refine_focal_length 0 \
      --Mapper.ba_refine_extra_params 0 >> "$c/log" 2>&1 || true
    local reg=0
    for m in "$c"/sparse/*/; do
      [ -f "$m/images.bin" ] || continue
      colmap model_converter --input_path "$m" --output_path "$m" --output_type TXT >> "$c/log" 2>&1
      local n
      n=$(awk '!/^#/ { n++ } END { print int(n / 2) }' "$m/images.txt")
      if [ "$n" -gt "$reg" ]; then reg=$n; fi
    done
    out="$out side $s: $reg/$(ls "$c/images" | wc -l) registered;"
  done
  echo "colmap-defaults:$out"
}

run() {
  local dir=$1 path=$2 build=${3:-build-release}
  local cli="$build/cli/aggscan"
  local work
  work=$(mktemp -d /tmp/aggscan-sfmspeed-XXXXXX)
  # shellcheck disable=SC2064
  trap "rm -rf '$work'" RETURN
  local t0 t1
  t0=$(date +%s.%N)
  cp -r "$dir/rock" "$work/rock"
  case "$path" in
    sfm | sfm-whole-frame)
      local extra=()
      [ "$path" = sfm-whole-frame ] && extra=(--sfm-whole-frame)
      taskset -c "$CORES" "$cli" reconstruct "$work/rock" --poses sfm --from poses "${extra[@]}" \
        > /dev/null 2> "$work/log" || { cat "$work/log"; return 1; }
      ;;
    colmap-defaults) colmap_defaults "$work/rock" "$dir/calibration.json" ;;
    *) echo "unknown path '$path': sfm, sfm-whole-frame or colmap-defaults"; return 2 ;;
  esac
  t1=$(date +%s.%N)
  /usr/bin/python3 - "$work/rock" "$path" "$t0" "$t1" <<'PY'
import json, sys
d, path, t0, t1 = sys.argv[1], sys.argv[2], float(sys.argv[3]), float(sys.argv[4])
print("%-16s wall %6.1f s" % (path, t1 - t0))
if path.startswith("sfm"):
    m = json.load(open(d + "/results/morphology.json"))
    t = json.load(open(d + "/truth.json"))
    rel = lambda k: 100 * (m["morphology_3d"][k] / t[k] - 1)
    print("  V %+.2f %% A %+.2f %% a %+.2f %% b %+.2f %% c %+.2f %%" % (
        rel("volume_mm3"), rel("surface_area_mm2"), rel("a_mm"), rel("b_mm"), rel("c_mm")))
    for side in (1, 2):
        s = json.load(open("%s/results/poses_side%d.json" % (d, side)))["sfm"]
        print("  side %d: %d/%d views, %.3f px, COLMAP %.1f s %s" % (
            side, s["registered_views"], s["input_views"], s["mean_reprojection_px"],
            s["colmap_s"], json.dumps(s.get("timings_s", {}))))
PY
}

case "${1:-all}" in
  prepare) shift; prepare "$@" ;;
  run) shift; run "$@" ;;
  all)
    DIR=$(mktemp -d /tmp/aggscan-sfmspeed-XXXXXX)
    trap 'rm -rf "$DIR"' EXIT
    prepare "$DIR"
    for p in sfm sfm-whole-frame colmap-defaults; do run "$DIR" "$p"; done
    ;;
  *) echo "usage: bench/sfm_speed.sh [prepare DIR [BUILD_DIR] [SEED] | run DIR PATH [BUILD_DIR]]"; exit 2 ;;
esac
