// The real aggscand with its turntable on a Modbus peer (the libmodbus server
// of modbus_test_server.h on loopback) and the sim camera and button: a side
// is captured and each view's sidecar carries the angle the peer reported; a
// peer that stops answering faults the capture with the actionable message.
#include <gtest/gtest.h>

#include <cmath>
#include <string>

#include "tests/drivers/modbus_test_server.h"
#include "tests/scenario/process.h"

namespace aggscan {
namespace {

using json = nlohmann::json;
using test::Daemon;
using test::ReadAll;
using test::TempDir;

std::string StateOf(const json& s) { return s.is_object() ? s.value("state", "") : ""; }

// Four views 90 deg apart, one a second, on the real clock.
std::string WriteModbusConfig(const TempDir& t, const testing::ModbusTestServer& server,
                              const std::string& capture_extra = "") {
  const TurntableConfig tt = testing::ModbusConfigFor(server, true);
  const std::string extra =
      "[turntable]\nbackend = \"modbus-tcp\"\nmax_speed_deg_s = 360.0\naccel_deg_s2 = 1440.0\n"
      "[turntable.modbus]\nprofile = \"" +
      tt.modbus.profile + "\"\nhost = \"127.0.0.1\"\nport = " + std::to_string(server.port()) +
      "\nmotor_steps_per_rev = 200\nmicrosteps = 16\n"
      "gear_ratio = 10.0\n";
  const std::string capture =
      "profile = \"custom\"\nsides = 1\nviews_per_side = 4\nstep_deg = 90.0\ninterval = \"1s\"\n"
      "settle = \"50ms\"\n" +
      capture_extra;
  return test::WriteConfig(t.path(), extra, 1.0, capture);
}

TEST(ModbusDaemon, SidecarsCarryTheAnglesThePeerReports) {
  auto server = testing::ModbusTestServer::StartTcp({});
  TempDir t;
  Daemon d(WriteModbusConfig(t, *server), t.path());
  ASSERT_TRUE(d.ok()) << ReadAll(d.log());
  json s = d.Get("/api/v1/status");
  EXPECT_EQ(s["devices"]["turntable"]["backend"], "modbus-tcp") << s.dump();
  EXPECT_TRUE(s["devices"]["turntable"]["healthy"]) << s.dump();

  int code = 0;
  d.Post("/api/v1/samples", R"({"id": "rock-mb"})", &code);
  ASSERT_EQ(code, 200);
  d.Post("/api/v1/button", "{}", &code);
  ASSERT_EQ(code, 200);
  json last;
  ASSERT_TRUE(d.WaitFor(
      [](const json& st) { return StateOf(st) == "idle" && st.value("views_captured", 0) == 4; },
      30, &last))
      << last.dump() << ReadAll(d.log());

  const double step = 360.0 / 32000;
  for (int i = 0; i < 4; ++i) {
    char name[64];
    std::snprintf(name, sizeof(name), "/state/samples/rock-mb/side1/view_%03d.json", i);
    json v = json::parse(ReadAll(t.path() + name), nullptr, false);
    ASSERT_FALSE(v.is_discarded()) << name;
    EXPECT_DOUBLE_EQ(v["commanded_angle_deg"].get<double>(), 90.0 * i) << name;
    EXPECT_NEAR(v["measured_angle_deg"].get<double>(), 90.0 * i, step) << name;
  }
  // The peer's own count: the platter stands at the last view.
  EXPECT_EQ(server->position_steps(), 3 * 8000);
  EXPECT_TRUE(server->homed());
}

TEST(ModbusDaemon, SilentPeerFaultsTheCaptureWithTheActionableMessage) {
  auto server = testing::ModbusTestServer::StartTcp({});
  TempDir t;
  Daemon d(WriteModbusConfig(t, *server), t.path());
  ASSERT_TRUE(d.ok()) << ReadAll(d.log());
  int code = 0;
  d.Post("/api/v1/samples", R"({"id": "rock-silent"})", &code);
  ASSERT_EQ(code, 200);
  server->SetSilent(true);
  d.Post("/api/v1/button", "{}", &code);
  json last;
  ASSERT_TRUE(d.WaitFor([](const json& st) { return StateOf(st) == "faulted"; }, 30, &last))
      << last.dump() << ReadAll(d.log());
  EXPECT_EQ(last["fault"]["class"], "timeout") << last.dump();
  EXPECT_NE(last["fault"]["message"].get<std::string>().find(
                "no answer from Modbus unit 1 at 127.0.0.1:" + std::to_string(server->port())),
            std::string::npos)
      << last.dump();
}

// A move that comes to rest outside the in-position window (a drive whose
// following error is larger than the default 0.05 deg = 4.4 steps): the
// fault says where the platter stood and which key sets the window.
TEST(ModbusDaemon, RestOutsideTheWindowSaysHowFarOffAndWhichKey) {
  auto server = testing::ModbusTestServer::StartTcp({});
  server->SetRestErrorSteps(8);  // 0.090 deg at 32000 steps per turn
  TempDir t;
  Daemon d(WriteModbusConfig(t, *server, "move_timeout = \"2s\"\n"), t.path());
  ASSERT_TRUE(d.ok()) << ReadAll(d.log());
  int code = 0;
  d.Post("/api/v1/samples", R"({"id": "rock-off"})", &code);
  ASSERT_EQ(code, 200);
  d.Post("/api/v1/button", "{}", &code);
  ASSERT_EQ(code, 200);
  json last;
  ASSERT_TRUE(d.WaitFor([](const json& st) { return StateOf(st) == "faulted"; }, 30, &last))
      << last.dump() << ReadAll(d.log());
  EXPECT_EQ(last["fault"]["class"], "timeout") << last.dump();
  const std::string m = last["fault"]["message"].get<std::string>();
  // Homing ends at 0 exactly; the first step, to 90 deg, rests 8 steps past.
  EXPECT_NE(m.find("move to 90.00 deg did not finish within 2s: the platter came to rest at "
                   "90.090 deg, +0.090 deg from the target (+8 steps at 32000 steps per turn), "
                   "outside turntable.modbus.in_position_window_deg = 0.050 deg: if the drive "
                   "cannot settle closer, raise turntable.modbus.in_position_window_deg above "
                   "0.090 deg"),
            std::string::npos)
      << m;
  EXPECT_EQ(server->rest_positions().size(), 1u);
}

}  // namespace
}  // namespace aggscan
