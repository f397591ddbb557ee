// Bring-up with hardware missing, against the real binaries: aggscand with its
// turntable on a Modbus TCP port where nothing listens (or a peer that does
// not answer) serves its API, reports the turntable in GET /api/v1/health
// with the actionable message, refuses to start a capture, logs the failure
// once however often it retries, and recovers by itself once the loopback
// libmodbus peer appears; `aggscan selftest` exits accordingly.
#include <gtest/gtest.h>

#include <chrono>
#include <string>
#include <thread>

#include "tests/drivers/modbus_test_server.h"
#include "tests/scenario/process.h"

namespace aggscan {
namespace {

using json = nlohmann::json;
using test::Bin;
using test::Daemon;
using test::ReadAll;
using test::TempDir;

// Four views 90 deg apart, one a second, on the real clock; devices retried
// from 100 ms doubling to 400 ms, so a test sees several retries quickly.
// `probe`: daemon.health_probe_interval ("0s" = off).
std::string WriteConfig(const TempDir& t, const std::string& profile, int port,
                        const std::string& probe = "0s") {
  const std::string path = t.path() + "/health.toml";
  std::ofstream f(path);
  f << "[daemon]\nstate_dir = \"" << t.path() << "/state\"\nlisten_port = 0\nlog_level = \"info\"\n"
    << "reopen_backoff_min = \"100ms\"\nreopen_backoff_max = \"400ms\"\n"
    << "health_probe_interval = \"" << probe << "\"\n\n"
    << "[capture]\nprofile = \"custom\"\nsides = 1\nviews_per_side = 4\nstep_deg = 90.0\n"
    << "interval = \"1s\"\nsettle = \"50ms\"\n\n"
    << "[camera]\nwidth = 640\nheight = 480\n\n"
    << "[turntable]\nbackend = \"modbus-tcp\"\nmax_speed_deg_s = 360.0\naccel_deg_s2 = 1440.0\n"
    << "[turntable.modbus]\nprofile = \"" << profile << "\"\nhost = \"127.0.0.1\"\nport = " << port
    << "\nresponse_timeout = \"200ms\"\nretries = 0\nmotor_steps_per_rev = 200\nmicrosteps = 16\n"
    << "gear_ratio = 10.0\n";
  return path;
}

// Runs `aggscan --url ... ARGS`; returns its exit code, output in *out.
int RunCli(const TempDir& t, int port, const std::vector<std::string>& args, std::string* out) {
  const std::string log = t.path() + "/cli.log";
  std::filesystem::remove(log);
  std::vector<std::string> argv = {Bin("cli/aggscan"), "--url",
                                   "http://127.0.0.1:" + std::to_string(port)};
  argv.insert(argv.end(), args.begin(), args.end());
  const int rc = test::WaitExit(test::Spawn(argv, log));
  *out = ReadAll(log);
  return rc;
}

// Polls GET /api/v1/health until `pred` holds or `seconds` pass.
template <typename P>
bool WaitForHealth(Daemon& d, P pred, double seconds, json* last, int* code) {
  const auto end = std::chrono::steady_clock::now() +
                   std::chrono::milliseconds(static_cast<int>(seconds * 1000));
  while (std::chrono::steady_clock::now() < end) {
    *last = d.Get("/api/v1/health", code);
    if (last->is_object() && pred(*last)) return true;
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  return false;
}

size_t CountLines(const std::string& text, const std::string& needle) {
  size_t n = 0;
  for (size_t p = text.find(needle); p != std::string::npos; p = text.find(needle, p + 1)) ++n;
  return n;
}

// Presses start and waits for the config's one 4-view side to be stored.
void PressAndCaptureOneSide(Daemon& d) {
  int code = 0;
  d.Post("/api/v1/button", "{}", &code);
  ASSERT_EQ(code, 200) << ReadAll(d.log());
  json last;
  ASSERT_TRUE(d.WaitFor(
      [](const json& st) {
        return st.value("state", "") == "idle" && st.value("views_captured", 0) == 4;
      },
      30, &last))
      << last.dump() << ReadAll(d.log());
}

TEST(HealthDaemon, MissingTurntableRefusesCaptureAndRecoversByItself) {
  // A free port: a peer's, closed again, so nothing listens there yet.
  auto probe = testing::ModbusTestServer::StartTcp({});
  const int mb_port = probe->port();
  const std::string profile = testing::ModbusConfigFor(*probe, true).modbus.profile;
  probe.reset();

  TempDir t;
  Daemon d(WriteConfig(t, profile, mb_port), t.path());
  ASSERT_TRUE(d.ok()) << "aggscand must serve its API with the turntable missing\n"
                      << ReadAll(d.log());

  int code = 0;
  json h = d.Get("/api/v1/health", &code);
  EXPECT_EQ(code, 503) << h.dump();
  EXPECT_EQ(h["status"], "unhealthy") << h.dump();
  EXPECT_EQ(h["devices"]["camera"]["state"], "ok") << h.dump();
  EXPECT_EQ(h["devices"]["button"]["state"], "ok") << h.dump();
  const json tt = h["devices"]["turntable"];
  EXPECT_EQ(tt["backend"], "modbus-tcp") << h.dump();
  EXPECT_FALSE(tt["healthy"].get<bool>()) << h.dump();
  EXPECT_EQ(tt["state"], "device_missing") << h.dump();
  const std::string msg = tt["message"].get<std::string>();
  EXPECT_EQ(msg.rfind("turntable: ", 0), 0u) << msg;
  EXPECT_NE(msg.find("127.0.0.1:" + std::to_string(mb_port)), std::string::npos) << msg;
  EXPECT_NE(msg.find("check"), std::string::npos) << msg;
  EXPECT_TRUE(tt["last_ok_utc"].is_null()) << h.dump();
  EXPECT_GE(tt["retries"].get<int>(), 1) << h.dump();
  EXPECT_TRUE(tt["next_retry_utc"].is_string()) << h.dump();
  EXPECT_LE(tt["next_retry_in_s"].get<double>(), 0.4) << h.dump();

  // No capture while the turntable is missing: arming is refused with the reason.
  json r = d.Post("/api/v1/samples", R"({"id": "rock-h"})", &code);
  EXPECT_EQ(code, 503) << r.dump();
  EXPECT_NE(r["error"]["message"].get<std::string>().find("cannot start a capture: turntable: "),
            std::string::npos)
      << r.dump();

  std::string out;
  EXPECT_EQ(RunCli(t, d.port(), {"selftest"}, &out), 4) << out;
  EXPECT_NE(out.find("turntable: FAIL device_missing [modbus-tcp"), std::string::npos) << out;
  EXPECT_NE(out.find("127.0.0.1:" + std::to_string(mb_port)), std::string::npos) << out;
  EXPECT_NE(out.find("1 of 4 devices unhealthy"), std::string::npos) << out;

  // Several retries (100, 200, 400, 400 ms ...), one log line for the class.
  int c = 0;
  ASSERT_TRUE(WaitForHealth(
      d, [](const json& j) { return j["devices"]["turntable"].value("retries", 0) >= 5; }, 15, &h,
      &c))
      << h.dump();
  EXPECT_LE(h["devices"]["turntable"]["next_retry_in_s"].get<double>(), 0.4)
      << "bounded backoff: " << h.dump();
  std::string log = ReadAll(d.log());
  EXPECT_EQ(CountLines(log, "devices: turntable: "), 1u) << log;
  EXPECT_EQ(CountLines(log, "[device_missing]"), 1u) << log;

  // The peer appears on that port: the daemon recovers without being asked.
  testing::ModbusServerOptions opt;
  opt.tcp_port = mb_port;
  auto server = testing::ModbusTestServer::StartTcp(opt);
  ASSERT_EQ(server->port(), mb_port);
  ASSERT_TRUE(WaitForHealth(
      d, [](const json& j) { return j.value("status", "") == "ok"; }, 10, &h, &c))
      << h.dump() << ReadAll(d.log());
  EXPECT_EQ(c, 200);
  EXPECT_EQ(h["devices"]["turntable"]["state"], "ok") << h.dump();
  EXPECT_EQ(h["devices"]["turntable"]["retries"], 0) << h.dump();
  EXPECT_TRUE(h["devices"]["turntable"]["last_ok_utc"].is_string()) << h.dump();
  EXPECT_TRUE(h["devices"]["turntable"]["next_retry_utc"].is_null()) << h.dump();
  log = ReadAll(d.log());
  EXPECT_EQ(CountLines(log, "devices: turntable: ok again after "), 1u) << log;
  EXPECT_EQ(CountLines(log, "devices: turntable: "), 2u) << "the failure once, the recovery once\n"
                                                         << log;

  EXPECT_EQ(RunCli(t, d.port(), {"selftest"}, &out), 0) << out;
  EXPECT_NE(out.find("all 4 devices ok"), std::string::npos) << out;

  // And a capture runs on the recovered turntable.
  d.Post("/api/v1/samples", R"({"id": "rock-h"})", &code);
  ASSERT_EQ(code, 200) << ReadAll(d.log());
  ASSERT_NO_FATAL_FAILURE(PressAndCaptureOneSide(d));
  EXPECT_EQ(server->position_steps(), 3 * 8000);
}

TEST(HealthDaemon, PeerSilentWhileArmedIsSeenByTheProbeAndThePressRefused) {
  auto server = testing::ModbusTestServer::StartTcp({});
  const std::string profile = testing::ModbusConfigFor(*server, true).modbus.profile;
  TempDir t;
  Daemon d(WriteConfig(t, profile, server->port(), "100ms"), t.path());
  ASSERT_TRUE(d.ok()) << ReadAll(d.log());
  int code = 0;
  d.Post("/api/v1/samples", R"({"id": "rock-p"})", &code);
  ASSERT_EQ(code, 200) << ReadAll(d.log());

  // The controller stops answering while the sample is armed: the idle probe
  // notices before anyone presses start.
  server->SetSilent(true);
  json h;
  int c = 0;
  ASSERT_TRUE(WaitForHealth(
      d, [](const json& j) { return j["devices"]["turntable"].value("state", "") == "timeout"; },
      15, &h, &c))
      << h.dump() << ReadAll(d.log());
  EXPECT_EQ(c, 503);
  EXPECT_EQ(h["state"], "armed") << h.dump();
  EXPECT_NE(h["devices"]["turntable"]["message"].get<std::string>().find(
                "no answer from Modbus unit 1 at 127.0.0.1:" + std::to_string(server->port())),
            std::string::npos)
      << h.dump();
  EXPECT_TRUE(h["devices"]["turntable"]["last_ok_utc"].is_string())
      << "it was ok at start: " << h.dump();

  json r = d.Post("/api/v1/button", "{}", &code);
  EXPECT_EQ(code, 503) << r.dump();
  EXPECT_EQ(r["error"]["class"], "timeout") << r.dump();
  EXPECT_NE(
      r["error"]["message"].get<std::string>().find("cannot start a capture: turntable: no answer"),
      std::string::npos)
      << r.dump();
  EXPECT_EQ(d.Get("/api/v1/status")["state"], "armed");
  std::string out;
  EXPECT_EQ(RunCli(t, d.port(), {"selftest"}, &out), 4) << out;
  EXPECT_NE(out.find("turntable: FAIL timeout [modbus-tcp"), std::string::npos) << out;

  // The controller answers again: reopened while armed, and the side runs.
  server->SetSilent(false);
  ASSERT_TRUE(WaitForHealth(
      d, [](const json& j) { return j.value("status", "") == "ok"; }, 10, &h, &c))
      << h.dump() << ReadAll(d.log());
  ASSERT_NO_FATAL_FAILURE(PressAndCaptureOneSide(d));
  const std::string log = ReadAll(d.log());
  EXPECT_EQ(CountLines(log, "[timeout] (further errors"), 1u) << log;
  EXPECT_EQ(CountLines(log, "devices: turntable: ok again after "), 1u) << log;
}

TEST(HealthDaemon, SilentPeerFaultsACaptureThenResetAndArmAreRefusedUntilItAnswers) {
  auto server = testing::ModbusTestServer::StartTcp({});
  const std::string profile = testing::ModbusConfigFor(*server, true).modbus.profile;
  TempDir t;
  Daemon d(WriteConfig(t, profile, server->port()), t.path());
  ASSERT_TRUE(d.ok()) << ReadAll(d.log());
  int code = 0;
  d.Post("/api/v1/samples", R"({"id": "rock-s"})", &code);
  ASSERT_EQ(code, 200) << ReadAll(d.log());

  // The controller stops answering after arming (the idle probe is off here):
  // the press starts homing, the controller does not answer, the capture faults.
  server->SetSilent(true);
  d.Post("/api/v1/button", "{}", &code);
  ASSERT_EQ(code, 200);
  json last;
  ASSERT_TRUE(
      d.WaitFor([](const json& st) { return st.value("state", "") == "faulted"; }, 30, &last))
      << last.dump() << ReadAll(d.log());
  json h = d.Get("/api/v1/health", &code);
  EXPECT_EQ(code, 503) << h.dump();
  const json tt = h["devices"]["turntable"];
  EXPECT_EQ(tt["state"], "timeout") << h.dump();
  EXPECT_NE(tt["message"].get<std::string>().find("no answer from Modbus unit 1 at 127.0.0.1:" +
                                                  std::to_string(server->port())),
            std::string::npos)
      << h.dump();
  EXPECT_TRUE(tt["last_ok_utc"].is_string()) << "it was ok at start: " << h.dump();

  // Reset while still silent: the turntable stays unhealthy, arming and the
  // button are refused with the turntable's message.
  d.Post("/api/v1/reset", "{}", &code);
  ASSERT_EQ(code, 200) << ReadAll(d.log());
  json r = d.Post("/api/v1/samples", R"({"id": "rock-s2"})", &code);
  EXPECT_EQ(code, 503) << r.dump();
  EXPECT_NE(r["error"]["message"].get<std::string>().find("cannot start a capture: turntable: "),
            std::string::npos)
      << r.dump();
  EXPECT_EQ(r["error"]["class"], "timeout") << r.dump();

  // Back: recovers by itself, and a capture can be armed again.
  server->SetSilent(false);
  int c = 0;
  ASSERT_TRUE(WaitForHealth(
      d, [](const json& j) { return j.value("status", "") == "ok"; }, 10, &h, &c))
      << h.dump() << ReadAll(d.log());
  d.Post("/api/v1/samples", R"({"id": "rock-s2"})", &code);
  EXPECT_EQ(code, 200) << ReadAll(d.log());
  const std::string log = ReadAll(d.log());
  EXPECT_EQ(CountLines(log, "[timeout] (further errors"), 1u) << log;
}

// Offline bring-up: `aggscan selftest --config FILE` opens the devices itself.
TEST(HealthSelftest, OfflineOpensEachDeviceOfTheConfigAndReports) {
  auto server = testing::ModbusTestServer::StartTcp({});
  const std::string profile = testing::ModbusConfigFor(*server, true).modbus.profile;
  TempDir t;
  const std::string log = t.path() + "/cli.log";
  auto run = [&](const std::string& config, std::string* out) {
    std::filesystem::remove(log);
    const int rc =
        test::WaitExit(test::Spawn({Bin("cli/aggscan"), "selftest", "--config", config}, log));
    *out = ReadAll(log);
    return rc;
  };
  std::string out;
  EXPECT_EQ(run(WriteConfig(t, profile, server->port()), &out), 0) << out;
  EXPECT_NE(out.find("turntable: ok [modbus-tcp"), std::string::npos) << out;
  EXPECT_NE(out.find("status read: angle"), std::string::npos) << out;
  EXPECT_NE(out.find("camera: ok [sim"), std::string::npos) << out;
  EXPECT_NE(out.find("all 3 devices ok"), std::string::npos) << out;

  const int port = server->port();
  server.reset();  // nothing listens there now
  EXPECT_EQ(run(WriteConfig(t, profile, port), &out), 4) << out;
  EXPECT_NE(out.find("turntable: FAIL device_missing [modbus-tcp"), std::string::npos) << out;
  EXPECT_NE(out.find("127.0.0.1:" + std::to_string(port)), std::string::npos) << out;
  EXPECT_NE(out.find("1 of 3 devices unhealthy"), std::string::npos) << out;

  EXPECT_EQ(run(t.path() + "/no-such.toml", &out), 2) << out;
}

}  // namespace
}  // namespace aggscan
