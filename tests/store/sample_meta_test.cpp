// A sample's description: what a person may give, how an edit changes
// sample.json alone, and the mass from the specific gravity.
#include "store/sample_meta.h"

#include <gtest/gtest.h>

#include <string>
#include <vector>

#include "common/fsutil.h"
#include "store/layout.h"
#include "store/sample_store.h"
#include "tests/util/temp_dir.h"

namespace aggscan {
namespace {

using nlohmann::json;
using test::TempDir;

std::string Message(const Result<json>& r) { return r ? std::string() : r.error().message; }

TEST(SampleMeta, CheckPatchNormalisesAndRefusesWithTheFieldNamed) {
  auto ok = sample_meta::CheckPatch(
      {{"id", "rock-1"},
       {"operator", "  M. Rossi "},
       {"notes", "wet\nchipped"},
       {"material", {{"name", " basalt "}, {"specific_gravity", 2.9}, {"basis", "oven-dry"}}}},
      /*allow_removal=*/false, {"id"});
  ASSERT_TRUE(ok) << Message(ok);
  EXPECT_EQ(
      *ok,
      (json{{"operator", "M. Rossi"},
            {"notes", "wet\nchipped"},
            {"material", {{"name", "basalt"}, {"specific_gravity", 2.9}, {"basis", "oven-dry"}}}}));
  const struct {
    json doc;
    const char* says;
  } bad[] = {
      {{{"mass", 3}}, "unknown field \"mass\""},
      {{{"operator", 7}}, "\"operator\" must be a string"},
      {{{"lot", "a\nb"}}, "\"lot\" contains a control character"},
      {{{"material", {{"specific_gravity", 2.65}}}}, "needs its basis"},
      {{{"material", {{"specific_gravity", 0.9}, {"basis", "bulk-ssd"}}}}, "1 to 6"},
      {{{"material", {{"specific_gravity", 2650}, {"basis", "bulk-ssd"}}}}, "kg/m3"},
      {{{"material", {{"specific_gravity", "2.65"}, {"basis", "bulk-ssd"}}}}, "must be a number"},
      {{{"material", {{"basis", "ssd"}}}}, "\"material.basis\" must be \"bulk-ssd\""},
      {{{"material", {{"colour", "grey"}}}}, "unknown field \"material.colour\""},
      {{{"material", "granite"}}, "\"material\" must be an object"},
      {json::array(), "expected a JSON object"},
  };
  for (const auto& b : bad) {
    auto r = sample_meta::CheckPatch(b.doc, true);
    ASSERT_FALSE(r) << b.doc.dump();
    EXPECT_EQ(r.error().cls, ErrorClass::kInvalidArgument);
    EXPECT_NE(r.error().message.find(b.says), std::string::npos)
        << b.doc.dump() << ": " << r.error().message;
  }
  // An edit may give the specific gravity alone when the basis is kept.
  auto sg_only = sample_meta::CheckPatch({{"material", {{"specific_gravity", 2.7}}}}, true, {},
                                         {{"basis", "bulk-ssd"}});
  EXPECT_TRUE(sg_only) << Message(sg_only);
  // In an edit null and empty text remove; at arming they are "not given".
  auto edit = sample_meta::CheckPatch({{"lot", nullptr}, {"notes", "  "}}, true);
  ASSERT_TRUE(edit);
  EXPECT_EQ(*edit, (json{{"lot", nullptr}, {"notes", nullptr}}));
  auto arm = sample_meta::CheckPatch({{"lot", nullptr}, {"notes", "  "}}, false);
  ASSERT_TRUE(arm);
  EXPECT_TRUE(arm->empty()) << arm->dump();
}

TEST(SampleMeta, ApplyPatchReportsWhatItChanged) {
  json meta = {{"lot", "L-1"}, {"material", {{"name", "granite"}, {"basis", "bulk-ssd"}}}};
  const json changed = sample_meta::ApplyPatch(
      meta, {{"lot", "L-2"}, {"notes", nullptr}, {"material", {{"specific_gravity", 2.65}}}});
  EXPECT_EQ(changed, (json{{"lot", "L-1"}, {"material.specific_gravity", nullptr}}));
  EXPECT_EQ(meta,
            (json{{"lot", "L-2"},
                  {"material",
                   {{"name", "granite"}, {"basis", "bulk-ssd"}, {"specific_gravity", 2.65}}}}));
  EXPECT_TRUE(sample_meta::ApplyPatch(meta, {{"lot", "L-2"}}).empty());
  EXPECT_EQ(sample_meta::ApplyPatch(meta, {{"material", nullptr}}).size(), 1u);
  EXPECT_FALSE(meta.contains("material"));
}

TEST(SampleMeta, MassFromVolumeAndSpecificGravity) {
  // 155,746.5 mm3 = 155.7465 cm3 of a stone 2.65 times as dense as water.
  const json meta = {{"material", {{"specific_gravity", 2.65}, {"basis", "bulk-ssd"}}}};
  const sample_meta::Mass m = sample_meta::MassOf(155746.5, meta);
  ASSERT_TRUE(m.grams.has_value()) << m.why_none;
  EXPECT_NEAR(*m.grams, 412.728, 1e-3);
  EXPECT_EQ(m.basis, "bulk-ssd");
  // No specific gravity: no mass, and what to do.
  const sample_meta::Mass none = sample_meta::MassOf(155746.5, json{{"lot", "L-1"}});
  EXPECT_FALSE(none.grams.has_value());
  EXPECT_NE(none.why_none.find("no specific gravity"), std::string::npos) << none.why_none;
  EXPECT_NE(none.why_none.find("aggscan meta"), std::string::npos) << none.why_none;
  // A hand-edited record with a density in kg/m3 gives no mass either.
  const sample_meta::Mass wrong = sample_meta::MassOf(
      155746.5, json{{"material", {{"specific_gravity", 2650}, {"basis", "bulk-ssd"}}}});
  EXPECT_FALSE(wrong.grams.has_value());
  EXPECT_NE(wrong.why_none.find("2650"), std::string::npos) << wrong.why_none;
  EXPECT_EQ(sample_meta::MaterialFromConfig("", 0, "bulk-ssd"), nullptr);
  EXPECT_EQ(sample_meta::MaterialFromConfig("granite", 2.65, "bulk-ssd"),
            (json{{"name", "granite"},
                  {"specific_gravity", 2.65},
                  {"basis", "bulk-ssd"},
                  {"source", "config"}}));
}

// An edit changes sample.json's "meta" alone, keeps who changed what, and
// leaves every stored photo byte for byte; the config's default material
// does not replace a resumed sample's own.
TEST(SampleMeta, EditChangesTheRecordOnlyAndKeepsItsHistory) {
  TempDir t;
  SampleStore store(t.path());
  ASSERT_TRUE(store.Init());
  SamplePlan plan;
  plan.sides = 2;
  plan.views_per_side = 2;
  plan.step_deg = 180;
  const json config_material = sample_meta::MaterialFromConfig("granite", 2.65, "bulk-ssd");
  ASSERT_TRUE(store.CreateOrResume("rock-e", plan, "# cfg\n",
                                   {{"lot", "L-1"}, {"material", config_material}}));
  ASSERT_TRUE(store.BeginSide("rock-e", 1));
  const std::vector<unsigned char> jpeg = {0xff, 0xd8, 1, 2, 3, 0xff, 0xd9};
  ASSERT_TRUE(store.WriteView("rock-e", 1, 0, jpeg, {{"view", 0}}));
  const std::string image = store.SampleDir("rock-e") + "/side1/" + layout::ViewImageName(0);
  const auto before = ReadFile(image);
  ASSERT_TRUE(before);
  json rest_before = *store.LoadRecord("rock-e");
  rest_before.erase("meta");
  rest_before.erase("updated_utc");  // every save stamps it

  auto r = store.EditMeta("rock-e",
                          {{"lot", "L-2"},
                           {"notes", "edge chipped"},
                           {"material", {{"name", "basalt"}, {"specific_gravity", 2.9}}}},
                          "qa");
  ASSERT_TRUE(r) << r.error().ToString();
  EXPECT_EQ((*r)["changed"], (json{{"lot", "L-1"},
                                   {"notes", nullptr},
                                   {"material.name", "granite"},
                                   {"material.specific_gravity", 2.65},
                                   {"material.source", "config"}}));
  auto rec = store.LoadRecord("rock-e");
  ASSERT_TRUE(rec);
  EXPECT_EQ((*rec)["meta"]["lot"], "L-2");
  EXPECT_EQ((*rec)["meta"]["material"]["specific_gravity"], 2.9);
  EXPECT_EQ((*rec)["meta"]["material"]["basis"], "bulk-ssd");
  ASSERT_EQ((*rec)["meta_history"].size(), 1u);
  EXPECT_EQ((*rec)["meta_history"][0]["by"], "qa");
  EXPECT_EQ((*rec)["meta_history"][0]["changed"]["lot"], "L-1");
  json rest_after = *rec;
  rest_after.erase("meta");
  rest_after.erase("meta_history");
  rest_after.erase("updated_utc");
  EXPECT_EQ(rest_after, rest_before);
  EXPECT_EQ(*ReadFile(image), *before);

  // The same edit again changes nothing and adds no history.
  r = store.EditMeta("rock-e", {{"lot", "L-2"}}, "qa");
  ASSERT_TRUE(r);
  EXPECT_TRUE((*r)["changed"].empty());
  rec = store.LoadRecord("rock-e");
  EXPECT_EQ((*rec)["meta_history"].size(), 1u);

  // A refused edit writes nothing.
  r = store.EditMeta("rock-e", {{"material", {{"specific_gravity", 9.5}}}}, "qa");
  EXPECT_FALSE(r);
  EXPECT_EQ((*store.LoadRecord("rock-e"))["meta"]["material"]["specific_gravity"], 2.9);
  EXPECT_EQ(store.EditMeta("no-such", {{"lot", "x"}}, "qa").error().cls, ErrorClass::kNotFound);

  // Resuming with the config's default keeps the edited material.
  ASSERT_TRUE(store.CreateOrResume("rock-e", plan, "# cfg\n", {{"material", config_material}}));
  EXPECT_EQ((*store.LoadRecord("rock-e"))["meta"]["material"]["name"], "basalt");
}

}  // namespace
}  // namespace aggscan
