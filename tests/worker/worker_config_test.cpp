// The one translation of a config into the worker's options, shared by
// aggscan-worker and `aggscan reconstruct`.
#include "pipeline/worker/worker_config.h"

#include <gtest/gtest.h>

#include <fstream>
#include <string>

#include "store/layout.h"
#include "tests/util/temp_dir.h"

namespace aggscan {
namespace {

TEST(WorkerConfig, EveryPosesWordSaysPathAndBundleAdjustment) {
  const struct {
    const char* word;
    PosesPath path;
    bool ba;
  } cases[] = {{"turntable+ba", PosesPath::kTurntable, true},
               {"turntable", PosesPath::kTurntable, false},
               {"sfm", PosesPath::kSfm, true},
               {"auto", PosesPath::kAuto, true}};
  for (const auto& c : cases) {
    PosesChoice p;
    ASSERT_TRUE(ParsePosesChoice(c.word, &p)) << c.word;
    EXPECT_EQ(p.path, c.path) << c.word;
    EXPECT_EQ(p.bundle_adjust, c.ba) << c.word;
    // The config gives the worker exactly what the CLI's --poses gives.
    Config cfg;
    cfg.worker.poses = c.word;
    auto ro = ReconstructOptionsFromConfig(cfg);
    ASSERT_TRUE(ro) << ro.error().ToString();
    EXPECT_EQ(ro->poses, c.path) << c.word;
    EXPECT_EQ(ro->bundle_adjust, c.ba) << c.word;
  }
  PosesChoice p;
  p.bundle_adjust = false;
  EXPECT_FALSE(ParsePosesChoice("colmap", &p));
  EXPECT_FALSE(p.bundle_adjust);  // untouched on refusal
  EXPECT_FALSE(ParsePosesChoice("", &p));
  EXPECT_FALSE(ParsePosesChoice("Turntable", &p));
}

TEST(WorkerConfig, DefaultsAreTheReconstructionDefaults) {
  auto ro = ReconstructOptionsFromConfig(Config{});
  ASSERT_TRUE(ro) << ro.error().ToString();
  const ReconstructOptions plain;
  EXPECT_EQ(ro->poses, plain.poses);
  EXPECT_EQ(ro->bundle_adjust, plain.bundle_adjust);
  EXPECT_TRUE(ro->bundle_adjust);
  EXPECT_EQ(ro->worker.mask_net, nullptr);  // classical masks by default
  EXPECT_DOUBLE_EQ(ro->worker.empty_turntable_max_angle_deg,
                   plain.worker.empty_turntable_max_angle_deg);
}

TEST(WorkerConfig, MaskSectionReachesTheSideJob) {
  Config cfg;
  cfg.mask.empty_turntable_max_angle_deg = 1.25;
  auto ro = ReconstructOptionsFromConfig(cfg);
  ASSERT_TRUE(ro);
  EXPECT_DOUBLE_EQ(ro->worker.empty_turntable_max_angle_deg, 1.25);
  // A network whose model is not there: the error names the file.
  cfg.mask.method = "onnx";
  cfg.mask.model = "/nonexistent/rock.onnx";
  auto bad = ReconstructOptionsFromConfig(cfg);
  ASSERT_FALSE(bad);
  EXPECT_NE(bad.error().message.find("/nonexistent/rock.onnx"), std::string::npos)
      << bad.error().ToString();
  // A word the config loader would have refused, from a Config built in code.
  Config odd;
  odd.worker.poses = "colmap";
  auto refused = ReconstructOptionsFromConfig(odd);
  ASSERT_FALSE(refused);
  EXPECT_EQ(refused.error().cls, ErrorClass::kInvalidArgument);
  EXPECT_NE(refused.error().message.find("turntable+ba"), std::string::npos);
}

TEST(WorkerConfig, SampleConfigIsTheOneItWasArmedWith) {
  test::TempDir tmp;
  std::string source;
  auto none = ConfigForSample(tmp.path(), &source);
  ASSERT_TRUE(none) << none.error().ToString();
  EXPECT_EQ(source, "defaults");
  EXPECT_EQ(none->worker.poses, Config{}.worker.poses);

  const std::string copy = tmp.path() + "/" + layout::kConfigCopy;
  std::ofstream(copy) << "[worker]\nposes = \"turntable\"\n[mask]\n"
                         "empty_turntable_max_angle_deg = 2\n";
  auto armed = ConfigForSample(tmp.path(), &source);
  ASSERT_TRUE(armed) << armed.error().ToString();
  EXPECT_EQ(source, copy);
  EXPECT_EQ(armed->worker.poses, "turntable");
  EXPECT_DOUBLE_EQ(armed->mask.empty_turntable_max_angle_deg, 2.0);

  std::ofstream(copy) << "[worker]\nposes = \"colmap\"\n";
  auto broken = ConfigForSample(tmp.path(), &source);
  ASSERT_FALSE(broken);
  EXPECT_EQ(broken.error().cls, ErrorClass::kCorrupt);
  EXPECT_NE(broken.error().message.find(copy), std::string::npos) << broken.error().message;
  EXPECT_NE(broken.error().message.find("--config"), std::string::npos) << broken.error().message;
  EXPECT_NE(broken.error().message.find("worker.poses"), std::string::npos)
      << broken.error().message;
}

}  // namespace
}  // namespace aggscan
