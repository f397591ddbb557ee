// The foreground mask on the sim renderer's views, against its ground truth.
#include <gtest/gtest.h>

#include <algorithm>
#include <cstdio>
#include <cstdlib>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <vector>

#include "common/clock.h"
#include "pipeline/masks/mask.h"
#include "tests/masks/sim_photos.h"
#include "tests/util/synth_scene.h"

namespace aggscan {
namespace {

// Target: IoU >= 0.98 (measured 0.9816-0.9984). 18 views at the
// rig's 2016 x 1512: ~25 s (the renderer is built with -O2
// even in Debug builds).
TEST(SimMask, IoUOnRenderedViews) {
  double worst = 1.0;
  for (uint64_t seed : {1, 2, 3}) {
    auto photos = testing::SimPhotos::Create(seed);
    ASSERT_TRUE(photos.ok()) << photos.error().ToString();
    for (int side : {1, 2}) {
      for (double angle : {0.0, 120.0, 240.0}) {
        const testing::SimPhoto view = photos->Render(side, angle);
        const cv::Mat& bgr = view.bgr;
        const cv::Mat& truth = view.truth;
        const TimeNs t0 = MonotonicNs();
        const cv::Mat mask = ComputeForegroundMask(bgr);
        const double ms = static_cast<double>(MonotonicNs() - t0) / 1e6;
        const double iou = testing::MaskIoU(mask, truth);
        std::printf("sim seed %llu side %d angle %.0f: IoU %.4f, %.0f ms\n",
                    static_cast<unsigned long long>(seed), side, angle, iou, ms);
        if (iou < 0.98 && std::getenv("AGGSCAN_DUMP")) {
          const std::string stem = "/tmp/sim_s" + std::to_string(seed) + "_" +
                                   std::to_string(side) + "_" +
                                   std::to_string(static_cast<int>(angle));
          cv::Mat half;
          cv::resize(bgr, half, cv::Size(), 0.5, 0.5, cv::INTER_AREA);
          cv::imwrite(stem + "_img.png", half);
          cv::Mat vis;
          cv::merge(std::vector<cv::Mat>{mask & ~truth, truth & mask, truth & ~mask}, vis);
          cv::resize(vis, half, cv::Size(), 0.5, 0.5, cv::INTER_NEAREST);
          cv::imwrite(stem + "_err.png", half);
        }
        worst = std::min(worst, iou);
        EXPECT_GE(iou, 0.98) << "seed " << seed << " side " << side << " angle " << angle;
      }
    }
  }
  std::printf("sim worst IoU %.4f\n", worst);
}

// A visual hull is the intersection of the views' cones, so rock that one
// mask leaves out is carved out of the model, whatever the other views say;
// rock a mask adds is carved by the others. Lost rock is therefore measured
// per view as the rock pixels missing from the mask per pixel of outline (a
// mean inward offset of the outline, px). Seeds 9 and 15 had the worst views
// of a 20-rock validation: a lit face as bright as the table and a shaded
// underside beside the shadow, which a 14 px wide full-resolution band gave to
// the background (up to 2.5 px), and an object marker along the silhouette,
// which a 30 % rim-contact rule left out (1.9 px). Measured since: at most
// 0.36 px lost and 0.94 px added over 160 views of 20 rocks.
TEST(SimMask, NoViewLosesRockAtTheSilhouette) {
  double worst_lost = 0, worst_added = 0;
  for (uint64_t seed : {9, 15}) {
    auto photos = testing::SimPhotos::Create(seed);
    ASSERT_TRUE(photos.ok()) << photos.error().ToString();
    for (int side : {1, 2}) {
      for (int k = 0; k < 12; ++k) {
        const double angle = 30.0 * k;
        const testing::SimPhoto v = photos->Render(side, angle);
        const cv::Mat mask = ComputeForegroundMask(v.bgr) > 127;
        const cv::Mat truth = v.truth > 127;
        std::vector<std::vector<cv::Point>> outline;
        cv::findContours(truth.clone(), outline, cv::RETR_EXTERNAL, cv::CHAIN_APPROX_NONE);
        double length = 0;
        for (const auto& c : outline) length += cv::arcLength(c, true);
        ASSERT_GT(length, 100.0);
        const double lost = cv::countNonZero(truth & ~mask) / length;
        const double added = cv::countNonZero(mask & ~truth) / length;
        std::printf("sim seed %llu side %d angle %3.0f: rock lost %.2f px, added %.2f px\n",
                    static_cast<unsigned long long>(seed), side, angle, lost, added);
        EXPECT_LE(lost, 0.6) << "seed " << seed << " side " << side << " angle " << angle;
        EXPECT_LE(added, 1.5) << "seed " << seed << " side " << side << " angle " << angle;
        worst_lost = std::max(worst_lost, lost);
        worst_added = std::max(worst_added, added);
      }
    }
  }
  std::printf("sim worst: rock lost %.2f px, added %.2f px per px of outline\n", worst_lost,
              worst_added);
}

}  // namespace
}  // namespace aggscan
