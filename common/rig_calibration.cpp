#include "common/rig_calibration.h"

#include <cmath>

#include "common/fsutil.h"

namespace aggscan {

using nlohmann::json;

bool CameraModel::Project(const std::array<double, 3>& p, double* u, double* v) const {
  if (!(p[2] > 1e-9)) return false;
  const double x = p[0] / p[2], y = p[1] / p[2];
  const double r2 = x * x + y * y;
  const double radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3));
  const double xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x);
  const double yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y;
  *u = fx * xd + cx;
  *v = fy * yd + cy;
  return true;
}

CameraModel CameraModel::Resized(int new_width, int new_height) const {
  CameraModel m = *this;
  const double sx = static_cast<double>(new_width) / width;
  const double sy = static_cast<double>(new_height) / height;
  m.width = new_width;
  m.height = new_height;
  m.fx = fx * sx;
  m.fy = fy * sy;
  // Pixel centres at integers: the image edge is at -0.5.
  m.cx = (cx + 0.5) * sx - 0.5;
  m.cy = (cy + 0.5) * sy - 0.5;
  return m;
}

CameraModel CameraModel::Cropped(int x, int y, int new_width, int new_height) const {
  CameraModel m = *this;
  m.width = new_width;
  m.height = new_height;
  m.cx = cx - x;
  m.cy = cy - y;
  return m;
}

std::array<double, 3> RigCalibration::CameraCentreTable0() const {
  const auto& R = R_cam_table0;
  const auto& t = t_cam_table0;
  // C = -R^T t
  return {-(R[0] * t[0] + R[3] * t[1] + R[6] * t[2]), -(R[1] * t[0] + R[4] * t[1] + R[7] * t[2]),
          -(R[2] * t[0] + R[5] * t[1] + R[8] * t[2])};
}

std::array<double, 16> RigCalibration::CamFromTable(double angle_deg) const {
  const double a = angle_deg * M_PI / 180.0;
  const double c = std::cos(a), s = std::sin(a);
  const double Rz[9] = {c, -s, 0, s, c, 0, 0, 0, 1};
  std::array<double, 16> m{};
  for (int r = 0; r < 3; ++r) {
    for (int col = 0; col < 3; ++col) {
      double acc = 0;
      for (int k = 0; k < 3; ++k) acc += R_cam_table0[r * 3 + k] * Rz[k * 3 + col];
      m[r * 4 + col] = acc;
    }
    m[r * 4 + 3] = t_cam_table0[r];
  }
  m[15] = 1;
  return m;
}

std::string CalibrationPath(const std::string& state_dir) {
  return state_dir + "/calibration.json";
}

json CalibrationToJson(const RigCalibration& cal) {
  const CameraModel& c = cal.camera;
  return {{"format", "aggscan-calibration-1"},
          {"units", "mm, degrees, pixels; rotation row-major; p_cam = R * Rz(angle) * p_table + t"},
          {"method", cal.method},
          {"created_utc", cal.created_utc},
          {"camera_id", cal.camera_id},
          {"source", cal.source},
          {"camera",
           {{"width", c.width},
            {"height", c.height},
            {"fx", c.fx},
            {"fy", c.fy},
            {"cx", c.cx},
            {"cy", c.cy},
            {"k1", c.k1},
            {"k2", c.k2},
            {"p1", c.p1},
            {"p2", c.p2},
            {"k3", c.k3}}},
          {"cam_from_table0", {{"R", cal.R_cam_table0}, {"t_mm", cal.t_cam_table0}}},
          {"camera_centre_table0_mm", cal.CameraCentreTable0()},
          {"reprojection_rms_px", cal.reprojection_rms_px},
          {"views_used", cal.views_used},
          {"corners_used", cal.corners_used},
          {"board", cal.board.is_null() ? json::object() : cal.board}};
}

namespace {

Error Bad(const std::string& what, const std::string& why) {
  return MakeError(
      ErrorClass::kCorrupt,
      what + ": " + why + "; run `aggscan calibrate` again to write a new calibration");
}

bool Finite(double v) { return std::isfinite(v); }

}  // namespace

Result<RigCalibration> CalibrationFromJson(const json& j, const std::string& what) {
  RigCalibration cal;
  try {
    if (!j.is_object()) return Bad(what, "not a JSON object");
    if (j.value("format", "") != "aggscan-calibration-1") {
      return Bad(what, "format is not \"aggscan-calibration-1\"");
    }
    const json& c = j.at("camera");
    CameraModel& m = cal.camera;
    m.width = c.at("width").get<int>();
    m.height = c.at("height").get<int>();
    m.fx = c.at("fx").get<double>();
    m.fy = c.at("fy").get<double>();
    m.cx = c.at("cx").get<double>();
    m.cy = c.at("cy").get<double>();
    m.k1 = c.value("k1", 0.0);
    m.k2 = c.value("k2", 0.0);
    m.p1 = c.value("p1", 0.0);
    m.p2 = c.value("p2", 0.0);
    m.k3 = c.value("k3", 0.0);
    cal.R_cam_table0 = j.at("cam_from_table0").at("R").get<std::array<double, 9>>();
    cal.t_cam_table0 = j.at("cam_from_table0").at("t_mm").get<std::array<double, 3>>();
    cal.reprojection_rms_px = j.value("reprojection_rms_px", 0.0);
    cal.views_used = j.value("views_used", 0);
    cal.corners_used = j.value("corners_used", 0);
    cal.method = j.value("method", "");
    cal.created_utc = j.value("created_utc", "");
    cal.camera_id = j.value("camera_id", "");
    cal.source = j.value("source", "");
    cal.board = j.value("board", json::object());
  } catch (const json::exception& e) {
    return Bad(what, std::string("missing or mistyped field (") + e.what() + ")");
  }
  const CameraModel& m = cal.camera;
  if (m.width <= 0 || m.height <= 0) return Bad(what, "camera width/height must be positive");
  for (double v : {m.fx, m.fy, m.cx, m.cy, m.k1, m.k2, m.p1, m.p2, m.k3, cal.reprojection_rms_px}) {
    if (!Finite(v)) return Bad(what, "a camera value is not a finite number");
  }
  if (m.fx <= 0 || m.fy <= 0) return Bad(what, "focal lengths fx, fy must be positive");
  if (m.cx < 0 || m.cx > m.width || m.cy < 0 || m.cy > m.height) {
    return Bad(what, "principal point (cx, cy) lies outside the image");
  }
  for (double v : cal.R_cam_table0) {
    if (!Finite(v)) return Bad(what, "rotation has a non-finite entry");
  }
  for (double v : cal.t_cam_table0) {
    if (!Finite(v)) return Bad(what, "translation has a non-finite entry");
  }
  // R R^T = I and det R = +1 within 1e-6.
  const auto& R = cal.R_cam_table0;
  for (int a = 0; a < 3; ++a) {
    for (int b = 0; b < 3; ++b) {
      double d = 0;
      for (int k = 0; k < 3; ++k) d += R[a * 3 + k] * R[b * 3 + k];
      if (std::abs(d - (a == b ? 1.0 : 0.0)) > 1e-6)
        return Bad(what, "cam_from_table0.R is not a rotation");
    }
  }
  const double det = R[0] * (R[4] * R[8] - R[5] * R[7]) - R[1] * (R[3] * R[8] - R[5] * R[6]) +
                     R[2] * (R[3] * R[7] - R[4] * R[6]);
  if (det < 0) return Bad(what, "cam_from_table0.R is a reflection, not a rotation");
  return cal;
}

Result<RigCalibration> LoadCalibration(const std::string& path) {
  auto text = ReadFile(path);
  if (!text) {
    if (text.error().cls == ErrorClass::kNotFound) {
      return MakeError(ErrorClass::kNotFound,
                       "no rig calibration at " + path +
                           "; put the ChArUco board on the turntable and run `aggscan calibrate`");
    }
    return text.error();
  }
  json j;
  try {
    j = json::parse(*text);
  } catch (const json::exception& e) {
    return Bad(path, std::string("not valid JSON (") + e.what() + ")");
  }
  return CalibrationFromJson(j, path);
}

Status SaveCalibration(const std::string& path, const RigCalibration& cal) {
  return WriteFileAtomic(path, CalibrationToJson(cal).dump(2) + "\n");
}

Status CheckCalibrationFits(const RigCalibration& cal, int width, int height) {
  const CameraModel& m = cal.camera;
  if (m.width == width && m.height == height) return {};
  // Same aspect ratio (to one pixel at the target size): the lens scales.
  const double expect_h = static_cast<double>(width) * m.height / m.width;
  if (std::abs(expect_h - height) <= 1.0) return {};
  return MakeError(ErrorClass::kInvalidConfig,
                   "the rig calibration was made at " + std::to_string(m.width) + "x" +
                       std::to_string(m.height) + " but the camera is configured for " +
                       std::to_string(width) + "x" + std::to_string(height) +
                       " with another aspect ratio; calibrate again at this resolution");
}

}  // namespace aggscan
