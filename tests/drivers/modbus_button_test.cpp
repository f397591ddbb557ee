// The Modbus button and status light against the libmodbus test server on
// loopback: a discrete input or coil polled as the start button (press =
// rising edge), a coil as the lamp, link errors classified, and one shared
// connection for a button and a light on the same link.
#include <gtest/gtest.h>

#include <chrono>
#include <thread>

#include "common/clock.h"
#include "config/config.h"
#include "drivers/factory.h"
#include "drivers/modbus/modbus_io.h"
#include "tests/drivers/modbus_test_server.h"
#include "tests/util/eventually.h"

namespace aggscan::modbus {
namespace {

using test::Eventually;

using testing::ModbusTestServer;

Config ButtonOn(int port, const std::string& input = "discrete", int address = 3) {
  Config c;
  c.button.backend = "modbus";
  c.button.debounce = 0;
  c.button.modbus.link = "tcp";
  c.button.modbus.host = "127.0.0.1";
  c.button.modbus.port = port;
  c.button.modbus.input = input;
  c.button.modbus.address = address;
  c.button.modbus.poll_interval = 5 * kNsPerMs;
  c.button.modbus.response_timeout = 100 * kNsPerMs;
  return c;
}

std::unique_ptr<ModbusButton> MakeButton(Clock& clock, const Config& c) {
  return std::make_unique<ModbusButton>(clock, c.button,
                                        std::make_shared<BitLink>(ButtonLinkSettings(c)));
}

// Lets the button poll `n` more times (the deterministic wait for "nothing happened").
void Polls(const ModbusButton& b, int n) {
  const int target = b.polls() + n;
  ASSERT_TRUE(Eventually([&] { return b.polls() >= target; }));
}

TEST(ModbusButton, RisingEdgeOfADiscreteInputIsOnePress) {
  auto server = ModbusTestServer::StartTcp({});
  RealClock clock;
  auto b = MakeButton(clock, ButtonOn(server->port()));
  int presses = 0;
  std::string source;
  ASSERT_TRUE(b->Start([&](const ButtonPress& p) {
                 source = p.source;
                 ++presses;
               }).ok());
  EXPECT_NE(b->Describe().find("discrete input 3 of unit 1 at 127.0.0.1"), std::string::npos)
      << b->Describe();
  Polls(*b, 3);
  EXPECT_EQ(presses, 0);
  server->SetDiscreteInput(3, true);
  ASSERT_TRUE(Eventually([&] { return presses == 1; }));
  EXPECT_EQ(source, "modbus");
  Polls(*b, 5);  // held down: still one press
  EXPECT_EQ(presses, 1);
  server->SetDiscreteInput(2, true);  // another input: not ours
  server->SetDiscreteInput(3, false);
  Polls(*b, 3);
  EXPECT_EQ(presses, 1);
  server->SetDiscreteInput(3, true);
  EXPECT_TRUE(Eventually([&] { return presses == 2; }));
  EXPECT_TRUE(b->Health().ok());
  b->Stop();
}

TEST(ModbusButton, CoilInputAndASetBitAtStartIsNoPress) {
  auto server = ModbusTestServer::StartTcp({});
  server->SetCoil(9, true);  // already set when the button starts
  RealClock clock;
  auto b = MakeButton(clock, ButtonOn(server->port(), "coil", 9));
  int presses = 0;
  ASSERT_TRUE(b->Start([&](const ButtonPress&) { ++presses; }).ok());
  Polls(*b, 3);
  EXPECT_EQ(presses, 0);
  server->SetCoil(9, false);
  Polls(*b, 2);
  server->SetCoil(9, true);
  EXPECT_TRUE(Eventually([&] { return presses == 1; }));
  b->Stop();
}

TEST(ModbusButton, LinkErrorsAreClassified) {
  RealClock clock;
  int free_port = 0;
  {
    auto probe = ModbusTestServer::StartTcp({});
    free_port = probe->port();
  }
  auto missing = MakeButton(clock, ButtonOn(free_port));
  Status s = missing->Start([](const ButtonPress&) {});
  ASSERT_FALSE(s.ok());
  EXPECT_EQ(s.error().cls, ErrorClass::kDeviceMissing) << s.error().ToString();
  EXPECT_NE(s.error().message.find("127.0.0.1:" + std::to_string(free_port)), std::string::npos);
  EXPECT_NE(s.error().message.find("[button.modbus]"), std::string::npos) << s.error().ToString();

  auto server = ModbusTestServer::StartTcp({});
  server->RejectRegister(3);  // the controller has no such input
  auto refused = MakeButton(clock, ButtonOn(server->port()));
  s = refused->Start([](const ButtonPress&) {});
  ASSERT_FALSE(s.ok());
  EXPECT_EQ(s.error().cls, ErrorClass::kDeviceFault) << s.error().ToString();
  EXPECT_NE(s.error().message.find("refused reading discrete input 3"), std::string::npos)
      << s.error().ToString();

  // A peer that stops answering while the button runs: a runtime fault.
  auto server2 = ModbusTestServer::StartTcp({});
  auto b = MakeButton(clock, ButtonOn(server2->port()));
  ASSERT_TRUE(b->Start([](const ButtonPress&) {}).ok());
  server2->SetSilent(true);
  ASSERT_TRUE(Eventually([&] { return !b->Health().ok(); }));
  EXPECT_EQ(b->Health().error().cls, ErrorClass::kTimeout) << b->Health().error().ToString();
  EXPECT_NE(b->Health().error().message.find("no answer from Modbus unit 1 at 127.0.0.1"),
            std::string::npos);
  // Restarted (as the daemon does) once the peer answers again.
  b->Stop();
  server2->SetSilent(false);
  ASSERT_TRUE(b->Start([](const ButtonPress&) {}).ok());
  EXPECT_TRUE(b->Health().ok());
  b->Stop();
}

TEST(ModbusButton, TurntableLinkTakesTheTurntablesTcpSettings) {
  Config c;
  c.turntable.backend = "modbus-tcp";
  c.turntable.modbus.host = "10.0.0.5";
  c.turntable.modbus.port = 1502;
  c.turntable.modbus.unit_id = 3;
  c.turntable.modbus.response_timeout = 150 * kNsPerMs;
  c.button.modbus.link = "turntable";
  c.button.modbus.host = "ignored";
  const LinkSettings b = ButtonLinkSettings(c);
  EXPECT_TRUE(b.tcp);
  EXPECT_EQ(b.Describe(), "unit 3 at 10.0.0.5:1502");
  EXPECT_EQ(b.response_timeout, 150 * kNsPerMs);
  EXPECT_NE(b.section.find("[turntable.modbus]"), std::string::npos) << b.section;
  c.light.modbus.link = "turntable";
  EXPECT_TRUE(LightLinkSettings(c).SameLink(b));
  c.button.modbus.link = "rtu";
  c.button.modbus.device = "/dev/ttyUSB1";
  c.button.modbus.parity = "even";
  EXPECT_EQ(ButtonLinkSettings(c).Describe(), "unit 1 on /dev/ttyUSB1 at 19200 8E1");
  EXPECT_FALSE(LightLinkSettings(c).SameLink(ButtonLinkSettings(c)));
}

TEST(ModbusLight, CoilFollowsThePattern) {
  auto server = ModbusTestServer::StartTcp({});
  server->SetCoil(7, true);
  ModbusLightConfig lc;
  lc.coil = 7;
  Config c = ButtonOn(server->port());
  ModbusLight light(lc, std::make_shared<BitLink>(ButtonLinkSettings(c)));
  ASSERT_TRUE(light.Open().ok());
  EXPECT_FALSE(server->coil(7)) << "dark after open";
  light.Show(LightPattern::kReady);
  EXPECT_TRUE(Eventually([&] { return server->coil(7); }));
  light.Show(LightPattern::kOff);
  EXPECT_TRUE(Eventually([&] { return !server->coil(7); }));
  light.Show(LightPattern::kFlip);  // blinks: the coil goes both ways
  EXPECT_TRUE(Eventually([&] { return server->coil(7); }));
  EXPECT_TRUE(Eventually([&] { return !server->coil(7); }));
  EXPECT_TRUE(Eventually([&] { return server->coil(7); }));
  EXPECT_TRUE(light.Health().ok());
  // Lost controller: the light reports it.
  server->SetSilent(true);
  EXPECT_TRUE(Eventually([&] { return !light.Health().ok(); }));
  EXPECT_EQ(light.Health().error().cls, ErrorClass::kTimeout);
  server->SetSilent(false);
  light.Close();
  EXPECT_FALSE(server->coil(7)) << "dark after close";
}

TEST(ModbusLight, FactoryBuildsButtonAndLightOnOneLink) {
  auto server = ModbusTestServer::StartTcp({});
  Config c = ButtonOn(server->port());
  c.light.backend = "modbus";
  c.light.modbus.link = "button";
  c.light.modbus.coil = 5;
  RealClock clock;
  Result<RigDevices> rig = CreateRig(c, clock);
  ASSERT_TRUE(rig.ok()) << rig.error().ToString();
  ASSERT_TRUE(rig->light);
  int presses = 0;
  ASSERT_TRUE(rig->button->Start([&](const ButtonPress&) { ++presses; }).ok());
  ASSERT_TRUE(rig->light->Open().ok());
  rig->light->Show(LightPattern::kReady);
  EXPECT_TRUE(Eventually([&] { return server->coil(5); }));
  server->SetDiscreteInput(3, true);
  EXPECT_TRUE(Eventually([&] { return presses == 1; }));
  rig->button->Stop();
  rig->light->Close();
}

}  // namespace
}  // namespace aggscan::modbus
