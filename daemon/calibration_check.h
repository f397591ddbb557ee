// What aggscand knows about the rig calibration (state_dir/calibration.json,
// written by `aggscan calibrate`): checked at start-up and at every arm, shown
// in the status API. Never fatal: a capture without a calibration is still a
// capture (the worker then gives it its 2D figures, or poses it by full SfM
// when [worker] poses is "sfm" or "auto").
#pragma once

#include <nlohmann/json.hpp>
#include <string>

namespace aggscan {

/// {"state": "ok" | "missing" | "invalid", "message": ..., "path": ...}; when
/// ok also "reprojection_rms_px", "created_utc", "views_used", "method",
/// "camera_id". invalid: damaged, or made at a resolution the camera config
/// (width x height) cannot use; the message says what to do.
nlohmann::json CheckRigCalibration(const std::string& state_dir, int width, int height);

}  // namespace aggscan
