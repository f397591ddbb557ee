// A simulated sample for the reconstruction tests, rendered offline.
#pragma once

#include <gtest/gtest.h>

#include <cstdio>
#include <filesystem>
#include <fstream>
#include <opencv2/imgcodecs.hpp>
#include <sstream>
#include <string>

#include "cli/sim_capture.h"
#include "common/rig_calibration.h"
#include "config/config.h"
#include "drivers/sim/world.h"

namespace aggscan::test {

// Puts the sim's ground-truth masks where the side stage keeps its masks (it
// reuses them), so that the geometric stages can be tested alone.
inline void PlaceTruthMasks(const std::string& sample, int sides, int views) {
  namespace fs = std::filesystem;
  for (int side = 1; side <= sides; ++side) {
    const std::string dst = sample + "/results/masks/side" + std::to_string(side);
    fs::create_directories(dst);
    for (int v = 0; v < views; ++v) {
      char name[32];
      std::snprintf(name, sizeof name, "view_%03d", v);
      const cv::Mat m =
          cv::imread(sample + "/truth/side" + std::to_string(side) + "/" + name + "_mask.pgm",
                     cv::IMREAD_GRAYSCALE);
      EXPECT_FALSE(m.empty()) << sample << " side " << side << " " << name;
      cv::imwrite(dst + "/" + name + ".png", m);
    }
  }
}

/// Renders `sides` x `views` photos (custom profile, `step_deg` apart) of the
/// sim rock `seed` at width x height into dir/sample and returns that path.
/// calibration: the sim's exact rig calibration is recorded in the sample.
/// truth_masks: the sim's ground-truth masks are put where the side stage
/// keeps its masks (it reuses them), to test the geometric stages alone.
/// extra_config: more TOML for the capture's config (e.g. a [rig] table);
/// capture_extra: more keys of its [capture] table.
inline std::string CaptureSimSample(const std::string& dir, uint64_t seed, int sides,
                                    bool calibration, bool truth_masks, int views, int width,
                                    int height, double step_deg,
                                    const std::string& extra_config = "",
                                    const std::string& capture_extra = "") {
  namespace fs = std::filesystem;
  const std::string cfg = dir + "/cfg.toml";
  std::ofstream(cfg) << "[capture]\nprofile = \"custom\"\nsides = " << sides
                     << "\nviews_per_side = " << views << "\nstep_deg = " << step_deg << "\n"
                     << capture_extra << extra_config;
  SimCaptureOptions o;
  o.seed = seed;
  o.out = dir + "/sample";
  o.config_path = cfg;
  o.width = width;
  o.height = height;
  std::ostringstream out, err;
  EXPECT_EQ(RunSimCapture(o, out, err), 0) << err.str();
  if (calibration) {
    Config c;
    c.sim.seed = seed;
    sim::SimWorld world(c);
    EXPECT_TRUE(
        SaveCalibration(o.out + "/calibration.json", world.TruthCalibration(width, height)));
  }
  if (truth_masks) PlaceTruthMasks(o.out, sides, views);
  return o.out;
}

}  // namespace aggscan::test
