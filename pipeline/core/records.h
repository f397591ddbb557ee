// The worker's records: what each stage of a sample leaves in results/ and the
// stages after it, the CLI and the quality check read back.
//
//   SideResult       results/side<N>_morph2d.json  masks and 2D figures of a side
//   PosesRecord      results/poses_side<N>.json    every view's pose, one side
//   StitchRecord     results/stitch.json           each side's table frame -> object frame
//   SurfaceRecord    results/surface.json          the mesh and how it was made
//   Morphology       results/morphology.json       the 3D and 2D figures, quality, warnings
//
// Each record is a struct with ToJson and FromJson and carries "schema"
// (kRecordSchema). A file without it was written before records carried a
// version and reads as version 1, which has the same fields; a newer version
// is refused. FromJson checks every field a reader relies on and names the
// file and the field when one is missing or of the wrong type.
//
// What a stage records for people rather than for the stages after it (the
// bundle adjustment's figures, COLMAP's summary, each stitch source's
// detail, the photo refinement's counters) is kept as JSON in a member named
// for it, and keys a record does not know (a newer writer's) in `extra`:
// both are written back as they were read, so nothing is lost on a round trip.
#pragma once

#include <map>
#include <nlohmann/json.hpp>
#include <optional>
#include <string>
#include <vector>

#include "common/error.h"
#include "common/json_io.h"
#include "pipeline/core/pose.h"
#include "pipeline/core/stats.h"

namespace aggscan::records {

/// The schema version this release writes (1: the same fields, no "schema").
inline constexpr int kRecordSchema = 2;

/// One figure's statistics across views, as recorded ({"mean", "min", "max",
/// "std", "cov", "n"}).
nlohmann::json StatsToJson(const Stats& s);
Result<Stats> StatsFromJson(const nlohmann::json& j, const jsonio::Source& src);

// --- results/side<N>_morph2d.json ------------------------------------------

/// One view of a side: its mask and 2D figures (morph2d.h), or why it has none.
struct View2D {
  int view = 0;
  std::string image;          // relative to the side directory
  std::string mask;           // relative to results/ ("" when none was made)
  bool ok = false;            // a whole rock silhouette with figures
  std::string error;          // why not, with what to do ("" when ok)
  std::string image_problem;  // the photo could not be used ("" when it could)
  std::optional<double> commanded_angle_deg, measured_angle_deg;  // from the sidecar
  std::optional<double> mask_area_fraction;                       // of the frame
  std::optional<int> mask_frame_px;  // mask pixels on the photo's border
  // The 2D figures (pixels, degrees), when ok.
  double l_max_px = 0, l_min_px = 0, fer_2d = 0, area_px = 0, perimeter_px = 0, circularity = 0,
         l_max_angle_deg = 0;
  std::optional<double> timing_ms;
  nlohmann::json extra = nlohmann::json::object();

  nlohmann::json ToJson() const;
  static Result<View2D> FromJson(const nlohmann::json& j, const jsonio::Source& src);
};

struct SideResult {
  std::string sample_id;
  int side = 1;
  std::vector<View2D> views;  // capture order
  int views_total = 0, views_ok = 0;
  std::string mask_problems;           // views left out for their masks, with what to do ("" none)
  std::string image_problems;          // views left out for their photos ("" none)
  std::map<std::string, Stats> stats;  // fer_2d, circularity, l_max_px, l_min_px over ok views
  std::string std_kind = "sample";
  std::string mask_method = "classical";            // "classical" or "onnx"
  std::optional<std::string> mask_empty_turntable;  // the empty-turntable set used
  int mask_empty_turntable_views = 0;               // views masked against it
  std::vector<std::string> mask_empty_turntable_problems;
  double timing_ms = 0;
  nlohmann::json extra = nlohmann::json::object();

  nlohmann::json ToJson() const;
  static Result<SideResult> FromJson(const nlohmann::json& j, const jsonio::Source& src);
};

// --- results/poses_side<N>.json --------------------------------------------

/// One posed view.
struct PosedViewRecord {
  int view = 0;
  std::string image;     // relative to the side directory
  std::string mask;      // relative to results/
  double angle_deg = 0;  // the turntable angle the pose is for (refined when adjusted)
  std::optional<double> measured_angle_deg, angle_correction_deg;  // bundle adjustment
  std::optional<bool> ba_adjusted;
  Pose cam_from_table = Pose::Identity();
  nlohmann::json extra = nlohmann::json::object();

  nlohmann::json ToJson() const;
  static Result<PosedViewRecord> FromJson(const nlohmann::json& j, const jsonio::Source& src);
};

struct PosesRecord {
  int side = 1;
  std::string method;  // "turntable", "turntable+ba", "sfm"
  std::string method_detail;
  std::vector<PosedViewRecord> views;
  double stage_seconds = 0;
  // Turntable path: the bundle adjustment's figures (refined, final_rms_px,
  // ...); null on the SfM path.
  nlohmann::json bundle_adjustment;
  // SfM path (sfm_poses.h): COLMAP's summary, the metric scale's fit, the
  // camera it posed with (a rig calibration record), the views it left out.
  nlohmann::json sfm, scale, calibration, unregistered_views;
  nlohmann::json extra = nlohmann::json::object();

  bool IsSfm() const { return method == "sfm"; }
  nlohmann::json ToJson() const;
  static Result<PosesRecord> FromJson(const nlohmann::json& j, const jsonio::Source& src);
};

// --- results/stitch.json ---------------------------------------------------

/// One source's estimate of a side's transform (object markers or features).
struct SourceEstimate {
  bool valid = false;
  std::optional<Pose> moving_to_reference;           // when valid
  nlohmann::json detail = nlohmann::json::object();  // inliers, pairs, rms_mm, note, points...

  nlohmann::json ToJson() const;
  static Result<SourceEstimate> FromJson(const nlohmann::json& j, const jsonio::Source& src);
};

/// How one side was put onto another.
struct SideStitch {
  int side = 2, onto_side = 1;
  std::string source;      // "markers", "features", "silhouettes", ...
  bool consistent = true;  // the sources agree within the tolerance
  std::string warning;     // why not, with what to do
  std::optional<SourceEstimate> markers, features;
  // The silhouette check and polish: "available", "deficit", "used", ...
  nlohmann::json silhouettes = nlohmann::json::object();
  nlohmann::json extra = nlohmann::json::object();  // cross_checked, disagreement_deg/_mm, ...

  bool SilhouettesAvailable() const;
  double SilhouetteDeficit() const;  // 0 when not available
  nlohmann::json ToJson() const;
  static Result<SideStitch> FromJson(const nlohmann::json& j, const jsonio::Source& src);
};

struct StitchRecord {
  std::string method;                     // the source of the stitch ("single side" for one side)
  std::map<int, Pose> table_from_object;  // per side; side 1's is the identity
  std::vector<SideStitch> stitches;
  std::optional<double> rms_mm, max_mm, silhouette_deficit, scale_residual_mm;
  std::optional<std::string> scale_reference;
  double stage_seconds = 0;
  nlohmann::json per_side = nlohmann::json::array();  // each side's labels, markers, timings
  nlohmann::json extra = nlohmann::json::object();

  nlohmann::json ToJson() const;
  static Result<StitchRecord> FromJson(const nlohmann::json& j, const jsonio::Source& src);
};

// --- results/surface.json --------------------------------------------------

/// A view named by the surface stage (left out, or disagreeing with the model).
struct ViewNote {
  int side = 0, view = 0;
  std::string reason;
  nlohmann::json extra = nlohmann::json::object();
};

struct ViewIoU {
  int side = 0, view = 0;
  double iou = 0;
  // Fraction of the carved hull's silhouette in the view that the final
  // surface does not cover (absent in records written before it was measured).
  std::optional<double> outline_loss;
};

struct SurfaceRecord {
  std::string method;  // "visual-hull", "visual-hull+photo"
  std::string method_detail;
  int vertices = 0, faces = 0, views = 0;
  double voxel_mm = 0;
  std::map<std::string, std::string> files;  // "ply", "obj", "stl" -> file name in results/
  std::vector<ViewIoU> silhouette_iou;       // each view's mask against the mesh's silhouette
  std::vector<ViewNote> views_left_out, views_disagreeing;
  double stage_seconds = 0;
  std::map<std::string, double> timings_s;  // carve, photo_refine, silhouette_check, colour, export
  nlohmann::json photo_refine = nlohmann::json::object();  // the refinement's counters
  nlohmann::json consistency = nlohmann::json::object();   // each view's sole carving
  nlohmann::json extra = nlohmann::json::object();

  /// silhouette_iou as written in surface.json: [{side, view, iou[, outline_loss]}].
  nlohmann::json SilhouetteIoUJson() const;
  nlohmann::json ToJson() const;
  static Result<SurfaceRecord> FromJson(const nlohmann::json& j, const jsonio::Source& src);
};

// --- results/morphology.json -----------------------------------------------

/// One view's 2D figures in the sample's summary, in pixels and in mm at the
/// rock's depth in that view.
struct MorphView2D {
  int side = 0, view = 0;
  std::optional<double> angle_deg;
  double fer_2d = 0, circularity = 0, l_max_px = 0, l_min_px = 0, area_px = 0, perimeter_px = 0;
  double mm_per_px_at_rock = 0, l_max_mm = 0, l_min_mm = 0;
};

/// Each side's poses in brief.
struct PosesSummary {
  int side = 0;
  std::string method;
  nlohmann::json figures = nlohmann::json::object();  // the method's own figures
};

struct Morphology {
  static constexpr const char* kFormat = "aggscan-morphology-1";
  std::string sample_id;
  std::string created_utc;
  std::string units;
  std::map<std::string, std::string> methods;  // calibration, poses, stitch, surface, masks
  // The 3D figures (common/mesh_props.h MeshPropsJson): volume_mm3,
  // surface_area_mm2, a_mm, b_mm, c_mm, fer_3d, sphericity, ... and
  // "watertight"; the typed fields below are read from it.
  nlohmann::json morphology_3d = nlohmann::json::object();
  double volume_mm3 = 0, surface_area_mm2 = 0, a_mm = 0, b_mm = 0, c_mm = 0, fer_3d = 0,
         sphericity = 0;
  bool watertight = false;
  std::vector<PosesSummary> poses;
  std::vector<MorphView2D> views_2d;
  nlohmann::json stats_2d = nlohmann::json::object();  // per side and overall: Stats per figure
  nlohmann::json comparison_2d_3d = nlohmann::json::object();
  // Quality: the typed flags below, the figures behind them in `quality`.
  nlohmann::json quality = nlohmann::json::object();
  bool confident = false;
  std::vector<std::string> warnings;
  nlohmann::json timings_s = nlohmann::json::object();
  std::map<std::string, std::string> files;
  /// What computed it: {"version" (common/version.h), "config_sha256" (of
  /// the effective config, as ConfigToToml writes it)}; for people and
  /// reports, so kept as written.
  nlohmann::json software = nlohmann::json::object();
  nlohmann::json extra = nlohmann::json::object();

  /// Sets the typed 3D figures from morphology_3d (after it is filled).
  Status Read3D(const jsonio::Source& src);
  nlohmann::json ToJson() const;
  static Result<Morphology> FromJson(const nlohmann::json& j, const jsonio::Source& src);
};

/// Reads and parses a record file (kNotFound when absent; kCorrupt naming the
/// file, the field and `redo` when it does not parse).
template <typename Record>
Result<Record> Read(const std::string& path, const std::string& what, const std::string& redo) {
  auto j = jsonio::ReadFile(path, what, redo);
  if (!j) return j.error();
  return Record::FromJson(*j, jsonio::Source{what, path, redo});
}

/// Writes a record atomically.
template <typename Record>
Status Write(const std::string& path, const Record& r) {
  return jsonio::WriteFile(path, r.ToJson());
}

}  // namespace aggscan::records
