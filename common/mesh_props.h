// Ground-truth 3D morphology of a closed triangle mesh, as defined by the
// source study (Huang et al.): volume, surface area, principal dimensions
// a <= b <= c from the minimum-volume bounding box, 3D flat-and-elongated
// ratio c/a and Wadell sphericity cbrt(36*pi*V^2)/A. Used for the sim's
// truth.json and for checking the reconstruction's morphology.
#pragma once

#include <array>
#include <nlohmann/json.hpp>
#include <vector>

#include "common/mesh.h"

namespace aggscan {

using Vec3d = std::array<double, 3>;

struct MeshProps {
  double volume_mm3 = 0.0;        // divergence theorem; |signed volume| (orientation-independent)
  double surface_area_mm2 = 0.0;  // sum of triangle areas
  double a_mm = 0.0;              // shortest side of the minimum-volume oriented bounding box
  double b_mm = 0.0;              // middle side
  double c_mm = 0.0;              // longest side
  double sphericity = 0.0;        // Wadell: cbrt(36*pi*V^2)/A (sphere 1, cube 0.806); 0 if A == 0
  double fer_3d = 0.0;            // flat-and-elongated ratio c/a; 0 if a == 0
  double c_over_b = 0.0;          // elongation; 0 if b == 0
  double b_over_a = 0.0;          // flatness; 0 if a == 0
  // The smallest other locally minimal box whose sorted sides differ from
  // a, b, c by more than kBoxDistinct: a rounded rock may have two boxes of
  // nearly the same volume and different shape, and which one is the
  // minimum then turns on a fraction of a percent of the surface (a, b, c
  // are ill-conditioned). Ratio 0: no such box found.
  double second_box_volume_ratio = 0.0;  // its volume / the minimum's (>= 1)
  double second_a_mm = 0.0, second_b_mm = 0.0, second_c_mm = 0.0;
  // Every distinct box the search found within kBoxAmbiguousVolume of the
  // minimum's volume (the second box among them when it is that near),
  // smallest first: the a, b, c a reconstruction good to 1 % may report.
  struct NearBox {
    double a_mm = 0, b_mm = 0, c_mm = 0;
    double volume_ratio = 0;  // its volume / the minimum's
  };
  std::vector<NearBox> near_boxes;
};

/// Sides of two boxes differing by more than this (relative) make them distinct shapes.
inline constexpr double kBoxDistinct = 0.02;
/// A second box within this (relative) of the minimum's volume makes a, b, c
/// ill-conditioned: a reconstruction good to 1 % in volume may pick either.
inline constexpr double kBoxAmbiguousVolume = 0.01;
inline bool BoxIllConditioned(const MeshProps& p) {
  return p.second_box_volume_ratio > 0 && p.second_box_volume_ratio <= 1 + kBoxAmbiguousVolume;
}

/// An oriented box: centre, three orthonormal axes and the full side length
/// along each axis (not sorted).
struct OrientedBox {
  Vec3d center{};
  std::array<Vec3d, 3> axes{};
  Vec3d size{};
  double Volume() const { return size[0] * size[1] * size[2]; }
};

/// Volume, area and the minimum-volume box of `mesh` (mm). A mesh with
/// misoriented faces gets a meaningless volume; open meshes likewise.
MeshProps ComputeMeshProps(const Mesh& mesh);

/// The figures as JSON with units in the names (volume_mm3, surface_area_mm2,
/// a_mm, b_mm, c_mm, fer_3d, ratio_c_b, ratio_b_a, sphericity): the one
/// spelling `aggscan morph --json` and results/morphology.json share.
nlohmann::json MeshPropsJson(const MeshProps& p);

/// Taubin's lambda|mu smoothing of the vertex positions (topology untouched):
/// each pass pair moves every vertex by lambda, then mu (< -lambda), times the
/// offset to its neighbours' mean, which removes ripples a few edges long
/// without the shrinkage of plain Laplacian smoothing.
void TaubinSmooth(Mesh* mesh, int iterations, double lambda = 0.5, double mu = -0.53);

/// Signed volume (positive for outward-facing counter-clockwise faces).
double SignedVolume(const Mesh& mesh);
double SurfaceArea(const Mesh& mesh);

/// Convex hull of points (Qhull, triangulated), faces outward. Returns false when the
/// points are degenerate (fewer than 4 not coplanar); `hull` is then empty.
bool ConvexHull(const std::vector<Vec3d>& points, Mesh* hull);

/// Approximately minimum-volume box enclosing `points`. Candidate box axes:
/// every hull face normal (a box face flush with a hull face), the normal to
/// every pair of hull edge directions on small hulls (catches e.g. the cube
/// around a regular tetrahedron), the principal axes; for each axis the
/// other two come from the exact minimum-area rectangle of the projected hull
/// (rotating calipers); the best few are then refined by a local search over
/// the axis direction. Large hulls are searched on a subset of extreme
/// points first and refined on the whole hull.
OrientedBox MinVolumeBox(const std::vector<Vec3d>& points);

/// The distinct locally minimal boxes the same search reaches from its
/// `starts` best candidate boxes, smallest volume first; front() is
/// MinVolumeBox's box.
std::vector<OrientedBox> MinVolumeBoxes(const std::vector<Vec3d>& points, int starts);

/// `n` unit directions spread nearly evenly over the sphere, or over the half
/// z >= 0 when `half` (a Fibonacci lattice: no randomness, same every call).
std::vector<Vec3d> FibonacciDirections(int n, bool half = false);

/// Minimum-area rectangle enclosing 2D points (exact, rotating calipers on
/// the convex hull). Returns the area; `dir` is the unit direction of one
/// side, `w` and `h` the side lengths along dir and its left normal, `lo`
/// the minimum coordinates along (dir, normal).
double MinAreaRect(const std::vector<std::array<double, 2>>& points, std::array<double, 2>* dir,
                   double* w, double* h, std::array<double, 2>* lo);

}  // namespace aggscan
