#include "pipeline/masks/mask.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <string>

#include "common/clock.h"
#include "tests/util/synth_scene.h"

namespace aggscan {
namespace {

using testing::MakeScene;
using testing::MaskIoU;
using testing::SceneParams;

struct Case {
  uint64_t seed;
  double albedo;
  double radius;
  double table_deg;
  double light_deg;
  bool marker_edge;
};

void CheckScene(const SceneParams& p, double* iou_out = nullptr, double* ms_out = nullptr) {
  const auto sc = MakeScene(p);
  const TimeNs t0 = MonotonicNs();
  const cv::Mat mask = ComputeForegroundMask(sc.bgr);
  const double ms = static_cast<double>(MonotonicNs() - t0) / 1e6;
  ASSERT_EQ(mask.size(), sc.bgr.size());
  ASSERT_EQ(mask.type(), CV_8UC1);
  const double iou = MaskIoU(mask, sc.truth);
  // Label pixels within 2 px of the rock are blurred mixtures of both: not judged.
  cv::Mat near_rock;
  cv::dilate(sc.truth, near_rock, cv::Mat(), cv::Point(-1, -1), 2);
  const int labels_hit = cv::countNonZero(mask & sc.labels & ~near_rock);
  const double markers_kept =
      static_cast<double>(cv::countNonZero(mask & sc.markers)) / cv::countNonZero(sc.markers);
  std::printf(
      "scene %dx%d seed %llu albedo %.2f: IoU %.4f, label px in mask %d, markers kept %.4f, %.0f "
      "ms\n",
      p.size.width, p.size.height, static_cast<unsigned long long>(p.seed), p.albedo, iou,
      labels_hit, markers_kept, ms);
  if ((iou < 0.97 || labels_hit > 0) && std::getenv("AGGSCAN_DUMP")) {
    const std::string stem = "/tmp/mask_seed" + std::to_string(p.seed);
    {
      cv::Mat half;
      cv::resize(sc.bgr, half, cv::Size(), 0.5, 0.5, cv::INTER_AREA);
      cv::imwrite(stem + "_img.png", half);
    }
    cv::Mat vis;
    cv::merge(std::vector<cv::Mat>{mask & ~sc.truth, sc.truth & mask, sc.truth & ~mask}, vis);
    cv::imwrite(stem + "_err.png", vis);
  }
  EXPECT_GE(iou, 0.97) << "seed " << p.seed;
  EXPECT_EQ(labels_hit, 0) << "colour label pixels became rock, seed " << p.seed;
  EXPECT_GE(markers_kept, 0.99) << "object markers lost, seed " << p.seed;
  if (iou_out) *iou_out = iou;
  if (ms_out) *ms_out = ms;
}

// The rig's still size (2016 x 1512) unless AGGSCAN_MASK_SIZE_HALF is set.
TEST(Mask, SyntheticScenes) {
  const Case cases[] = {
      {1, 0.25, 0.14, 0, 135, false}, {2, 0.4, 0.12, 20, 120, false},
      {3, 0.6, 0.16, 45, 150, false}, {4, 0.3, 0.10, 70, 100, true},
      {5, 0.5, 0.18, 10, 160, true},  {6, 0.6, 0.13, 33, 45, false},
      {7, 0.25, 0.17, 80, 60, true},  {8, 0.45, 0.11, 5, 135, false},
  };
  for (const auto& c : cases) {
    SceneParams p;
    if (std::getenv("AGGSCAN_MASK_SIZE_HALF")) p.size = {1008, 756};
    p.seed = c.seed;
    p.albedo = c.albedo;
    p.rock_radius_frac = c.radius;
    p.turntable_deg = c.table_deg;
    p.light_azimuth_deg = c.light_deg;
    p.marker_on_edge = c.marker_edge;
    CheckScene(p);
  }
}

// Diagnostic: where the texture cue lies on rock, shadow and the rest of the
// background (percentiles), so thresholds can be judged.
TEST(Mask, TextureCueSeparatesRockFromShadow) {
  for (uint64_t seed : {1, 8}) {
    SceneParams p;
    p.size = {1008, 756};
    p.seed = seed;
    p.albedo = seed == 1 ? 0.25 : 0.45;
    const auto sc = MakeScene(p);
    cv::Mat small, truth;
    cv::resize(sc.bgr, small, cv::Size(), 0.5, 0.5, cv::INTER_AREA);
    cv::resize(sc.truth, truth, small.size(), 0, 0, cv::INTER_NEAREST);
    const cv::Mat t = TextureMap(small);
    cv::Mat inner, outer;
    cv::erode(truth, inner, cv::Mat(), cv::Point(-1, -1), 4);
    cv::dilate(truth, outer, cv::Mat(), cv::Point(-1, -1), 4);
    auto pct = [&](const cv::Mat& sel, double q) {
      std::vector<float> v;
      for (int y = 0; y < t.rows; ++y)
        for (int x = 0; x < t.cols; ++x)
          if (sel.at<uchar>(y, x)) v.push_back(t.at<float>(y, x));
      if (v.empty()) return 0.0f;
      std::nth_element(v.begin(), v.begin() + static_cast<long>(q * (v.size() - 1)), v.end());
      return v[static_cast<size_t>(q * (v.size() - 1))];
    };
    const cv::Mat bg = outer == 0;
    std::printf(
        "texture seed %llu: rock p01 %.4f p05 %.4f p50 %.4f | background p50 %.4f p99 %.4f p999 "
        "%.4f\n",
        static_cast<unsigned long long>(seed), pct(inner, 0.01), pct(inner, 0.05), pct(inner, 0.5),
        pct(bg, 0.5), pct(bg, 0.99), pct(bg, 0.999));
    EXPECT_GT(pct(inner, 0.05), pct(bg, 0.99));
  }
}

// The empty turntable as the background: the stone is found on the disc the
// border does not show, its soft shadow is not.
TEST(Mask, EmptyTurntablePhotoTakesTheDiscAndFloorOut) {
  for (uint64_t seed : {1, 2, 3}) {
    const testing::FloorScene sc = testing::MakeFloorScene(seed);
    const double plain = MaskIoU(ComputeForegroundMask(sc.photo), sc.truth);
    const double iou = MaskIoU(ComputeForegroundMask(sc.photo, sc.empty, MaskOptions{}), sc.truth);
    std::printf(
        "disc on a pebbled floor, seed %llu: IoU without the empty turntable %.4f, with it %.4f\n",
        static_cast<unsigned long long>(seed), plain, iou);
    EXPECT_GE(iou, 0.97) << "seed " << seed;
    EXPECT_GT(iou, plain) << "seed " << seed;
  }
}

// Nothing on the disc: the photo and the empty turntable differ only by noise
// and light, and no rock is found.
TEST(Mask, EmptyTurntableAgainstItselfFindsNothing) {
  const testing::FloorScene sc = testing::MakeFloorScene(4);
  cv::Mat again = sc.empty.clone();
  cv::Mat noise(again.size(), CV_8UC3);
  cv::randn(noise, 0, 2);
  again += noise;
  EXPECT_EQ(cv::countNonZero(ComputeForegroundMask(again, sc.empty, MaskOptions{})), 0);
}

TEST(Mask, EmptySceneGivesEmptyMask) {
  cv::Mat white(300, 400, CV_8UC3, cv::Scalar(240, 240, 240));
  cv::Mat noise(white.size(), CV_8UC3);
  cv::randn(noise, 0, 2);
  white += noise;
  EXPECT_EQ(cv::countNonZero(ComputeForegroundMask(white)), 0);
}

// Real photos from the MSR GrabCut set: stone1 a rock on a plain orange table,
// stone2 the same rock on a busy patterned cloth (apples and pine cones). The
// scenes differ from the rig's, so the figures are held where they were
// measured (stone1 0.9857, stone2 0.9616, 640 x 480, default options) with
// 0.01 of slack: a change that loses more on real photos shows up here.
// stone2 scored 0.0035 before the colour cue's hysteresis (mask.h, step 2).
TEST(Mask, GrabCutStoneReport) {
  const std::string dir = std::string(AGGSCAN_SHARED_DATA) + "/masks/grabcut";
  if (!std::filesystem::exists(dir + "/boundary_GT/stone1.bmp")) GTEST_SKIP() << "no " << dir;
  const struct {
    const char* name;
    double min_iou;
  } stones[] = {{"stone1", 0.9857 - 0.01}, {"stone2", 0.9616 - 0.01}};
  for (const auto& stone : stones) {
    const cv::Mat img = cv::imread(dir + "/data_GT/" + stone.name + ".JPG", cv::IMREAD_COLOR);
    const cv::Mat gt =
        cv::imread(dir + "/boundary_GT/" + stone.name + ".bmp", cv::IMREAD_GRAYSCALE);
    if (img.empty() || gt.empty()) GTEST_SKIP() << "unreadable " << stone.name << " in " << dir;
    ASSERT_EQ(img.size(), gt.size());
    const cv::Mat mask = ComputeForegroundMask(img);
    const double iou = MaskIoU(mask, gt == 255, gt == 128);  // 128: unlabelled border band
    std::printf("grabcut %s (%dx%d): IoU %.4f\n", stone.name, img.cols, img.rows, iou);
    RecordProperty(std::string("iou_") + stone.name, std::to_string(iou));
    EXPECT_GE(iou, stone.min_iou) << stone.name;
  }
}

}  // namespace
}  // namespace aggscan
