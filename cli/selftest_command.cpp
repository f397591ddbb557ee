#include "cli/selftest_command.h"

#include <nlohmann/json.hpp>

#include "cli/client.h"
#include "common/clock.h"
#include "common/error.h"
#include "config/config.h"
#include "drivers/factory.h"

namespace aggscan {

namespace {

using json = nlohmann::json;

struct Check {
  std::string name, backend, id;
  Status status;
  std::string detail;  // what was read when ok ("angle 12.00 deg, homed")
};

Check CheckCamera(RigDevices& rig, const Config& config) {
  Check c{"camera", config.camera.backend, config.camera.id, OkStatus(), {}};
  Status s = rig.camera->Open();
  if (s) {
    const CameraInfo info = rig.camera->Info();
    c.id = info.id;
    s = rig.camera->Configure(CameraSettingsFor(config));
    if (s) {
      c.detail = "opened and configured " + std::to_string(config.camera.width) + "x" +
                 std::to_string(config.camera.height);
    }
  }
  rig.camera->Close();
  if (!s) c.status = MakeError(s.error().cls, "camera: " + s.error().ToString());
  return c;
}

Check CheckTurntable(RigDevices& rig, const Config& config) {
  Check c{"turntable", config.turntable.backend, rig.turntable->Info().id, OkStatus(), {}};
  Status s = rig.turntable->Open();
  if (s) {
    Result<TurntableStatus> st = rig.turntable->ReadStatus();
    if (!st) {
      s = st.error();
    } else if (st->alarm) {
      s = MakeError(ErrorClass::kDeviceFault, "alarm " + std::to_string(st->alarm_code) + " " +
                                                  st->alarm_text +
                                                  "; clear the cause at the controller");
    } else {
      char b[96];
      std::snprintf(b, sizeof b, "status read: angle %.2f deg, %s, %s", st->angle_deg,
                    st->homed ? "homed" : "not homed", st->enabled ? "enabled" : "not enabled");
      c.detail = b;
    }
  }
  rig.turntable->Close();
  if (!s) c.status = MakeError(s.error().cls, "turntable: " + s.error().ToString());
  return c;
}

Check CheckButton(RigDevices& rig, const Config& config) {
  Check c{"button", config.button.backend, rig.button->Describe(), OkStatus(), {}};
  Status s = rig.button->Start([](const ButtonPress&) {});
  rig.button->Stop();
  if (!s)
    c.status = MakeError(s.error().cls, "button: " + s.error().ToString());
  else
    c.detail = "input opened";
  return c;
}

}  // namespace

bool IsOfflineSelftest(const std::vector<std::string>& args) {
  bool selftest = false, config = false;
  for (const auto& a : args) {
    selftest = selftest || a == "selftest";
    config = config || a == "--config" || a.rfind("--config=", 0) == 0;
  }
  return selftest && config;
}

int RunOfflineSelftest(const std::vector<std::string>& args, std::ostream& out, std::ostream& err) {
  std::string path;
  bool json_out = false;
  bool seen_word = false;
  for (size_t i = 0; i < args.size(); ++i) {
    if (args[i] == "selftest" && !seen_word) {
      seen_word = true;
    } else if (args[i] == "--json") {
      json_out = true;
    } else if (args[i] == "--config" && i + 1 < args.size()) {
      path = args[++i];
    } else if (args[i].rfind("--config=", 0) == 0) {
      path = args[i].substr(9);
    } else {
      err << "aggscan selftest: unexpected argument '" << args[i]
          << "' (usage: aggscan selftest --config FILE [--json])\n";
      return kClientExitUsage;
    }
  }
  if (path.empty()) {
    err << "aggscan selftest: --config needs a file\n";
    return kClientExitUsage;
  }
  std::vector<ConfigProblem> problems;
  Result<Config> config = LoadConfigFile(path, &problems);
  if (!config || !problems.empty()) {
    err << "aggscan selftest: invalid configuration " << path << ":\n";
    for (const auto& p : problems) err << "  " << p.ToString() << "\n";
    if (!config && problems.empty()) err << "  " << config.error().ToString() << "\n";
    return kClientExitUsage;
  }
  RealClock clock;
  Result<RigDevices> rig = CreateRig(*config, clock);
  if (!rig) {
    err << "aggscan selftest: " << rig.error().ToString() << "\n";
    return kClientExitUsage;
  }
  std::vector<Check> checks;
  if (rig->camera) checks.push_back(CheckCamera(*rig, *config));
  if (rig->turntable) checks.push_back(CheckTurntable(*rig, *config));
  if (rig->button) checks.push_back(CheckButton(*rig, *config));

  int bad = 0;
  json report = {{"config", path}, {"devices", json::object()}};
  for (const Check& c : checks) {
    const bool ok = c.status.ok();
    if (!ok) ++bad;
    report["devices"][c.name] = {{"backend", c.backend},
                                 {"id", c.id},
                                 {"healthy", ok},
                                 {"state", ok ? "ok" : ErrorClassName(c.status.error().cls)},
                                 {"message", ok ? c.detail : c.status.error().message}};
    if (json_out) continue;
    out << c.name << ": "
        << (ok ? "ok" : std::string("FAIL ") + ErrorClassName(c.status.error().cls)) << " ["
        << c.backend << " " << c.id << "]\n";
    out << "    " << (ok ? c.detail : c.status.error().message) << "\n";
  }
  report["status"] = bad == 0 ? "ok" : "unhealthy";
  if (json_out) {
    out << report.dump(2) << "\n";
  } else {
    out << (bad == 0 ? "all " + std::to_string(checks.size()) + " devices ok"
                     : std::to_string(bad) + " of " + std::to_string(checks.size()) +
                           " devices unhealthy")
        << "\n";
  }
  return bad == 0 ? kClientExitOk : kClientExitUnhealthy;
}

}  // namespace aggscan
