// The stitch stage of the reconstruction: puts every side's turntable frame
// into one object frame (side 1's turntable frame). Adapts the per-view inputs
// of reconstruct.cpp to the marker and stitching library (markers.h,
// stitch.h) and records what it found as results/stitch.json.
#pragma once

#include <map>
#include <string>
#include <vector>

#include <Eigen/Geometry>
#include <nlohmann/json.hpp>

#include "common/error.h"
#include "common/rig_calibration.h"

namespace aggscan {

struct StitchViewInput {
  int view = 0;
  double angle_deg = 0;
  std::string image;  // path of the photo
  std::string mask;   // path of its rock mask (PNG)
  Eigen::Isometry3d cam_from_table = Eigen::Isometry3d::Identity();
};

struct StitchStageInput {
  std::string sample_dir;
  const RigCalibration* calibration = nullptr;
  std::map<int, std::vector<StitchViewInput>> views;  // per side (1-based)
};

/// The stitch record: {"method", "sides": [{"side", "table_from_object_4x4"}],
/// "rms_mm", "max_mm", "scale_residual_mm", ..., "stage_seconds"}. With one
/// side the object frame is that side's turntable frame.
Result<nlohmann::json> RunStitchStage(const StitchStageInput& in);

}  // namespace aggscan
