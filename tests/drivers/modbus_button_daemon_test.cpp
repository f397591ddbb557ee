// The real aggscand with a Modbus start button and a Modbus coil status light
// on the loopback libmodbus peer (sim camera and turntable): health reports
// the missing button with its actionable message and refuses a capture, the
// button recovers by itself when the peer appears, a press on the discrete
// input starts the armed capture, the lamp follows the state (steady ready,
// blinking while capturing, fast blink for the flip), and a peer lost while idle makes the button
// unhealthy again at the next health probe.
#include <gtest/gtest.h>

#include <chrono>
#include <fstream>
#include <string>
#include <thread>

#include "tests/drivers/modbus_test_server.h"
#include "tests/scenario/process.h"
#include "tests/util/eventually.h"

namespace aggscan {
namespace {

using test::Eventually;

using json = nlohmann::json;
using testing::ModbusServerOptions;
using testing::ModbusTestServer;

TEST(ModbusButtonDaemon, HealthPressAndLampThroughTheRealDaemon) {
  int port = 0;
  {
    auto probe = ModbusTestServer::StartTcp({});
    port = probe->port();
  }
  test::TempDir t;
  const std::string config = test::WriteConfig(
      t.path(),
      "[button]\nbackend = \"modbus\"\ndebounce = \"0s\"\n[button.modbus]\nlink = \"tcp\"\n"
      "host = \"127.0.0.1\"\nport = " +
          std::to_string(port) +
          "\ninput = \"discrete\"\naddress = 2\n"
          "poll_interval = \"10ms\"\n\n[light]\nbackend = \"modbus\"\n[light.modbus]\nlink = "
          "\"button\"\n"
          "coil = 5\n\n[turntable]\nmax_speed_deg_s = 360.0\naccel_deg_s2 = 1440.0\n",
      1,
      "profile = \"custom\"\nsides = 2\nviews_per_side = 2\nstep_deg = 90.0\ninterval = \"1s\"\n"
      "settle = \"50ms\"\n");
  // Quick retries and probes, so the test sees recovery and loss at once.
  std::string text = test::ReadAll(config);
  text.replace(text.find("[daemon]\n"), 9,
               "[daemon]\nreopen_backoff_min = \"100ms\"\nreopen_backoff_max = \"200ms\"\n"
               "health_probe_interval = \"100ms\"\n");
  // No worker runs beside this daemon: its health is the devices' alone.
  text += "\n[worker]\nsilent_after = \"0s\"\n";
  std::ofstream(config) << text;

  test::Daemon d(config, t.path());
  ASSERT_TRUE(d.ok()) << test::ReadAll(d.log());
  int code = 0;
  json h = d.Get("/api/v1/health", &code);
  EXPECT_EQ(code, 503) << h.dump();
  const json b = h["devices"]["button"];
  EXPECT_EQ(b["state"], "device_missing") << h.dump();
  EXPECT_EQ(b["backend"], "modbus") << h.dump();
  const std::string msg = b["message"].get<std::string>();
  EXPECT_EQ(msg.rfind("button: cannot reach Modbus unit 1 at 127.0.0.1:" + std::to_string(port), 0),
            0u)
      << msg;
  EXPECT_NE(msg.find("[button.modbus]"), std::string::npos) << msg;
  EXPECT_FALSE(h["devices"]["light"]["healthy"].get<bool>()) << h.dump();
  json r = d.Post("/api/v1/samples", R"({"id": "rock-m"})", &code);
  EXPECT_EQ(code, 503) << r.dump();
  EXPECT_NE(r.dump().find("cannot start a capture: button: "), std::string::npos) << r.dump();

  // The controller comes up: the button and the lamp recover by themselves.
  ModbusServerOptions o;
  o.tcp_port = port;
  auto server = ModbusTestServer::StartTcp(o);
  ASSERT_TRUE(Eventually([&] {
    h = d.Get("/api/v1/health", &code);
    return code == 200;
  })) << h.dump();
  EXPECT_EQ(h["devices"]["light"]["pattern"], "ready") << h.dump();
  EXPECT_TRUE(Eventually([&] { return server->coil(5); })) << "lamp steady on when ready";

  r = d.Post("/api/v1/samples", R"({"id": "rock-m"})", &code);
  ASSERT_EQ(code, 200) << r.dump();
  server->SetDiscreteInput(2, true);  // the operator presses start
  json st;
  ASSERT_TRUE(d.WaitFor([](const json& s) { return s.value("state", "") != "armed"; }, 20, &st))
      << st.dump() << test::ReadAll(d.log());
  EXPECT_EQ(st["side"], 1);
  server->SetDiscreteInput(2, false);
  EXPECT_TRUE(Eventually([&] { return !server->coil(5); })) << "lamp blinks while capturing";
  // Side 1 done: the lamp asks for the rock to be flipped; the next press
  // shoots side 2.
  ASSERT_TRUE(
      d.WaitFor([](const json& s) { return s.value("state", "") == "awaiting_pose"; }, 30, &st))
      << st.dump() << test::ReadAll(d.log());
  h = d.Get("/api/v1/health", &code);
  EXPECT_EQ(h["devices"]["light"]["pattern"], "flip") << h.dump();
  server->SetDiscreteInput(2, true);
  ASSERT_TRUE(
      d.WaitFor([](const json& s) { return s.value("state", "") != "awaiting_pose"; }, 20, &st))
      << st.dump();
  server->SetDiscreteInput(2, false);
  ASSERT_TRUE(d.WaitFor(
      [](const json& s) {
        return s.value("state", "") == "idle" && s.value("views_captured", 0) == 4;
      },
      30, &st))
      << st.dump() << test::ReadAll(d.log());
  EXPECT_TRUE(Eventually([&] { return server->coil(5); })) << "steady again when idle";

  // The controller stops answering: the button turns unhealthy, the lamp
  // cannot be switched (its health says so too), arming is refused.
  server->SetSilent(true);
  ASSERT_TRUE(Eventually([&] {
    h = d.Get("/api/v1/health", &code);
    return h["devices"]["button"].value("state", "") == "timeout";
  })) << h.dump();
  EXPECT_NE(
      h["devices"]["button"]["message"].get<std::string>().find("no answer from Modbus unit 1"),
      std::string::npos)
      << h.dump();
  EXPECT_EQ(h["devices"]["light"]["pattern"], "fault") << h.dump();
  r = d.Post("/api/v1/samples", R"({"id": "rock-n"})", &code);
  EXPECT_EQ(code, 503) << r.dump();
  // Back again, then aggscand stops: the lamp goes dark.
  server->SetSilent(false);
  ASSERT_TRUE(Eventually([&] {
    h = d.Get("/api/v1/health", &code);
    return code == 200;
  })) << h.dump();
  EXPECT_TRUE(Eventually([&] { return server->coil(5); })) << "steady on when ready again";
  EXPECT_EQ(d.Stop(), 0);
  EXPECT_FALSE(server->coil(5)) << "dark once aggscand has stopped";
}

}  // namespace
}  // namespace aggscan
