// Batches: what a person may give, which samples belong, and the files.
#include "store/batches.h"

#include <gtest/gtest.h>

#include <string>
#include <vector>

#include "common/fsutil.h"
#include "tests/util/temp_dir.h"

namespace aggscan {
namespace {

using nlohmann::json;
using test::TempDir;

json Sample(const std::string& id, const std::string& created, const std::string& lot) {
  json s = {{"id", id}, {"created_utc", created}, {"meta", json::object()}};
  if (!lot.empty()) s["meta"]["lot"] = lot;
  return s;
}

TEST(Batches, RequestIsCheckedWithTheFieldNamed) {
  auto ok = BatchFromRequest("week-49", {{"lot", "L-7"},
                                         {"from", "2026-12-01"},
                                         {"to", "2026-12-05"},
                                         {"samples", {"rock-1", "rock-1", "rock-9"}}});
  ASSERT_TRUE(ok) << ok.error().message;
  EXPECT_EQ(ok->samples, (std::vector<std::string>{"rock-1", "rock-9"}));
  const struct {
    std::string name;
    json doc;
    const char* says;
  } bad[] = {
      {"../x", {{"lot", "L"}}, "invalid batch name"},
      {"b", json::object(), "names no sample"},
      {"b", {{"from", "1.12.2026"}}, "give a date as YYYY-MM-DD"},
      {"b", {{"from", "2026-13-01"}}, "YYYY-MM-DD"},
      {"b", {{"from", "2026-12-05"}, {"to", "2026-12-01"}}, "is after"},
      {"b", {{"samples", "rock-1"}}, "must be a list"},
      {"b", {{"samples", {"a/b"}}}, "not a sample id"},
      {"b", {{"lot", 7}}, "\"lot\" must be a string"},
      {"b", {{"grade", "A"}}, "unknown field \"grade\""},
  };
  for (const auto& b : bad) {
    auto r = BatchFromRequest(b.name, b.doc);
    ASSERT_FALSE(r) << b.doc.dump();
    EXPECT_NE(r.error().message.find(b.says), std::string::npos) << r.error().message;
  }
}

TEST(Batches, MembersByLotDatesAndList) {
  const json samples = json::array({Sample("r1", "2026-11-30T23:59:59.000Z", "L-7"),
                                    Sample("r2", "2026-12-01T00:00:00.000Z", "L-7"),
                                    Sample("r3", "2026-12-05T23:59:59.999Z", "L-7"),
                                    Sample("r4", "2026-12-06T00:00:00.000Z", "L-7"),
                                    Sample("r5", "2026-12-03T10:00:00.000Z", "L-8"),
                                    Sample("r6", "2026-12-03T11:00:00.000Z", "")});
  auto ids = [&](const json& doc) {
    auto b = BatchFromRequest("b", doc);
    EXPECT_TRUE(b) << b.error().message;
    return ResolveBatch(*b, samples);
  };
  EXPECT_EQ(ids({{"lot", "L-7"}}).ids, (std::vector<std::string>{"r1", "r2", "r3", "r4"}));
  // Both ends of the range are whole days, included.
  EXPECT_EQ(ids({{"from", "2026-12-01"}, {"to", "2026-12-05"}}).ids,
            (std::vector<std::string>{"r2", "r3", "r5", "r6"}));
  EXPECT_EQ(ids({{"lot", "L-7"}, {"from", "2026-12-01"}, {"to", "2026-12-05"}}).ids,
            (std::vector<std::string>{"r2", "r3"}));
  EXPECT_EQ(ids({{"to", "2026-11-30"}}).ids, (std::vector<std::string>{"r1"}));
  // Listed ones belong whatever their lot; those the rig lacks are named.
  const BatchMembers m = ids({{"lot", "L-8"}, {"samples", {"r6", "r99"}}});
  EXPECT_EQ(m.ids, (std::vector<std::string>{"r5", "r6"}));
  EXPECT_EQ(m.missing, (std::vector<std::string>{"r99"}));
  EXPECT_EQ(ids({{"samples", {"r4", "r1"}}}).ids, (std::vector<std::string>{"r1", "r4"}));
}

TEST(Batches, StoreKeepsCreationTimeListsAndRemoves) {
  TempDir t;
  BatchStore store(t.path());
  EXPECT_TRUE(store.List().empty());
  auto missing = store.Get("week-49");
  ASSERT_FALSE(missing);
  EXPECT_EQ(missing.error().cls, ErrorClass::kNotFound);
  EXPECT_NE(missing.error().message.find("aggscan batch set"), std::string::npos);
  auto first = store.Put(*BatchFromRequest("week-49", {{"lot", "L-7"}}));
  ASSERT_TRUE(first) << first.error().message;
  ASSERT_TRUE(store.Put(*BatchFromRequest("a-lot", {{"samples", {"r1"}}})));
  auto again = store.Put(*BatchFromRequest("week-49", {{"lot", "L-8"}, {"notes", "re-cut"}}));
  ASSERT_TRUE(again);
  auto got = store.Get("week-49");
  ASSERT_TRUE(got);
  EXPECT_EQ(got->lot, "L-8");
  EXPECT_EQ(got->notes, "re-cut");
  EXPECT_EQ(got->created_utc, first->created_utc);
  const std::vector<BatchDef> all = store.List();
  ASSERT_EQ(all.size(), 2u);
  EXPECT_EQ(all[0].name, "a-lot");
  missing = store.Get("nope");
  EXPECT_NE(missing.error().message.find("there are: a-lot, week-49"), std::string::npos)
      << missing.error().message;
  // A file damaged by hand is named, not fatal to the list.
  ASSERT_TRUE(WriteFileAtomic(t.path() + "/batches/broken.json", std::string_view("{\"lot\": 3}")));
  std::vector<std::string> problems;
  EXPECT_EQ(store.List(&problems).size(), 2u);
  ASSERT_EQ(problems.size(), 1u);
  EXPECT_NE(problems[0].find("broken.json"), std::string::npos) << problems[0];
  ASSERT_TRUE(store.Remove("a-lot"));
  EXPECT_FALSE(store.Get("a-lot"));
  EXPECT_EQ(store.Remove("a-lot").error().cls, ErrorClass::kNotFound);
}

}  // namespace
}  // namespace aggscan
