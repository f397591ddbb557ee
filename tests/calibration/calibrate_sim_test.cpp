// End to end on the sim rig: a charuco capture (30 views over a full turn,
// sensor noise, lens distortion k1 -0.08 k2 0.02, JPEG, turntable angle
// errors and settle ringing), `aggscan calibrate`, compared with the sim's
// exact calibration (SimWorld::TruthCalibration).
#include <gtest/gtest.h>

#include <chrono>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <sstream>

#include "cli/calibrate_command.h"
#include "cli/sim_capture.h"
#include "common/fsutil.h"
#include "common/rig_calibration.h"
#include "config/config.h"
#include "drivers/sim/world.h"
#include "pipeline/calib/calibrate.h"
#include "tests/util/temp_dir.h"

namespace aggscan {
namespace {

namespace fs = std::filesystem;
using nlohmann::json;

// The board as an operator lays it: off the axis and turned.
constexpr double kBoardX = 6.0, kBoardY = -4.0, kBoardYaw = 12.0;

std::string WriteToml(const std::string& dir, const std::string& body) {
  const std::string path = dir + "/capture.toml";
  std::ofstream(path) << body;
  return path;
}

std::string CaptureToml(int width, int height) {
  std::ostringstream t;
  t << "[camera]\nwidth = " << width << "\nheight = " << height
    << "\n\n[sim]\nseed = 11\nboard_x_mm = " << kBoardX << "\nboard_y_mm = " << kBoardY
    << "\nboard_yaw_deg = " << kBoardYaw << "\n";
  return t.str();
}

// Renders a calibration capture into dir/samples/<id>; returns the sample dir.
std::string Capture(const std::string& dir, const std::string& id, int width, int height,
                    const std::string& scene = "charuco", int views = 0,
                    const std::string& calibration = "") {
  SimCaptureOptions o;
  o.calibration = calibration;
  o.scene = scene;
  o.seed = 11;
  o.config_path = WriteToml(dir, CaptureToml(width, height));
  o.out = dir + "/samples/" + id;
  if (views > 0) {
    o.profile = "full-turn";
    o.views_per_side = views;
  }
  std::ostringstream out, err;
  fs::create_directories(dir + "/samples");
  const int rc = RunSimCapture(o, out, err);
  EXPECT_EQ(rc, 0) << err.str();
  return o.out;
}

// The camera the sim renders with, at that resolution.
RigCalibration Truth(int width, int height) {
  Config c;
  c.camera.width = width;
  c.camera.height = height;
  c.sim.seed = 11;
  sim::SimWorld w(c, {.rock_faces = 2000});
  return w.TruthCalibration(width, height);
}

double AngleBetweenDeg(const std::array<double, 3>& a, const std::array<double, 3>& b) {
  const double d = a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
  const double na = std::hypot(a[0], a[1], a[2]), nb = std::hypot(b[0], b[1], b[2]);
  return std::acos(std::clamp(d / (na * nb), -1.0, 1.0)) * 180 / M_PI;
}

// Rotation angle of R1^T R2 (row-major), degrees.
double RotationDiffDeg(const std::array<double, 9>& R1, const std::array<double, 9>& R2) {
  double tr = 0;
  for (int i = 0; i < 3; ++i)
    for (int k = 0; k < 3; ++k) tr += R1[k * 3 + i] * R2[k * 3 + i];
  return std::acos(std::clamp((tr - 1) / 2, -1.0, 1.0)) * 180 / M_PI;
}

// Largest pixel difference between the two calibrations' projections of
// table points over the disc, from its top up to 150 mm above it (where a
// rock is), at several turntable angles.
double MaxProjectionDiffPx(const RigCalibration& a, const RigCalibration& b) {
  double worst = 0;
  for (double angle : {0.0, 90.0, 180.0, 270.0}) {
    const auto Ma = a.CamFromTable(angle), Mb = b.CamFromTable(angle);
    for (double z : {0.0, 75.0, 150.0}) {
      for (double r : {0.0, 50.0, 100.0, 150.0}) {
        for (int k = 0; k < 12; ++k) {
          const double p[3] = {r * std::cos(k * M_PI / 6), r * std::sin(k * M_PI / 6), z};
          auto proj = [&](const std::array<double, 16>& M, const CameraModel& cam, double* u,
                          double* v) {
            const std::array<double, 3> pc = {M[0] * p[0] + M[1] * p[1] + M[2] * p[2] + M[3],
                                              M[4] * p[0] + M[5] * p[1] + M[6] * p[2] + M[7],
                                              M[8] * p[0] + M[9] * p[1] + M[10] * p[2] + M[11]};
            return cam.Project(pc, u, v);
          };
          double ua, va, ub, vb;
          if (!proj(Ma, a.camera, &ua, &va) || !proj(Mb, b.camera, &ub, &vb)) return 1e9;
          worst = std::max(worst, std::hypot(ua - ub, va - vb));
        }
      }
    }
  }
  return worst;
}

class CalibrateSim : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    tmp_ = new test::TempDir();
    const auto t0 = std::chrono::steady_clock::now();
    sample_ = Capture(tmp_->path(), "board-1", kW, kH);
    capture_s_ = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  }
  static void TearDownTestSuite() {
    delete tmp_;
    tmp_ = nullptr;
  }
  // A copy of the capture to damage.
  static std::string CopyOfSample(const std::string& name) {
    const std::string dst = tmp_->path() + "/samples/" + name;
    fs::copy(sample_, dst, fs::copy_options::recursive);
    return dst;
  }
  // The rig's own resolution.
  static constexpr int kW = 2016, kH = 1512;
  static test::TempDir* tmp_;
  static std::string sample_;
  static double capture_s_;
};
test::TempDir* CalibrateSim::tmp_ = nullptr;
std::string CalibrateSim::sample_;
double CalibrateSim::capture_s_ = 0;

// What a free k2 does with the board's coverage of the image (calibrate.h):
// measured and printed, not asserted beyond a sane fx.
TEST_F(CalibrateSim, FreeK2IsPoorlyDetermined) {
  CalibrateOptions o;
  o.k2 = CalibrateOptions::K2::kFree;
  auto r = CalibrateSampleSide(sample_, 1, CalibrationConfig{}, o);
  ASSERT_TRUE(r) << r.error().ToString();
  const RigCalibration truth = Truth(kW, kH);
  std::printf(
      "free k2: fx %+.4f %%, k1 %.4f (sigma %.4f), k2 %.4f (sigma %.4f; truth %.2f), projection "
      "max %.3f px\n",
      100 * (r->cal.camera.fx / truth.camera.fx - 1), r->cal.camera.k1, r->sigma_k1,
      r->cal.camera.k2, r->sigma_k2, truth.camera.k2, MaxProjectionDiffPx(r->cal, truth));
  EXPECT_LT(std::abs(r->cal.camera.fx / truth.camera.fx - 1), 0.005);
  EXPECT_GT(r->sigma_k2, CalibrateOptions{}.max_k2_sigma);  // so kAuto fixes it
}

TEST_F(CalibrateSim, MatchesTheSimTruth) {
  CalibrationConfig board;  // the [calibration] defaults the capture used
  auto r = CalibrateSampleSide(sample_, 1, board);
  ASSERT_TRUE(r) << r.error().ToString();
  const RigCalibration& cal = r->cal;
  const RigCalibration truth = Truth(kW, kH);
  const auto C = cal.CameraCentreTable0(), Ct = truth.CameraCentreTable0();
  // The turntable axis (table z) as the camera sees it: third column of R.
  const std::array<double, 3> axis = {cal.R_cam_table0[2], cal.R_cam_table0[5],
                                      cal.R_cam_table0[8]};
  const std::array<double, 3> axis_t = {truth.R_cam_table0[2], truth.R_cam_table0[5],
                                        truth.R_cam_table0[8]};
  const double fx_err = cal.camera.fx / truth.camera.fx - 1;
  const double centre_err = std::hypot(C[0] - Ct[0], C[1] - Ct[1], C[2] - Ct[2]);
  const double axis_err = AngleBetweenDeg(axis, axis_t);
  const double rot_err = RotationDiffDeg(cal.R_cam_table0, truth.R_cam_table0);
  const double proj_err = MaxProjectionDiffPx(cal, truth);
  std::printf(
      "capture %.1f s, calibrate %.1f s: views %d/%d, corners %d, RMS %.3f px (worst view %.3f, "
      "OpenCV init "
      "%.3f)\n  fx %.2f (truth %.2f, %+.4f %%, sigma %.2f px), k1 %.4f (%.4f), k2 %.4f (%.4f)\n  "
      "camera centre "
      "error %.3f mm, "
      "axis %.4f deg, rotation %.4f deg, board (%.2f, %.2f) mm yaw %.3f deg\n  projection over the "
      "disc "
      "up to 150 mm: max %.3f px\n",
      capture_s_, r->seconds, cal.views_used, r->views_total, cal.corners_used,
      cal.reprojection_rms_px, r->max_view_rms_px, r->init_rms_px, cal.camera.fx, truth.camera.fx,
      100 * fx_err, r->sigma_fx_px, cal.camera.k1, truth.camera.k1, cal.camera.k2, truth.camera.k2,
      centre_err, axis_err, rot_err, r->board_x_mm, r->board_y_mm, r->board_yaw_deg, proj_err);
  EXPECT_EQ(cal.views_used, 30);
  EXPECT_GE(cal.corners_used, 30 * 20);
  // Measured (seed 11, 2016x1512): RMS 0.045 px, fx -0.0000 % (sigma 0.39 px = 0.014 %), k1
  // -0.0801, centre 0.007 mm, axis 0.0004 deg, board 0.00 mm / 0.000 deg, projection 0.13 px.
  // Tolerances leave 5-20x margin for other seeds and platforms.
  EXPECT_LT(cal.reprojection_rms_px, 0.2);
  EXPECT_LT(std::abs(fx_err), 0.001);
  EXPECT_NEAR(cal.camera.k1, truth.camera.k1, 0.005);
  EXPECT_NEAR(cal.camera.cx, truth.camera.cx, 1e-9);
  EXPECT_LT(centre_err, 0.5);
  EXPECT_LT(axis_err, 0.02);
  EXPECT_LT(rot_err, 0.02);
  EXPECT_NEAR(r->board_x_mm, kBoardX, 0.2);
  EXPECT_NEAR(r->board_y_mm, kBoardY, 0.2);
  EXPECT_NEAR(r->board_yaw_deg, kBoardYaw, 0.05);
  EXPECT_LT(proj_err, 0.5);
  EXPECT_FALSE(r->k2_estimated);  // see FreeK2IsPoorlyDetermined
  EXPECT_EQ(cal.method, "charuco");
  EXPECT_EQ(cal.camera_id, "sim-cam0");
}

TEST_F(CalibrateSim, CommandWritesTheFileAndKeepsThePreviousOne) {
  const std::string state = tmp_->path() + "/state";
  fs::create_directories(state);
  std::ostringstream out, err;
  ASSERT_EQ(RunCalibrateCommand({sample_, "--state-dir", state}, out, err), 0) << err.str();
  EXPECT_NE(out.str().find("reprojection RMS"), std::string::npos) << out.str();
  auto first = LoadCalibration(CalibrationPath(state));
  ASSERT_TRUE(first) << first.error().ToString();
  EXPECT_EQ(first->board.value("squares_x", 0), 7);
  // Again: never a silent overwrite.
  std::ostringstream out2, err2;
  ASSERT_EQ(RunCalibrateCommand({sample_, "--state-dir", state}, out2, err2), 0) << err2.str();
  EXPECT_NE(err2.str().find("previous calibration is kept as"), std::string::npos) << err2.str();
  int prev = 0;
  for (const auto& e : fs::directory_iterator(state)) {
    if (e.path().filename().string().rfind("calibration.json.prev-", 0) == 0) {
      ++prev;
      auto kept = LoadCalibration(e.path().string());
      ASSERT_TRUE(kept);
      EXPECT_EQ(kept->created_utc, first->created_utc);
    }
  }
  EXPECT_EQ(prev, 1);
  // --out and --state-dir together are a usage error.
  std::ostringstream o3, e3;
  EXPECT_EQ(
      RunCalibrateCommand({sample_, "--state-dir", state, "--out", state + "/x.json"}, o3, e3), 2);
}

TEST_F(CalibrateSim, TooFewViewsIsRefusedWithWhatToDo) {
  // Keep five views in the manifest.
  const std::string s = CopyOfSample("few");
  json m = json::parse(*ReadFile(s + "/side1/manifest.json"));
  m["views"].erase(m["views"].begin() + 5, m["views"].end());
  ASSERT_TRUE(WriteFileAtomic(s + "/side1/manifest.json", m.dump()));
  auto r = CalibrateSampleSide(s, 1, CalibrationConfig{});
  ASSERT_FALSE(r);
  EXPECT_EQ(r.error().cls, ErrorClass::kInvalidArgument);
  const std::string msg = r.error().message;
  EXPECT_NE(msg.find("found in 5 of 5 views"), std::string::npos) << msg;
  EXPECT_NE(msg.find("at least 8 views"), std::string::npos) << msg;
  for (const char* hint : {"in view", "lit", "focus"})
    EXPECT_NE(msg.find(hint), std::string::npos) << hint;
  // Views over too little rotation: the axis cannot be found.
  CalibrateOptions narrow;
  narrow.min_views = 3;
  narrow.min_rotation_deg = 60;
  r = CalibrateSampleSide(s, 1, CalibrationConfig{}, narrow);
  ASSERT_FALSE(r);
  EXPECT_NE(r.error().message.find("deg of turntable rotation"), std::string::npos)
      << r.error().message;
}

TEST_F(CalibrateSim, WrongBoardConfigFindsNoCorners) {
  CalibrationConfig other;
  other.dictionary = "DICT_4X4_50";
  auto r = CalibrateSampleSide(sample_, 1, other);
  ASSERT_FALSE(r);
  EXPECT_NE(r.error().message.find("found in 0 of 30 views"), std::string::npos)
      << r.error().message;
  EXPECT_NE(r.error().message.find("DICT_4X4_50"), std::string::npos);
}

TEST_F(CalibrateSim, DamagedSidecarIsAnErrorNamingIt) {
  const std::string s = CopyOfSample("damaged");
  ASSERT_TRUE(WriteFileAtomic(s + "/side1/view_003.json", "{\"measured_angle_deg\": \"forty\""));
  auto r = CalibrateSampleSide(s, 1, CalibrationConfig{});
  ASSERT_FALSE(r);
  EXPECT_EQ(r.error().cls, ErrorClass::kCorrupt);
  EXPECT_NE(r.error().message.find("side1/view_003.json"), std::string::npos) << r.error().message;
  EXPECT_NE(r.error().message.find("measured_angle_deg"), std::string::npos);
  // Through the command: exit 1 and the same message, nothing written.
  std::ostringstream out, err;
  EXPECT_EQ(RunCalibrateCommand({s, "--out", tmp_->path() + "/never.json"}, out, err), 1);
  EXPECT_NE(err.str().find("view_003.json"), std::string::npos) << err.str();
  EXPECT_FALSE(PathExists(tmp_->path() + "/never.json"));
  // A side that was never captured.
  r = CalibrateSampleSide(s, 2, CalibrationConfig{});
  ASSERT_FALSE(r);
  EXPECT_NE(r.error().message.find("no manifest.json"), std::string::npos) << r.error().message;
}

TEST(CalibrateSimRock, RockCaptureHasNoBoardAndRecordsTheCalibrationGiven) {
  test::TempDir tmp;
  const std::string cal_path = tmp.path() + "/rig.json";
  RigCalibration given = Truth(640, 480);
  given.created_utc = "2026-03-04T05:06:07Z";
  ASSERT_TRUE(SaveCalibration(cal_path, given));
  const std::string s = Capture(tmp.path(), "rock", 640, 480, "rock", 6, cal_path);
  auto recorded = LoadCalibration(s + "/calibration.json");
  ASSERT_TRUE(recorded) << recorded.error().ToString();
  EXPECT_EQ(recorded->created_utc, "2026-03-04T05:06:07Z");
  auto r = CalibrateSampleSide(s, 1, CalibrationConfig{});
  ASSERT_FALSE(r);
  EXPECT_NE(r.error().message.find("found in 0 of 6 views"), std::string::npos)
      << r.error().message;
}

}  // namespace
}  // namespace aggscan
