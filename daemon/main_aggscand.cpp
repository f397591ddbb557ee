// aggscand: the capture daemon. Drives the camera, turntable and start button
// (the simulated rig out of the box), stores every view durably, queues each
// captured side for aggscan-worker, and serves the HTTP API.
#include <signal.h>

#include <cstdio>
#include <cstring>
#include <iostream>
#include <memory>
#include <string>

#include "common/fsutil.h"
#include "common/log.h"
#include "common/version.h"
#include "config/config.h"
#include "config/turntable_profile.h"
#include "daemon/capture_service.h"
#include "daemon/event_loop.h"
#include "daemon/http_api.h"
#include "daemon/systemd_notify.h"
#include "drivers/factory.h"
#include "drivers/sim/truth.h"
#include "store/layout.h"
#include "store/queue.h"
#include "store/sample_store.h"

namespace {

constexpr int kExitConfig = 78;  // EX_CONFIG: systemd shows it; Restart= won't loop on it

void Usage(std::FILE* f) {
  std::fprintf(
      f,
      "usage: aggscand [--config FILE] [--check-config] [--print-config]\n"
      "                [--state-dir DIR] [--port N] [--port-file FILE] [--log-level LEVEL]\n"
      "       aggscand --version\n"
      "  --config FILE     TOML config (default: built-in defaults, sim rig)\n"
      "  --check-config    validate the config, list every problem, exit (78 if invalid)\n"
      "  --print-config    print the effective config as TOML and exit\n"
      "  --state-dir DIR   override daemon.state_dir\n"
      "  --port N          override daemon.listen_port (0 = any free port)\n"
      "  --port-file FILE  write the bound HTTP port to FILE once listening\n"
      "  --log-level L     error|warning|notice|info|debug\n"
      "  --version         print the software version and exit\n");
}

}  // namespace

int main(int argc, char** argv) {
  using namespace aggscan;
  std::string config_path, state_dir_override, port_file, log_level;
  int port_override = -1;
  bool check_only = false, print_only = false;
  // Answered before the other options are judged: neither may open a config,
  // the state directory or the port, whatever else is on the line.
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    if (a == "--version") {
      std::printf("aggscand %s\n", SoftwareVersion());
      return 0;
    }
    if (a == "-h" || a == "--help") {
      Usage(stdout);
      return 0;
    }
  }
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    auto need = [&](const char* what) -> std::string {
      if (i + 1 >= argc) {
        std::fprintf(stderr, "aggscand: %s needs a value\n", what);
        std::exit(2);
      }
      return argv[++i];
    };
    if (a == "--config")
      config_path = need("--config");
    else if (a == "--check-config")
      check_only = true;
    else if (a == "--print-config")
      print_only = true;
    else if (a == "--state-dir")
      state_dir_override = need("--state-dir");
    else if (a == "--port") {
      const std::string v = need("--port");
      char* end = nullptr;
      const long p = std::strtol(v.c_str(), &end, 10);
      if (v.empty() || *end != '\0' || p < 0 || p > 65535) {
        std::fprintf(stderr, "aggscand: --port expects 0..65535, got '%s'\n", v.c_str());
        return 2;
      }
      port_override = static_cast<int>(p);
    } else if (a == "--port-file")
      port_file = need("--port-file");
    else if (a == "--log-level")
      log_level = need("--log-level");
    else if (a == "-h" || a == "--help") {
      Usage(stdout);
      return 0;
    } else {
      std::fprintf(stderr, "aggscand: unknown argument '%s'\n", a.c_str());
      Usage(stderr);
      return 2;
    }
  }

  // ---- configuration: every problem listed, exit 78 when invalid ----
  Config config;
  std::vector<ConfigProblem> problems;
  if (!config_path.empty()) {
    Result<Config> c = LoadConfigFile(config_path, &problems);
    if (c) config = *c;
  } else {
    ApplyProfile(&config);
    ValidateConfig(config, "<defaults>", &problems);
  }
  if (!state_dir_override.empty()) config.daemon.state_dir = state_dir_override;
  if (port_override >= 0) config.daemon.listen_port = port_override;
  if (!log_level.empty()) config.daemon.log_level = log_level;
  if (!problems.empty()) {
    std::fprintf(stderr, "aggscand: invalid configuration (%zu problem%s):\n", problems.size(),
                 problems.size() == 1 ? "" : "s");
    for (const auto& p : problems) std::fprintf(stderr, "  %s\n", p.ToString().c_str());
    return kExitConfig;
  }
  LogLevel lvl;
  if (!ParseLogLevel(config.daemon.log_level, &lvl)) {
    std::fprintf(stderr, "aggscand: unknown log level '%s' (error|warning|notice|info|debug)\n",
                 config.daemon.log_level.c_str());
    return kExitConfig;
  }
  SetLogLevel(lvl);
  const std::string effective = ConfigToToml(config);
  if (print_only) {
    std::fputs(effective.c_str(), stdout);
    return 0;
  }
  if (check_only) {
    // A Modbus turntable's register-map profile is a file of its own: check it too.
    if (config.turntable.backend.rfind("modbus-", 0) == 0) {
      Result<TurntableProfile> profile = FindTurntableProfile(config.turntable.modbus.profile,
                                                              config.turntable.modbus.profile_dir);
      if (!profile) {
        std::fprintf(stderr, "aggscand: invalid turntable profile:\n  %s\n",
                     profile.error().message.c_str());
        if (!profile.error().detail.empty() && profile.error().detail != profile.error().message) {
          std::fprintf(stderr, "%s\n", profile.error().detail.c_str());
        }
        return kExitConfig;
      }
    }
    std::printf("%s: configuration is valid\n",
                config_path.empty() ? "<defaults>" : config_path.c_str());
    return 0;
  }

  // ---- clock: the sim rig may run faster than real time ----
  std::unique_ptr<Clock> clock;
  if (config.daemon.time_scale > 1.0) {
    clock = std::make_unique<ScaledClock>(config.daemon.time_scale);
    AGG_LOGI("main", "sim clock runs %.1fx faster than real time", config.daemon.time_scale);
  } else {
    clock = std::make_unique<RealClock>();
  }

  // ---- durable store: recover from whatever the last run left ----
  SampleStore store(config.daemon.state_dir);
  if (Status s = store.Init(); !s) {
    AGG_LOGE("main", "cannot use state directory %s: %s", config.daemon.state_dir.c_str(),
             s.error().ToString().c_str());
    return 1;
  }
  Result<RecoveryReport> rec = store.Recover();
  if (!rec) {
    AGG_LOGE("main", "start-up recovery failed: %s", rec.error().ToString().c_str());
    return 1;
  }
  AGG_LOGI("main",
           "state dir %s: %d samples, %d temporary files removed, %d interrupted sides, %d sides "
           "completed from "
           "their stored views",
           config.daemon.state_dir.c_str(), rec->samples, rec->temp_files_removed,
           rec->sides_interrupted, rec->sides_completed);
  for (const auto& id : rec->completed_samples) {
    LogLine(LogLevel::kNotice, "main", id,
            "had every side stored: marked captured and queued for the worker");
  }
  for (const auto& id : rec->interrupted_samples) {
    LogLine(LogLevel::kNotice, "main", id,
            "was interrupted by a crash or power loss: arm it again to re-shoot");
  }
  auto queue = JobQueue::Open(layout::QueuePath(config.daemon.state_dir));
  if (!queue) {
    AGG_LOGE("main", "%s", queue.error().ToString().c_str());
    return 1;
  }
  // Every captured side must reach the worker: queue what the queue lacks.
  for (const auto& [id, side] : store.CapturedWork()) {
    auto jobs = (*queue)->JobsForSample(id);
    bool have = false;
    if (jobs) {
      for (const Job& j : *jobs) have = have || j.side == side;
    }
    if (!have) {
      auto q = (*queue)->Enqueue(id, side);
      if (q)
        LogLine(LogLevel::kNotice, "main", id,
                "re-queued " + (side ? "side " + std::to_string(side) : std::string("sample job")));
      else
        LogLine(LogLevel::kError, "main", id, "cannot queue: " + q.error().ToString());
    }
  }

  // Calibration captures: recovered like samples; a captured board the
  // worker has no job for gets its calibration job.
  SampleStore cal_store(config.daemon.state_dir, layout::kCalibrationCollection);
  if (Status s = cal_store.Init(); !s) {
    AGG_LOGE("main", "cannot use state directory %s: %s", config.daemon.state_dir.c_str(),
             s.error().ToString().c_str());
    return 1;
  }
  if (Result<RecoveryReport> crec = cal_store.Recover(); !crec) {
    AGG_LOGE("main", "start-up recovery of the calibration captures failed: %s",
             crec.error().ToString().c_str());
    return 1;
  }
  for (const auto& [id, side] : cal_store.CapturedWork()) {
    // The board is one side (no sample job); captures made offline (`aggscan
    // sim capture --scene charuco`) are solved with `aggscan calibrate`.
    if (side != 1 || id.rfind(layout::kCalibrationIdPrefix, 0) != 0) continue;
    auto jobs = (*queue)->JobsForSample(id);
    if (jobs && !jobs->empty()) continue;
    auto q = (*queue)->Enqueue(id, side, kJobCalibration);
    if (q)
      LogLine(LogLevel::kNotice, "main", id, "re-queued the calibration capture for the worker");
    else
      LogLine(LogLevel::kError, "main", id, "cannot queue: " + q.error().ToString());
  }

  // Signals go to the loop: block them before any other thread starts.
  EventLoop loop(*clock);
  loop.HandleSignals({SIGTERM, SIGINT, SIGHUP}, [&loop](int sig) {
    AGG_LOGI("main", "signal %s: stopping", strsignal(sig));
    loop.Quit(0);
  });
  signal(SIGPIPE, SIG_IGN);

  Result<RigDevices> rig = CreateRig(config, *clock);
  if (!rig) {
    AGG_LOGE("main", "%s", rig.error().ToString().c_str());
    return kExitConfig;
  }
  // Sim rig with sim.write_truth: ground-truth masks and poses next to each
  // sample (tests and the accuracy harness compare the worker against them).
  std::unique_ptr<sim::TruthRecorder> truth;
  if (config.sim.write_truth && rig->world) {
    truth = std::make_unique<sim::TruthRecorder>(rig->world);
    truth->Attach(*rig, [&store](const std::string& id) {
      return store.SampleDir(id) + "/" + layout::kTruthDir;
    });
  }
  // Declared before the service and the API, which publish and stream it.
  EventHub events;
  // The live view's JPEG quality: enough for framing the rock on a screen.
  constexpr int kPreviewQuality = 70;
  std::unique_ptr<PreviewHub> preview;
  if (config.daemon.preview_interval > 0)
    preview = std::make_unique<PreviewHub>(config.daemon.preview_max_side, kPreviewQuality);
  CaptureService service(loop, config, effective, std::move(*rig), store, queue->get());
  service.SetEventHub(&events);
  service.SetPreviewHub(preview.get());
  // The rig calibration: checked now and at every arm; missing or invalid is a
  // warning and a status field, never a reason not to capture.
  service.RefreshCalibration();
  SystemdNotifier notifier(loop);
  service.SetStatusListener([&notifier](const std::string& line) { notifier.Status(line); });
  service.Start();

  HttpApiOptions api_options;
  api_options.allowed_hosts = SplitCommaList(config.daemon.allowed_hosts);
  api_options.allowed_origins = SplitCommaList(config.daemon.allowed_origins);
  api_options.events = &events;
  api_options.preview = preview.get();
  std::unique_ptr<AccessControl> access;
  if (!config.daemon.credentials_file.empty()) {
    Result<std::unique_ptr<AccessControl>> opened =
        AccessControl::Open(config.daemon.credentials_file);
    if (!opened) {
      AGG_LOGE("main", "%s", opened.error().ToString().c_str());
      service.Shutdown();
      return kExitConfig;
    }
    access = std::move(*opened);
    api_options.access = access.get();
    AGG_LOGI("main", "API credentials: %zu account(s) from %s", access->accounts(),
             config.daemon.credentials_file.c_str());
  }
  if (!config.daemon.tls_certificate.empty()) {
    Result<std::string> cert = ReadFile(config.daemon.tls_certificate);
    Result<std::string> key = ReadFile(config.daemon.tls_key);
    if (!cert || !key) {
      AGG_LOGE("main",
               "cannot read daemon.%s: %s (it must be readable by the user aggscand runs as)",
               !cert ? "tls_certificate" : "tls_key",
               (!cert ? cert.error() : key.error()).ToString().c_str());
      service.Shutdown();
      return kExitConfig;
    }
    api_options.tls_certificate_pem = std::move(*cert);
    api_options.tls_key_pem = std::move(*key);
  }
  // The console: a configured folder must hold it; the default is looked
  // for beside the binaries and, missing, only the console is off.
  if (!config.daemon.web_root.empty()) {
    if (!PathExists(config.daemon.web_root + "/index.html")) {
      AGG_LOGE("main",
               "daemon.web_root %s has no index.html: point it at the console's files "
               "(share/aggscan/web of the installation) or leave it empty",
               config.daemon.web_root.c_str());
      service.Shutdown();
      return kExitConfig;
    }
    api_options.web_root = config.daemon.web_root;
  } else {
    const std::string exe = ExecutableDir();
    for (const std::string& dir : {exe + "/../share/aggscan/web", exe + "/../web"}) {
      if (!exe.empty() && PathExists(dir + "/index.html")) {
        api_options.web_root = dir;
        break;
      }
    }
    if (api_options.web_root.empty())
      AGG_LOGW("main", "no console files beside %s: the API works, the console at / does not",
               exe.c_str());
  }
  const bool tls = !api_options.tls_certificate_pem.empty();
  HttpApi api(service, config.daemon.listen_address, config.daemon.listen_port,
              std::move(api_options));
  if (Status s = api.Start(); !s) {
    AGG_LOGE("main", "%s", s.error().ToString().c_str());
    service.Shutdown();
    return s.error().cls == ErrorClass::kInvalidConfig ? kExitConfig : 1;
  }
  AGG_LOGI("main", "API listening on %s://%s:%d", tls ? "https" : "http",
           config.daemon.listen_address.c_str(), api.port());
  if (!port_file.empty()) {
    if (Status s = WriteFileAtomic(port_file, std::to_string(api.port()) + "\n"); !s) {
      AGG_LOGE("main", "%s", s.error().ToString().c_str());
    }
  }
  notifier.Ready(service.StatusLine());
  notifier.StartWatchdog();

  const int rc = loop.Run();
  notifier.Stopping();
  api.Stop();
  service.Shutdown();
  AGG_LOGI("main", "stopped");
  return rc;
}
