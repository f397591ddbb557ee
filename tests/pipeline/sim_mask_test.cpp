// The foreground mask on the sim renderer's views, against its ground truth.
#include <algorithm>
#include <cstdio>
#include <cstdlib>
#include <vector>

#include <gtest/gtest.h>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "common/clock.h"
#include "config/config.h"
#include "drivers/sim/render.h"
#include "pipeline/mask.h"
#include "synth_scene.h"

namespace aggscan {
namespace {

// Issue 3 item 2: IoU >= 0.98 (measured 0.9816-0.9984). 18 views at the
// rig's 2016 x 1512: ~25 s (the renderer is built with -O2
// even in Debug builds).
TEST(SimMask, IoUOnRenderedViews) {
  double worst = 1.0;
  for (uint64_t seed : {1, 2, 3}) {
    Config cfg;
    cfg.sim.seed = seed;
    auto world = sim::SimWorld::Create(cfg);
    ASSERT_TRUE(world.ok()) << world.error().ToString();
    sim::Renderer r(**world, 2016, 1512);
    for (int side : {1, 2}) {
      for (double angle : {0.0, 120.0, 240.0}) {
        sim::RenderOptions o;
        o.want_mask = true;
        o.noise_seed = seed * 100 + side;
        const sim::RenderedImage img = r.Render(side, angle, o);
        cv::Mat rgb(img.height, img.width, CV_8UC3, const_cast<uint8_t*>(img.rgb.data()));
        cv::Mat bgr;
        cv::cvtColor(rgb, bgr, cv::COLOR_RGB2BGR);
        std::vector<unsigned char> jpg;
        cv::imencode(".jpg", bgr, jpg, {cv::IMWRITE_JPEG_QUALITY, 92});
        bgr = cv::imdecode(jpg, cv::IMREAD_COLOR);
        const cv::Mat truth(img.height, img.width, CV_8UC1, const_cast<uint8_t*>(img.mask.data()));
        const TimeNs t0 = MonotonicNs();
        const cv::Mat mask = ComputeForegroundMask(bgr);
        const double ms = static_cast<double>(MonotonicNs() - t0) / 1e6;
        const double iou = testing::MaskIoU(mask, truth);
        std::printf("sim seed %llu side %d angle %.0f: IoU %.4f, %.0f ms\n", static_cast<unsigned long long>(seed), side,
                    angle, iou, ms);
        if (iou < 0.98 && std::getenv("AGGSCAN_DUMP")) {
          const std::string stem = "/tmp/sim_s" + std::to_string(seed) + "_" + std::to_string(side) + "_" +
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

}  // namespace
}  // namespace aggscan
