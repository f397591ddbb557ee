// `aggscan empty-turntable`: a simulated capture of the turntable without a
// rock installed as the rig's empty-turntable photos, shown, and the usage
// and input errors named.
#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <sys/wait.h>

#include <cstdio>
#include <filesystem>
#include <string>

#include "store/empty_turntable.h"
#include "store/layout.h"
#include "store/sample_store.h"
#include "tests/util/shell.h"
#include "tests/util/temp_dir.h"

namespace aggscan {
namespace {

using ::testing::HasSubstr;

const std::string kAggscan = std::string(AGGSCAN_BINARY_DIR) + "/cli/aggscan";

using test::Shell;

TEST(EmptyTurntableCommand, InstallsACaptureAndShowsIt) {
  test::TempDir t;
  const std::string state = t.path() + "/state";
  const std::string sample = state + "/samples/empty-1";
  std::string out;
  // The sim's board scene is a capture without a rock over one full turn.
  ASSERT_EQ(
      Shell(kAggscan + " sim capture --scene charuco --views 6 --width 320 --height 240 --out " +
                sample,
            &out),
      0)
      << out;
  ASSERT_EQ(Shell(kAggscan + " empty-turntable --state-dir " + state, &out), 3) << out;
  EXPECT_THAT(out, HasSubstr("no empty-turntable photos installed"));

  ASSERT_EQ(Shell(kAggscan + " empty-turntable " + sample, &out), 0) << out;
  EXPECT_THAT(out, HasSubstr("installed for " + state));
  EXPECT_THAT(out, HasSubstr("6 photos of 320x240"));
  auto set = CurrentEmptyTurntableSet(state);
  ASSERT_TRUE(set) << set.error().ToString();
  EXPECT_EQ(set->views.size(), 6u);
  EXPECT_EQ(set->width, 320);

  ASSERT_EQ(Shell(kAggscan + " empty-turntable --state-dir " + state, &out), 0) << out;
  EXPECT_THAT(out, HasSubstr("empty-turntable set " + set->id + ": 6 photos of 320x240"));

  // A sample armed now takes it in.
  SampleStore store(state);
  SamplePlan plan;
  ASSERT_TRUE(store.CreateOrResume("rock-1", plan, "# cfg\n"));
  EXPECT_EQ(LoadEmptyTurntableSet(store.SampleDir("rock-1") + "/" + layout::kEmptyDir)->id,
            set->id);
}

TEST(EmptyTurntableCommand, BadUseIsNamed) {
  test::TempDir t;
  std::string out;
  EXPECT_EQ(Shell(kAggscan + " empty-turntable", &out), 2);
  EXPECT_THAT(out, HasSubstr("give the sample directory"));
  EXPECT_EQ(Shell(kAggscan + " empty-turntable --side 0 x", &out), 2);
  EXPECT_THAT(out, HasSubstr("--side expects 1..8"));
  EXPECT_EQ(
      Shell(kAggscan + " empty-turntable " + t.path() + "/nothing --state-dir " + t.path(), &out),
      1);
  EXPECT_THAT(out, HasSubstr("is not a sample directory"));
  // Outside a state directory, without saying which rig.
  const std::string loose = t.path() + "/loose";
  ASSERT_EQ(
      Shell(kAggscan + " sim capture --scene charuco --views 6 --width 320 --height 240 --out " +
                loose,
            &out),
      0)
      << out;
  EXPECT_EQ(Shell(kAggscan + " empty-turntable " + loose, &out), 2);
  EXPECT_THAT(out, HasSubstr("not inside a state directory"));
  // A side that was not captured.
  EXPECT_EQ(
      Shell(kAggscan + " empty-turntable " + loose + " --side 2 --state-dir " + t.path() + "/s",
            &out),
      1);
  EXPECT_THAT(out, HasSubstr("holds no photos"));
}

}  // namespace
}  // namespace aggscan
