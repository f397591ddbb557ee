// The steps of RefineByPhotoConsistency (photo_refine.h describes the method
// and its options), one function each, so that a test can run one step on a
// small synthetic input. RefineByPhotoConsistency is these steps in
// this order and nothing else:
//   CheckInputs, MakeSurface, PrepareViews (PrepareView, RasterizeDepth),
//   ChooseScoredVertices, SearchDepths (per vertex SearchVertexDepth:
//   ChooseViews, MakePatch, PatchScorer, SearchScores, PickDepth),
//   RegulariseField, ChooseMoveDirections, MoveVertices, SmoothMovedRegion,
//   Summarise.
// Lengths are in mm, angles off a normal as cosines, scores are mean NCC.
#pragma once

#include <Eigen/Core>
#include <array>
#include <cstdint>
#include <functional>
#include <opencv2/core.hpp>
#include <optional>
#include <utility>
#include <vector>

#include "common/error.h"
#include "common/mesh.h"
#include "common/rig_calibration.h"
#include "pipeline/surface/photo_refine.h"

namespace aggscan::photo_refine {

using Vec3 = Eigen::Vector3d;
using Faces = std::vector<std::array<int, 3>>;
using Rings = std::vector<std::vector<int>>;

/// Score of a hypothesis that could not be scored: below any NCC (>= -1).
inline constexpr double kNoScore = -2.0;

/// Options valid, at least two views, each image and mask usable; the error
/// names every problem of the options, or the first view at fault.
Status CheckInputs(const std::vector<PhotoView>& views, const PhotoRefineOptions& opts);

/// The hull as the steps see it.
struct Surface {
  std::vector<Vec3> V;  // vertices
  Faces F;              // counter-clockwise seen from outside
  Rings nb;             // each vertex's 1-ring, sorted
  // Unit normals: area-weighted, then 3 passes of 1-ring averaging (the
  // hull's facets are voxel-noisy). A vertex in no face gets +z.
  std::vector<Vec3> N;
};
Surface MakeSurface(const Mesh& hull);

/// A view ready for sampling: grey float image (scaled, blurred), its lens,
/// the pose split into rotation and translation, and the current mesh's
/// depth map.
struct PreparedView {
  cv::Mat grey;  // CV_32F
  CameraModel cam;
  Eigen::Matrix3d R;
  Vec3 t;
  Vec3 centre;    // camera centre, object frame
  cv::Mat depth;  // CV_32F, +inf where empty, at cam / depth_map_downscale
  CameraModel depth_cam;
  cv::Mat mask;  // CV_8UC1 at cam's size (nonzero: rock), or empty
};

/// One view scaled, grey, blurred, its mask at the working scale, its depth
/// map's lens (at least 8 x 8 pixels); `depth` is left empty.
PreparedView PrepareView(const PhotoView& v, const PhotoRefineOptions& opts);
/// Z-buffer of the mesh (camera z) in pv's depth_cam, triangles filled at
/// pixel centres; no back-face culling: the nearest surface is what occludes.
void RasterizeDepth(const std::vector<Vec3>& V, const Faces& F, PreparedView* pv);
/// Every view prepared and rasterised, opts.threads at a time.
std::vector<PreparedView> PrepareViews(const std::vector<PhotoView>& views, const Surface& s,
                                       const PhotoRefineOptions& opts);

/// Whether `q` sees p unoccluded: p projects into its depth map, and its
/// camera z is at most depth_tolerance_mm behind the map's surface there.
bool Unoccluded(const PreparedView& q, const Vec3& p, double depth_tolerance_mm);

/// The vertices to score (1): every vertex for sample_rings 0; otherwise
/// greedily in index order, each blocking its rings up to sample_rings.
std::vector<char> ChooseScoredVertices(const Rings& nb, int sample_rings);

/// A view chosen for a vertex: (cosine of its angle off the normal, index).
using ViewPick = std::pair<double, int>;
/// The views that see p frontally (cosine >= min_cos) and unoccluded, most
/// frontal first, each at least min_baseline_deg from those before it as
/// seen from p, at most views_per_vertex; the first is the reference. Fewer
/// than two: empty or the one, nothing to compare.
std::vector<ViewPick> ChooseViews(const Vec3& p, const Vec3& n,
                                  const std::vector<PreparedView>& views,
                                  const PhotoRefineOptions& opts);

/// The square patch around a vertex on the hull.
struct Patch {
  Vec3 p, n;       // centre on the hull, unit normal
  Vec3 t1, t2;     // tangent basis
  double spacing;  // mm between samples: about patch_spacing_px reference pixels
  // Local quadric (A, B, C) of the hull in (t1, t2): heights -(A x^2 + 2 B x y
  // + C y^2) / 2; zero for a tangent-plane patch.
  Eigen::Vector3d quad = Eigen::Vector3d::Zero();
  int radius = 0;  // (2 radius + 1)^2 samples
};
Patch MakePatch(const Surface& s, size_t i, const PreparedView& ref,
                const PhotoRefineOptions& opts);

/// Scores depth hypotheses of one patch: the mean NCC of the reference
/// view's samples against each other chosen view's (over their samples on
/// the rock in both, with masks). Reuses its sample buffers between calls;
/// views, picks and patch are referenced, not copied: they must outlive it.
class PatchScorer {
 public:
  PatchScorer(const std::vector<PreparedView>& views, const std::vector<ViewPick>& picks,
              const Patch& patch, const PhotoRefineOptions& opts);
  /// The patch moved depth_mm inward along n (negative: outward); kNoScore
  /// when the reference patch leaves its image or no other view compares.
  double Score(double depth_mm);

 private:
  const std::vector<PreparedView>& views_;
  const std::vector<ViewPick>& picks_;
  const Patch& patch_;
  int ns_;           // samples per view
  int min_on_rock_;  // samples on the rock in both views for a pair to count
  std::vector<float> samples_;
  std::vector<uint8_t> on_rock_;
  std::vector<char> ok_;
};

/// The depth hypotheses: k in [0, count) at depth (k - k_out) step_mm, k_out
/// steps outside the hull so that a peak at the hull gets its sub-step
/// position.
struct DepthGrid {
  int k_out = 0;
  int count = 0;
  double step_mm = 0;
};
DepthGrid MakeDepthGrid(const PhotoRefineOptions& opts);

/// Every stride-th hypothesis (k_out's among them), then those within a
/// stride of the best until the best stays put; stride 1: every one. Returns
/// the scores, kNoScore where not scored.
std::vector<double> SearchScores(const std::function<double(double depth_mm)>& score,
                                 const DepthGrid& grid, int stride);

/// The vertex's depth from its scores, sub-step by a parabola through the
/// peak; none unless confident (best >= min_ncc and, for a peak deeper than
/// near_hull_mm, min_gain above the hull's score: failing that, 0 when the
/// hull itself scores min_ncc). Negative only with outside_mm > 0.
std::optional<double> PickDepth(const std::vector<double>& score, const DepthGrid& grid,
                                const PhotoRefineOptions& opts);

/// The hull's largest convex curvature at vertex i (1/mm, >= 0; at most
/// 1 / reach_mm): the local quadric over the vertices within reach_mm; 0
/// where the hull is convex in no direction.
double HullConvexCurvature(const Surface& s, size_t i, double reach_mm);

/// A confident peak this deep is a highlight's when deeper than near_hull_mm
/// and than highlight_depth_ratio / k, k the hull's largest convex curvature
/// there (PhotoRefineOptions::highlight_depth_ratio; never when 0).
/// `curvature` is called only when the depth and the options leave it to k.
bool LooksLikeHighlight(double depth_mm, const std::function<double()>& curvature,
                        const PhotoRefineOptions& opts);

struct VertexDepth {
  bool had_views = false;          // at least two views to compare
  std::optional<double> depth_mm;  // confident data, inward
  bool highlight = false;          // a confident peak refused as a highlight's
};
VertexDepth SearchVertexDepth(const Surface& s, size_t i, const std::vector<PreparedView>& views,
                              const PhotoRefineOptions& opts);

/// Per vertex: the data for the regularisation.
struct DepthData {
  std::vector<double> depth_mm;  // 0 without data
  std::vector<double> weight;    // 1 with data, else 0
  std::vector<char> had_views;
  std::vector<char> highlight;  // VertexDepth::highlight
};
/// SearchVertexDepth over the `scored` vertices, opts.threads at a time.
DepthData SearchDepths(const Surface& s, const std::vector<PreparedView>& views,
                       const std::vector<char>& scored, const PhotoRefineOptions& opts);

/// The displacement field: data-weighted Laplacian smoothing (x_i <- (w_i d_i
/// + lambda mean_j x_j) / (w_i + lambda), smooth_iterations passes), data
/// farther than outlier_mm from it dropped, smoothed again from there,
/// clamped to [0, max_depth_mm].
std::vector<double> RegulariseField(const DepthData& data, const Rings& nb,
                                    const PhotoRefineOptions& opts);

/// Unit move directions: N smoothed over about reach x the vertex's move
/// (k 1-ring passes spread a normal over about e sqrt(k), e the mean edge).
struct MoveDirections {
  std::vector<Vec3> dir;
  int max_passes = 0;  // most smoothing passes a direction took
};
MoveDirections ChooseMoveDirections(const Surface& s, const std::vector<double>& field,
                                    double move_reach);

/// Which faces of moved positions turned more than max_face_turn_deg from
/// the hull's, or collapsed (|cross product| <= 1e-12 mm^2). References s's
/// faces: s must outlive it.
class FoldTest {
 public:
  FoldTest(const Surface& s, double max_face_turn_deg);
  /// The number of such faces in X (same faces as the hull); *bad marks
  /// their vertices.
  int Find(const std::vector<Vec3>& X, std::vector<char>* bad) const;

 private:
  const Faces& F_;
  std::vector<Vec3> fn0_;  // the hull's unit face normals
  double cos_turn_;
};

/// Vertices moved by field along dirs, folds undone: folding vertices go to
/// their neighbours' centroid (never outward of the hull), up to
/// untangle_passes, then what still folds is pulled back towards the hull.
struct MovedVertices {
  std::vector<Vec3> W;
  int64_t faces_folded = 0;  // before undoing
  int untangle_passes = 0;
  int fold_passes = 0;  // pull-back passes
};
MovedVertices MoveVertices(const Surface& s, const std::vector<double>& field,
                           const std::vector<Vec3>& dirs, const FoldTest& folds,
                           int untangle_passes);

/// Taubin smoothing (0.5 | -0.53) of the vertices that moved (field > 0.05),
/// no vertex outward of the hull, undone at vertices of faces it folds.
std::vector<Vec3> SmoothMovedRegion(const Surface& s, const std::vector<double>& field,
                                    std::vector<Vec3> W, const FoldTest& folds, int iterations);

/// res's mesh (s's faces, W) and counts and displacements (moved: > 0.05 mm);
/// leaves the pass counts and seconds alone.
void Summarise(const Surface& s, const DepthData& data, const std::vector<Vec3>& W,
               PhotoRefineResult* res);

}  // namespace aggscan::photo_refine
