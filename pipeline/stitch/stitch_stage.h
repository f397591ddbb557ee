// The stitch stage of the reconstruction: puts every side's turntable frame
// into one object frame (side 1's turntable frame). Adapts the per-view inputs
// of reconstruct.cpp to the marker and stitching library (markers.h,
// stitch.h) and records what it found as results/stitch.json.
//
// Per side: every view's background labels and object markers are detected
// (with its rock mask and the calibrated lens); the labels are triangulated
// and their distances compared with the configured ones (the scale check of a
// calibrated rig: its residual is the sample's scale residual); so are the
// ArUco scale markers when rig.aruco_markers lists any (aruco_scale.h: their
// sides, diagonals and centre distances), the alternative reference; the object
// markers' heads and tails are triangulated; SIFT features inside the masks of
// the side's distinct viewpoints are matched and triangulated into a feature
// cloud. Every further side is then stitched onto side 1 (StitchSides: markers
// and features, cross-checked, and the silhouettes of the distinct viewpoints
// of both sides refining, checking or rescuing them: silhouette_stitch.h).
#pragma once

#include <Eigen/Geometry>
#include <map>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "common/error.h"
#include "common/rig_calibration.h"
#include "config/config.h"
#include "pipeline/core/records.h"
#include "pipeline/core/view.h"
#include "pipeline/markers/view_evidence.h"

namespace aggscan {

struct StitchStageInput {
  std::string sample_dir;
  const RigCalibration* calibration = nullptr;
  RigConfig rig;  // background labels and ArUco scale markers (the sample's config)
  std::vector<std::string> object_colors = {"purple", "red"};  // the study's object markers
  std::map<int, std::vector<SampleView>> views;                // per side (1-based)
  /// What earlier stages found in the views (photo path -> evidence), when
  /// its options are StitchEvidenceOptions of this input: a view found there
  /// is not decoded for its markers, and a view decoded here is added to it.
  ViewEvidenceCache* evidence = nullptr;
};

/// What the stitch stage detects in each view of `in` (its lens, labels,
/// object markers and ArUco markers), for a ViewEvidenceCache that stages
/// before it fill; `window_margin` is the surface stage's (RockWindow).
EvidenceOptions StitchEvidenceOptions(const StitchStageInput& in, int window_margin);

/// The stitch record (records.h StitchRecord): each side's table frame to
/// the object frame (side 1's table frame), the residual of the source chosen,
/// the scale check (which references gave it: "labels", "aruco",
/// "labels+aruco"), and per side its labels, object markers, ArUco markers and
/// feature cloud, the two estimates and their cross-check. With one side the
/// object frame is that side's turntable frame (the labels are still located
/// for the scale check). Errors say what was seen on each side and what to do.
Result<records::StitchRecord> RunStitchStage(const StitchStageInput& in);

}  // namespace aggscan
