// The status light's base: the pattern table, and the pattern thread driving
// a recording backend (levels written on changes only, in the pattern's
// order, a failed write reported as health and retried).
#include "drivers/status_light.h"

#include <gtest/gtest.h>

#include <mutex>
#include <vector>

#include "tests/util/eventually.h"

namespace aggscan {
namespace {

using test::Eventually;

class RecordingLight final : public StatusLight {
 public:
  ~RecordingLight() override { Close(); }
  std::string Describe() const override { return "recording light"; }
  std::vector<bool> levels() {
    std::lock_guard<std::mutex> l(mu_);
    return levels_;
  }
  void Fail(bool fail) {
    std::lock_guard<std::mutex> l(mu_);
    fail_ = fail;
  }

 protected:
  Status DoOpen() override { return OkStatus(); }
  Status DoSet(bool on) override {
    std::lock_guard<std::mutex> l(mu_);
    if (fail_) return MakeError(ErrorClass::kDisconnected, "lamp link lost");
    levels_.push_back(on);
    return OkStatus();
  }
  void DoClose() override {}

 private:
  std::mutex mu_;
  std::vector<bool> levels_;
  bool fail_ = false;
};

TEST(StatusLight, PatternTable) {
  EXPECT_EQ(PatternSteps(LightPattern::kReady).size(), 1u);
  EXPECT_TRUE(PatternSteps(LightPattern::kReady)[0].on);
  EXPECT_FALSE(PatternSteps(LightPattern::kOff)[0].on);
  // Capturing blinks slower than the flip request; fault is a double flash.
  EXPECT_GT(PatternSteps(LightPattern::kCapturing)[0].duration,
            PatternSteps(LightPattern::kFlip)[0].duration);
  // "Turn the table now" is faster still, so it is not taken for a flip.
  EXPECT_LT(PatternSteps(LightPattern::kTurn)[0].duration,
            PatternSteps(LightPattern::kFlip)[0].duration);
  const auto& fault = PatternSteps(LightPattern::kFault);
  ASSERT_EQ(fault.size(), 4u);
  EXPECT_TRUE(fault[0].on && !fault[1].on && fault[2].on && !fault[3].on);
  for (LightPattern p : {LightPattern::kOff, LightPattern::kReady, LightPattern::kCapturing,
                         LightPattern::kFlip, LightPattern::kFault, LightPattern::kTurn}) {
    for (const LightStep& s : PatternSteps(p)) EXPECT_GT(s.duration, 0) << LightPatternName(p);
  }
}

TEST(StatusLight, ThreadWritesLevelChangesInPatternOrder) {
  RecordingLight light;
  ASSERT_TRUE(light.Open().ok());
  EXPECT_EQ(light.Open().error().cls, ErrorClass::kInvalidState);
  EXPECT_EQ(light.levels(), std::vector<bool>{false}) << "dark at open";
  light.Show(LightPattern::kReady);
  ASSERT_TRUE(Eventually([&] { return light.levels().size() == 2; }));
  EXPECT_TRUE(light.levels().back());
  light.Show(LightPattern::kFlip);  // already lit: the first write is the next "off"
  ASSERT_TRUE(Eventually([&] { return light.levels().size() >= 6; }));
  const std::vector<bool> v = light.levels();
  for (size_t i = 1; i < v.size(); ++i)
    EXPECT_NE(v[i], v[i - 1]) << "only changes are written, at " << i;
  EXPECT_EQ(light.pattern(), LightPattern::kFlip);
  light.Close();
  EXPECT_FALSE(light.levels().back()) << "dark after close";
}

TEST(StatusLight, FailedWriteIsHealthAndIsRetried) {
  RecordingLight light;
  ASSERT_TRUE(light.Open().ok());
  light.Fail(true);
  light.Show(LightPattern::kReady);
  ASSERT_TRUE(Eventually([&] { return !light.Health().ok(); }));
  EXPECT_EQ(light.Health().error().cls, ErrorClass::kDisconnected);
  light.Fail(false);  // the link is back: the steady pattern is written again
  ASSERT_TRUE(Eventually([&] { return light.Health().ok() && light.levels().back(); }));
  light.Close();
}

}  // namespace
}  // namespace aggscan
