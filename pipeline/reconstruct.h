// The sample stages after the per-side masks (side_job.h): from a captured,
// masked sample to a metric, closed rock model and its morphology.
//
// Stages, each finished iff its output file exists (written atomically), so a
// crash or kill at any stage resumes at that stage:
//   results/calibration_used.json  the rig calibration the sample is reconstructed with
//                                  (samples/<id>/calibration.json, else the state dir's)
//   results/poses_side<N>.json     every view's pose in its side's turntable frame
//                                  (measured angles, refined by bundle adjustment; or
//                                  full SfM scaled by the background labels: "method": "sfm",
//                                  its model exported to results/sfm/side<N>/)
//   (SfM without a calibration: calibration_used.json is then written after the poses,
//   from side 1's SfM camera, "method": "sfm"; every later side is posed with it fixed,
//   so all views share one camera model, as the surface stage needs)
//   results/stitch.json            each side's turntable frame -> side 1's (object frame)
//   results/surface.json           the mesh files below are complete
//     results/mesh.ply (binary, per-vertex colour), mesh.obj, mesh.stl   (mm, object frame)
//   results/morphology.json        3D figures, every view's 2D figures, statistics,
//                                  2D-vs-3D comparison, quality figures, timings
// and one row per sample appended to state_dir/library.csv.
#pragma once

#include <atomic>
#include <functional>
#include <string>

#include <nlohmann/json.hpp>

#include "common/error.h"
#include "pipeline/bundle_adjust.h"
#include "pipeline/photo_refine.h"
#include "pipeline/sfm_poses.h"
#include "pipeline/side_job.h"
#include "pipeline/visual_hull.h"

namespace aggscan {

/// Where the views' poses come from (issue 3 item 4): the calibrated
/// turntable (fast path) or full SfM through COLMAP (pipeline/sfm_poses.h).
enum class PosesPath {
  kAuto,       // the turntable when the sample has a rig calibration, SfM otherwise
  kTurntable,  // calibration and measured angles (+ bundle adjustment)
  kSfm,        // COLMAP; intrinsics fixed from the calibration when there is one
};
/// "auto" | "turntable" | "sfm"; false for anything else.
bool ParsePosesPath(const std::string& name, PosesPath* out);
const char* PosesPathName(PosesPath p);

struct ReconstructOptions {
  WorkerOptions worker;        // per-side masks
  /// The poses path. The turntable by default: the SfM path costs minutes a
  /// side on the rig's 2 cores (../shared/notes/colmap-debian.md) and is
  /// asked for explicitly ([worker] poses, aggscan reconstruct --poses).
  PosesPath poses = PosesPath::kTurntable;
  SfmPosesOptions sfm;         // the SfM path's settings
  /// Poses: refine each side's measured turntable angles by bundle adjustment
  /// over the features inside the rock masks (pipeline/bundle_adjust.h);
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
  VisualHullOptions hull;      // surface
  bool photo_refine = true;    // refine the hull by photo-consistency (concavities the silhouettes miss)
  PhotoRefineOptions photo;    // ... with these options
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
  std::string state_dir;       // for the library CSV and the fallback calibration; may be empty
  const std::atomic<bool>* cancel = nullptr;
};

namespace results {
inline constexpr const char* kMorphology = "morphology.json";
inline constexpr const char* kSurface = "surface.json";
inline constexpr const char* kStitch = "stitch.json";
inline constexpr const char* kCalibrationUsed = "calibration_used.json";
inline constexpr const char* kMeshPly = "mesh.ply";
inline constexpr const char* kMeshObj = "mesh.obj";
inline constexpr const char* kMeshStl = "mesh.stl";
inline constexpr const char* kLibraryCsv = "library.csv";
std::string PosesName(int side);  // "poses_side1.json"
}  // namespace results

/// Runs every unfinished stage of the sample (sides first) and writes
/// results/morphology.json. Errors name the stage and what to do.
Status ReconstructSample(const std::string& sample_dir, const ReconstructOptions& opts);

/// results/morphology.json of a sample, parsed; kNotFound before it exists.
Result<nlohmann::json> ReadMorphology(const std::string& sample_dir);

/// The CSV header of the library and one sample's row (from morphology.json).
std::string LibraryCsvHeader();
std::string LibraryCsvRow(const nlohmann::json& morphology);

}  // namespace aggscan
