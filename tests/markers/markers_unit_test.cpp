// Geometry helpers and the stitch decisions on synthetic data (no rendering).
#include <gtest/gtest.h>

#include <cmath>
#include <opencv2/imgproc.hpp>
#include <random>

#include "pipeline/core/geometry.h"
#include "pipeline/markers/markers.h"
#include "pipeline/markers/view_evidence.h"
#include "pipeline/stitch/stitch.h"

namespace aggscan {
namespace {

using Eigen::Vector2d;
using Eigen::Vector3d;

CameraModel RigLikeCamera() {
  CameraModel c;
  c.width = 2016, c.height = 1512;
  c.fx = c.fy = 2769.0, c.cx = 1007.5, c.cy = 755.5;
  c.k1 = -0.08, c.k2 = 0.02, c.p1 = 1e-4, c.p2 = -2e-4;
  return c;
}

// A camera 650 mm from the origin looking at it from 35 deg up, turned by a.
geom::Rigid3 LookAtOrigin(double a_deg) {
  const double el = 35.0 * M_PI / 180, az = a_deg * M_PI / 180;
  const Vector3d C(650 * std::cos(el) * std::cos(az), 650 * std::cos(el) * std::sin(az),
                   650 * std::sin(el));
  const Vector3d z = (-C).normalized(), x = z.cross(Vector3d::UnitZ()).normalized(), y = z.cross(x);
  geom::Rigid3 T;
  T.R.row(0) = x, T.R.row(1) = y, T.R.row(2) = z;
  T.t = -(T.R * C);
  return T;
}

TEST(Geometry, UndistortInvertsTheLens) {
  const CameraModel cam = RigLikeCamera();
  double worst = 0;
  for (double u = 0; u <= 2015; u += 125) {
    for (double v = 0; v <= 1511; v += 125) {
      const Vector2d und = geom::UndistortPixel(cam, {u, v});
      double uu = 0, vv = 0;
      cam.Project({(und.x() - cam.cx) / cam.fx, (und.y() - cam.cy) / cam.fy, 1.0}, &uu, &vv);
      worst = std::max(worst, (Vector2d(uu, vv) - Vector2d(u, v)).norm());
    }
  }
  EXPECT_LT(worst, 1e-6);
}

TEST(Geometry, TriangulatesThroughNoiseAndOutliers) {
  const CameraModel cam = RigLikeCamera();
  const Vector3d X(12.0, -30.0, 41.0);
  std::mt19937 rng(3);
  std::normal_distribution<double> noise(0.0, 0.3);
  std::vector<geom::Sighting> s;
  for (int i = 0; i < 12; ++i) {
    const geom::Rigid3 pose = LookAtOrigin(30.0 * i);
    Vector2d px = *geom::ProjectPoint(cam, pose, X) + Vector2d(noise(rng), noise(rng));
    if (i == 4 || i == 9) px += Vector2d(25, -14);  // two gross outliers
    s.push_back(geom::MakeSighting(cam, pose, px, i));
  }
  Result<geom::TriangulatedPoint> t = geom::TriangulatePoint(s);
  ASSERT_TRUE(t.ok()) << t.error().ToString();
  EXPECT_LT((t->X - X).norm(), 0.1);
  EXPECT_EQ(t->inliers.size(), 10u);
  EXPECT_LT(t->rms_px, 0.6);
  EXPECT_GT(t->residual_px[4], 20.0);

  // One view, or two views from the same place: no point.
  EXPECT_FALSE(geom::TriangulatePoint({s[0]}).ok());
  EXPECT_FALSE(geom::TriangulatePoint({s[0], s[0]}).ok());
}

TEST(Geometry, AlignsWithAndWithoutScale) {
  std::mt19937 rng(5);
  std::uniform_real_distribution<double> u(-100, 100);
  geom::Similarity3 truth;
  truth.scale = 0.037;
  truth.R = Eigen::AngleAxisd(0.7, Vector3d(1, 2, 3).normalized()).toRotationMatrix();
  truth.t = Vector3d(5, -2, 9);
  std::vector<Vector3d> a, b;
  for (int i = 0; i < 6; ++i) {
    a.emplace_back(u(rng), u(rng), u(rng));
    b.push_back(truth.Apply(a.back()));
  }
  const std::optional<geom::Similarity3> s = geom::AlignPoints(a, b, true);
  ASSERT_TRUE(s);
  EXPECT_NEAR(s->scale, truth.scale, 1e-9);
  EXPECT_LT(geom::RotationAngleDeg(s->R * truth.R.transpose()), 1e-6);
  EXPECT_LT((s->t - truth.t).norm(), 1e-9);
  // Collinear points leave a rotation free.
  EXPECT_FALSE(geom::AlignPoints({{0, 0, 0}, {1, 1, 1}, {2, 2, 2}},
                                 {{0, 0, 0}, {1, 1, 1}, {2, 2, 2}}, false));
}

TEST(Geometry, RansacRigidIgnoresHalfWrongPairs) {
  std::mt19937 rng(9);
  std::uniform_real_distribution<double> u(-60, 60);
  std::normal_distribution<double> n(0, 0.2);
  geom::Rigid3 truth;
  truth.R = Eigen::AngleAxisd(2.5, Vector3d(0.3, -1, 0.2).normalized()).toRotationMatrix();
  truth.t = Vector3d(4, 8, -30);
  std::vector<Vector3d> a, b;
  for (int i = 0; i < 200; ++i) {
    a.emplace_back(u(rng), u(rng), u(rng));
    b.push_back(i % 2 ? Vector3d(u(rng), u(rng), u(rng))
                      : Vector3d(truth.Apply(a.back()) + Vector3d(n(rng), n(rng), n(rng))));
  }
  const std::optional<geom::RansacRigidResult> r = geom::RansacRigid(a, b);
  ASSERT_TRUE(r);
  EXPECT_GE(r->inliers.size(), 99u);
  EXPECT_LE(r->inliers.size(), 103u);
  EXPECT_LT(geom::RotationAngleDeg(r->T.R * truth.R.transpose()), 0.1);
  EXPECT_LT(r->rms_mm, 0.5);
}

SideMarkers MarkersAt(const std::vector<Vector3d>& p) {
  SideMarkers s;
  const char* names[4][2] = {
      {"purple", "head"}, {"purple", "tail"}, {"red", "head"}, {"red", "tail"}};
  for (size_t i = 0; i < 4; ++i) {
    MarkerPoint m;
    m.color = names[i][0], m.segment = names[i][1];
    m.located = i < p.size() && p[i].allFinite();
    if (m.located) m.position = p[i];
    if (!m.located) m.problem = "the marker was not seen in any of the 30 views";
    s.points.push_back(m);
  }
  return s;
}

TEST(StitchUnit, MarkersFitDropTheBadPointAndRefuseTwo) {
  geom::Rigid3 truth;
  truth.R = Eigen::AngleAxisd(2.0, Vector3d(0.2, 1, 0.1).normalized()).toRotationMatrix();
  truth.t = Vector3d(3, -4, 60);
  const std::vector<Vector3d> side2{{40, 10, 30}, {45, -10, 28}, {-38, 12, 25}, {-42, -8, 31}};
  std::vector<Vector3d> side1;
  for (const Vector3d& p : side2) side1.push_back(truth.Apply(p));
  StitchEstimate e = StitchFromMarkers(MarkersAt(side1), MarkersAt(side2));
  ASSERT_TRUE(e.valid) << e.note;
  EXPECT_EQ(e.inliers, 4);
  EXPECT_LT(geom::RotationAngleDeg(e.T.R * truth.R.transpose()), 1e-6);
  EXPECT_GT(e.rotation_sigma_deg, 0.2);  // head-tail ~20 mm apart: a weak axis

  side1[1] += Vector3d(0, 6, 0);  // a bent tail located 6 mm off
  e = StitchFromMarkers(MarkersAt(side1), MarkersAt(side2));
  ASSERT_TRUE(e.valid) << e.note;
  EXPECT_EQ(e.inliers, 3);
  EXPECT_NE(e.note.find("dropped purple tail"), std::string::npos) << e.note;

  const Vector3d nan = Vector3d::Constant(NAN);
  e = StitchFromMarkers(MarkersAt({side1[0], nan, side1[2], nan}), MarkersAt(side2));
  EXPECT_FALSE(e.valid);
  EXPECT_NE(e.note.find("only 2 marker points"), std::string::npos) << e.note;
}

// Synthetic feature clouds: random points and descriptors, the moving side a
// moved copy of part of the reference with a few fresh points.
void MakeClouds(const geom::Rigid3& truth, int shared, FeatureCloud* ref, FeatureCloud* mov) {
  std::mt19937 rng(21);
  std::uniform_real_distribution<double> u(-50, 50);
  std::uniform_real_distribution<float> d(0, 100);
  std::normal_distribution<double> n(0, 0.2);
  const geom::Rigid3 inv = truth.Inverse();
  std::vector<cv::Mat> rr, mr;
  for (int i = 0; i < 300; ++i) {
    const Vector3d p(u(rng), u(rng), u(rng));
    cv::Mat desc(1, 128, CV_32F);
    for (int k = 0; k < 128; ++k) desc.at<float>(k) = d(rng);
    ref->points.push_back(p);
    rr.push_back(desc);
    ref->point_of_row.push_back(i);
    if (i < shared) {
      mov->points.push_back(inv.Apply(p) + Vector3d(n(rng), n(rng), n(rng)));
      cv::Mat dm = desc + 3.0f;  // a similar descriptor from another viewpoint
      mr.push_back(dm);
      mov->point_of_row.push_back(static_cast<int>(mov->points.size()) - 1);
    }
  }
  cv::vconcat(rr, ref->descriptors);
  if (!mr.empty()) cv::vconcat(mr, mov->descriptors);
}

TEST(StitchUnit, FeaturesWhenMarkersAreMissingAndAnErrorWhenNeither) {
  geom::Rigid3 truth;
  truth.R = Eigen::AngleAxisd(2.6, Vector3d(1, 0.1, 0).normalized()).toRotationMatrix();
  truth.t = Vector3d(0, 5, 70);
  FeatureCloud ref, mov;
  MakeClouds(truth, 80, &ref, &mov);
  const Vector3d nan = Vector3d::Constant(NAN);
  const SideMarkers s1 = MarkersAt({{40, 10, 30}, {45, -10, 28}, {-38, 12, 25}, {-42, -8, 31}});
  const SideMarkers s2 = MarkersAt({{1, 2, 3}, {4, 5, 6}, nan, nan});
  Result<StitchResult> r = StitchSides(s1, s2, &ref, &mov);
  ASSERT_TRUE(r.ok()) << r.error().ToString();
  EXPECT_EQ(r->source, "features");
  EXPECT_FALSE(r->markers.valid);
  EXPECT_GE(r->features.inliers, 75);
  EXPECT_LT(geom::RotationAngleDeg(r->T.R * truth.R.transpose()), 0.2);

  FeatureCloud few_ref, few_mov;
  MakeClouds(truth, 5, &few_ref, &few_mov);
  r = StitchSides(s1, s2, &few_ref, &few_mov);
  ASSERT_FALSE(r.ok());
  EXPECT_EQ(r.error().cls, ErrorClass::kInvalidArgument);
  const std::string msg = r.error().ToString();
  EXPECT_NE(msg.find("stitch: only 2 marker points"), std::string::npos) << msg;
  EXPECT_NE(msg.find("Re-shoot side 2"), std::string::npos) << msg;
  EXPECT_NE(msg.find("red head"), std::string::npos) << msg;
}

// Clouds of a rock seen across the flip: points on a 40 mm sphere, the
// moving side a moved, noisy copy of some of them. Most shared points have a
// look-alike elsewhere on the rock (grain that repeats: its descriptor as
// near the moving sighting as the true one's), so a ratio test over the whole
// rock keeps only the few without one (`unique`).
struct FlipClouds {
  FeatureCloud ref, mov;
};
FlipClouds MakeFlipClouds(const geom::Rigid3& truth, int shared, int unique) {
  std::mt19937 rng(5);
  std::normal_distribution<double> g(0, 1);
  std::uniform_real_distribution<float> d(0, 100);
  std::normal_distribution<float> view_change(0, 6);
  auto on_sphere = [&] {
    const Vector3d v(g(rng), g(rng), g(rng));
    return Vector3d(40 * v.normalized());
  };
  auto descriptor = [&] {
    cv::Mat m(1, 128, CV_32F);
    for (int k = 0; k < 128; ++k) m.at<float>(k) = d(rng);
    return m;
  };
  auto seen_again = [&](const cv::Mat& m) {
    cv::Mat o = m.clone();
    for (int k = 0; k < 128; ++k) o.at<float>(k) += view_change(rng);
    return o;
  };
  FlipClouds c;
  std::vector<cv::Mat> rr, mr;
  auto add_ref = [&](const Vector3d& p, const cv::Mat& m) {
    c.ref.point_of_row.push_back(static_cast<int>(c.ref.points.size()));
    c.ref.points.push_back(p);
    rr.push_back(m);
  };
  const geom::Rigid3 inv = truth.Inverse();
  std::normal_distribution<double> noise(0, 0.15);
  for (int i = 0; i < shared; ++i) {
    const Vector3d p = on_sphere();
    const cv::Mat m = descriptor();  // the patch; each sighting sees it changed
    add_ref(p, seen_again(m));
    c.mov.point_of_row.push_back(static_cast<int>(c.mov.points.size()));
    c.mov.points.push_back(inv.Apply(p) + Vector3d(noise(rng), noise(rng), noise(rng)));
    mr.push_back(seen_again(m));
    if (i >= unique) {
      Vector3d q = on_sphere();
      while ((q - p).norm() < 30) q = on_sphere();
      add_ref(q, seen_again(m));  // the look-alike
    }
  }
  for (int i = 0; i < 500; ++i) add_ref(on_sphere(), descriptor());  // the rest of side 1
  for (int i = 0; i < 150; ++i) {                                    // side 2 only
    c.mov.point_of_row.push_back(static_cast<int>(c.mov.points.size()));
    c.mov.points.push_back(inv.Apply(on_sphere()));
    mr.push_back(descriptor());
  }
  cv::vconcat(rr, c.ref.descriptors);
  cv::vconcat(mr, c.mov.descriptors);
  return c;
}

geom::Rigid3 Turned(const geom::Rigid3& T, double deg, const Vector3d& axis) {
  geom::Rigid3 d;
  d.R = Eigen::AngleAxisd(deg * M_PI / 180, axis.normalized()).toRotationMatrix();
  return d * T;  // about side 1's origin, the cloud's centre
}

TEST(StitchUnit, GuidedMatchingFindsTheMatchesLookAlikesHideFromTheGlobalRatioTest) {
  geom::Rigid3 truth;
  truth.R = Eigen::AngleAxisd(2.8, Vector3d(0.9, 0.3, 0.1).normalized()).toRotationMatrix();
  truth.t = Vector3d(3, -4, 62);
  const FlipClouds c = MakeFlipClouds(truth, 60, 8);
  auto rot_err = [&](const geom::Rigid3& T) {
    return geom::RotationAngleDeg(T.R * truth.R.transpose());
  };

  const StitchEstimate f = StitchFromFeatures(c.ref, c.mov);
  ASSERT_TRUE(f.valid) << f.note;
  EXPECT_EQ(f.guided_from, "features");
  EXPECT_LT(f.unguided_inliers, 12);  // the global ratio test alone fails (measured 9)
  EXPECT_GE(f.unguided_inliers, 3);
  EXPECT_GE(f.inliers, 45);  // measured 59 of 60
  EXPECT_LT(rot_err(f.T), 0.2);
  EXPECT_LT((f.T.t - truth.t).norm(), 0.3);

  // A start 10 deg off converges; far starts find too few consistent matches
  // and are never taken for a motion.
  const StitchEstimate near = GuidedFeatureFit(c.ref, c.mov, Turned(truth, 10, {0, 1, 1}));
  ASSERT_TRUE(near.valid) << near.note;
  EXPECT_LT(rot_err(near.T), 0.2);
  for (const double deg : {45.0, 90.0, 135.0, 180.0}) {
    for (const Vector3d& axis : {Vector3d(1, 0, 0), Vector3d(0, 1, 1), Vector3d(1, -1, 0.5)}) {
      const StitchEstimate far = GuidedFeatureFit(c.ref, c.mov, Turned(truth, deg, axis));
      EXPECT_TRUE(!far.valid || rot_err(far.T) < 0.5)
          << deg << " deg off: " << far.inliers << " inliers, " << rot_err(far.T) << " deg";
    }
  }

  // No look-alike-free point at all: the global matching has no fit, and
  // the marker fit, 3 mm RMS off its points (too loose to be a stitch),
  // guides the features instead.
  const FlipClouds blind = MakeFlipClouds(truth, 60, 0);
  EXPECT_FALSE(StitchFromFeatures(blind.ref, blind.mov).valid);
  const std::vector<Vector3d> side1 = {{40, 10, 30}, {45, -10, 28}, {-38, 12, 25}, {-42, -8, 31}};
  const std::vector<Vector3d> wobble = {{3, -2, 1}, {-3, 2, -2}, {2, 3, -3}, {-2, -3, 4}};
  std::vector<Vector3d> side2;
  for (size_t i = 0; i < side1.size(); ++i)
    side2.push_back(truth.Inverse().Apply(side1[i] + wobble[i]));
  Result<StitchResult> r = StitchSides(MarkersAt(side1), MarkersAt(side2), &blind.ref, &blind.mov);
  ASSERT_TRUE(r.ok()) << r.error().ToString();
  EXPECT_FALSE(r->markers.valid);
  EXPECT_EQ(r->source, "features");
  EXPECT_EQ(r->features.guided_from, "markers");
  EXPECT_LT(rot_err(r->T), 0.2);
}

TEST(MarkersUnit, OptionsAreChecked) {
  MarkerDetectOptions o;
  EXPECT_EQ(o.Check(), "");
  o.min_saturation = 1.5;
  EXPECT_NE(o.Check(), "");
  cv::Mat img(40, 40, CV_8UC3, cv::Scalar(200, 200, 200)), mask(40, 40, CV_8UC1, cv::Scalar(0));
  EXPECT_FALSE(DetectViewMarkers(img, mask, {"pink"}, {}, nullptr).ok());
  EXPECT_FALSE(DetectViewMarkers(img, cv::Mat(), {"red"}, {}, nullptr).ok());
  Result<ViewMarkers> vm = DetectViewMarkers(img, mask, {"red"}, {"purple"}, nullptr);
  ASSERT_TRUE(vm.ok());
  EXPECT_TRUE(vm->labels.empty());
  ASSERT_EQ(vm->objects.size(), 1u);
  EXPECT_FALSE(vm->objects[0].seen());
}

// The colour classes follow the rule stated on OpenCV's HSV planes (paint:
// saturation and chroma over their floors; class: the hue's interval, a later
// class winning an overlap) on every pixel of a photo of random colours, with
// the default classes and with overlapping, wrapping ones.
TEST(MarkersUnit, ColourClassesFollowTheRuleOnEveryPixel) {
  std::mt19937 rng(7);
  std::uniform_int_distribution<int> byte(0, 255);
  cv::Mat img(300, 400, CV_8UC3);
  for (int y = 0; y < img.rows; ++y)
    for (int x = 0; x < img.cols; ++x)
      img.at<cv::Vec3b>(y, x) =
          cv::Vec3b(static_cast<uchar>(byte(rng)), static_cast<uchar>(byte(rng)),
                    static_cast<uchar>(byte(rng)));
  MarkerDetectOptions overlapping;
  overlapping.colors = {{"a", 350.0, 30.0}, {"b", 10.0, 20.0}, {"c", 180.0, 90.0}};
  overlapping.min_saturation = 0.2;
  overlapping.min_chroma = 0.05;
  for (const MarkerDetectOptions& o : {MarkerDetectOptions{}, overlapping}) {
    cv::Mat hsv;
    cv::cvtColor(img, hsv, cv::COLOR_BGR2HSV_FULL);
    std::vector<cv::Mat> ch;
    cv::split(hsv, ch);
    cv::Mat chroma;
    cv::multiply(ch[1], ch[2], chroma, 1.0 / 255.0, CV_8U);
    const cv::Mat paint = (ch[1] >= o.min_saturation * 255.0) & (chroma >= o.min_chroma * 255.0);
    cv::Mat expected(img.size(), CV_8UC1, cv::Scalar(0));
    for (size_t i = 0; i < o.colors.size(); ++i) {
      const double lo = (o.colors[i].hue_deg - o.colors[i].hue_tol_deg) * 256.0 / 360.0;
      const double hi = (o.colors[i].hue_deg + o.colors[i].hue_tol_deg) * 256.0 / 360.0;
      cv::Mat in = lo < 0        ? (ch[0] >= lo + 256.0) | (ch[0] <= hi)
                   : hi >= 256.0 ? (ch[0] >= lo) | (ch[0] <= hi - 256.0)
                                 : (ch[0] >= lo) & (ch[0] <= hi);
      expected.setTo(cv::Scalar(static_cast<double>(i + 1)), in & paint);
    }
    const cv::Mat got = ClassifyColors(img, o);
    EXPECT_EQ(cv::countNonZero(got != expected), 0);
    EXPECT_GT(cv::countNonZero(got), 1000);  // the photo holds paint of every class
    for (int k = 1; k <= static_cast<int>(o.colors.size()); ++k)
      EXPECT_GT(cv::countNonZero(got == k), 0) << k;
  }
}

// --- view evidence ---

TEST(ViewEvidence, RockWindowHoldsTheRockAndItsMarginWithEvenCorners) {
  cv::Mat mask = cv::Mat::zeros(151, 201, CV_8U);  // odd frame
  cv::circle(mask, {101, 73}, 20, cv::Scalar(255), cv::FILLED);
  const cv::Rect box = cv::boundingRect(mask);
  const cv::Rect w = RockWindow(mask, 9);
  EXPECT_EQ(w.x % 2, 0);
  EXPECT_EQ(w.y % 2, 0);
  EXPECT_EQ(w.width % 2, 0);
  EXPECT_EQ(w.height % 2, 0);
  EXPECT_LE(w.x, box.x - 9);
  EXPECT_LE(w.y, box.y - 9);
  EXPECT_GE(w.x + w.width, box.x + box.width + 9);
  EXPECT_GE(w.y + w.height, box.y + box.height + 9);
  EXPECT_LE(w.x + w.width, box.x + box.width + 9 + 2);  // at most the rounding more
  // Near the edge of an odd frame: clipped to the frame rounded up to even.
  cv::Mat edge = cv::Mat::zeros(151, 201, CV_8U);
  cv::rectangle(edge, cv::Rect(180, 130, 21, 21), cv::Scalar(255), cv::FILLED);
  const cv::Rect we = RockWindow(edge, 9);
  EXPECT_EQ(we.x + we.width, 202);
  EXPECT_EQ(we.y + we.height, 152);
  const cv::Mat crop = CropPadded(edge, we);
  EXPECT_EQ(crop.size(), we.size());
  EXPECT_EQ(cv::countNonZero(crop), cv::countNonZero(edge));  // the padding is zero
  // No rock: the whole frame.
  EXPECT_EQ(RockWindow(cv::Mat::zeros(151, 201, CV_8U), 9), cv::Rect(0, 0, 202, 152));
}

TEST(ViewEvidence, CacheKeepsTheWindowsAndGivesTheMaskBackWhole) {
  cv::Mat mask = cv::Mat::zeros(300, 400, CV_8U);
  cv::ellipse(mask, {210, 140}, {50, 30}, 20, 0, 360, cv::Scalar(255), cv::FILLED);
  cv::Mat bgr(300, 400, CV_8UC3);
  cv::randu(bgr, cv::Scalar::all(0), cv::Scalar::all(255));
  EvidenceOptions o;
  o.camera = {400, 300, 380, 380, 200, 150};
  o.label_colors = {"red", "green"};
  o.object_colors = {"purple", "red"};
  o.window_margin = 12;
  // Room for one colour window only.
  const size_t one = static_cast<size_t>(RockWindow(mask, 12).area()) * 3;
  ViewEvidenceCache cache(o, one);
  EXPECT_EQ(cache.Find("a.jpg"), nullptr);
  cache.Add("a.jpg", bgr, mask);
  cache.Add("b.jpg", bgr, mask);
  cache.Add("c.jpg", bgr, cv::Mat::zeros(10, 10, CV_8U));  // not the photo's size: not kept
  EXPECT_EQ(cache.views(), 2u);
  EXPECT_EQ(cache.Find("c.jpg"), nullptr);
  const auto a = cache.Find("a.jpg"), b = cache.Find("b.jpg");
  ASSERT_TRUE(a && b);
  EXPECT_EQ(a->frame, mask.size());
  EXPECT_EQ(a->window, RockWindow(mask, 12));
  EXPECT_EQ(cv::norm(a->FullMask(), mask, cv::NORM_INF), 0.0);
  ASSERT_FALSE(a->bgr.empty());
  EXPECT_EQ(cv::norm(a->bgr, bgr(a->window), cv::NORM_INF), 0.0);
  EXPECT_TRUE(b->bgr.empty()) << "over the colour budget";
  EXPECT_EQ(cv::norm(b->FullMask(), mask, cv::NORM_INF), 0.0);
  EXPECT_EQ(cache.bytes(), a->bytes() + b->bytes());
  // A view already kept is not replaced.
  cache.Add("a.jpg", bgr, cv::Mat::zeros(300, 400, CV_8U));
  EXPECT_EQ(cache.Find("a.jpg"), a);
  // Random pixels hold no labels; the detection ran and found none.
  EXPECT_TRUE(a->markers_found);
  EXPECT_TRUE(a->markers.labels.empty());
  EXPECT_FALSE(a->aruco_found);  // no ArUco markers configured: not searched
}

TEST(ViewEvidence, KeysDifferWhenWhatIsFoundDiffers) {
  EvidenceOptions o;
  o.camera = {400, 300, 380, 380, 200, 150};
  o.label_colors = {"red"};
  const std::string k = o.Key();
  EXPECT_EQ(k, EvidenceOptions(o).Key());
  EvidenceOptions lens = o;
  lens.camera.k1 = 1e-9;
  EvidenceOptions labels = o;
  labels.label_colors.push_back("blue");
  EvidenceOptions size = o;
  size.markers.expected_label_side_px = 30;
  EvidenceOptions aruco = o;
  aruco.rig.aruco_markers = {{3, 10.0, 20.0, 0.0}};
  for (const EvidenceOptions* d : {&lens, &labels, &size, &aruco}) EXPECT_NE(d->Key(), k);
}

}  // namespace
}  // namespace aggscan
