#include "pipeline/morph/morph2d.h"

#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <numbers>
#include <opencv2/imgproc.hpp>
#include <vector>

namespace aggscan {
namespace {

constexpr double kPi = std::numbers::pi;

// Digitised disc: every pixel whose centre lies within radius r.
cv::Mat Disc(double r, cv::Size size = {600, 600}) {
  cv::Mat m = cv::Mat::zeros(size, CV_8UC1);
  const double cx = size.width / 2.0, cy = size.height / 2.0;
  for (int y = 0; y < m.rows; ++y)
    for (int x = 0; x < m.cols; ++x)
      if ((x - cx) * (x - cx) + (y - cy) * (y - cy) <= r * r) m.at<uchar>(y, x) = 255;
  return m;
}

// Filled polygon with sub-pixel vertices; a pixel is inside when its centre is.
cv::Mat Polygon(const std::vector<cv::Point2d>& pts, cv::Size size = {800, 800}) {
  constexpr int kShift = 8;
  std::vector<cv::Point> p;
  for (const auto& q : pts)
    p.emplace_back(cvRound(q.x * (1 << kShift)), cvRound(q.y * (1 << kShift)));
  cv::Mat m = cv::Mat::zeros(size, CV_8UC1);
  cv::fillPoly(m, std::vector<std::vector<cv::Point>>{p}, cv::Scalar(255), cv::LINE_8, kShift);
  return m;
}

// Rectangle w x h centred at c, rotated by deg.
std::vector<cv::Point2d> Rect(double w, double h, double deg, cv::Point2d c = {400.3, 399.7}) {
  const double a = deg * kPi / 180, ca = std::cos(a), sa = std::sin(a);
  std::vector<cv::Point2d> out;
  for (auto [sx, sy] : {std::pair{-1, -1}, {1, -1}, {1, 1}, {-1, 1}}) {
    const double x = sx * w / 2, y = sy * h / 2;
    out.emplace_back(c.x + ca * x - sa * y, c.y + sa * x + ca * y);
  }
  return out;
}

std::vector<cv::Point2d> Triangle(double side, double deg, cv::Point2d c = {400.2, 410.6}) {
  std::vector<cv::Point2d> out;
  const double r = side / std::sqrt(3.0);
  for (int k = 0; k < 3; ++k) {
    const double a = (deg + 90 + 120 * k) * kPi / 180;
    out.emplace_back(c.x + r * std::cos(a), c.y - r * std::sin(a));
  }
  return out;
}

TEST(Morph2D, Disc) {
  auto m = ComputeMorph2D(Disc(100));
  ASSERT_TRUE(m.ok()) << m.error().ToString();
  std::printf("disc r=100: circularity %.4f L_max %.2f L_min %.2f P %.2f A %.0f\n", m->circularity,
              m->l_max_px, m->l_min_px, m->perimeter_px, m->area_px);
  EXPECT_NEAR(m->circularity, 1.0, 0.02);
  EXPECT_NEAR(m->l_max_px, 200.0, 2.0);
  EXPECT_NEAR(m->l_min_px, 200.0, 2.0);
  EXPECT_NEAR(m->fer_2d, 1.0, 0.01);
  EXPECT_NEAR(m->area_px, kPi * 100 * 100, 0.005 * kPi * 100 * 100);
  EXPECT_NEAR(m->perimeter_px, 2 * kPi * 100, 0.01 * 2 * kPi * 100);
}

TEST(Morph2D, SquaresAxisAlignedAndRotated) {
  for (double deg : {0.0, 30.0, 45.0, 12.5}) {
    auto m = ComputeMorph2D(Polygon(Rect(200, 200, deg)));
    ASSERT_TRUE(m.ok());
    std::printf("square %.1f deg: circularity %.4f (pi/4 = 0.7854) L_max %.2f\n", deg,
                m->circularity, m->l_max_px);
    EXPECT_NEAR(m->circularity, kPi / 4, 0.02 * kPi / 4) << deg << " deg";
    EXPECT_NEAR(m->area_px, 40000, 800) << deg << " deg";  // fillPoly is inclusive: ~201 x 201
    EXPECT_NEAR(m->l_max_px, 200 * std::sqrt(2.0), 0.01 * 200 * std::sqrt(2.0)) << deg << " deg";
  }
}

TEST(Morph2D, EquilateralTriangle) {
  const double expected = kPi * std::sqrt(3.0) / 9;
  for (double deg : {0.0, 17.0, 30.0}) {
    auto m = ComputeMorph2D(Polygon(Triangle(300, deg)));
    ASSERT_TRUE(m.ok());
    std::printf("triangle %.1f deg: circularity %.4f (0.6046)\n", deg, m->circularity);
    EXPECT_NEAR(m->circularity, expected, 0.02 * expected) << deg << " deg";
    EXPECT_NEAR(m->l_max_px, 300, 3) << deg << " deg";
    // Perpendicular to a side: the height of the triangle.
    EXPECT_NEAR(m->l_min_px, 300 * std::sqrt(3.0) / 2, 0.01 * 300 * std::sqrt(3.0) / 2)
        << deg << " deg";
  }
}

// A 300 x 100 rectangle: the longest Feret diameter is the diagonal and L_min
// the width perpendicular to it (2*w*h/diag), so FER = diag^2/(2wh) = 5/3.
// (The 300/100 = 3 ratio is the minimum-area bounding box, not the paper's FER.)
TEST(Morph2D, RectangleFeret) {
  const double diag = std::hypot(300.0, 100.0);
  for (double deg : {0.0, 30.0, 77.0, 135.0}) {
    auto m = ComputeMorph2D(Polygon(Rect(300, 100, deg)));
    ASSERT_TRUE(m.ok());
    EXPECT_NEAR(m->l_max_px, diag, 0.01 * diag) << deg;
    EXPECT_NEAR(m->l_min_px, 2 * 300 * 100 / diag, 0.01 * 2 * 300 * 100 / diag) << deg;
    std::printf("rect 300x100 %.0f deg: L_max %.2f L_min %.2f FER %.4f\n", deg, m->l_max_px,
                m->l_min_px, m->fer_2d);
    EXPECT_NEAR(m->fer_2d, 5.0 / 3.0, 0.01 * 5.0 / 3.0) << deg;
    EXPECT_NEAR(m->circularity, 4 * kPi * 30000 / (800.0 * 800.0),
                0.02 * 4 * kPi * 30000 / (800.0 * 800.0))
        << deg;
  }
}

TEST(Morph2D, ElongatedEllipseFerIsAxisRatio) {
  for (double deg : {0.0, 40.0}) {
    cv::Mat m = cv::Mat::zeros(800, 800, CV_8UC1);
    cv::ellipse(m, cv::RotatedRect({400, 400}, {300, 100}, static_cast<float>(deg)),
                cv::Scalar(255), cv::FILLED);
    auto r = ComputeMorph2D(m);
    ASSERT_TRUE(r.ok());
    EXPECT_NEAR(r->fer_2d, 3.0, 0.03) << deg;
    const double ang = std::fmod(r->l_max_angle_deg - deg + 360.0, 180.0);
    EXPECT_TRUE(ang < 1.0 || ang > 179.0) << r->l_max_angle_deg << " vs " << deg;
  }
}

TEST(Morph2D, RotationInvariance) {
  std::vector<cv::Point2d> base = {{-120, -40}, {60, -90},  {150, 10},
                                   {70, 80},    {-40, 110}, {-150, 30}};
  std::vector<double> fer, circ, lmax;
  for (double deg = 0; deg < 180; deg += 23) {
    const double a = deg * kPi / 180;
    std::vector<cv::Point2d> p;
    for (auto q : base)
      p.emplace_back(400.4 + std::cos(a) * q.x - std::sin(a) * q.y,
                     399.8 + std::sin(a) * q.x + std::cos(a) * q.y);
    auto m = ComputeMorph2D(Polygon(p));
    ASSERT_TRUE(m.ok());
    fer.push_back(m->fer_2d);
    circ.push_back(m->circularity);
    lmax.push_back(m->l_max_px);
  }
  EXPECT_LT(ComputeStats(fer).cov, 0.005);
  EXPECT_LT(ComputeStats(circ).cov, 0.005);
  EXPECT_LT(ComputeStats(lmax).cov, 0.003);
}

TEST(Morph2D, LargestComponentAndHoles) {
  cv::Mat m = Disc(100);
  cv::circle(m, {60, 60}, 30, cv::Scalar(255), cv::FILLED);  // smaller blob: ignored
  cv::circle(m, {300, 300}, 20, cv::Scalar(0), cv::FILLED);  // hole: filled
  auto r = ComputeMorph2D(m);
  ASSERT_TRUE(r.ok());
  EXPECT_NEAR(r->area_px, kPi * 100 * 100, 0.005 * kPi * 100 * 100);
  EXPECT_NEAR(r->circularity, 1.0, 0.02);
}

TEST(Morph2D, TinyObjects) {
  cv::Mat m = cv::Mat::zeros(50, 50, CV_8UC1);
  m.at<uchar>(10, 10) = 255;
  auto r = ComputeMorph2D(m);
  ASSERT_TRUE(r.ok());
  EXPECT_EQ(r->area_px, 1);
  EXPECT_GT(r->l_max_px, 0);
  cv::line(m, {5, 30}, {40, 30}, cv::Scalar(255), 1);
  r = ComputeMorph2D(m);
  ASSERT_TRUE(r.ok());
  EXPECT_NEAR(r->l_max_px, 36, 1.5);
}

TEST(Morph2D, EmptyMaskIsAClearError) {
  auto r = ComputeMorph2D(cv::Mat::zeros(100, 100, CV_8UC1));
  ASSERT_FALSE(r.ok());
  EXPECT_EQ(r.error().cls, ErrorClass::kInvalidArgument);
  EXPECT_NE(r.error().message.find("no foreground"), std::string::npos);
  EXPECT_FALSE(ComputeMorph2D(cv::Mat()).ok());
  EXPECT_FALSE(ComputeMorph2D(cv::Mat::zeros(10, 10, CV_32F)).ok());
}

TEST(Stats, SampleStdAndCov) {
  Stats s = ComputeStats({2, 4, 4, 4, 5, 5, 7, 9});
  EXPECT_EQ(s.n, 8);
  EXPECT_DOUBLE_EQ(s.mean, 5);
  EXPECT_DOUBLE_EQ(s.min, 2);
  EXPECT_DOUBLE_EQ(s.max, 9);
  EXPECT_NEAR(s.std, std::sqrt(32.0 / 7.0), 1e-12);  // sample std (n-1)
  EXPECT_NEAR(s.cov, std::sqrt(32.0 / 7.0) / 5, 1e-12);
  Stats one = ComputeStats({3});
  EXPECT_EQ(one.std, 0);
  EXPECT_EQ(one.mean, 3);
  Stats none = ComputeStats({});
  EXPECT_EQ(none.n, 0);
  EXPECT_EQ(none.mean, 0);
}

// Views' sole carvings: one far above the rest is an outlier; near-identical
// values (MAD about 0) flag nothing below the floor; the floor holds back a
// value that is far in MADs but small in absolute terms.
TEST(Stats, HighOutliersAboveTheMedianByMadsAndTheFloor) {
  const std::vector<double> v{10, 12, 11, 9, 10, 95, 11, 10};
  EXPECT_EQ(HighOutliers(v, 50), std::vector<size_t>{5});
  EXPECT_TRUE(HighOutliers(v, 100).empty());
  EXPECT_TRUE(HighOutliers({5, 5, 5, 5}, 1).empty());
  EXPECT_EQ(HighOutliers({5, 5, 5, 5.5}, 1), std::vector<size_t>{3});
  EXPECT_TRUE(HighOutliers({5, 5, 5, 5.5}, 6).empty());
  EXPECT_EQ(HighOutliers({1, 2, 3, 4, 5, 6}, 0, 1.0), std::vector<size_t>{5});
  EXPECT_TRUE(HighOutliers({}, 0).empty());
}

}  // namespace
}  // namespace aggscan
