#include "cli/sim_capture.h"

#include <unistd.h>

#include <filesystem>

#include "common/fsutil.h"
#include "common/log.h"
#include "common/rig_calibration.h"
#include "config/config.h"
#include "daemon/capture_service.h"
#include "daemon/event_loop.h"
#include "drivers/factory.h"
#include "drivers/sim/truth.h"
#include "pipeline/calib/calibrate.h"
#include "pipeline/markers/aruco_scale.h"
#include "store/layout.h"
#include "store/sample_store.h"

namespace aggscan {

namespace fs = std::filesystem;

int RunSimCapture(const SimCaptureOptions& opt, std::ostream& out, std::ostream& err) {
  if (opt.out.empty()) {
    err << "aggscan sim capture: --out DIR is required\n";
    return 2;
  }
  if (!opt.seed && opt.mesh.empty() && opt.scene != "charuco") {
    err << "aggscan sim capture: give --seed N (procedural rock) or --mesh FILE --unit mm|cm|m\n";
    return 2;
  }
  if (fs::exists(opt.out)) {
    err << "aggscan sim capture: " << opt.out
        << " already exists; refusing to overwrite it (choose a new --out)\n";
    return 1;
  }
  std::vector<ConfigProblem> problems;
  Config config;
  if (!opt.config_path.empty()) {
    Result<Config> c = LoadConfigFile(opt.config_path, &problems);
    if (c) config = *c;
  }
  // A hand-turned table stays one: the sim's hand turns the sim platter.
  config.camera.backend = config.button.backend = "sim";
  if (config.turntable.backend != "manual") config.turntable.backend = "sim";
  if (opt.seed) config.sim.seed = *opt.seed;
  if (!opt.mesh.empty()) {
    config.sim.rock_mesh = opt.mesh;
    config.sim.rock_unit = opt.unit;
  }
  if (!opt.profile.empty()) config.capture.profile = opt.profile;
  if (opt.views_per_side > 0) config.capture.views_per_side = opt.views_per_side;
  if (opt.width > 0) config.camera.width = opt.width;
  if (opt.height > 0) config.camera.height = opt.height;
  const std::string staging = opt.out + ".staging-" + std::to_string(::getpid());
  std::string board_pgm;  // drawn here for a charuco scene without sim.board_image
  if (!opt.scene.empty()) config.sim.scene = opt.scene;
  if (config.sim.scene == "charuco") {
    // A calibration capture: one side, the board seen all round.
    if (opt.profile.empty() && (opt.config_path.empty() || config.capture.profile == "paper")) {
      config.capture.profile = "full-turn";
      config.capture.sides = 1;
    }
    if (config.sim.board_image.empty()) config.sim.board_image = board_pgm = staging + "/board.pgm";
  }
  std::string aruco_pgm;  // drawn here for ArUco scale markers without sim.aruco_image
  if (!config.rig.aruco_markers.empty() && config.sim.aruco_image.empty()) {
    config.sim.aruco_image = aruco_pgm = staging + "/aruco.pgm";
  }
  if (problems.empty()) {
    ApplyProfile(&config);
    ValidateConfig(config, opt.config_path.empty() ? "<command line>" : opt.config_path, &problems);
  }
  if (!problems.empty()) {
    err << "aggscan sim capture: invalid configuration:\n";
    for (const auto& p : problems) err << "  " << p.ToString() << "\n";
    return 78;
  }

  // The sample id is the output folder's name when it is a valid id.
  std::string id = fs::path(opt.out).filename().string();
  if (!layout::IsValidSampleId(id)) id = "sim-" + std::to_string(config.sim.seed);
  if (!board_pgm.empty()) {
    // 10 px/mm: finer than the camera sees the disc (~4 px/mm at 2016 px).
    Status s = MakeDirsDurable(staging);
    if (s) s = WriteBoardImage(config.calibration, board_pgm, 10.0, 0.0);
    if (!s) {
      err << "aggscan sim capture: cannot draw the board: " << s.error().ToString() << "\n";
      return 1;
    }
  }
  if (!aruco_pgm.empty()) {
    Status s = MakeDirsDurable(staging);
    if (s) s = WriteArucoSheet(config.rig, aruco_pgm, 10.0);
    if (!s) {
      err << "aggscan sim capture: cannot draw the ArUco markers: " << s.error().ToString() << "\n";
      return 1;
    }
  }
  config.daemon.state_dir = staging;
  const std::string effective = ConfigToToml(config);

  SampleStore store(staging);
  if (Status s = store.Init(); !s) {
    err << "aggscan sim capture: " << s.error().ToString() << "\n";
    return 1;
  }
  if (!opt.calibration.empty()) {
    // In the staging state dir, where arming copies it into the sample.
    Result<RigCalibration> cal = LoadCalibration(opt.calibration);
    if (!cal) {
      err << "aggscan sim capture: --calibration: " << cal.error().ToString() << "\n";
      return 1;
    }
    if (Status s = SaveCalibration(CalibrationPath(staging), *cal); !s) {
      err << "aggscan sim capture: " << s.error().ToString() << "\n";
      return 1;
    }
  }
  VirtualClock clock;
  EventLoop loop(clock);
  Result<RigDevices> rig = CreateRig(config, clock);
  if (!rig) {
    err << "aggscan sim capture: " << rig.error().ToString() << "\n";
    return 78;
  }
  std::shared_ptr<sim::SimWorld> world = rig->world;
  sim::TruthRecorder truth(world);
  truth.Attach(*rig, [&store](const std::string& sid) {
    return store.SampleDir(sid) + "/" + layout::kTruthDir;
  });

  CaptureService service(loop, config, effective, std::move(*rig), store, nullptr);
  int rc = 0;
  std::string failure;
  service.SetTransitionListener([&](const capture::State& s) {
    if (s.phase == capture::Phase::kAwaitingPose) {
      // The simulated operator flips the rock and presses start again.
      loop.Post([&] {
        auto r = service.PressOnLoop("sim-operator");
        if (!r) {
          failure = r.error().ToString();
          loop.Quit(1);
        }
      });
    } else if (s.phase == capture::Phase::kIdle) {
      // Idle after a finished sample, or after an abort: only the first is a success.
      auto rec = store.LoadRecord(id);
      const bool captured = rec && rec->value("state", "") == "captured";
      if (!captured) failure = "the capture ended without completing the sample";
      loop.Quit(captured ? 0 : 1);
    } else if (s.phase == capture::Phase::kFaulted) {
      failure = s.fault_message;
      loop.Quit(1);
    }
  });
  service.Start();
  loop.Post([&] {
    auto a = service.ArmOnLoop(id);
    if (!a) {
      failure = a.error().ToString();
      loop.Quit(1);
      return;
    }
    auto p = service.PressOnLoop("sim-operator");
    if (!p) {
      failure = p.error().ToString();
      loop.Quit(1);
    }
  });
  const TimeNs real_start = MonotonicNs();
  rc = loop.Run();
  service.Shutdown();
  if (rc != 0) {
    err << "aggscan sim capture: capture failed: " << failure << "\n"
        << "  (partial sample kept in " << store.SampleDir(id) << ")\n";
    return 1;
  }
  if (Status s = truth.WriteTruthJson(store.SampleDir(id) + "/truth.json", config); !s) {
    err << "aggscan sim capture: " << s.error().ToString() << "\n";
    return 1;
  }
  // Move the finished sample to its place, then drop the staging area.
  if (Status s = MakeDirsDurable(
          fs::path(opt.out).parent_path().empty() ? "." : fs::path(opt.out).parent_path().string());
      !s) {
    err << "aggscan sim capture: " << s.error().ToString() << "\n";
    return 1;
  }
  if (Status s = RenameDurable(store.SampleDir(id), opt.out); !s) {
    err << "aggscan sim capture: " << s.error().ToString() << "\n";
    return 1;
  }
  if (!board_pgm.empty()) {
    // The board the views show, kept with them (the staging copy goes).
    if (Status s = RenameDurable(board_pgm, opt.out + "/board.pgm"); !s) {
      err << "aggscan sim capture: " << s.error().ToString() << "\n";
      return 1;
    }
  }
  std::error_code ec;
  fs::remove_all(staging, ec);
  const double real_s = static_cast<double>(MonotonicNs() - real_start) / 1e9;
  out << "captured sample " << id << " into " << opt.out << ": " << config.capture.sides
      << " sides x " << config.capture.views_per_side << " views ("
      << (static_cast<double>(clock.Now()) / 1e9) << " s simulated, " << real_s << " s real)\n";
  return 0;
}

}  // namespace aggscan
