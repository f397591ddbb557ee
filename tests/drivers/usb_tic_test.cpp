// The USB turntable backend's device-free parts: the Tic's variable block,
// unit conversions, error texts, the [turntable.usb] config and what Open
// says when no Tic is attached. The backend against an emulated Tic runs in
// the VM lane (usb_tic_vm_test).
#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <array>
#include <cstdint>

#include "common/clock.h"
#include "config/config.h"
#include "drivers/factory.h"
#include "drivers/usb/tic_protocol.h"
#include "drivers/usb/usb_tic_turntable.h"

namespace aggscan {
namespace {

using ::testing::HasSubstr;

// A block laid out by hand from the user's guide's table (section 7), not
// through the parser's own offsets.
std::array<uint8_t, 0x2A> Block() {
  std::array<uint8_t, 0x2A> b{};
  b[0x00] = 10;    // operation state: normal
  b[0x01] = 0x13;  // energized, position uncertain, homing active
  b[0x02] = 0x82;  // error status: motor driver error (bit 1), safe start violation (bit 7)
  b[0x03] = 0x01;  //               ERR line high (bit 8)
  b[0x09] = 1;     // planning mode: target position
  // target position -1600 = 0xFFFFF9C0, little-endian
  b[0x0A] = 0xC0;
  b[0x0B] = 0xF9;
  b[0x0C] = 0xFF;
  b[0x0D] = 0xFF;
  // max speed 2'666'667 = 0x0028B0AB
  b[0x16] = 0xAB;
  b[0x17] = 0xB0;
  b[0x18] = 0x28;
  b[0x19] = 0x00;
  // current position 123456 = 0x0001E240
  b[0x22] = 0x40;
  b[0x23] = 0xE2;
  b[0x24] = 0x01;
  b[0x25] = 0x00;
  // current velocity -10000 = 0xFFFFD8F0
  b[0x26] = 0xF0;
  b[0x27] = 0xD8;
  b[0x28] = 0xFF;
  b[0x29] = 0xFF;
  return b;
}

TEST(TicProtocol, ParsesTheVariableBlock) {
  const auto b = Block();
  Result<tic::Variables> v = tic::ParseVariables(b);
  ASSERT_TRUE(v.ok()) << v.error().ToString();
  EXPECT_EQ(v->operation_state, tic::kStateNormal);
  EXPECT_TRUE(v->energized());
  EXPECT_TRUE(v->position_uncertain());
  EXPECT_TRUE(v->homing_active());
  EXPECT_EQ(v->error_status, 0x0182);
  EXPECT_TRUE(v->has_error(tic::kErrMotorDriver));
  EXPECT_FALSE(v->has_error(tic::kErrCommandTimeout));
  EXPECT_EQ(v->planning_mode, 1);
  EXPECT_EQ(v->target_position, -1600);
  EXPECT_EQ(v->max_speed, 2'666'667u);
  EXPECT_EQ(v->current_position, 123456);
  EXPECT_EQ(v->current_velocity, -10000);
}

TEST(TicProtocol, RejectsAShortBlockAndAnUnknownState) {
  auto b = Block();
  Result<tic::Variables> shortr = tic::ParseVariables(std::span<const uint8_t>(b.data(), 0x20));
  ASSERT_FALSE(shortr.ok());
  EXPECT_EQ(shortr.error().cls, ErrorClass::kDeviceFault);
  EXPECT_THAT(shortr.error().message, HasSubstr("32 bytes, expected 42"));
  b[0] = 7;
  Result<tic::Variables> bad = tic::ParseVariables(b);
  ASSERT_FALSE(bad.ok());
  EXPECT_THAT(bad.error().message, HasSubstr("operation state 7"));
}

TEST(TicProtocol, NamesErrorsAndStates) {
  EXPECT_EQ(tic::ErrorStatusText(0), "none");
  EXPECT_EQ(tic::ErrorStatusText(0x0182),
            "motor driver error, safe start violation, ERR line high");
  EXPECT_EQ(tic::ErrorStatusText(1u << 12), "error bit 12");
  EXPECT_STREQ(tic::OperationStateName(2), "de-energized");
  EXPECT_STREQ(tic::ProductName(0x00B5), "Tic T834");
  EXPECT_EQ(tic::ProductName(0x1234), nullptr);
}

TEST(TicProtocol, ConvertsRatesToTheTicsUnits) {
  // 60 deg/s at 1600 microsteps/rev = 266.67 microsteps/s = 2'666'667 per 10000 s.
  Result<uint32_t> v = tic::SpeedUnits(60.0, 1600.0);
  ASSERT_TRUE(v.ok());
  EXPECT_EQ(*v, 2'666'667u);
  // 180 deg/s^2 = 800 microsteps/s^2 = 80'000 per 100 s^2.
  Result<uint32_t> a = tic::AccelUnits(180.0, 1600.0);
  ASSERT_TRUE(a.ok());
  EXPECT_EQ(*a, 80'000u);
  // 3600 deg/s at 256 x 200 x 100 microsteps/rev is far beyond 50 kHz.
  Result<uint32_t> fast = tic::SpeedUnits(3600.0, 200.0 * 256 * 100);
  ASSERT_FALSE(fast.ok());
  EXPECT_EQ(fast.error().cls, ErrorClass::kInvalidConfig);
  EXPECT_THAT(fast.error().message, HasSubstr("turntable.max_speed_deg_s"));
  // Below the Tic's least acceleration (1 microstep/s^2).
  Result<uint32_t> slow = tic::AccelUnits(0.01, 200.0);
  ASSERT_FALSE(slow.ok());
  EXPECT_THAT(slow.error().message, HasSubstr("turntable.accel_deg_s2"));
}

TEST(TicProtocol, StepModes) {
  EXPECT_EQ(tic::StepModeCode(1), 0);
  EXPECT_EQ(tic::StepModeCode(8), 3);
  EXPECT_EQ(tic::StepModeCode(32), 5);
  EXPECT_EQ(tic::StepModeCode(256), 9);
  EXPECT_FALSE(tic::StepModeCode(3).has_value());
}

TEST(UsbTicConfig, LoadsTheUsbBlock) {
  std::vector<ConfigProblem> problems;
  Result<Config> c = LoadConfigString(
      "[turntable]\nbackend = \"usb-tic\"\n[turntable.usb]\nserial_number = \"00123456\"\n"
      "product_id = 0xB5\nmicrosteps = 16\ngear_ratio = 3.0\nhome = \"forward\"\n"
      "timeout = \"250ms\"\n",
      "t.toml", &problems);
  ASSERT_TRUE(c.ok()) << c.error().ToString();
  EXPECT_EQ(c->turntable.usb.serial_number, "00123456");
  EXPECT_EQ(c->turntable.usb.vendor_id, 0x1FFB);
  EXPECT_EQ(c->turntable.usb.product_id, 0xB5);
  EXPECT_EQ(c->turntable.usb.home, "forward");
  EXPECT_EQ(c->turntable.usb.timeout, 250 * kNsPerMs);
  EXPECT_DOUBLE_EQ(c->turntable.usb.steps_per_rev(), 200.0 * 16 * 3);
}

TEST(UsbTicConfig, RejectsAStepModeNoTicHasAndAnUnknownHome) {
  std::vector<ConfigProblem> problems;
  Result<Config> c = LoadConfigString(
      "[turntable]\nbackend = \"usb-tic\"\n[turntable.usb]\nmicrosteps = 12\nhome = \"up\"\n",
      "t.toml", &problems);
  ASSERT_FALSE(c.ok());
  ASSERT_EQ(problems.size(), 2u);
  std::string all;
  for (const auto& p : problems) all += p.ToString() + "\n";
  EXPECT_THAT(all, HasSubstr("turntable.usb.microsteps"));
  EXPECT_THAT(all, HasSubstr("1, 2, 4, 8, 16, 32"));
  EXPECT_THAT(all, HasSubstr("turntable.usb.home"));
}

TEST(UsbTicTurntable, FactoryBuildsItWithoutOpening) {
  VirtualClock clock;
  Config c;
  c.turntable.backend = "usb-tic";
  c.turntable.usb.serial_number = "00999999";
  Result<RigDevices> rig = CreateRig(c, clock);
  ASSERT_TRUE(rig.ok()) << rig.error().ToString();
  TurntableInfo info = rig->turntable->Info();
  EXPECT_EQ(info.backend, "usb-tic");
  EXPECT_EQ(info.id, "usb:1ffb:0000/00999999");
  EXPECT_FALSE(rig->turntable->is_open());
}

// No Tic with this serial on the machine running the tests (there is no USB
// device here, or at least not this one): missing, named, with what to check.
TEST(UsbTicTurntable, NoDeviceIsMissingWithTheSelectionNamed) {
  TurntableConfig cfg;
  cfg.backend = "usb-tic";
  cfg.usb.serial_number = "00999999";
  usb::UsbTicTurntable t(cfg);
  Status s = t.Open();
  ASSERT_FALSE(s.ok());
  EXPECT_EQ(s.error().cls, ErrorClass::kDeviceMissing);
  EXPECT_THAT(s.error().message, HasSubstr("1ffb"));
  EXPECT_THAT(s.error().message, HasSubstr("serial 00999999"));
  EXPECT_FALSE(t.is_open());
}

TEST(UsbTicTurntable, LimitsTheTicCannotTakeAreConfigErrorsBeforeAnyIo) {
  TurntableConfig cfg;
  cfg.backend = "usb-tic";
  cfg.max_speed_deg_s = 3600;
  cfg.usb.microsteps = 256;
  cfg.usb.gear_ratio = 100;
  usb::UsbTicTurntable t(cfg);
  Status s = t.Open();
  ASSERT_FALSE(s.ok());
  EXPECT_EQ(s.error().cls, ErrorClass::kInvalidConfig);
  EXPECT_THAT(s.error().message, HasSubstr("max_speed_deg_s"));
}

}  // namespace
}  // namespace aggscan
