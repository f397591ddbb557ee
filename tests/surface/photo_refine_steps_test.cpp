// The photo refinement's steps one at a time, on small synthetic scenes:
// flat grids for meshes, pinhole cameras 300 mm away, a plane with a random
// texture rendered by ray casting.
#include "pipeline/surface/photo_refine_steps.h"

#include <gtest/gtest.h>

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <functional>
#include <opencv2/imgproc.hpp>
#include <optional>
#include <vector>

namespace aggscan::photo_refine {
namespace {

// n x n vertices `spacing` mm apart in the plane z, centred on (0, 0), the
// faces counter-clockwise seen from +z (their outside).
Mesh Grid(int n, double spacing, double z) {
  Mesh m;
  const double x0 = -0.5 * (n - 1) * spacing;
  for (int r = 0; r < n; ++r)
    for (int c = 0; c < n; ++c) m.vertices.push_back({x0 + c * spacing, x0 + r * spacing, z});
  for (int r = 0; r + 1 < n; ++r) {
    for (int c = 0; c + 1 < n; ++c) {
      const int a = r * n + c, b = a + 1, d = a + n, e = d + 1;
      m.faces.push_back({a, b, e});
      m.faces.push_back({a, e, d});
    }
  }
  return m;
}

int Centre(int n) { return (n / 2) * n + n / 2; }

// b's vertices and faces appended to a's.
Mesh Join(Mesh a, const Mesh& b) {
  const int off = static_cast<int>(a.vertices.size());
  a.vertices.insert(a.vertices.end(), b.vertices.begin(), b.vertices.end());
  for (const auto& f : b.faces) a.faces.push_back({f[0] + off, f[1] + off, f[2] + off});
  return a;
}

// 320 x 240, 600 px focal length: 0.5 mm a pixel at 300 mm.
CameraModel Lens() {
  CameraModel c;
  c.width = 320;
  c.height = 240;
  c.fx = c.fy = 600;
  c.cx = 159.5;
  c.cy = 119.5;
  return c;
}

// A camera at `centre` looking at the origin.
Eigen::Isometry3d LookAtOrigin(const Eigen::Vector3d& centre) {
  const Eigen::Vector3d z = (-centre).normalized();
  const Eigen::Vector3d x = z.unitOrthogonal(), y = z.cross(x);
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  T.linear().row(0) = x.transpose();
  T.linear().row(1) = y.transpose();
  T.linear().row(2) = z.transpose();
  T.translation() = -T.linear() * centre;
  return T;
}

// Camera 300 mm from the origin, `deg` off +z towards +x.
Eigen::Vector3d Above(double deg) {
  const double a = deg * M_PI / 180;
  return 300 * Eigen::Vector3d(std::sin(a), 0, std::cos(a));
}

PhotoView FlatGreyView(const Eigen::Vector3d& centre) {
  PhotoView v;
  v.camera = Lens();
  v.cam_from_object = LookAtOrigin(centre);
  v.image = cv::Mat(v.camera.height, v.camera.width, CV_8UC1, cv::Scalar(128));
  return v;
}

// The plane z = 0 with a random texture (features about 1 mm across, grey
// 40..215, 0.25 mm texels over 100 x 100 mm), seen by a camera at `centre`.
PhotoView TexturedPlaneView(const Eigen::Vector3d& centre) {
  constexpr double kTexel = 0.25, kHalf = 50;
  static const cv::Mat tex = [] {
    const int n = static_cast<int>(2 * kHalf / kTexel);
    cv::Mat t(n, n, CV_32F);
    cv::RNG rng(12345);
    rng.fill(t, cv::RNG::UNIFORM, 0.0, 1.0);
    cv::GaussianBlur(t, t, cv::Size(0, 0), 2.0);
    cv::normalize(t, t, 40, 215, cv::NORM_MINMAX);
    return t;
  }();
  PhotoView v = FlatGreyView(centre);
  const CameraModel& c = v.camera;
  const Eigen::Matrix3d Rt = v.cam_from_object.linear().transpose();
  cv::Mat mx(c.height, c.width, CV_32F), my(c.height, c.width, CV_32F);
  for (int y = 0; y < c.height; ++y) {
    for (int x = 0; x < c.width; ++x) {
      const Eigen::Vector3d d = Rt * Eigen::Vector3d((x - c.cx) / c.fx, (y - c.cy) / c.fy, 1);
      const Eigen::Vector3d p = centre - (centre.z() / d.z()) * d;  // on z = 0
      mx.at<float>(y, x) = static_cast<float>((p.x() + kHalf) / kTexel);
      my.at<float>(y, x) = static_cast<float>((p.y() + kHalf) / kTexel);
    }
  }
  cv::Mat img;
  cv::remap(tex, img, mx, my, cv::INTER_LINEAR, cv::BORDER_REFLECT);
  img.convertTo(v.image, CV_8U);
  return v;
}

// A vertex under another surface is hidden from the camera above both; the
// same vertex without that surface, and one beside it, are seen.
TEST(PhotoRefineSteps, DepthMapHidesAVertexBehindAnotherSurface) {
  const Mesh floor = Grid(9, 5.0, 0.0);  // 40 x 40 mm
  const Mesh roof = Grid(3, 5.0, 10.0);  // 10 x 10 mm, 10 mm above its middle
  const Surface both = MakeSurface(Join(floor, roof));
  const PhotoRefineOptions opts;
  const PhotoView photo = FlatGreyView(Above(0));
  const Eigen::Vector3d under(0, 0, 0), beside(15, 15, 0), on_roof(0, 0, 10);
  ASSERT_EQ(MakeSurface(floor).V[Centre(9)], under);

  PreparedView with_roof = PrepareView(photo, opts);
  RasterizeDepth(both.V, both.F, &with_roof);
  EXPECT_FALSE(Unoccluded(with_roof, under, opts.depth_tolerance_mm));
  EXPECT_TRUE(Unoccluded(with_roof, beside, opts.depth_tolerance_mm));
  EXPECT_TRUE(Unoccluded(with_roof, on_roof, opts.depth_tolerance_mm));
  // The depth map there is the roof's: 290 mm from the camera, not 300.
  EXPECT_NEAR(with_roof.depth.at<float>(with_roof.depth.rows / 2, with_roof.depth.cols / 2), 290.0,
              1e-3);

  PreparedView floor_only = PrepareView(photo, opts);
  const Surface s = MakeSurface(floor);
  RasterizeDepth(s.V, s.F, &floor_only);
  EXPECT_TRUE(Unoccluded(floor_only, under, opts.depth_tolerance_mm));
}

// Views are chosen most frontal first, a view from nearly the direction of
// one already chosen is skipped, and one that sees the vertex too obliquely
// is never a candidate.
TEST(PhotoRefineSteps, ChooseViewsKeepsABaselineAndSkipsObliqueViews) {
  const Mesh floor = Grid(9, 5.0, 0.0);
  const Surface s = MakeSurface(floor);
  PhotoRefineOptions opts;
  opts.min_baseline_deg = 5;
  // 2 deg from the first: no baseline; 75 deg: cos 0.26 < min_cos 0.35.
  const std::vector<PhotoView> photos = {FlatGreyView(Above(20)), FlatGreyView(Above(3)),
                                         FlatGreyView(Above(1)), FlatGreyView(Above(75))};
  const std::vector<PreparedView> views = PrepareViews(photos, s, opts);
  const size_t i = Centre(9);
  ASSERT_EQ(s.N[i], Eigen::Vector3d::UnitZ());
  const std::vector<ViewPick> picks = ChooseViews(s.V[i], s.N[i], views, opts);
  ASSERT_EQ(picks.size(), 2u);
  EXPECT_EQ(picks[0].second, 2);  // 1 deg off the normal
  EXPECT_EQ(picks[1].second, 0);  // 20 deg; 3 deg is 2 from the reference
  EXPECT_NEAR(picks[0].first, std::cos(M_PI / 180), 1e-9);

  opts.min_baseline_deg = 1;  // 3 deg is now far enough from 1 deg
  const std::vector<ViewPick> close = ChooseViews(s.V[i], s.N[i], views, opts);
  ASSERT_EQ(close.size(), 3u);
  EXPECT_EQ(close[1].second, 1);
}

// A hull 0, 1.3 or 3 mm above a textured plane seen by two cameras 30 deg
// apart: the depth search puts the plane where it is, to a fraction of a
// step (0.2 mm), in every case.
TEST(PhotoRefineSteps, DepthSearchFindsATexturedPlaneBelowTheHull) {
  const std::vector<PhotoView> photos = {TexturedPlaneView(Above(-15)),
                                         TexturedPlaneView(Above(15))};
  const PhotoRefineOptions opts;
  for (double above : {0.0, 1.3, 3.0}) {
    SCOPED_TRACE(above);
    const Surface s = MakeSurface(Grid(21, 1.0, above));
    const std::vector<PreparedView> views = PrepareViews(photos, s, opts);
    const size_t i = Centre(21);
    const VertexDepth r = SearchVertexDepth(s, i, views, opts);
    ASSERT_TRUE(r.had_views);
    ASSERT_TRUE(r.depth_mm.has_value());
    EXPECT_NEAR(*r.depth_mm, above, 0.02);  // a tenth of a step

    // The peak is a clear one: the reference patch matches the other view
    // there, and not at the hull when the plane is deeper than a patch's
    // parallax can hide.
    const std::vector<ViewPick> picks = ChooseViews(s.V[i], s.N[i], views, opts);
    ASSERT_EQ(picks.size(), 2u);
    const Patch patch = MakePatch(s, i, views[picks[0].second], opts);
    EXPECT_NEAR(patch.spacing, 0.5, 0.01);  // one reference pixel at 300 mm
    EXPECT_LT(patch.quad.norm(), 1e-9);     // a plane has no curvature
    PatchScorer scorer(views, picks, patch, opts);
    EXPECT_GT(scorer.Score(above), 0.9);
    if (above > 2) {
      EXPECT_LT(scorer.Score(0.0), 0.5);
    }
  }
}

// Strided search: every other hypothesis, then around the best, finds the
// peak of a smooth score without scoring them all; unscored ones say so.
TEST(PhotoRefineSteps, StridedSearchFindsThePeakWithFewerScores) {
  PhotoRefineOptions opts;  // 0.2 mm steps to 15 mm, 3 outside the hull
  const DepthGrid grid = MakeDepthGrid(opts);
  EXPECT_EQ(grid.k_out, 3);
  EXPECT_EQ(grid.count, 76 + 3);
  int calls = 0;
  auto bump = [&](double d) {
    ++calls;
    // An NCC-like peak between two steps (4.2, 4.4 mm), a parabola near it.
    return std::max(-1.0, 0.95 - 0.1 * (d - 4.3) * (d - 4.3));
  };
  const std::vector<double> strided = SearchScores(bump, grid, 2);
  const int strided_calls = calls;
  calls = 0;
  const std::vector<double> every = SearchScores(bump, grid, 1);
  EXPECT_EQ(calls, grid.count);
  EXPECT_LT(strided_calls, grid.count / 2 + 4);
  EXPECT_EQ(std::count(strided.begin(), strided.end(), kNoScore), grid.count - strided_calls);
  // The hypotheses around the peak are scored, as in the full search.
  const int peak = grid.k_out + 22;  // 4.4 mm
  for (int k = peak - 2; k <= peak + 2; ++k) EXPECT_EQ(strided[k], every[k]) << k;
  const std::optional<double> d = PickDepth(strided, grid, opts);
  ASSERT_TRUE(d.has_value());
  EXPECT_NEAR(*d, 4.3, 1e-9);  // the parabola through a parabola's samples is exact
}

// A vertex's data: the sub-step peak when confident; a deep peak barely
// better than the hull gives the hull (0) when the hull itself matches, and
// nothing when it does not; no peak reaching min_ncc gives nothing.
TEST(PhotoRefineSteps, PickDepthKeepsOnlyConfidentPeaks) {
  PhotoRefineOptions opts;
  opts.outside_mm = 0;  // hypothesis k at k x 0.2 mm
  const DepthGrid grid = MakeDepthGrid(opts);
  ASSERT_EQ(grid.k_out, 0);
  auto scores = [&](double hull, int peak_k, double peak) {
    std::vector<double> s(grid.count, 0.1);
    s[0] = hull;
    s[peak_k] = peak;
    s[peak_k - 1] = s[peak_k + 1] = peak - 0.05;
    return s;
  };
  std::optional<double> d = PickDepth(scores(0.2, 10, 0.9), grid, opts);
  ASSERT_TRUE(d.has_value());
  EXPECT_NEAR(*d, 2.0, 1e-12);                                   // symmetric peak at k = 10
  EXPECT_EQ(PickDepth(scores(0.85, 10, 0.9), grid, opts), 0.0);  // gain 0.05 < 0.1
  EXPECT_EQ(PickDepth(scores(0.55, 10, 0.6), grid, opts), std::nullopt);  // nor the hull
  EXPECT_EQ(PickDepth(scores(0.2, 10, 0.5), grid, opts), std::nullopt);   // below min_ncc
  // A shallow peak (within near_hull_mm) needs no gain over the hull.
  d = PickDepth(scores(0.85, 2, 0.9), grid, opts);
  ASSERT_TRUE(d.has_value());
  EXPECT_NEAR(*d, 0.4, 1e-12);
}

// The regularisation keeps a constant field, fills a vertex without data
// from its neighbours, drops an outlier (so that it ends near its
// neighbours, not pulled only part way as one smoothing pass leaves it) and
// keeps the field within [0, max_depth_mm].
TEST(PhotoRefineSteps, RegularisationKeepsAConstantFieldAndDropsAnOutlier) {
  constexpr int kN = 11;
  const Surface s = MakeSurface(Grid(kN, 1.0, 0.0));
  const size_t nv = s.V.size(), centre = Centre(kN), corner = 0;
  DepthData data;
  data.depth_mm.assign(nv, 2.0);
  data.weight.assign(nv, 1.0);
  data.had_views.assign(nv, 1);
  PhotoRefineOptions opts;
  std::vector<double> field = RegulariseField(data, s.nb, opts);
  for (size_t i = 0; i < nv; ++i) EXPECT_EQ(field[i], 2.0) << i;

  data.depth_mm[centre] = 6.0;
  data.depth_mm[corner] = 0.0;
  data.weight[corner] = 0.0;  // no data there
  field = RegulariseField(data, s.nb, opts);
  EXPECT_NEAR(field[centre], 2.0, 0.01);
  EXPECT_NEAR(field[corner], 2.0, 0.01);
  for (int j : s.nb[centre]) EXPECT_NEAR(field[j], 2.0, 0.01) << j;

  opts.outlier_mm = 10;  // kept: smoothed but not dropped
  const std::vector<double> kept = RegulariseField(data, s.nb, opts);
  EXPECT_GT(kept[centre], 2.5);
  EXPECT_LT(kept[centre], 6.0);

  opts = PhotoRefineOptions{};
  data.depth_mm.assign(nv, opts.max_depth_mm + 5);
  data.weight.assign(nv, 1.0);
  field = RegulariseField(data, s.nb, opts);
  EXPECT_EQ(field[centre], opts.max_depth_mm);
  data.depth_mm.assign(nv, -0.4);  // data outside the hull, as outside_mm allows
  field = RegulariseField(data, s.nb, opts);
  EXPECT_EQ(field[centre], 0.0);
}

// The hull's convex curvature, on grids bent into a cap (a sphere's, radius
// 20 mm), a cylinder's side (radius 20 mm), a bowl and a plane: 1 / R where
// convex in some direction, none where it is convex in no direction.
TEST(PhotoRefineSteps, HullConvexCurvatureIsOneOverTheSmallestConvexRadius) {
  constexpr int kN = 41;
  constexpr double kR = 20.0;
  auto bent = [&](double sx, double sy) {
    Mesh m = Grid(kN, 0.5, 0);
    for (auto& v : m.vertices) v[2] = -(sx * v[0] * v[0] + sy * v[1] * v[1]) / (2 * kR);
    return MakeSurface(m);
  };
  const size_t c = Centre(kN);
  EXPECT_NEAR(HullConvexCurvature(bent(1, 1), c, 8.0), 1 / kR, 0.05 / kR);  // cap
  EXPECT_NEAR(HullConvexCurvature(bent(1, 0), c, 8.0), 1 / kR, 0.05 / kR);  // cylinder
  EXPECT_NEAR(HullConvexCurvature(bent(-1, -1), c, 8.0), 0.0, 1e-9);        // bowl
  EXPECT_NEAR(HullConvexCurvature(bent(0, 0), c, 8.0), 0.0, 1e-6);          // plane
  // A tighter cap than the reach can tell is held at 1 / reach.
  Mesh tight = Grid(kN, 0.25, 0);
  for (auto& v : tight.vertices) v[2] = -(v[0] * v[0] + v[1] * v[1]) / (2 * 3.0);
  EXPECT_NEAR(HullConvexCurvature(MakeSurface(tight), c, 8.0), 1 / 8.0, 1e-9);

  // The curvature is asked for only when the depth and the options leave
  // the verdict to it (it fits a quadric).
  int asked = 0;
  auto k = [&](double v) {
    return std::function<double()>([&asked, v] {
      ++asked;
      return v;
    });
  };
  PhotoRefineOptions opts;
  EXPECT_EQ(opts.highlight_depth_ratio, 0.0);  // off unless asked for
  EXPECT_FALSE(LooksLikeHighlight(8.0, k(1 / kR), opts));
  opts.highlight_depth_ratio = 0.3;
  EXPECT_FALSE(LooksLikeHighlight(0.4, k(1.0), opts));  // a near-hull peak is never one
  EXPECT_EQ(asked, 0);
  EXPECT_TRUE(LooksLikeHighlight(8.0, k(1 / kR), opts));   // 0.4 R deep under a 20 mm cap
  EXPECT_FALSE(LooksLikeHighlight(5.0, k(1 / kR), opts));  // 0.25 R
  EXPECT_FALSE(LooksLikeHighlight(12.0, k(0.0), opts));    // under flat hull: a hollow
  EXPECT_EQ(asked, 3);
  opts.highlight_depth_ratio = -0.1;
  EXPECT_FALSE(opts.Check().empty());
}

}  // namespace
}  // namespace aggscan::photo_refine
