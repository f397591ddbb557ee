#include "daemon/calibration_check.h"

#include <cstdio>

#include "common/rig_calibration.h"

namespace aggscan {

nlohmann::json CheckRigCalibration(const std::string& state_dir, int width, int height) {
  const std::string path = CalibrationPath(state_dir);
  Result<RigCalibration> cal = LoadCalibration(path);
  if (!cal) {
    const bool missing = cal.error().cls == ErrorClass::kNotFound;
    return {{"state", missing ? "missing" : "invalid"},
            {"path", path},
            {"message", cal.error().ToString()}};
  }
  if (Status fits = CheckCalibrationFits(*cal, width, height); !fits) {
    return {{"state", "invalid"}, {"path", path}, {"message", path + ": " + fits.error().message}};
  }
  char rms[32];
  std::snprintf(rms, sizeof rms, "%.3f", cal->reprojection_rms_px);
  return {{"state", "ok"},
          {"path", path},
          {"message",
           "rig calibration of " + cal->created_utc + " (" + cal->method + ", RMS " + rms + " px)"},
          {"reprojection_rms_px", cal->reprojection_rms_px},
          {"created_utc", cal->created_utc},
          {"views_used", cal->views_used},
          {"method", cal->method},
          {"camera_id", cal->camera_id}};
}

}  // namespace aggscan
