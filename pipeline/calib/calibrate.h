// Rig calibration from a ChArUco board lying on the turntable.
//
// One captured side of a "sample" made with the [calibration] board flat on
// the disc: every view's ArUco markers are detected and the ChArUco corners
// interpolated (OpenCV aruco); OpenCV's calibrateCamera gives the lens and a
// pose per view; a joint Ceres refinement then fits the whole rig at once
// over every corner of every view:
//
//   pixel = project_K( cam_from_table0 * Rz(theta_i) * (Rz(psi) p_board + b) )
//
// theta_i the view's measured turntable angle (sidecar), p_board a corner in
// the board frame (config.h, CalibrationConfig), (b, psi) the board's pose on
// the disc (z = 0 on the disc top), cam_from_table0 the camera (6 dof), and
// K = fx = fy, cx, cy, k1, k2 (OpenCV's lens model, rig_calibration.h).
//
// Why some intrinsics are fixed: the board lies in the disc's plane in every
// view, so all views show ONE plane (turning it within that plane adds no
// new plane orientation). Seen through one plane the undistorted images are
// one homography (8 dof) of known table coordinates, while a free pinhole
// with its pose has 9 (fx, cx, cy + 6): the principal point trades off
// against the camera's tilt and cannot be measured. So cx, cy stay at the
// image centre, fy = fx (square pixels), p1 = p2 = k3 = 0; fx is measured
// from the perspective of the tilted plane, k1, k2 from the corners' spread
// over the image radius. A principal point a few pixels off centre is then
// absorbed as a tiny tilt of cam_from_table0: a consistent rig model.
// The board on the disc covers only the middle of the image (normalised
// radius up to ~0.25 of ~0.45 at the corners with the default rig), where
// k2 r^4 is nearly k1 r^2: k2 is then undetermined (on the sim it came out
// anywhere in -0.25..+0.7 for a true 0.02) and extrapolates badly above the
// disc. So k2 is kept only when the fit determines it (CalibrateOptions::k2),
// else fixed at 0 and k1 carries the distortion the board sees.
//
// Gauge: the table frame's rotation about the axis is not seen by the board
// (board yaw and table x trade off). The result fixes it the way the sim and
// the rig drawing do: at turntable angle 0 the camera centre lies in the
// table's x = 0 plane at negative y (table +x is to the camera's right); the
// board's pose on the disc is reported in that frame.
#pragma once

#include <array>
#include <string>
#include <vector>

#include "common/error.h"
#include "common/rig_calibration.h"
#include "config/config.h"

namespace aggscan {

/// Writes the board image: the squares area at px_per_mm (dpi / 25.4) with a
/// white margin of margin_mm around it, PNG or PGM by the file's extension.
/// margin_mm = 0 gives the image the sim's charuco scene reads.
Status WriteBoardImage(const CalibrationConfig& board, const std::string& path, double px_per_mm,
                       double margin_mm);

/// The board corners found in one view.
struct BoardView {
  std::string name;      // "side1/view_007.jpg"
  double angle_deg = 0;  // measured turntable angle (sidecar measured_angle_deg)
  int markers = 0;       // ArUco markers detected
  std::vector<int> ids;  // ChArUco corner ids (OpenCV numbering)
  std::vector<std::array<double, 2>> corners;  // their pixels (centres at integers)
};

/// Detects the board in an image file (markers, then interpolated corners).
Result<BoardView> DetectBoardInImage(const std::string& image_path, const CalibrationConfig& board,
                                     int* width = nullptr, int* height = nullptr);

/// A ChArUco corner's position in the board frame (mm, z = 0).
std::array<double, 2> BoardCornerMm(const CalibrationConfig& board, int corner_id);

struct CalibrateOptions {
  int min_views = 8;               // views with a usable detection needed
  int min_corners_per_view = 8;    // corners for a view to count as usable
  double min_rotation_deg = 60.0;  // turntable rotation the usable views must span
  // k2: kAuto estimates it when the fit determines it (standard deviation at
  // most max_k2_sigma) and fixes it at 0 otherwise; kFree always; kZero never.
  enum class K2 { kAuto, kFree, kZero };
  K2 k2 = K2::kAuto;
  double max_k2_sigma = 0.01;
};

struct CalibrationResult {
  RigCalibration cal;  // method "charuco"; board JSON with the pose on the disc
  double board_x_mm = 0, board_y_mm = 0, board_yaw_deg = 0;  // pose on the disc, table frame
  int views_total = 0;                                       // views in the side
  std::vector<std::string> skipped;                          // unused views and why
  double max_view_rms_px = 0;                                // worst view
  double init_rms_px = 0;    // OpenCV calibrateCamera (free pose per view)
  int outlier_corners = 0;   // corners with a residual above 2 px (Huber-weighted)
  bool k2_estimated = true;  // false: k2 fixed at 0 (CalibrateOptions::k2)
  double k2_free_value = 0, k2_free_sigma = 0;  // kAuto, when it fixed k2: what a free k2 gave
  double sigma_fx_px = 0, sigma_k1 = 0, sigma_k2 = 0;  // standard deviations from the fit
  double seconds = 0;                                  // detection + solve, wall time
};

/// Solves from detections (views of one side, in any order).
Result<CalibrationResult> SolveRigCalibration(const std::vector<BoardView>& views,
                                              const CalibrationConfig& board, int width, int height,
                                              const CalibrateOptions& options = {});

/// Reads a captured side (manifest.json, view images, sidecars with the
/// measured angle), detects the board in every view and solves. Errors name
/// what is wrong and what to do: no manifest, a damaged sidecar, too few views
/// or corners detected (light, focus, board in view).
Result<CalibrationResult> CalibrateSampleSide(const std::string& sample_dir, int side,
                                              const CalibrationConfig& board,
                                              const CalibrateOptions& options = {});

/// Writes `cal` to `path` atomically; an existing file is first kept as
/// <path>.prev-<UTC> (a hard link, else a durable copy), so nothing is
/// overwritten. Returns the name of the kept file, "" when there was none.
Result<std::string> InstallRigCalibration(const std::string& path, const RigCalibration& cal);

/// The worker's job on a calibration capture (layout::kCalibrationCollection):
/// solves side `side` of `capture_dir` with the board of its config.toml,
/// installs the result as state_dir/calibration.json (InstallRigCalibration)
/// and writes the summary to capture_dir/results/calibration_result.json:
/// {"calibration", "previous", "reprojection_rms_px", "max_view_rms_px",
/// "views_used", "views_total", "corners_used", "skipped", "outlier_corners",
/// "fx_px", "k1", "camera_distance_mm", "seconds", "created_utc"}.
Status RunCalibrationCapture(const std::string& capture_dir, int side,
                             const std::string& state_dir);

}  // namespace aggscan
