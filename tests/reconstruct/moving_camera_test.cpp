// A rock too big for the turntable, the study's advice: it lies still and the
// operator walks the camera round it. On the simulated rig the rock rests on
// the ground, a 1.2 m mat, among the four labels as ground control points;
// nothing turns. The sim's walker carries
// the camera to a rough ring of positions (elevations alternating about
// 23 and 47 deg, azimuth, distance, aim and roll off the plan by a person's
// amounts) in a shuffled order. The worker masks the views (classical
// masks), poses them by SfM alone (every pair matched), scales them by the
// labels, stitches the two sides and measures the rock.
#include <gtest/gtest.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <string>

#include "common/fsutil.h"
#include "config/config.h"
#include "drivers/sim/world.h"
#include "pipeline/core/geometry.h"
#include "pipeline/sfm/colmap_sfm.h"
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

constexpr int kViews = 12;
constexpr int kWidth = 2016, kHeight = 1512;

// The camera centre (table frame, mm) of a truth view: the disc does not turn,
// so the table frame is the world frame at platter 0.
Eigen::Vector3d TrueCentre(const json& t, const sim::SimWorld& world, int side) {
  std::array<double, 16> m{};
  for (int i = 0; i < 16; ++i) m[i] = t["rock_to_camera_4x4"][i].get<double>();
  const geom::Rigid3 rock_to_cam = geom::Rigid3::FromRowMajor4(m);
  const sim::Rigid rest = world.RockToWorld(side, t["platter_deg"].get<double>());
  const geom::Rigid3 rock_to_table = geom::Rigid3::FromRowMajor4(rest.Matrix4());
  const geom::Rigid3 cam_from_table = rock_to_cam * rock_to_table.Inverse();
  return -(cam_from_table.R.transpose() * cam_from_table.t);
}

TEST(MovingCamera, WalkedRoundAStillRockPosedByColmapScaledByTheLabels) {
  if (!PathExists(ColmapSfmOptions{}.colmap_binary)) {
    GTEST_SKIP() << "needs Debian's colmap";
  }
  test::TempDir tmp;
  const uint64_t seed = 1;
  const std::string sample =
      test::CaptureSimSample(tmp.path(), seed, 2, true, true, kViews, kWidth, kHeight, 30.0,
                             "[turntable]\nbackend = \"manual\"\n[sim]\nwalk_shuffle = true\n"
                             "[rig]\nturntable_diameter_mm = 1200.0\n",
                             "mode = \"moving_camera\"\n");
  const json car = ReadJsonFile(sample + "/side1/view_004.json");
  EXPECT_EQ(car.value("capture_mode", ""), "moving_camera") << car.dump();
  EXPECT_FALSE(car.contains("measured_angle_deg"));

  // The walker went round: elevations on both sides of the tripod's, and the
  // photos out of ring order.
  Config c;
  c.sim.seed = seed;
  const sim::SimWorld world(c);
  const json truth = ReadJsonFile(sample + "/truth.json");
  std::map<std::pair<int, int>, Eigen::Vector3d> centre;
  double lowest = 90, highest = 0;
  int out_of_order = 0;
  for (int side : {1, 2}) {
    double prev_az = 0;
    for (const json& t : truth["views"]) {
      if (t["side"] != side) continue;
      const Eigen::Vector3d C = TrueCentre(t, world, side);
      centre[{side, t["view"].get<int>()}] = C;
      const double el = std::atan2(C.z(), std::hypot(C.x(), C.y())) * 180 / M_PI;
      lowest = std::min(lowest, el), highest = std::max(highest, el);
      const double az = std::atan2(C.x(), -C.y()) * 180 / M_PI;
      if (t["view"].get<int>() > 0 && std::abs(std::remainder(az - prev_az, 360.0) + 30) > 20)
        ++out_of_order;
      prev_az = az;
      EXPECT_EQ(t["platter_deg"].get<double>(), 0.0) << "the disc must not turn";
    }
  }
  std::printf("walker: elevations %.1f .. %.1f deg, %d of %d steps not the ring's next\n", lowest,
              highest, out_of_order, 2 * (kViews - 1));
  EXPECT_LT(lowest, 30.0);
  EXPECT_GT(highest, 40.0);
  EXPECT_GT(out_of_order, 10);

  // The rig's poses setting is for its turntable (the default, turntable+ba):
  // a walked camera's views go to SfM whatever it says.
  ReconstructOptions opts;
  ASSERT_EQ(opts.poses, PosesPath::kTurntable);
  auto st = ReconstructSample(sample, opts);
  ASSERT_TRUE(st) << st.error().ToString();
  for (int side : {1, 2}) {
    // The rock in every view, though the disc's rim and its labels cross the
    // frame's edge in the higher, closer views.
    const json sr = ReadJsonFile(sample + "/results/side" + std::to_string(side) + "_morph2d.json");
    int whole = 0;
    for (const json& v : sr["views"]) whole += v.value("ok", false) ? 1 : 0;
    EXPECT_EQ(whole, kViews) << "side " << side;
    const json p = ReadJsonFile(sample + "/results/poses_side" + std::to_string(side) + ".json");
    ASSERT_EQ(p["method"], "sfm") << p.dump().substr(0, 300);
    const json& s = p["sfm"];
    EXPECT_EQ(s["registered_views"], kViews) << s.dump();
    EXPECT_EQ(s["pairs"], "exhaustive");
    EXPECT_EQ(s["capture_mode"], "moving_camera");
    EXPECT_TRUE(s["checks_passed"].get<bool>()) << s["checks"].dump();
    EXPECT_EQ(p["scale"]["reference"], "labels");
    const double residual = p["scale"]["residual_mm"].get<double>();
    EXPECT_LT(residual, 0.5) << p["scale"].dump();
    // Each camera where the walker held it.
    double worst = 0;
    for (const json& v : p["views"]) {
      std::array<double, 16> m{};
      for (int i = 0; i < 16; ++i) m[i] = v["cam_from_table_4x4"][i].get<double>();
      const geom::Rigid3 T = geom::Rigid3::FromRowMajor4(m);
      const Eigen::Vector3d C = -(T.R.transpose() * T.t);
      worst = std::max(worst, (C - centre.at({side, v["view"].get<int>()})).norm());
    }
    std::printf(
        "side %d: %d/%d views, %.3f px, scale residual %.3f mm, worst centre %.2f mm, "
        "COLMAP %.1f s\n",
        side, s["registered_views"].get<int>(), s["input_views"].get<int>(),
        s["mean_reprojection_px"].get<double>(), residual, worst, s["colmap_s"].get<double>());
    // As for the turntable's SfM path: the labels fix the frame at the disc,
    // ~650 mm from the camera; a wrong model lands centimetres off.
    EXPECT_LT(worst, 15.0);
  }
  test::ExpectRockMatchesTruth(sample, truth, "moving camera");
}

}  // namespace
}  // namespace aggscan
