// The study's protocol on the simulated rig, without a motor: the sim's hand
// turns the table after each prompt by the step plus up to +-5 deg, with
// uneven reaction and turn times, and is late twice a side (the table turns
// while the camera exposes: a blurred view). The worker measures each view's
// angle from the disc's labels with the rig calibration, names and leaves out
// the blurred views, and the turntable path measures the rock.
#include <gtest/gtest.h>

#include <cmath>
#include <filesystem>
#include <map>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <set>
#include <string>

#include "common/fsutil.h"
#include "common/rig_calibration.h"
#include "config/config.h"
#include "pipeline/core/geometry.h"
#include "pipeline/markers/markers.h"
#include "pipeline/worker/reconstruct.h"
#include "tests/reconstruct/sim_sample.h"
#include "tests/reconstruct/truth_check.h"
#include "tests/util/temp_dir.h"

namespace aggscan {
namespace {

using nlohmann::json;

json ReadJsonFile(const std::string& path) {
  auto text = ReadFile(path);
  EXPECT_TRUE(text) << path;
  return text ? json::parse(*text) : json();
}

TEST(HandTurnedCapture, AnglesFromTheLabelsBlurredViewsNamedRockMeasured) {
  test::TempDir tmp;
  // A phone's indoor shutter (1/30 s): a turn during the exposure smears it.
  // The sim lights the scene for the configured exposure, so only the smear changes.
  const std::string extra =
      "[turntable]\nbackend = \"manual\"\n"
      "[camera.exposure]\nexposure_us = 33000.0\n"
      "[sim]\nhand_late_every = 5\n";
  const std::string sample =
      test::CaptureSimSample(tmp.path(), 1, 2, true, false, 12, 1008, 756, 30.0, extra);

  // Nothing measured the angles: the sidecars say so.
  const json car = ReadJsonFile(sample + "/side1/view_003.json");
  EXPECT_FALSE(car.contains("measured_angle_deg")) << car.dump();
  EXPECT_EQ(car.value("turntable_backend", ""), "manual");

  ReconstructOptions opts;
  auto st = ReconstructSample(sample, opts);
  ASSERT_TRUE(st) << st.error().ToString();

  const json truth = ReadJsonFile(sample + "/truth.json");
  const auto true_deg = test::TruePlatterDeg(truth);
  // The hand's 11 turns a side continue their count across the flip: late
  // turns 5, 10 (side 1's views 5, 10) and 15, 20 (side 2's views 4, 9).
  const std::map<int, std::set<int>> late = {{1, {5, 10}}, {2, {4, 9}}};
  double worst_plan = 0, worst_err = 0;
  for (int side : {1, 2}) {
    const json p = ReadJsonFile(sample + "/results/poses_side" + std::to_string(side) + ".json");
    EXPECT_TRUE(p.value("hand_turned", false)) << p.dump().substr(0, 400);
    std::set<int> left;
    for (const json& l : p["views_left_out"]) {
      left.insert(l["view"].get<int>());
      EXPECT_NE(l["reason"].get<std::string>().find("shot while the table was turning"),
                std::string::npos)
          << l.dump();
    }
    EXPECT_EQ(left, late.at(side)) << p["views_left_out"].dump();
    EXPECT_EQ(p["views"].size(), 12u - late.at(side).size());
    const double first_truth = true_deg.at({side, 0});
    for (const json& v : p["views"]) {
      const int view = v["view"].get<int>();
      EXPECT_EQ(v["angle_source"], "labels");
      EXPECT_LT(v["angle_fit_rms_px"].get<double>(), 1.0) << v.dump();
      const double t = true_deg.at({side, view});
      // How far the hand strayed from the plan, the side's first view as zero.
      worst_plan = std::max(worst_plan, std::abs((t - first_truth) - 30.0 * view));
      // Label angles are absolute: the same turn as the truth, up to whole turns.
      const double err = std::remainder(v["angle_deg"].get<double>() - t, 360.0);
      worst_err = std::max(worst_err, std::abs(err));
    }
  }
  std::printf("hand: worst departure from the plan %.2f deg; worst angle error %.3f deg\n",
              worst_plan, worst_err);
  EXPECT_GT(worst_plan, 4.0) << "the hand must stray from the plan for this test to mean anything";
  EXPECT_LT(worst_err, 0.15);

  test::ExpectRockMatchesTruth(sample, truth, "hand +-5 deg");
  auto m = ReadMorphology(sample);
  ASSERT_TRUE(m) << m.error().ToString();
  // The four views left out are in the result's warnings, by side and view.
  int named = 0;
  for (const json& w : (*m)["warnings"]) {
    if (w.get<std::string>().find("left out of the poses: shot while the table was turning") !=
        std::string::npos)
      ++named;
  }
  EXPECT_EQ(named, 4) << (*m)["warnings"].dump();
}

// Paints over every label of one view (a hand or a cloth over them): the
// disc's colour from a ring just outside each label.
void CoverLabels(const std::string& sample, int side, int view, double platter_deg) {
  auto cal = LoadCalibration(sample + "/calibration.json");
  ASSERT_TRUE(cal) << cal.error().ToString();
  const Config config;
  const std::string path = sample + "/side" + std::to_string(side) + "/view_" +
                           (view < 10 ? "00" : "0") + std::to_string(view) + ".jpg";
  cv::Mat img = cv::imread(path);
  ASSERT_FALSE(img.empty()) << path;
  const double side_px = ExpectedLabelSidePx(*cal, config.rig);
  const geom::Rigid3 cam = geom::Rigid3::FromRowMajor4(cal->CamFromTable(platter_deg));
  for (const RigMarker& m : config.rig.markers) {
    auto p = geom::ProjectPoint(cal->camera, cam, Eigen::Vector3d(m.x_mm, m.y_mm, 0));
    if (!p) continue;
    const cv::Point c(static_cast<int>(std::lround(p->x())), static_cast<int>(std::lround(p->y())));
    const int r = static_cast<int>(std::ceil(1.2 * side_px));
    cv::Mat ring = cv::Mat::zeros(img.size(), CV_8U);
    cv::circle(ring, c, r + 6, 255, cv::FILLED);
    cv::circle(ring, c, r, 0, cv::FILLED);
    cv::circle(img, c, r, cv::mean(img, ring), cv::FILLED);
  }
  ASSERT_TRUE(cv::imwrite(path, img));
  // The side's manifest holds each photo's size: the edited one's is new.
  const std::string manifest = sample + "/side" + std::to_string(side) + "/manifest.json";
  json mf = ReadJsonFile(manifest);
  const std::string name = std::filesystem::path(path).filename().string();
  for (json& v : mf["views"]) {
    if (v["image"] == name) v["bytes"] = std::filesystem::file_size(path);
  }
  ASSERT_TRUE(WriteFileAtomic(manifest, mf.dump(2)));
}

// Turns from about 5 to 55 deg (the plan's 30 +-25), and one view whose labels
// are covered: the angles still follow, the covered view is named with what
// to do.
TEST(HandTurnedCapture, TurnsFarFromThePlanAndCoveredLabels) {
  test::TempDir tmp;
  const std::string extra =
      "[turntable]\nbackend = \"manual\"\n"
      "[sim]\nhand_angle_error_deg = 25.0\n";
  const std::string sample =
      test::CaptureSimSample(tmp.path(), 2, 2, true, false, 12, 1008, 756, 30.0, extra);
  const json truth = ReadJsonFile(sample + "/truth.json");
  const auto true_deg = test::TruePlatterDeg(truth);
  CoverLabels(sample, 1, 7, true_deg.at({1, 7}));
  auto st = ReconstructSample(sample, ReconstructOptions{});
  ASSERT_TRUE(st) << st.error().ToString();
  double smallest = 360, largest = 0, worst_err = 0;
  for (int side : {1, 2}) {
    for (int v = 1; v < 12; ++v) {
      const double turn = true_deg.at({side, v}) - true_deg.at({side, v - 1});
      smallest = std::min(smallest, turn);
      largest = std::max(largest, turn);
    }
    const json p = ReadJsonFile(sample + "/results/poses_side" + std::to_string(side) + ".json");
    if (side == 1) {
      ASSERT_EQ(p["views_left_out"].size(), 1u) << p["views_left_out"].dump();
      EXPECT_EQ(p["views_left_out"][0]["view"], 7);
      const std::string why = p["views_left_out"][0]["reason"];
      EXPECT_NE(why.find("no turntable angle from the disc"), std::string::npos) << why;
      EXPECT_NE(why.find("keep them uncovered"), std::string::npos) << why;
    } else {
      EXPECT_TRUE(p["views_left_out"].empty()) << p["views_left_out"].dump();
    }
    for (const json& v : p["views"]) {
      const double t = true_deg.at({side, v["view"].get<int>()});
      worst_err =
          std::max(worst_err, std::abs(std::remainder(v["angle_deg"].get<double>() - t, 360.0)));
    }
  }
  std::printf("turns %.1f .. %.1f deg; worst angle error %.3f deg\n", smallest, largest, worst_err);
  EXPECT_LT(smallest, 15.0);
  EXPECT_GT(largest, 45.0);
  EXPECT_LT(worst_err, 0.15);
  test::ExpectRockMatchesTruth(sample, truth, "hand +-25 deg, labels covered");
}

}  // namespace
}  // namespace aggscan
