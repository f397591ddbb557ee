#include "common/rig_calibration.h"

#include <gtest/gtest.h>

#include <fstream>

#include "config/config.h"
#include "drivers/sim/world.h"
#include "tests/util/temp_dir.h"

namespace aggscan {
namespace {

RigCalibration SimCalibration(const sim::SimWorld& world) {
  return world.TruthCalibration(world.config().camera.width, world.config().camera.height);
}

TEST(RigCalibration, ProjectsTablePointsLikeTheSimCamera) {
  Config config;
  config.sim.seed = 3;
  sim::SimWorld world(config);
  const RigCalibration cal = SimCalibration(world);
  const sim::Intrinsics intr = world.intrinsics();
  for (double angle : {0.0, 30.0, 137.5, 300.0}) {
    for (const sim::Vec3 p :
         {sim::Vec3{120, 0, 0}, sim::Vec3{-50, 80, 40}, sim::Vec3{10, -140, 90}}) {
      double u0, v0;
      ASSERT_TRUE(world.ProjectTurntablePoint(p, angle, intr, &u0, &v0));
      const auto m = cal.CamFromTable(angle);
      const std::array<double, 3> pc = {m[0] * p.x + m[1] * p.y + m[2] * p.z + m[3],
                                        m[4] * p.x + m[5] * p.y + m[6] * p.z + m[7],
                                        m[8] * p.x + m[9] * p.y + m[10] * p.z + m[11]};
      double u1, v1;
      ASSERT_TRUE(cal.camera.Project(pc, &u1, &v1));
      EXPECT_NEAR(u0, u1, 1e-9);
      EXPECT_NEAR(v0, v1, 1e-9);
    }
  }
  // The camera sits at the configured distance and elevation from the centre.
  const auto c = cal.CameraCentreTable0();
  const double horiz = std::hypot(c[0], c[1]);
  EXPECT_GT(c[2], 0);
  EXPECT_NEAR(std::atan2(c[2] - sim::kAimHeightMm, horiz) * 180 / M_PI,
              config.sim.camera_elevation_deg, 3.0);
}

TEST(RigCalibration, JsonRoundTripAndFileIo) {
  Config config;
  sim::SimWorld world(config);
  RigCalibration cal = SimCalibration(world);
  cal.reprojection_rms_px = 0.21;
  cal.views_used = 30;
  test::TempDir tmp;
  const std::string path = CalibrationPath(tmp.path());
  ASSERT_TRUE(SaveCalibration(path, cal));
  auto back = LoadCalibration(path);
  ASSERT_TRUE(back) << back.error().ToString();
  EXPECT_EQ(back->camera.width, cal.camera.width);
  EXPECT_DOUBLE_EQ(back->camera.fx, cal.camera.fx);
  EXPECT_DOUBLE_EQ(back->camera.k1, cal.camera.k1);
  EXPECT_EQ(back->R_cam_table0, cal.R_cam_table0);
  EXPECT_EQ(back->t_cam_table0, cal.t_cam_table0);
  EXPECT_DOUBLE_EQ(back->reprojection_rms_px, 0.21);
  EXPECT_EQ(back->views_used, 30);
  EXPECT_EQ(back->method, "sim-truth");
}

TEST(RigCalibration, MissingFileSaysHowToCalibrate) {
  test::TempDir tmp;
  auto r = LoadCalibration(CalibrationPath(tmp.path()));
  ASSERT_FALSE(r);
  EXPECT_EQ(r.error().cls, ErrorClass::kNotFound);
  EXPECT_NE(r.error().message.find("aggscan calibrate"), std::string::npos);
}

TEST(RigCalibration, DamagedFilesAreRefusedWithTheReason) {
  Config config;
  sim::SimWorld world(config);
  const nlohmann::json good = CalibrationToJson(SimCalibration(world));
  struct Case {
    const char* name;
    std::function<void(nlohmann::json&)> edit;
    const char* expect;
  };
  const std::vector<Case> cases = {
      {"format", [](nlohmann::json& j) { j["format"] = "other"; }, "format"},
      {"fx", [](nlohmann::json& j) { j["camera"]["fx"] = -5.0; }, "focal"},
      {"centre", [](nlohmann::json& j) { j["camera"]["cx"] = 1e6; }, "principal point"},
      {"missing", [](nlohmann::json& j) { j["camera"].erase("fy"); }, "missing or mistyped"},
      {"rotation", [](nlohmann::json& j) { j["cam_from_table0"]["R"][0] = 2.0; }, "not a rotation"},
      {"reflection",
       [](nlohmann::json& j) {
         for (int k = 0; k < 3; ++k)
           j["cam_from_table0"]["R"][k] = -j["cam_from_table0"]["R"][k].get<double>();
       },
       "reflection"},
  };
  for (const Case& c : cases) {
    nlohmann::json j = good;
    c.edit(j);
    auto r = CalibrationFromJson(j, "calibration.json");
    ASSERT_FALSE(r) << c.name;
    EXPECT_EQ(r.error().cls, ErrorClass::kCorrupt) << c.name;
    EXPECT_NE(r.error().message.find(c.expect), std::string::npos)
        << c.name << ": " << r.error().message;
  }
  test::TempDir tmp;
  std::ofstream(tmp.path() + "/calibration.json") << "{ not json";
  auto r = LoadCalibration(tmp.path() + "/calibration.json");
  ASSERT_FALSE(r);
  EXPECT_EQ(r.error().cls, ErrorClass::kCorrupt);
}

TEST(RigCalibration, FitsSameResolutionOrSameAspect) {
  Config config;
  sim::SimWorld world(config);
  const RigCalibration cal = world.TruthCalibration(2016, 1512);
  EXPECT_TRUE(CheckCalibrationFits(cal, 2016, 1512));
  EXPECT_TRUE(CheckCalibrationFits(cal, 1008, 756));
  auto bad = CheckCalibrationFits(cal, 1920, 1080);
  ASSERT_FALSE(bad);
  EXPECT_NE(bad.error().message.find("2016x1512"), std::string::npos);
  // Resized lens equals the sim's own lens at that resolution.
  const CameraModel half = cal.camera.Resized(1008, 756);
  const RigCalibration truth_half = world.TruthCalibration(1008, 756);
  EXPECT_NEAR(half.fx, truth_half.camera.fx, 1e-9);
  EXPECT_NEAR(half.cx, truth_half.camera.cx, 1e-9);
  EXPECT_NEAR(half.cy, truth_half.camera.cy, 1e-9);
}

// A window of the frame projects every point where the full frame does,
// shifted by the window's corner (distortion included), and halving an
// even-cornered window gives the lens of the halved frame's window.
TEST(CameraModel, CroppedProjectsAsTheFullFrameShifted) {
  CameraModel c;
  c.width = 2016, c.height = 1512;
  c.fx = 2600, c.fy = 2610, c.cx = 1011.3, c.cy = 749.8;
  c.k1 = -0.12, c.k2 = 0.05, c.p1 = 0.001, c.p2 = -0.0007, c.k3 = 0.01;
  const CameraModel w = c.Cropped(600, 402, 800, 640);
  EXPECT_EQ(w.width, 800);
  EXPECT_EQ(w.height, 640);
  for (const std::array<double, 3>& p :
       {std::array<double, 3>{10, -20, 600}, std::array<double, 3>{-150, 90, 640},
        std::array<double, 3>{0, 0, 500}}) {
    double u = 0, v = 0, uw = 0, vw = 0;
    ASSERT_TRUE(c.Project(p, &u, &v));
    ASSERT_TRUE(w.Project(p, &uw, &vw));
    EXPECT_NEAR(uw, u - 600, 1e-9);
    EXPECT_NEAR(vw, v - 402, 1e-9);
    double uh = 0, vh = 0, uwh = 0, vwh = 0;
    ASSERT_TRUE(c.Resized(1008, 756).Project(p, &uh, &vh));
    ASSERT_TRUE(w.Resized(400, 320).Project(p, &uwh, &vwh));
    EXPECT_NEAR(uwh, uh - 300, 1e-9);
    EXPECT_NEAR(vwh, vh - 201, 1e-9);
  }
}

}  // namespace
}  // namespace aggscan
