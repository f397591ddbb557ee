// Multi-view geometry shared by the marker, scale and stitching stages: rigid
// and similarity transforms, the lens model on pixels, robust triangulation of
// one point from many views, Umeyama alignment and RANSAC on 3D-3D pairs.
//
// Conventions: millimetres; a pose cam_from_frame maps frame points into the
// camera (OpenCV axes: x right, y down, z forward); pixels have their centres
// at integers. Reprojection errors are measured in undistorted pixels (the
// camera's K without the lens distortion), which near the image centre equal
// the distorted ones to within the distortion's local stretch (< 5 % on the rig).
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <array>
#include <cstdint>
#include <optional>
#include <utility>
#include <vector>

#include "common/error.h"
#include "common/rig_calibration.h"

namespace aggscan::geom {

/// Rigid transform p' = R p + t.
struct Rigid3 {
  Eigen::Matrix3d R = Eigen::Matrix3d::Identity();
  Eigen::Vector3d t = Eigen::Vector3d::Zero();

  Eigen::Vector3d Apply(const Eigen::Vector3d& p) const { return R * p + t; }
  Rigid3 Inverse() const { return {R.transpose(), -(R.transpose() * t)}; }
  /// (a * b).Apply(p) == a.Apply(b.Apply(p)).
  friend Rigid3 operator*(const Rigid3& a, const Rigid3& b) { return {a.R * b.R, a.R * b.t + a.t}; }
  /// From a row-major homogeneous 4x4 (RigCalibration::CamFromTable, sim Matrix4).
  static Rigid3 FromRowMajor4(const std::array<double, 16>& m);
  /// Rotation about +z by `deg` (counter-clockwise seen from above).
  static Rigid3 RotZ(double deg);
};

/// Similarity p' = scale * R p + t.
struct Similarity3 {
  double scale = 1.0;
  Eigen::Matrix3d R = Eigen::Matrix3d::Identity();
  Eigen::Vector3d t = Eigen::Vector3d::Zero();

  Eigen::Vector3d Apply(const Eigen::Vector3d& p) const { return scale * (R * p) + t; }
};

/// Angle (degrees, [0, 180]) of the rotation R.
double RotationAngleDeg(const Eigen::Matrix3d& R);

/// Pose of the view at measured turntable angle `angle_deg`: cam_from_table =
/// cam_from_table0 * Rz(angle) (common/rig_calibration.h).
Rigid3 CamFromTable(const RigCalibration& cal, double angle_deg);

/// The camera matrix K (no distortion).
Eigen::Matrix3d CameraMatrix(const CameraModel& cam);

/// A rigid transform from a row-major 4x4 matrix (RigCalibration's form).
Eigen::Isometry3d IsoFromRowMajor(const std::array<double, 16>& m);

/// Removes the lens distortion from a pixel: the pixel where the same ray would
/// land through an ideal lens with the same K. Iterative (converges to 1e-6 px
/// within the rig's distortion range).
Eigen::Vector2d UndistortPixel(const CameraModel& cam, const Eigen::Vector2d& pixel);

/// Distorted pixel of a frame point seen from cam_from_frame; nullopt when the
/// point is not in front of the camera.
std::optional<Eigen::Vector2d> ProjectPoint(const CameraModel& cam, const Rigid3& cam_from_frame,
                                            const Eigen::Vector3d& p);

/// One sighting of a 3D point in one view, in the generic form: P = K [R | t]
/// maps homogeneous frame points to homogeneous undistorted pixels, `uv` is the
/// observed undistorted pixel. Any 3x4 projection (an SfM camera, a
/// calibration) can be used directly; MakeSighting builds one from a pose and
/// the lens model.
struct Sighting {
  Eigen::Matrix<double, 3, 4> P;
  Eigen::Vector2d uv;
  int view = -1;  // caller's view index, carried through to the result
};

/// Sighting of the distorted pixel `pixel` in a view with pose cam_from_frame.
Sighting MakeSighting(const CameraModel& cam, const Rigid3& cam_from_frame,
                      const Eigen::Vector2d& pixel, int view);

struct TriangulationOptions {
  double inlier_px = 2.0;      // a sighting farther than this from the solution is an outlier
  int min_views = 2;           // fewer inliers: no point
  double min_angle_deg = 3.0;  // smallest ray angle among the inliers (baseline check)
  bool robust = true;  // pick the two-view seed with most inliers (all pairs); else all views
  int refine_iterations = 10;  // Gauss-Newton steps on the pixel reprojection error

  /// Empty when valid, else what is wrong.
  std::string Check() const;
};

struct TriangulatedPoint {
  Eigen::Vector3d X = Eigen::Vector3d::Zero();  // frame coordinates (mm)
  double rms_px = 0;                            // reprojection RMS over the inliers
  double max_px = 0;                            // largest inlier residual
  double max_angle_deg = 0;                     // widest angle between two inlier rays
  std::vector<int> inliers;                     // indices into the sightings
  std::vector<double> residual_px;              // per sighting (all of them, inliers or not)
};

/// Triangulates one point from its sightings: linear (DLT) seed, Gauss-Newton
/// refinement of the pixel reprojection error, outliers (> inlier_px) dropped.
/// kInvalidArgument when there are too few sightings, fewer than min_views
/// agree, or the rays are too nearly parallel.
Result<TriangulatedPoint> TriangulatePoint(const std::vector<Sighting>& sightings,
                                           const TriangulationOptions& opts = {});

/// Least-squares similarity (with_scale) or rigid motion mapping src[i] to
/// dst[i] (Umeyama 1991). Needs >= 3 non-collinear pairs; nullopt otherwise.
std::optional<Similarity3> AlignPoints(const std::vector<Eigen::Vector3d>& src,
                                       const std::vector<Eigen::Vector3d>& dst, bool with_scale);

/// A length reconstructed and the same length as configured (mm).
using LengthPair = std::pair<double, double>;

struct LengthScaleFit {
  double scale = 1.0;             // s minimising sum (s * reconstructed - configured)^2
  double rms_mm = 0, max_mm = 0;  // of s * reconstructed - configured
};

/// Least-squares scale of reconstructed onto configured lengths (1 when there
/// are none) and its residuals: the scale check of labels and ArUco markers.
LengthScaleFit FitLengthScale(const std::vector<LengthPair>& lengths);

/// Residuals of `lengths` under a given scale (scale field = that scale).
LengthScaleFit LengthResiduals(double scale, const std::vector<LengthPair>& lengths);

/// RMS and max of |T(src[i]) - dst[i]| (mm).
void AlignmentResidual(const Similarity3& T, const std::vector<Eigen::Vector3d>& src,
                       const std::vector<Eigen::Vector3d>& dst, double* rms, double* max);

struct RansacRigidOptions {
  double inlier_mm = 2.0;    // a pair farther apart than this after the motion is an outlier
  int iterations = 2000;     // minimal (3-pair) samples tried
  uint64_t seed = 1;         // deterministic sampling
  double min_spread_mm = 5;  // a sample whose pairs are closer than this is degenerate
};

struct RansacRigidResult {
  Rigid3 T;                  // src -> dst, refitted on all inliers
  std::vector<int> inliers;  // indices of the pairs
  double rms_mm = 0;         // over the inliers
  double max_mm = 0;
};

/// Robust rigid motion from putative 3D-3D pairs (many wrong). nullopt when no
/// sample gives 3 or more inliers.
std::optional<RansacRigidResult> RansacRigid(const std::vector<Eigen::Vector3d>& src,
                                             const std::vector<Eigen::Vector3d>& dst,
                                             const RansacRigidOptions& opts = {});

}  // namespace aggscan::geom
