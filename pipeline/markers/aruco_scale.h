// ArUco markers as the alternative per-sample scale reference (to the colour
// labels of markers.h): square ArUco markers of rig.aruco_dictionary, each
// printed with a black square of rig.aruco_size_mm, laid flat on the disc at
// the configured centres (rig.aruco_markers).
//
// Each view: cv::aruco::detectMarkers on the photo with sub-pixel corner
// refinement; markers the rock hides in part (their outline within
// rock_clearance_px of the rock mask) and ids not configured are dropped.
// Then the corners are refined from the edges: OpenCV's corners of a blurred
// black square in a gamma-encoded photo lie inside the true square (measured
// 0.1-0.5 px, enough to make a 30 mm marker 0.5 % small), so along each of
// the four outer sides the edge is found where the intensity, linearised by
// the sRGB curve, is halfway between the black border and the white paper
// (unbiased for any symmetric blur), a line is fitted to each side's edge
// points in undistorted pixels (straight there) and adjacent lines meet in
// the corners.
// Per side: each marker's four corners are triangulated from every view that
// saw it (corner k is the same printed corner in every view: OpenCV orders
// them from the printed image's top-left, clockwise), then the scale check:
// the four sides (rig.aruco_size_mm) and two diagonals (sqrt(2) times that) of
// every located marker and the distances between located markers' centres
// (from the configured positions) against the reconstructed ones.
#pragma once

#include <Eigen/Core>
#include <array>
#include <opencv2/aruco/dictionary.hpp>
#include <opencv2/core.hpp>
#include <string>
#include <vector>

#include "common/error.h"
#include "common/rig_calibration.h"
#include "config/config.h"
#include "pipeline/core/geometry.h"

namespace aggscan {

/// The OpenCV ArUco dictionary of one of the names config.cpp accepts
/// (calibration.dictionary, rig.aruco_dictionary); kInvalidConfig otherwise.
Result<cv::Ptr<cv::aruco::Dictionary>> ArucoDictionary(const std::string& name);

/// The markers of rig.aruco_markers side by side in list order, each its
/// black square only (no margin) at `px_per_marker` pixels a side, 8-bit
/// grey: the image the sim draws them from (sim.aruco_image). px_per_marker is
/// rounded down to a multiple of the marker's cells. kInvalidConfig for an
/// unknown dictionary, an id outside it or no markers.
Result<cv::Mat> DrawArucoSheet(const RigConfig& rig, int px_per_marker);

/// Writes DrawArucoSheet at `px_per_mm` (dpi / 25.4) to a .pgm or .png file,
/// atomically (aggscan calibrate aruco).
Status WriteArucoSheet(const RigConfig& rig, const std::string& path, double px_per_mm);

/// Configured corner k (OpenCV order: the printed image's top-left, top-right,
/// bottom-right, bottom-left) of an ArUco marker in the turntable frame (z = 0).
Eigen::Vector3d ArucoCornerMm(const ArucoMarker& marker, double size_mm, int k);

struct ArucoDetectOptions {
  // A marker whose outline comes this close to the rock mask is dropped: the
  // rock may hide part of it, and the edge profiles reach up to 6 px out.
  int rock_clearance_px = 8;
  bool subpixel_corners = true;   // OpenCV's CORNER_REFINE_SUBPIX (else the contour corners)
  int subpixel_window_px = 5;     // half window of that refinement
  bool edge_refine = true;        // corners from lines fitted to the outer edges (above)
  bool srgb_photo = true;         // edge_refine: the photo is sRGB-encoded (JPEG); false = linear
  double edge_end_margin = 0.12;  // edge_refine: fraction of each side left out at both ends
  int min_edge_points = 6;        // edge_refine: fewer on a side: OpenCV's corners are kept

  /// Empty when valid, else what is wrong.
  std::string Check() const;
};

/// One configured ArUco marker in one view.
struct ArucoSighting {
  int id = -1;
  std::array<Eigen::Vector2d, 4> corners_px{};  // distorted pixels, pixel centres at integers
};

/// Everything ArUco in one view.
struct ArucoViewDetections {
  std::vector<ArucoSighting> markers;  // configured ids only, at most one per id
  int edge_refined = 0;                // of those, corners refined from the edges
  int near_rock = 0;                   // configured markers dropped: touching the rock mask
  int unknown_ids = 0;                 // markers of the dictionary not in rig.aruco_markers
  int duplicate_ids = 0;               // a configured id seen twice in the view: both dropped
};

/// Detects the configured ArUco markers in a BGR or grey photo with its rock
/// mask (0/255, same size; empty = no rock). The camera model, when given,
/// removes the lens distortion from the edges before the lines are fitted;
/// without it the image is taken as undistorted. kInvalidArgument for wrong
/// image types or sizes, kInvalidConfig for an unknown dictionary.
Result<ArucoViewDetections> DetectArucoMarkers(const cv::Mat& image, const cv::Mat& rock_mask,
                                               const RigConfig& rig, const CameraModel* camera,
                                               const ArucoDetectOptions& opts = {});

struct ArucoLocateOptions {
  geom::TriangulationOptions triangulation{.inlier_px = 1.5, .min_views = 2, .min_angle_deg = 5.0};
  int min_markers = 1;  // fewer located markers: no scale (one gives 6 lengths)
};

/// One ArUco marker's corners in 3D.
struct ArucoMarkerPoint {
  int id = -1;
  std::array<Eigen::Vector3d, 4> configured{};       // corners from rig.aruco_markers (table frame)
  bool located = false;                              // all four corners triangulated
  std::array<Eigen::Vector3d, 4> corners{};          // triangulated, in the poses' frame
  Eigen::Vector3d center = Eigen::Vector3d::Zero();  // mean of the corners
  double rms_px = 0, max_px = 0;  // reprojection over the four corners' inlier views
  int views_seen = 0;             // views where the marker was detected
  int views_used = 0;             // fewest inlier views among its corners
  std::string problem;            // why not located
};

/// The ArUco scale check of one side.
struct ArucoScale {
  std::vector<ArucoMarkerPoint> markers;  // rig.aruco_markers order
  int markers_used = 0;
  int views = 0;               // views of the side
  int views_with_markers = 0;  // views where at least one configured marker was detected
  /// Configured / reconstructed length, least squares over all lengths (the
  /// labels' convention, LabelScale::scale): ~1 on a calibrated rig.
  double scale = 1.0;
  int lengths = 0;                              // sides + diagonals + centre pairs compared
  double rms_mm = 0, max_mm = 0;                // |scale * d_rec - d_conf| over all lengths
  double edge_rms_mm = 0, edge_max_mm = 0;      // over sides and diagonals only
  double centre_rms_mm = 0, centre_max_mm = 0;  // over centre-to-centre distances only
  int centre_pairs = 0;
  /// Similarity (Umeyama, with scale) from the poses' frame onto the
  /// configured corners, and its residual (mm).
  geom::Similarity3 frame_to_table;
  double align_rms_mm = 0, align_max_mm = 0;
};

/// Triangulates every configured marker's corners from the detections of all
/// views (views[i] taken with cam_from_frame[i]) and compares the lengths with
/// the configured ones. Never fatal for a marker: one that cannot be located
/// says why. kInvalidArgument when fewer than min_markers are located, naming
/// each missing marker and in how many views it was seen.
Result<ArucoScale> LocateArucoMarkers(const std::vector<ArucoViewDetections>& views,
                                      const std::vector<geom::Rigid3>& cam_from_frame,
                                      const CameraModel& camera, const RigConfig& rig,
                                      const ArucoLocateOptions& opts = {});

}  // namespace aggscan
