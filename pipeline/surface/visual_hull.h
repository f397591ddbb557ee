// The rock's visual hull from calibrated silhouettes, as one closed, manifold
// mesh (mm), in whatever object frame the views' poses are given in.
//
// Method:
//  1. Per view, the signed distance to the silhouette boundary in pixels
//     (positive inside), from two exact Euclidean distance transforms.
//  2. A field over space: at a point, each view's signed distance at the
//     point's projection, converted to millimetres at the point's depth
//     (px * z / f), and each half-space's signed distance (a side's turntable
//     top: the rock lies on it, nothing of it is below). The field is the
//     minimum over all of them: positive inside every cone and above every
//     floor, zero on the visual hull's surface, about a distance in mm.
//  3. A coarse grid over the search box finds the occupied region; a fine
//     grid over it evaluates the field only near the surface (elsewhere the
//     coarse field's sign is certain) and is contoured by marching
//     tetrahedra (six tetrahedra per cube around the main diagonal, shared
//     edge vertices), which gives a closed 2-manifold with the surface placed
//     between grid nodes by linear interpolation of the field.
//  The fine spacing follows the surface area seen on the coarse grid so that
//  the mesh has about `target_faces` faces.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <array>
#include <cstddef>
#include <cstdint>
#include <opencv2/core.hpp>
#include <vector>

#include "common/error.h"
#include "common/mesh.h"
#include "common/rig_calibration.h"

namespace aggscan {

struct SilhouetteView {
  cv::Mat mask;        // CV_8UC1, 0 background / 255 rock, at camera.width x camera.height
  CameraModel camera;  // lens for that resolution
  Eigen::Isometry3d cam_from_object = Eigen::Isometry3d::Identity();  // mm
};

/// Keeps points with normal . p + offset >= 0 (object frame, mm, unit normal).
struct HalfSpace {
  Eigen::Vector3d normal = Eigen::Vector3d::UnitZ();
  double offset = 0;
};

struct VisualHullOptions {
  double coarse_mm = 4.0;      // coarse grid spacing
  double voxel_mm = 0.0;       // fine grid spacing; 0 = chosen for target_faces
  int target_faces = 100000;   // about this many faces when voxel_mm is 0
  double min_voxel_mm = 0.35;  // lower bound of the chosen spacing
  int threads = 2;
};

struct VisualHullResult {
  Mesh mesh;
  double voxel_mm = 0;
  Eigen::AlignedBox3d box;        // bounds of the occupied region (object frame, mm)
  int64_t field_evaluations = 0;  // exact field evaluations (both grids)
  double seconds = 0;
};

/// Per-view signed distance to the silhouette boundary (CV_32F, px, positive
/// inside, +-0.5 at the pixel edges next to the boundary).
cv::Mat SilhouetteSignedDistance(const cv::Mat& mask);

/// Bilinear sample of a SilhouetteSignedDistance map at (u, v); outside the
/// image, the border value (at most 0) minus the distance to the border: the
/// image edge is background on the rig.
double SampleSignedDistance(const cv::Mat& sd, double u, double v);

/// The views whose masks disagree with the others, from each view's sole
/// carving (what its mask alone carves away of what every other view and the
/// floor hold to be rock) and the volume they all agree on, in any one unit:
/// those above median + 5 MAD of the views and over 5 % of the agreed volume.
/// A mask that lost part of the rock cuts that part out of the hull; a good
/// view carves alone only a thin shell at its outline.
std::vector<std::size_t> DisagreeingViews(const std::vector<double>& sole_carving, double agreed);

/// Carves the visual hull inside `search_box`. Errors: no views, a mask of
/// the wrong size or type, nothing left (the silhouettes do not intersect:
/// poses or masks are wrong), or the hull touching the search box (the rock
/// is not inside it: the box or the poses are wrong).
Result<VisualHullResult> CarveVisualHull(const std::vector<SilhouetteView>& views,
                                         const std::vector<HalfSpace>& floors,
                                         const Eigen::AlignedBox3d& search_box,
                                         const VisualHullOptions& opts = {});

}  // namespace aggscan
