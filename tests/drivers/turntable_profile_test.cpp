// Turntable register-map profiles: the shipped ones, and refusals that name
// the file, the field and what to do.
#include "config/turntable_profile.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <filesystem>
#include <string>

namespace aggscan {
namespace {

using ::testing::HasSubstr;

const std::string kDir = std::string(AGGSCAN_SOURCE_DIR) + "/config/turntables";

// The generic map, register by register as the reference map gives it.
TEST(TurntableProfile, GenericIsTheReferenceMap) {
  Result<TurntableProfile> p = FindTurntableProfile("generic", kDir);
  ASSERT_TRUE(p.ok()) << p.error().ToString() << "\n" << p.error().detail;
  EXPECT_EQ(p->name, "generic");
  EXPECT_EQ(p->word_order, WordOrder::kHighFirst);
  EXPECT_EQ(p->target_address, 0);
  EXPECT_EQ(p->move, (RegisterWrite{2, 1}));
  EXPECT_EQ(p->home, (RegisterWrite{2, 2}));
  EXPECT_EQ(p->stop, (RegisterWrite{2, 3}));
  EXPECT_EQ(p->reset_alarm, (RegisterWrite{2, 4}));
  EXPECT_EQ(p->enabled, (StatusFlag{3, 0, false}));
  EXPECT_EQ(p->moving, (StatusFlag{3, 1, false}));
  EXPECT_EQ(p->in_position, (StatusFlag{3, 2, false}));
  EXPECT_EQ(p->homed, (StatusFlag{3, 3, false}));
  EXPECT_EQ(p->alarm, (StatusFlag{3, 4, false}));
  EXPECT_EQ(p->actual_address, 4);
  EXPECT_EQ(p->alarm_code_address, 6);
  EXPECT_EQ(p->speed.addresses, std::vector<int>{7});
  EXPECT_EQ(p->speed_unit, SpeedUnit::kTableDegPerS);
  EXPECT_DOUBLE_EQ(p->speed.scale, 0.1);
  EXPECT_EQ(p->accel.addresses, std::vector<int>{8});
  EXPECT_EQ(p->accel_unit, AccelUnit::kTableDegPerS2);
  EXPECT_DOUBLE_EQ(p->accel.scale, 0.1);
  EXPECT_TRUE(p->on_open.empty());
}

TEST(TurntableProfile, EveryShippedProfileLoadsAndNamesItsSource) {
  int n = 0;
  for (const auto& e : std::filesystem::directory_iterator(kDir)) {
    if (e.path().extension() != ".toml") continue;
    SCOPED_TRACE(e.path().string());
    Result<TurntableProfile> p = LoadTurntableProfile(e.path().string());
    ASSERT_TRUE(p.ok()) << p.error().ToString() << "\n" << p.error().detail;
    EXPECT_EQ(p->name, e.path().stem().string());  // the name is the file's
    EXPECT_FALSE(p->model.empty());
    EXPECT_FALSE(p->source.empty());
    ++n;
  }
  EXPECT_GE(n, 2);
}

TEST(TurntableProfile, LeadshineUsesTriggerRegisterAndSeparateReset) {
  Result<TurntableProfile> p = FindTurntableProfile("leadshine-iem-rs", kDir);
  ASSERT_TRUE(p.ok()) << p.error().ToString() << "\n" << p.error().detail;
  EXPECT_EQ(p->move, (RegisterWrite{0x6207, 0x10}));
  EXPECT_EQ(p->home, (RegisterWrite{0x6002, 0x20}));
  EXPECT_EQ(p->reset_alarm, (RegisterWrite{0x1801, 0x1111}));
  EXPECT_EQ(p->actual_address, 0x1014);
  EXPECT_EQ(p->alarm_code_address, 0x2203);
  EXPECT_FALSE(p->alarm.present());  // alarm = non-zero code
  EXPECT_EQ(p->accel.addresses, (std::vector<int>{0x6204, 0x6205}));
  EXPECT_EQ(p->accel_unit, AccelUnit::kMsPer1000Rpm);
  EXPECT_EQ(p->speed_unit, SpeedUnit::kMotorRpm);
  EXPECT_EQ(p->alarm_texts.count(1), 1u);
}

constexpr const char* kMinimal = R"(
[profile]
name = "t"
word_order = "low_first"
[position]
target = 10
actual = 12
[commands]
move = { address = 20, value = 1 }
home = { address = 20, value = 2 }
stop = { address = 20, value = 3 }
[status]
moving = { address = 21, bit = 0 }
in_position = { address = 21, bit = 1, active_low = true }
alarm = { address = 21, bit = 2 }
)";

TEST(TurntableProfile, MinimalProfileAndDefaults) {
  Result<TurntableProfile> p = ParseTurntableProfile(kMinimal, "t.toml");
  ASSERT_TRUE(p.ok()) << p.error().ToString() << "\n" << p.error().detail;
  EXPECT_EQ(p->word_order, WordOrder::kLowFirst);
  EXPECT_TRUE(p->in_position.active_low);
  EXPECT_FALSE(p->speed.present());
  EXPECT_FALSE(p->homed.present());
  EXPECT_EQ(p->reset_alarm.address, -1);
}

// `text` with `from` replaced by `to` must be refused with every `want` in the message.
void ExpectRefused(const std::string& from, const std::string& to,
                   const std::vector<std::string>& want) {
  std::string text = kMinimal;
  const size_t at = text.find(from);
  ASSERT_NE(at, std::string::npos) << from;
  text.replace(at, from.size(), to);
  SCOPED_TRACE(text);
  Result<TurntableProfile> p = ParseTurntableProfile(text, "bad.toml");
  ASSERT_FALSE(p.ok());
  EXPECT_EQ(p.error().cls, ErrorClass::kInvalidConfig);
  // One problem: the message; several: "N problems ..., first: ..." and all in the detail.
  const std::string all = p.error().message + "\n" + p.error().detail;
  for (const auto& w : want) EXPECT_THAT(all, HasSubstr(w));
}

TEST(TurntableProfile, MissingFieldsAreNamedWithWhatToGive) {
  ExpectRefused("move = { address = 20, value = 1 }\n", "",
                {"bad.toml: commands.move: missing; give { address = REGISTER, value = VALUE }",
                 "starts the move"});
  ExpectRefused("word_order = \"low_first\"\n", "",
                {"bad.toml: profile.word_order: missing; give \"high_first\" or \"low_first\""});
  ExpectRefused("actual = 12\n", "", {"bad.toml: position.actual: missing"});
  ExpectRefused("moving = { address = 21, bit = 0 }\n", "", {"bad.toml: status.moving: missing"});
  ExpectRefused("alarm = { address = 21, bit = 2 }\n", "",
                {"status.alarm: missing, and there is no alarm.code either"});
  ExpectRefused("home = { address = 20, value = 2 }", "home = { address = 20 }",
                {"commands.home.value: missing"});
}

TEST(TurntableProfile, ContradictionsAreRefused) {
  ExpectRefused("value = 2 }", "value = 1 }",
                {"commands.home: same register and value as commands.move"});
  ExpectRefused("in_position = { address = 21, bit = 1,", "in_position = { address = 21, bit = 0,",
                {"status.in_position: same register and bit as status.moving"});
  ExpectRefused("actual = 12", "actual = 11",
                {"position.actual: register 0x000B is also position.target"});
  ExpectRefused("stop = { address = 20,", "stop = { address = 12,",
                {"commands.stop: register 0x000C is also position.actual"});
}

TEST(TurntableProfile, BadValuesAreRefused) {
  ExpectRefused(
      "\"low_first\"", "\"middle_first\"",
      {"profile.word_order: must be \"high_first\" or \"low_first\", got \"middle_first\""});
  ExpectRefused("bit = 2 }", "bit = 16 }", {"status.alarm.bit: must be in 0..15, got 16"});
  ExpectRefused("target = 10", "target = -1", {"position.target: must be in 0..65534"});
  ExpectRefused("[status]", "[speed]\naddresses = [30]\nunit = \"furlongs\"\n[status]",
                {"speed.unit: must be one of table_deg_per_s | motor_rpm | steps_per_s"});
  ExpectRefused("[status]",
                "[accel]\naddresses = [30]\nunit = \"steps_per_s2\"\nscale = 0\n[status]",
                {"accel.scale: must be a number > 0"});
  ExpectRefused("[status]", "[speed]\nunit = \"motor_rpm\"\n[status]",
                {"speed.addresses: must be a non-empty array"});
  ExpectRefused("[position]", "[postion]",
                {"bad.toml: postion: unknown key", "position: missing table"});
  ExpectRefused("moving = { address = 21, bit = 0 }", "moving = { adress = 21, bit = 0 }",
                {"status.moving.adress: unknown key; known here: active_low, address, bit"});
  Result<TurntableProfile> p = ParseTurntableProfile("[profile\n", "syntax.toml");
  ASSERT_FALSE(p.ok());
  EXPECT_THAT(p.error().message, HasSubstr("syntax.toml:1: TOML syntax error"));
}

TEST(TurntableProfile, EveryProblemIsListed) {
  Result<TurntableProfile> p = ParseTurntableProfile("[profile]\nname = \"x\"\n", "empty.toml");
  ASSERT_FALSE(p.ok());
  EXPECT_THAT(p.error().message, HasSubstr("problems in turntable profile empty.toml"));
  for (const char* field : {"profile.word_order", "position:", "commands:", "status:"}) {
    EXPECT_THAT(p.error().detail, HasSubstr(std::string("empty.toml: ") + field)) << field;
  }
}

TEST(TurntableProfile, MissingFileNamesTheSettings) {
  Result<TurntableProfile> p = FindTurntableProfile("nope", "/nonexistent");
  ASSERT_FALSE(p.ok());
  EXPECT_EQ(p.error().cls, ErrorClass::kInvalidConfig);
  EXPECT_THAT(p.error().message, HasSubstr("cannot read turntable profile /nonexistent/nope.toml"));
  EXPECT_THAT(p.error().message, HasSubstr("turntable.modbus.profile"));
}

}  // namespace
}  // namespace aggscan
