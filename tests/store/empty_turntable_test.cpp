#include "store/empty_turntable.h"

#include <gtest/gtest.h>
#include <sys/stat.h>

#include <filesystem>
#include <fstream>

#include "common/fsutil.h"
#include "store/layout.h"
#include "store/sample_store.h"
#include "tests/util/temp_dir.h"

namespace aggscan {
namespace {

using nlohmann::json;
using test::TempDir;

std::vector<unsigned char> Bytes(const std::string& s) { return {s.begin(), s.end()}; }

SamplePlan FourViews() {
  SamplePlan p;
  p.sides = 1;
  p.views_per_side = 4;
  p.step_deg = 90;
  return p;
}

// A one-side capture of the empty turntable as the daemon stores it, the
// sidecars carrying the angles the turntable measured.
void CaptureEmpty(SampleStore& store, const std::string& id, const std::string& tag,
                  bool with_angles = true) {
  ASSERT_TRUE(store.CreateOrResume(id, FourViews(), "# cfg\n"));
  ASSERT_TRUE(store.BeginSide(id, 1));
  for (int v = 0; v < 4; ++v) {
    json sidecar = {{"view", v}, {"commanded_angle_deg", 90.0 * v}};
    if (with_angles) sidecar["measured_angle_deg"] = 90.0 * v + 0.05;
    ASSERT_TRUE(store.WriteView(id, 1, v, Bytes(tag + std::to_string(v)), sidecar));
  }
  ASSERT_TRUE(store.FinishSide(id, 1));
}

ino_t Inode(const std::string& path) {
  struct stat st {};
  return ::stat(path.c_str(), &st) == 0 ? st.st_ino : 0;
}

// Installed from a capture, the set becomes current; a sample armed after
// that links it in (the same files), records it, and keeps it when another
// set is installed later; one armed then gets the new one.
TEST(EmptyTurntable, InstalledSetIsLinkedIntoSamplesArmedAfterIt) {
  TempDir t;
  SampleStore store(t.path());
  ASSERT_TRUE(store.Init());
  CaptureEmpty(store, "empty-1", "first");
  auto set = InstallEmptyTurntableSet(t.path(), store.SampleDir("empty-1"), 1, 640, 480);
  ASSERT_TRUE(set.ok()) << set.error().ToString();
  ASSERT_EQ(set->views.size(), 4u);
  EXPECT_DOUBLE_EQ(set->views[2].angle_deg, 180.05);
  EXPECT_EQ(set->width, 640);
  auto cur = CurrentEmptyTurntableSet(t.path());
  ASSERT_TRUE(cur.ok()) << cur.error().ToString();
  EXPECT_EQ(cur->id, set->id);

  ASSERT_TRUE(store.CreateOrResume("rock-1", FourViews(), "# cfg\n"));
  const std::string linked = store.SampleDir("rock-1") + "/" + layout::kEmptyDir;
  auto own = LoadEmptyTurntableSet(linked);
  ASSERT_TRUE(own.ok()) << own.error().ToString();
  EXPECT_EQ(own->id, set->id);
  EXPECT_EQ(*ReadFile(linked + "/" + own->views[1].image), "first1");
  EXPECT_EQ(Inode(linked + "/" + own->views[1].image),
            Inode(EmptyTurntableRoot(t.path()) + "/" + set->id + "/" + set->views[1].image));
  EXPECT_EQ((*store.LoadRecord("rock-1"))["empty_turntable"]["set"], set->id);

  // A newer set does not change the sample armed before it.
  CaptureEmpty(store, "empty-2", "second");
  auto set2 = InstallEmptyTurntableSet(t.path(), store.SampleDir("empty-2"), 1, 640, 480);
  ASSERT_TRUE(set2.ok());
  EXPECT_NE(set2->id, set->id);
  EXPECT_EQ(CurrentEmptyTurntableSet(t.path())->id, set2->id);
  ASSERT_TRUE(store.CreateOrResume("rock-1", FourViews(), "# cfg\n"));  // a resume
  EXPECT_EQ(LoadEmptyTurntableSet(linked)->id, set->id);
  ASSERT_TRUE(store.CreateOrResume("rock-2", FourViews(), "# cfg\n"));
  const std::string linked2 = store.SampleDir("rock-2") + "/" + layout::kEmptyDir;
  EXPECT_EQ(LoadEmptyTurntableSet(linked2)->id, set2->id);
  EXPECT_EQ(*ReadFile(linked2 + "/" + set2->views[0].image), "second0");
  // The first set is still there, whole.
  EXPECT_TRUE(LoadEmptyTurntableSet(EmptyTurntableRoot(t.path()) + "/" + set->id).ok());
}

TEST(EmptyTurntable, WithoutASetTheSampleRecordSaysWhy) {
  TempDir t;
  SampleStore store(t.path());
  ASSERT_TRUE(store.Init());
  ASSERT_TRUE(store.CreateOrResume("rock-1", FourViews(), "# cfg\n"));
  const json rec = *store.LoadRecord("rock-1");
  EXPECT_TRUE(rec["empty_turntable"]["set"].is_null()) << rec.dump();
  EXPECT_NE(rec["empty_turntable"]["reason"].get<std::string>().find(
                "no empty-turntable photos installed"),
            std::string::npos);
  EXPECT_FALSE(PathExists(store.SampleDir("rock-1") + "/" + layout::kEmptyDir));
}

TEST(EmptyTurntable, NearestAngleWrapsAroundTheTurn) {
  EmptyTurntableSet s;
  s.views = {{"a.jpg", 0.1}, {"b.jpg", 120.0}, {"c.jpg", 240.0}};
  double d = -1;
  EXPECT_EQ(s.Nearest(359.8, &d)->image, "a.jpg");
  EXPECT_NEAR(d, 0.3, 1e-9);
  EXPECT_EQ(s.Nearest(-121.0, &d)->image, "c.jpg");
  EXPECT_NEAR(d, 1.0, 1e-9);
  EXPECT_EQ(s.Nearest(725.0, &d)->image, "a.jpg");  // two turns and 5 deg
  EXPECT_NEAR(d, 4.9, 1e-9);
  EXPECT_EQ(EmptyTurntableSet{}.Nearest(0, &d), nullptr);
}

TEST(EmptyTurntable, WhatCannotBeInstalledOrReadIsNamed) {
  TempDir t;
  SampleStore store(t.path());
  ASSERT_TRUE(store.Init());
  // A side not captured to the end (no manifest).
  ASSERT_TRUE(store.CreateOrResume("half", FourViews(), "# cfg\n"));
  ASSERT_TRUE(store.BeginSide("half", 1));
  auto r = InstallEmptyTurntableSet(t.path(), store.SampleDir("half"), 1, 640, 480);
  ASSERT_FALSE(r.ok());
  EXPECT_EQ(r.error().cls, ErrorClass::kNotFound);
  EXPECT_NE(r.error().message.find("not a complete capture"), std::string::npos)
      << r.error().message;
  // Sidecars without the measured angle (a turntable that does not report one).
  CaptureEmpty(store, "no-angles", "x", /*with_angles=*/false);
  r = InstallEmptyTurntableSet(t.path(), store.SampleDir("no-angles"), 1, 640, 480);
  ASSERT_FALSE(r.ok());
  EXPECT_EQ(r.error().cls, ErrorClass::kInvalidArgument);
  EXPECT_NE(r.error().message.find("no measured turntable angle"), std::string::npos)
      << r.error().message;
  EXPECT_EQ(CurrentEmptyTurntableSet(t.path()).error().cls, ErrorClass::kNotFound);

  // A damaged manifest and one naming a photo that is not there.
  CaptureEmpty(store, "ok", "y");
  auto set = InstallEmptyTurntableSet(t.path(), store.SampleDir("ok"), 1, 640, 480);
  ASSERT_TRUE(set.ok());
  const std::string dir = EmptyTurntableRoot(t.path()) + "/" + set->id;
  const std::string manifest = *ReadFile(dir + "/manifest.json");
  ASSERT_TRUE(WriteFileAtomic(dir + "/manifest.json", std::string_view("{\"format\": 1")));
  auto bad = LoadEmptyTurntableSet(dir);
  ASSERT_FALSE(bad.ok());
  EXPECT_EQ(bad.error().cls, ErrorClass::kCorrupt);
  EXPECT_NE(bad.error().message.find("manifest.json"), std::string::npos) << bad.error().message;
  ASSERT_TRUE(WriteFileAtomic(dir + "/manifest.json", std::string_view(manifest)));
  std::filesystem::remove(dir + "/" + set->views[3].image);
  bad = LoadEmptyTurntableSet(dir);
  ASSERT_FALSE(bad.ok());
  EXPECT_NE(bad.error().message.find("lists " + set->views[3].image + ", which is not in"),
            std::string::npos)
      << bad.error().message;
  // A sample armed now records why it has none instead of linking a broken set.
  ASSERT_TRUE(store.CreateOrResume("rock", FourViews(), "# cfg\n"));
  EXPECT_TRUE((*store.LoadRecord("rock"))["empty_turntable"]["set"].is_null());
}

}  // namespace
}  // namespace aggscan
