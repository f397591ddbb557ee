// The rig calibration: the camera's intrinsics and distortion, and where the
// camera sits relative to the turntable. One file, state_dir/calibration.json,
// written by `aggscan calibrate`, checked by aggscand at start-up, copied into
// every sample (samples/<id>/calibration.json) and read by the worker.
//
// Frames (millimetres, right-handed):
//   table   origin on the turntable axis at the disc's top surface, z up along
//           the axis; rotates with the platter.
//   table0  the table frame when the turntable reports angle 0.
//   camera  OpenCV: x right, y down, z along the optical axis.
// A view taken at measured turntable angle θ (degrees, counter-clockwise seen
// from above, as the turntable reports it) sees a table point p at
//   p_cam = cam_from_table0 * Rz(θ) * p.
//
// Lens model (OpenCV's): normalised x, y; r² = x² + y²;
//   x_d = x (1 + k1 r² + k2 r⁴ + k3 r⁶) + 2 p1 x y + p2 (r² + 2 x²)
//   y_d = y (1 + k1 r² + k2 r⁴ + k3 r⁶) + p1 (r² + 2 y²) + 2 p2 x y
//   u = fx x_d + cx, v = fy y_d + cy (pixel centres at integers).
// This header has no OpenCV or Eigen: the daemon reads the file too.
#pragma once

#include <array>
#include <cmath>
#include <nlohmann/json.hpp>
#include <string>

#include "common/error.h"

namespace aggscan {

struct CameraModel {
  int width = 0, height = 0;
  double fx = 0, fy = 0, cx = 0, cy = 0;
  double k1 = 0, k2 = 0, p1 = 0, p2 = 0, k3 = 0;

  /// Projects a camera-frame point (mm) to a pixel with distortion; false
  /// when it is not in front of the camera.
  bool Project(const std::array<double, 3>& p_cam, double* u, double* v) const;
  /// The same lens at another resolution with the same aspect ratio (focal
  /// lengths and centre scale with the width).
  CameraModel Resized(int new_width, int new_height) const;
  /// The same lens seen through the window of `width` x `height` pixels whose
  /// top-left pixel is (x, y) of the full frame: only the centre moves, so a
  /// crop of a photo projects exactly as the photo did (distortion is applied
  /// before the centre is added).
  CameraModel Cropped(int x, int y, int new_width, int new_height) const;
};

struct RigCalibration {
  CameraModel camera;
  std::array<double, 9> R_cam_table0{1, 0, 0, 0, 1, 0, 0, 0, 1};  // row-major rotation
  std::array<double, 3> t_cam_table0{0, 0, 0};                    // mm
  double reprojection_rms_px = 0;  // RMS over every detected board corner
  int views_used = 0;              // board views that entered the solution
  int corners_used = 0;
  std::string method;       // "charuco" | "sim-truth"
  std::string created_utc;  // ISO 8601
  std::string camera_id;    // the camera the views came from (sidecar camera_id)
  std::string source;       // where the views came from (sample directory)
  nlohmann::json board;     // board description used (type, squares, sizes, dictionary)

  /// Camera centre in the table0 frame (mm).
  std::array<double, 3> CameraCentreTable0() const;
  /// Row-major 4x4 of cam_from_table(θ) = cam_from_table0 * Rz(θ).
  std::array<double, 16> CamFromTable(double angle_deg) const;
};

/// Pinhole focal length in pixels of a lens whose horizontal field of view is
/// `hfov_deg` across `width` pixels (the sim's lens; a nominal lens hint).
inline double FocalPxFromHfov(double hfov_deg, int width) {
  return width / 2.0 / std::tan(hfov_deg * 3.14159265358979323846 / 360.0);
}

/// state_dir + "/calibration.json".
std::string CalibrationPath(const std::string& state_dir);

nlohmann::json CalibrationToJson(const RigCalibration& cal);
/// Parses and checks a calibration (positive focal lengths, centre inside the
/// image, a proper rotation, finite values). `what` names the source in errors.
Result<RigCalibration> CalibrationFromJson(const nlohmann::json& j, const std::string& what);

/// Reads and checks the file; kNotFound when it does not exist, kCorrupt with
/// the reason when it cannot be used (run `aggscan calibrate` again).
Result<RigCalibration> LoadCalibration(const std::string& path);
/// Writes atomically (temporary file, fsync, rename, directory fsync).
Status SaveCalibration(const std::string& path, const RigCalibration& cal);

/// Whether a calibration fits a camera configured at width x height: same
/// resolution, or the same aspect ratio (then Resized() is used). An error
/// saying what differs otherwise.
Status CheckCalibrationFits(const RigCalibration& cal, int width, int height);

}  // namespace aggscan
