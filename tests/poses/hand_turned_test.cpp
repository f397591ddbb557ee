// A hand-turned table's angle from the disc's labels and ArUco markers, and
// the sharpness that names a view shot while the table turned: on sightings
// projected from the sim rig's true calibration at known angles.
#include "pipeline/poses/hand_turned.h"

#include <gtest/gtest.h>

#include <cmath>
#include <opencv2/imgproc.hpp>
#include <random>

#include "config/config.h"
#include "drivers/sim/world.h"
#include "pipeline/core/geometry.h"

namespace aggscan {
namespace {

constexpr int kW = 1008, kH = 756;

struct Rig {
  Config config;
  RigCalibration cal;
};

Rig SimRig() {
  Rig r;
  sim::SimWorld world(r.config);
  r.cal = world.TruthCalibration(kW, kH);
  return r;
}

// The labels (and ArUco markers) of `rig` seen at `angle_deg`, each pixel
// moved by Gaussian noise of `noise_px`.
ViewMarkers LabelsAt(const Rig& r, double angle_deg, double noise_px, std::mt19937* rng) {
  std::normal_distribution<double> n(0.0, noise_px);
  const geom::Rigid3 cam = geom::Rigid3::FromRowMajor4(r.cal.CamFromTable(angle_deg));
  ViewMarkers vm;
  for (const RigMarker& m : r.config.rig.markers) {
    auto p = geom::ProjectPoint(r.cal.camera, cam, Eigen::Vector3d(m.x_mm, m.y_mm, 0));
    if (!p) continue;
    LabelSighting s;
    s.color = m.color;
    s.center_px = *p + Eigen::Vector2d(n(*rng), n(*rng));
    vm.labels.push_back(s);
  }
  return vm;
}

double AngleDiff(double a, double b) { return std::remainder(a - b, 360.0); }

TEST(HandTurned, AngleFromTheLabelsOverAWholeTurn) {
  const Rig r = SimRig();
  ASSERT_GE(r.config.rig.markers.size(), 3u);
  std::mt19937 rng(7);
  double worst = 0;
  for (double truth = -20.0; truth < 380.0; truth += 23.7) {
    const ViewMarkers vm = LabelsAt(r, truth, 0.2, &rng);
    const TableAngleFit f = FitTableAngle(vm, nullptr, r.cal, r.config.rig);
    ASSERT_TRUE(f.ok) << f.problem;
    EXPECT_GE(f.angle_deg, 0.0);
    EXPECT_LT(f.angle_deg, 360.0);
    EXPECT_EQ(f.labels, static_cast<int>(vm.labels.size()));
    EXPECT_LT(f.rms_px, 0.5);
    worst = std::max(worst, std::abs(AngleDiff(f.angle_deg, truth)));
  }
  // 0.2 px of noise per coordinate, labels ~4 px per degree of turn apart at
  // 1008 px: about 0.025 deg per view (1 sigma); the worst of 17 views within 4 sigma.
  EXPECT_LT(worst, 0.1);
}

TEST(HandTurned, TwoLabelsSufficeOneDoesNot) {
  const Rig r = SimRig();
  std::mt19937 rng(3);
  ViewMarkers vm = LabelsAt(r, 131.0, 0.1, &rng);
  vm.labels.resize(2);
  TableAngleFit f = FitTableAngle(vm, nullptr, r.cal, r.config.rig);
  ASSERT_TRUE(f.ok) << f.problem;
  EXPECT_LT(std::abs(AngleDiff(f.angle_deg, 131.0)), 0.05);
  vm.labels.resize(1);
  f = FitTableAngle(vm, nullptr, r.cal, r.config.rig);
  EXPECT_FALSE(f.ok);
  EXPECT_NE(f.problem.find("only 1 of the disc's labels"), std::string::npos) << f.problem;
  EXPECT_NE(f.problem.find("uncovered"), std::string::npos) << f.problem;
}

TEST(HandTurned, ALabelAtOddsWithTheOthersIsDropped) {
  const Rig r = SimRig();
  std::mt19937 rng(5);
  ViewMarkers vm = LabelsAt(r, 250.0, 0.1, &rng);
  ASSERT_GE(vm.labels.size(), 4u);
  vm.labels[1].center_px += Eigen::Vector2d(25.0, -12.0);  // half hidden, or a smear of its colour
  const TableAngleFit f = FitTableAngle(vm, nullptr, r.cal, r.config.rig);
  ASSERT_TRUE(f.ok) << f.problem;
  ASSERT_EQ(f.dropped.size(), 1u);
  EXPECT_EQ(f.dropped[0], vm.labels[1].color + " label");
  EXPECT_LT(std::abs(AngleDiff(f.angle_deg, 250.0)), 0.05);
  // Two bad labels of four: the fit is refused, naming what to check.
  vm.labels[2].center_px += Eigen::Vector2d(-30.0, 20.0);
  const TableAngleFit g = FitTableAngle(vm, nullptr, r.cal, r.config.rig);
  EXPECT_FALSE(g.ok);
  EXPECT_NE(g.problem.find("disagree"), std::string::npos) << g.problem;
}

TEST(HandTurned, ArucoCornersGiveTheAngleToo) {
  Rig r = SimRig();
  r.config.rig.aruco_markers = {{3, 110.0, -40.0, 15.0}, {7, -100.0, 60.0, -30.0}};
  const double truth = 77.7;
  const geom::Rigid3 cam = geom::Rigid3::FromRowMajor4(r.cal.CamFromTable(truth));
  ArucoViewDetections ad;
  for (const ArucoMarker& m : r.config.rig.aruco_markers) {
    ArucoSighting s;
    s.id = m.id;
    for (int k = 0; k < 4; ++k) {
      auto p =
          geom::ProjectPoint(r.cal.camera, cam, ArucoCornerMm(m, r.config.rig.aruco_size_mm, k));
      ASSERT_TRUE(p);
      s.corners_px[k] = *p;
    }
    ad.markers.push_back(s);
  }
  const TableAngleFit f = FitTableAngle(ViewMarkers{}, &ad, r.cal, r.config.rig);
  ASSERT_TRUE(f.ok) << f.problem;
  EXPECT_EQ(f.aruco_markers, 2);
  EXPECT_EQ(f.labels, 0);
  EXPECT_LT(std::abs(AngleDiff(f.angle_deg, truth)), 0.01);
}

TEST(HandTurned, UnwrapKeepsTheCumulativeAngle) {
  EXPECT_DOUBLE_EQ(UnwrapNear(10.0, 365.0), 370.0);
  EXPECT_DOUBLE_EQ(UnwrapNear(350.0, -5.0), -10.0);
  EXPECT_DOUBLE_EQ(UnwrapNear(200.0, 200.0), 200.0);
  EXPECT_DOUBLE_EQ(UnwrapNear(20.0, 740.0), 740.0);
}

TEST(HandTurned, ASmearedPhotoIsLessSharp) {
  // A stone's grain: a noise texture, smoothed to a few pixels, inside a disc.
  cv::Mat grain(300, 400, CV_8UC3);
  cv::randu(grain, 60, 200);
  cv::GaussianBlur(grain, grain, cv::Size(0, 0), 1.5);
  cv::Mat mask = cv::Mat::zeros(grain.size(), CV_8U);
  cv::circle(mask, {200, 150}, 120, 255, cv::FILLED);
  // Sensor noise on top of both, as a camera adds it after the smear.
  cv::Mat noise(grain.size(), CV_8UC3);
  cv::randn(noise, 0, 2);
  cv::Mat sharp = grain + noise;
  cv::Mat smeared;
  const cv::Mat kernel = cv::Mat::ones(1, 9, CV_32F) / 9.0;  // 9 px along the turn
  cv::filter2D(grain, smeared, -1, kernel);
  smeared += noise;
  const double s0 = RockSharpness(sharp, mask), s1 = RockSharpness(smeared, mask);
  EXPECT_GT(s0, 0);
  EXPECT_LT(s1 / s0, 0.5) << s0 << " " << s1;
  EXPECT_EQ(RockSharpness(sharp, cv::Mat::zeros(grain.size(), CV_8U)), 0.0);
  // Along the smear the loss is larger than over the whole gradient, and
  // larger than across it.
  const double along0 = RockSharpness(sharp, mask, {1, 0});
  const double along1 = RockSharpness(smeared, mask, {1, 0});
  const double across0 = RockSharpness(sharp, mask, {0, 2});
  const double across1 = RockSharpness(smeared, mask, {0, 2});
  EXPECT_LT(along1 / along0, s1 / s0);
  EXPECT_LT(along1 / along0, across1 / across0);
}

TEST(HandTurned, TheTurnMovesTheRockAcrossTheImageOfTheAxis) {
  // The sim camera looks at the disc level with the horizon: the axis is
  // upright in the image, and the turn moves the rock sideways.
  const Rig r = SimRig();
  const cv::Point2d d = TurnDirection(r.cal);
  EXPECT_NEAR(std::hypot(d.x, d.y), 1.0, 1e-9);
  EXPECT_GT(std::abs(d.x), 0.99) << d;
}

}  // namespace
}  // namespace aggscan
