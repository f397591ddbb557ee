// The sample job: from a captured sample to a metric, closed rock model and
// its morphology, as a declared list of stages run by the stage runner
// (pipeline/core/stage_runner.h: each stage kept only while its fingerprint of
// options and inputs matches, results/stages.json the ledger):
//   masks side N     results/masks/side<N>/, results/side<N>_morph2d.json (side_job.h;
//                    the side jobs usually ran these already)
//   2d               results/morph2d.json: the 2D figures over all sides
//   calibration      results/calibration_used.json: the rig calibration the sample is
//                    reconstructed with (samples/<id>/calibration.json, else the state dir's)
//   poses side N     results/poses_side<N>.json: every view's pose in its side's turntable
//                    frame (measured angles, refined by bundle adjustment; or full SfM
//                    scaled by the background labels: "method": "sfm", its model exported
//                    to results/sfm/side<N>/, COLMAP's workspace in work/side<N>/sfm, whose
//                    steps keep their own fingerprints)
//   (SfM without a calibration: the calibration stage comes after the poses and takes
//   side 1's SfM camera, "method": "sfm"; every later side is posed with it fixed,
//   so all views share one camera model, as the surface stage needs)
//   stitch           results/stitch.json: each side's turntable frame -> side 1's (object frame)
//   surface          results/surface.json and the meshes (mm, object frame):
//                    results/mesh.ply (binary, per-vertex colour), mesh.obj, mesh.stl
//   morphology       results/morphology.json: 3D figures, every view's 2D figures,
//                    statistics, 2D-vs-3D comparison, quality figures, timings
// and the sample's row in state_dir/library.csv (replaced when it changes).
#pragma once

#include <atomic>
#include <functional>
#include <nlohmann/json.hpp>
#include <string>

#include "common/error.h"
#include "pipeline/poses/bundle_adjust.h"
#include "pipeline/poses/hand_turned.h"
#include "pipeline/sfm/sfm_poses.h"
#include "pipeline/surface/photo_refine.h"
#include "pipeline/surface/visual_hull.h"
#include "pipeline/worker/side_job.h"

namespace aggscan {

/// Where the views' poses come from: the calibrated
/// turntable (fast path) or full SfM through COLMAP (pipeline/sfm/sfm_poses.h).
enum class PosesPath {
  kAuto,       // the turntable when the sample has a rig calibration, SfM otherwise
  kTurntable,  // calibration and measured angles (+ bundle adjustment)
  kSfm,        // COLMAP; intrinsics fixed from the calibration when there is one
};
/// "auto" | "turntable" | "sfm"; false for anything else.
bool ParsePosesPath(const std::string& name, PosesPath* out);
const char* PosesPathName(PosesPath p);

struct ReconstructOptions {
  WorkerOptions worker;  // per-side masks
  /// The poses path. The turntable by default: the SfM path costs minutes a
  /// side on the rig's 2 cores (../shared/notes/colmap-debian.md) and is
  /// asked for explicitly ([worker] poses, aggscan reconstruct --poses).
  PosesPath poses = PosesPath::kTurntable;
  SfmPosesOptions sfm;  // the SfM path's settings
  /// Poses: refine each side's measured turntable angles by bundle adjustment
  /// over the features inside the rock masks (pipeline/poses/bundle_adjust.h);
  /// recorded as "turntable+ba", or "turntable" with the reason when there
  /// are too few tracks or the adjustment does not lower the reprojection
  /// error. On by default. It corrects misread angles (tests/poses: 0.4 deg
  /// reading errors -> 0.07-0.26 deg); where the angles are read exactly (the
  /// sim's platter encoder) it moves them by its own noise, at most 0.08 deg
  /// at 2016 x 1512, and changes the volume by -0.21 to +0.09 % (8 validate
  /// rocks); it costs ~2.5 s a side on 2 cores (Release).
  bool bundle_adjust = true;
  /// Every view takes part, not only the distinct viewpoints: repeated
  /// viewpoints lengthen the tracks and each view gets its own angle (the
  /// distinct viewpoints alone correct only 10-50 % of a large error).
  BundleAdjustOptions ba = [] {
    BundleAdjustOptions o;
    o.features.distinct_viewpoints_only = false;
    return o;
  }();
  /// A table turned by hand (views without a measured angle): each view's
  /// angle from the disc's labels and ArUco markers (pipeline/poses/
  /// hand_turned.h), and a view whose sharpness inside the rock is below
  /// this fraction of its side's median is named as shot while the table
  /// turned and left out.
  TableAngleOptions hand;
  double hand_min_sharpness_ratio = 0.75;
  VisualHullOptions hull;  // surface
  bool photo_refine =
      true;  // refine the hull by photo-consistency (concavities the silhouettes miss)
  PhotoRefineOptions photo;  // ... with these options
  /// ... on the photos scaled to at most this width (0: full size). Its
  /// patches were tuned at 1008 x 756; on full 2016 x 1512 photos the same
  /// 9 x 9 px patch covers a quarter of the rock surface and the refinement
  /// carved too deep (validate, 2016 x 1512: volume -1.0 and -2.4 % on seeds
  /// 1 and 2 against +0.2 % at 1008 x 756 on seed 1).
  int photo_max_width = 1008;
  /// Taubin passes over the final surface (0: none). Validate, 2016 x 1512,
  /// seeds 1, 6, 9, 15: area error +2.92 -> +2.47 % (mean) with 10, volume
  /// unchanged (0.02 %); 20 passes gain only 0.1 % more.
  int surface_smooth_iterations = 10;
  std::string state_dir;  // for the library CSV and the fallback calibration; may be empty
  /// Run this stage ("masks", "2d", "calibration", "poses", "stitch",
  /// "surface", "morphology", or one side's: "poses side 2") and every one
  /// after it again, whatever the ledger says. Empty: only what changed.
  std::string from_stage;
  const std::atomic<bool>* cancel = nullptr;
};

/// Runs every stage of the sample whose result is missing or was made with
/// other options or inputs (sides first) and writes results/morphology.json.
/// Errors name the stage and what to do; cancellation is kCancelled.
Status ReconstructSample(const std::string& sample_dir, const ReconstructOptions& opts);

/// The masks of every side and the 2D figures over them (a sample without a
/// rig calibration on the turntable path), through the same stages.
Status TwoDFigures(const std::string& sample_dir, const WorkerOptions& opts);

/// results/morphology.json of a sample, read and checked (records.h);
/// kNotFound before it exists, kCorrupt naming the field when it does not read.
Result<records::Morphology> ReadMorphologyRecord(const std::string& sample_dir);
/// The same record as JSON (ToJson of the above).
Result<nlohmann::json> ReadMorphology(const std::string& sample_dir);

}  // namespace aggscan
