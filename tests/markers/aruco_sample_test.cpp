// ArUco scale markers end to end: a sample captured by `aggscan sim capture`
// with ArUco markers and no colour labels in its config (the marker image is
// drawn by the capture itself), reconstructed by the worker's stages; the
// sample's stitch.json and morphology.json say the scale was checked by the
// ArUco markers, with the residual against the configured sizes.
#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <opencv2/imgcodecs.hpp>
#include <sstream>

#include "cli/sim_capture.h"
#include "common/fsutil.h"
#include "drivers/sim/world.h"
#include "pipeline/worker/reconstruct.h"
#include "tests/util/temp_dir.h"

namespace aggscan {
namespace {

namespace fs = std::filesystem;
using nlohmann::json;

// One side, 30 views at 1008 x 756, the sim's exact calibration and its
// ground-truth masks (the geometric stages alone; the classical masks with
// markers on the disc are checked in aruco_scale_test): ~9 s in Debug.
TEST(ArucoSample, CaptureAndReconstructRecordTheArucoScale) {
  test::TempDir tmp;
  const std::string cfg = tmp.path() + "/cfg.toml";
  std::ofstream(cfg)
      << "[capture]\nprofile = \"custom\"\nsides = 1\nviews_per_side = 30\nstep_deg = 30\n"
         "[sim]\nrock_size_mm = 100.0\n"
         "[rig]\nmarkers = []\n"
         "aruco_markers = [{id = 1, x_mm = 80.0, y_mm = 80.0},\n"
         "  {id = 5, x_mm = -80.0, y_mm = 80.0, yaw_deg = 30.0},\n"
         "  {id = 9, x_mm = -80.0, y_mm = -80.0, yaw_deg = -60.0}]\n";
  SimCaptureOptions o;
  o.seed = 11;
  o.out = tmp.path() + "/sample";
  o.config_path = cfg;
  o.width = 1008;
  o.height = 756;
  std::ostringstream out, err;
  ASSERT_EQ(RunSimCapture(o, out, err), 0) << err.str();
  Config c;
  sim::SimWorld world(c);
  ASSERT_TRUE(SaveCalibration(o.out + "/calibration.json", world.TruthCalibration(1008, 756)));
  const std::string dst = o.out + "/results/masks/side1";
  fs::create_directories(dst);
  for (int v = 0; v < 30; ++v) {
    char name[32];
    std::snprintf(name, sizeof name, "view_%03d", v);
    const cv::Mat m =
        cv::imread(o.out + "/truth/side1/" + name + "_mask.pgm", cv::IMREAD_GRAYSCALE);
    ASSERT_FALSE(m.empty());
    cv::imwrite(dst + "/" + name + ".png", m);
  }

  ReconstructOptions opts;
  opts.state_dir = tmp.path();
  const Status st = ReconstructSample(o.out, opts);
  ASSERT_TRUE(st) << st.error().ToString();
  Result<std::string> text = ReadFile(o.out + "/results/stitch.json");
  ASSERT_TRUE(text.ok()) << text.error().ToString();
  const json stitch = json::parse(*text);
  const json& aru = stitch["per_side"][0]["aruco_scale"];
  std::printf("stitch.json aruco_scale: %s\nscale_residual_mm %s, scale_reference %s\n",
              aru.dump().c_str(), stitch["scale_residual_mm"].dump().c_str(),
              stitch["scale_reference"].dump().c_str());
  ASSERT_TRUE(aru.value("ok", false)) << aru.dump();
  EXPECT_EQ(aru["markers_used"].get<int>(), 3);
  EXPECT_NEAR(aru["scale"].get<double>(), 1.0, 2e-4);  // measured 1.00000004
  EXPECT_LT(aru["rms_mm"].get<double>(), 0.03);        // measured 0.0043 over 21 lengths
  EXPECT_EQ(stitch["scale_reference"], "aruco");
  EXPECT_DOUBLE_EQ(stitch["scale_residual_mm"].get<double>(), aru["rms_mm"].get<double>());
  Result<json> m = ReadMorphology(o.out);
  ASSERT_TRUE(m.ok()) << m.error().ToString();
  EXPECT_EQ((*m)["quality"]["scale_reference"], "aruco");
  EXPECT_DOUBLE_EQ((*m)["quality"]["scale_residual_mm"].get<double>(), aru["rms_mm"].get<double>());
}

}  // namespace
}  // namespace aggscan
