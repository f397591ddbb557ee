// aggscand and the rig calibration: checked at start and at every arm, shown
// in the status API, never fatal; every sample records the calibration in
// effect (samples/<id>/calibration.json, write-once).
#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <sstream>

#include "cli/calibrate_command.h"
#include "common/fsutil.h"
#include "common/rig_calibration.h"
#include "config/config.h"
#include "daemon/calibration_check.h"
#include "drivers/sim/world.h"
#include "store/queue.h"
#include "store/sample_store.h"
#include "tests/scenario/process.h"

namespace aggscan::test {
namespace {

using nlohmann::json;

RigCalibration SimCalibration(int width, int height, const std::string& created) {
  Config c;
  sim::SimWorld w(c, {.rock_faces = 2000});
  RigCalibration cal = w.TruthCalibration(width, height);
  cal.method = "charuco";
  cal.created_utc = created;
  cal.reprojection_rms_px = 0.123;
  cal.views_used = 30;
  return cal;
}

json Calibration(Daemon& d) { return d.Get("/api/v1/status").value("calibration", json()); }

TEST(CalibrationDaemon, MissingThenWrittenWhileRunning) {
  TempDir t;
  const std::string cfg = WriteConfig(t.path());
  const std::string state = t.path() + "/state";
  Daemon d(cfg, t.path());
  ASSERT_TRUE(d.ok()) << ReadAll(d.log());
  json c = Calibration(d);
  ASSERT_TRUE(c.is_object()) << d.Get("/api/v1/status").dump();
  EXPECT_EQ(c["state"], "missing");
  EXPECT_NE(c["message"].get<std::string>().find("aggscan calibrate"), std::string::npos)
      << c.dump();
  EXPECT_NE(ReadAll(d.log()).find("rig calibration missing"), std::string::npos)
      << ReadAll(d.log());

  // Not fatal: a sample can be armed; it records that there was none.
  int code = 0;
  d.Post("/api/v1/samples", R"({"id": "no-cal"})", &code);
  ASSERT_EQ(code, 200);
  EXPECT_FALSE(PathExists(state + "/samples/no-cal/calibration.json"));
  json rec = json::parse(ReadAll(state + "/samples/no-cal/sample.json"));
  EXPECT_TRUE(rec["calibration"]["file"].is_null()) << rec.dump();
  d.Post("/api/v1/abort", "{}", &code);
  ASSERT_EQ(code, 200);

  // `aggscan calibrate` writes one while aggscand runs: the next arm sees it
  // and copies it into the sample.
  ASSERT_TRUE(
      SaveCalibration(CalibrationPath(state), SimCalibration(640, 480, "2026-01-02T03:04:05Z")));
  d.Post("/api/v1/samples", R"({"id": "with-cal"})", &code);
  ASSERT_EQ(code, 200);
  c = Calibration(d);
  EXPECT_EQ(c["state"], "ok") << c.dump();
  EXPECT_EQ(c["created_utc"], "2026-01-02T03:04:05Z");
  EXPECT_DOUBLE_EQ(c["reprojection_rms_px"].get<double>(), 0.123);
  const std::string copy = state + "/samples/with-cal/calibration.json";
  ASSERT_TRUE(PathExists(copy));
  EXPECT_EQ(ReadAll(copy), ReadAll(CalibrationPath(state)));
  rec = json::parse(ReadAll(state + "/samples/with-cal/sample.json"));
  EXPECT_EQ(rec["calibration"]["file"], "calibration.json") << rec.dump();
  EXPECT_EQ(rec["calibration"]["created_utc"], "2026-01-02T03:04:05Z");
  EXPECT_EQ(d.Stop(), 0);
}

TEST(CalibrationDaemon, PresentAtStartAndInvalidOnes) {
  TempDir t;
  const std::string cfg = WriteConfig(t.path());
  const std::string state = t.path() + "/state";
  std::filesystem::create_directories(state);
  ASSERT_TRUE(
      SaveCalibration(CalibrationPath(state), SimCalibration(1280, 960, "2026-02-03T04:05:06Z")));
  {
    // 1280x960 has the camera's 640x480 aspect: the lens scales, so ok.
    Daemon d(cfg, t.path());
    ASSERT_TRUE(d.ok()) << ReadAll(d.log());
    const json c = Calibration(d);
    EXPECT_EQ(c["state"], "ok") << c.dump();
    EXPECT_EQ(c["created_utc"], "2026-02-03T04:05:06Z");
    EXPECT_TRUE(c["reprojection_rms_px"].is_number());
  }
  // Another aspect ratio: invalid, and says to calibrate again.
  ASSERT_TRUE(
      SaveCalibration(CalibrationPath(state), SimCalibration(1920, 1080, "2026-02-03T04:05:06Z")));
  {
    Daemon d(cfg, t.path());
    ASSERT_TRUE(d.ok()) << ReadAll(d.log());
    const json c = Calibration(d);
    EXPECT_EQ(c["state"], "invalid") << c.dump();
    EXPECT_NE(c["message"].get<std::string>().find("1920x1080"), std::string::npos) << c.dump();
    EXPECT_NE(c["message"].get<std::string>().find("calibrate again"), std::string::npos)
        << c.dump();
    // Capture still works.
    int code = 0;
    d.Post("/api/v1/samples", R"({"id": "s1"})", &code);
    EXPECT_EQ(code, 200);
  }
  // Damaged file: invalid with the reason.
  std::ofstream(CalibrationPath(state)) << "{ \"format\": \"aggscan-calibration-1\", ";
  {
    Daemon d(cfg, t.path());
    ASSERT_TRUE(d.ok()) << ReadAll(d.log());
    const json c = Calibration(d);
    EXPECT_EQ(c["state"], "invalid") << c.dump();
    EXPECT_NE(c["message"].get<std::string>().find("not valid JSON"), std::string::npos)
        << c.dump();
  }
}

// The console's calibrate flow on the sim rig: the daemon captures the board
// lying on the disc as a calibration capture (its own folder, a calibration
// job, never a sample), the worker solves it and installs calibration.json,
// and the status shows the new calibration.
TEST(CalibrationDaemon, BoardCapturedByTheDaemonAndSolvedByTheWorker) {
  TempDir t;
  const std::string state = t.path() + "/state";
  const std::string board = t.path() + "/board.pgm";
  std::ostringstream out, err;
  ASSERT_EQ(RunCalibrateCommand({"board", "--out", board, "--margin-mm", "0"}, out, err), 0)
      << err.str();
  auto config = [&](const std::string& board_image) {
    const std::string path = t.path() + "/rig.toml";
    std::ofstream(path) << "[daemon]\nstate_dir = \"" << state
                        << "\"\nlisten_port = 0\ntime_scale = 5\nlog_level = \"info\"\n\n"
                        << "[camera]\nwidth = 1008\nheight = 756\n\n"
                        << "[sim]\nseed = 11\nboard_image = \"" << board_image << "\"\n";
    return path;
  };

  {
    // A sim rig without a board to draw says how to get one.
    Daemon d(config(""), t.path());
    ASSERT_TRUE(d.ok()) << ReadAll(d.log());
    int code = 0;
    const json r = d.Post("/api/v1/calibration", "{}", &code);
    EXPECT_EQ(code, 500) << r.dump();
    EXPECT_NE(r.dump().find("sim.board_image"), std::string::npos) << r.dump();
    EXPECT_NE(r.dump().find("aggscan calibrate board"), std::string::npos) << r.dump();
  }

  Daemon d(config(board), t.path());
  ASSERT_TRUE(d.ok()) << ReadAll(d.log());
  EXPECT_EQ(Calibration(d)["state"], "missing");
  int code = 0;
  // The prefix is the calibration captures': a rock may not take it.
  json r = d.Post("/api/v1/samples", R"({"id": "calibration-1"})", &code);
  EXPECT_EQ(code, 400) << r.dump();
  r = d.Post("/api/v1/calibration", "{}", &code);
  ASSERT_EQ(code, 200) << r.dump();
  EXPECT_EQ(r["capture_kind"], "calibration");
  EXPECT_EQ(r["sides"], 1);
  const std::string id = r.value("sample_id", "");
  ASSERT_EQ(id.rfind("calibration-", 0), 0u) << r.dump();
  EXPECT_EQ(r["calibration_capture"]["id"], id);
  d.Post("/api/v1/button", "{}", &code);
  ASSERT_EQ(code, 200);
  json last;
  ASSERT_TRUE(d.WaitFor(
      [](const json& s) {
        return s["state"] == "idle" && s["calibration_capture"]["state"] == "queued";
      },
      120, &last))
      << last.dump(2) << ReadAll(d.log());

  // Stored as a calibration capture, never as a sample; queued as calibration.
  const std::string dir = state + "/calibration-captures/" + id;
  EXPECT_TRUE(PathExists(dir + "/side1/manifest.json"));
  EXPECT_FALSE(PathExists(dir + "/side2"));
  EXPECT_FALSE(PathExists(state + "/samples/" + id));
  const json list = d.Get("/api/v1/samples");
  EXPECT_TRUE(list.is_array() && list.empty()) << list.dump();
  {
    auto q = JobQueue::Open(state + "/queue.db");
    ASSERT_TRUE(q);
    auto jobs = (*q)->JobsForSample(id);
    ASSERT_TRUE(jobs);
    ASSERT_EQ(jobs->size(), 1u);
    EXPECT_EQ((*jobs)[0].kind, kJobCalibration);
    EXPECT_EQ((*jobs)[0].side, 1);
  }

  // The worker solves it into the rig calibration.
  const int wrc = WaitExit(Spawn({Bin("pipeline/aggscan-worker"), "--state-dir", state, "--once"},
                                 t.path() + "/worker.log"));
  EXPECT_EQ(wrc, 0) << ReadAll(t.path() + "/worker.log");
  EXPECT_TRUE(PathExists(state + "/calibration.json")) << ReadAll(t.path() + "/worker.log");
  const json result =
      json::parse(ReadAll(dir + "/results/calibration_result.json"), nullptr, false);
  ASSERT_TRUE(result.is_object()) << ReadAll(t.path() + "/worker.log");
  EXPECT_EQ(result["views_total"], 30);
  EXPECT_GE(result["views_used"].get<int>(), 20) << result.dump(2);
  EXPECT_LT(result["reprojection_rms_px"].get<double>(), 0.5) << result.dump(2);
  EXPECT_TRUE(result["previous"].is_null());
  // The daemon sees it without a restart or an arm.
  ASSERT_TRUE(d.WaitFor(
      [](const json& s) {
        return s["calibration"]["state"] == "ok" && s["calibration_capture"]["state"] == "done";
      },
      20, &last))
      << last.dump(2);
  EXPECT_NEAR(last["calibration"]["reprojection_rms_px"].get<double>(),
              result["reprojection_rms_px"].get<double>(), 1e-9);
  EXPECT_NEAR(last["calibration_capture"]["result"]["reprojection_rms_px"].get<double>(),
              result["reprojection_rms_px"].get<double>(), 1e-9);

  // A board capture the solver cannot use (here: three views) fails once,
  // with the reason, and leaves the installed calibration alone.
  const std::string bad = state + "/calibration-captures/calibration-bad";
  std::filesystem::copy(dir, bad, std::filesystem::copy_options::recursive);
  std::filesystem::remove_all(bad + "/results");
  json manifest = json::parse(ReadAll(bad + "/side1/manifest.json"));
  manifest["views"].erase(manifest["views"].begin() + 3, manifest["views"].end());
  std::ofstream(bad + "/side1/manifest.json") << manifest.dump();
  const std::string installed = ReadAll(state + "/calibration.json");
  {
    auto q = JobQueue::Open(state + "/queue.db");
    ASSERT_TRUE(q);
    ASSERT_TRUE((*q)->Enqueue("calibration-bad", 1, kJobCalibration));
  }
  WaitExit(Spawn({Bin("pipeline/aggscan-worker"), "--state-dir", state, "--once"},
                 t.path() + "/worker-bad.log"));
  auto q = JobQueue::Open(state + "/queue.db");
  ASSERT_TRUE(q);
  auto jobs = (*q)->JobsForSample("calibration-bad");
  ASSERT_TRUE(jobs && jobs->size() == 1u);
  EXPECT_EQ((*jobs)[0].state, "failed") << ReadAll(t.path() + "/worker-bad.log");
  EXPECT_EQ((*jobs)[0].attempts, 1) << "an unusable board is not retried";
  EXPECT_NE((*jobs)[0].error.find("views"), std::string::npos) << (*jobs)[0].error;
  EXPECT_NE(ReadAll(t.path() + "/worker-bad.log").find("calibrate again"), std::string::npos);
  EXPECT_EQ(ReadAll(state + "/calibration.json"), installed);
  EXPECT_FALSE(PathExists(bad + "/results/calibration_result.json"));
}

TEST(CalibrationStore, SampleCopyIsWriteOnce) {
  TempDir t;
  SampleStore store(t.path());
  ASSERT_TRUE(store.Init());
  SamplePlan plan;
  plan.sides = 1;
  ASSERT_TRUE(SaveCalibration(CalibrationPath(t.path()), SimCalibration(640, 480, "first")));
  ASSERT_TRUE(store.CreateOrResume("r1", plan, "cfg"));
  const std::string copy = store.SampleDir("r1") + "/calibration.json";
  ASSERT_TRUE(PathExists(copy));
  // A new calibration before the sample is resumed: the sample keeps the
  // one its first views were shot with.
  ASSERT_TRUE(SaveCalibration(CalibrationPath(t.path()), SimCalibration(640, 480, "second")));
  ASSERT_TRUE(store.CreateOrResume("r1", plan, "cfg"));
  auto kept = LoadCalibration(copy);
  ASSERT_TRUE(kept);
  EXPECT_EQ(kept->created_utc, "first");
  // A damaged state-dir calibration is not copied; the record says why.
  std::ofstream(CalibrationPath(t.path())) << "garbage";
  ASSERT_TRUE(store.CreateOrResume("r2", plan, "cfg"));
  EXPECT_FALSE(PathExists(store.SampleDir("r2") + "/calibration.json"));
  auto rec = store.LoadRecord("r2");
  ASSERT_TRUE(rec);
  EXPECT_NE((*rec)["calibration"].value("reason", "").find("not valid JSON"), std::string::npos)
      << rec->dump();
}

TEST(CalibrationCheck, StatesWithoutTheDaemon) {
  TempDir t;
  EXPECT_EQ(CheckRigCalibration(t.path(), 640, 480)["state"], "missing");
  ASSERT_TRUE(SaveCalibration(CalibrationPath(t.path()), SimCalibration(640, 480, "x")));
  EXPECT_EQ(CheckRigCalibration(t.path(), 640, 480)["state"], "ok");
  EXPECT_EQ(CheckRigCalibration(t.path(), 640, 400)["state"], "invalid");
}

}  // namespace
}  // namespace aggscan::test
