// library.csv: plain decimals, the description and the mass beside the
// figures, quoted text, one row per rock however many processes write it.
#include "store/library_csv.h"

#include <gtest/gtest.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <filesystem>
#include <fstream>
#include <regex>
#include <sstream>
#include <string>
#include <vector>

#include "common/fsutil.h"
#include "tests/util/temp_dir.h"

namespace aggscan {
namespace {

using nlohmann::json;
using test::TempDir;

json Morphology() {
  // A record of the release before this one (tests/core/data), as written.
  std::ifstream f(std::string(AGGSCAN_SOURCE_DIR) + "/tests/core/data/morphology_v1.json");
  std::stringstream s;
  s << f.rdbuf();
  return json::parse(s.str());
}

std::vector<std::string> Fields(const std::string& line) { return library_csv::SplitLine(line); }

std::string Column(const std::string& row, const std::string& name) {
  const std::vector<std::string> h = Fields(library_csv::Header());
  const auto it = std::find(h.begin(), h.end(), name);
  EXPECT_NE(it, h.end()) << name;
  const std::vector<std::string> f = Fields(row);
  const size_t i = static_cast<size_t>(it - h.begin());
  return i < f.size() ? f[i] : "<missing>";
}

TEST(LibraryCsv, SplitLineReadsQuotedFields) {
  EXPECT_EQ(library_csv::SplitLine("a,\"b, \"\"c\"\"\",,d\r\n"),
            (std::vector<std::string>{"a", "b, \"c\"", "", "d"}));
  EXPECT_EQ(library_csv::SplitLine(""), (std::vector<std::string>{""}));
}

TEST(LibraryCsv, RowHasPlainNumbersMassAndTheDescription) {
  json m = Morphology();
  m["software"] = {{"version", "0.1.0+gabc"}, {"config_sha256", "ab12"}};
  m["warnings"] = json::array({"side 2 view 7 left out, \"blurred\""});
  const json meta = {
      {"operator", "M. Rossi"},
      {"lot", "L-7, north face"},
      {"notes", "not in the library"},
      {"material", {{"name", "granite"}, {"specific_gravity", 2.65}, {"basis", "bulk-ssd"}}}};
  const std::string row = library_csv::Row(m, meta);
  EXPECT_EQ(Fields(row).size(), Fields(library_csv::Header()).size()) << row;
  EXPECT_FALSE(std::regex_search(row, std::regex("[0-9][eE][-+]?[0-9]"))) << row;
  EXPECT_EQ(row.back(), '\n');
  EXPECT_EQ(Column(row, "sample_id"), m["sample_id"].get<std::string>());
  EXPECT_EQ(Column(row, "volume_mm3"), "155746.5");
  EXPECT_EQ(Column(row, "a_mm"), "49.96");
  EXPECT_EQ(Column(row, "sphericity"), "0.8883");
  // 155.7465 cm3 x 2.65 g/cm3.
  EXPECT_EQ(Column(row, "mass_g"), "412.7");
  EXPECT_EQ(Column(row, "specific_gravity"), "2.650");
  EXPECT_EQ(Column(row, "sg_basis"), "bulk-ssd");
  EXPECT_EQ(Column(row, "material"), "granite");
  EXPECT_EQ(Column(row, "lot"), "L-7, north face");
  EXPECT_EQ(Column(row, "views"), "3");  // the fixture keeps three views
  EXPECT_EQ(Column(row, "confident"), "yes");
  EXPECT_EQ(Column(row, "warnings"), "side 2 view 7 left out, \"blurred\"");
  EXPECT_EQ(Column(row, "software_version"), "0.1.0+gabc");
  EXPECT_EQ(Column(row, "config_sha256"), "ab12");
  EXPECT_EQ(row.find("not in the library"), std::string::npos);
  // Without a specific gravity the mass is empty, not a guess.
  const std::string bare = library_csv::Row(m, json::object());
  EXPECT_EQ(Column(bare, "mass_g"), "");
  EXPECT_EQ(Column(bare, "specific_gravity"), "");
  EXPECT_EQ(Column(bare, "lot"), "");
  // A doubtful result says so.
  m["quality"]["confident"] = false;
  m["quality"]["flags"] = json::array({{{"code", "stitch_unconfirmed"}, {"reason", "x"}},
                                       {{"code", "mask_consistency"}, {"reason", "y"}}});
  const std::string doubtful = library_csv::Row(m, meta);
  EXPECT_EQ(Column(doubtful, "confident"), "no");
  EXPECT_EQ(Column(doubtful, "quality_flags"), "stitch_unconfirmed;mask_consistency");
}

TEST(LibraryCsv, UpsertReplacesTheSamplesRowAndKeepsAnOlderFileAside) {
  TempDir t;
  const std::string path = t.path() + "/library.csv";
  // A library of the earlier release, with other columns.
  ASSERT_TRUE(WriteFileAtomic(path, std::string_view("sample_id,volume_mm3\nold,1.5e+06\n")));
  ASSERT_TRUE(library_csv::Upsert(t.path(), "rock-1", "rock-1,a\n"));
  ASSERT_TRUE(library_csv::Upsert(t.path(), "rock-2", "rock-2,b\n"));
  ASSERT_TRUE(library_csv::Upsert(t.path(), "rock-1", "rock-1,c\n"));
  EXPECT_EQ(*ReadFile(path), library_csv::Header() + "rock-1,c\nrock-2,b\n");
  int kept = 0;
  for (const auto& e : std::filesystem::directory_iterator(t.path())) {
    const std::string n = e.path().filename().string();
    if (n.rfind("library-", 0) == 0) {
      ++kept;
      EXPECT_EQ(*ReadFile(t.path() + "/" + n), "sample_id,volume_mm3\nold,1.5e+06\n");
    }
  }
  EXPECT_EQ(kept, 1);
}

// The worker (a rock reconstructed) and the daemon (a description edited)
// write the library from two processes: no row may be lost.
TEST(LibraryCsv, TwoProcessesWritingLoseNoRow) {
  TempDir t;
  constexpr int kEach = 40;
  std::vector<pid_t> kids;
  for (int p = 0; p < 2; ++p) {
    const pid_t pid = ::fork();
    ASSERT_GE(pid, 0);
    if (pid == 0) {
      bool ok = true;
      for (int i = 0; i < kEach; ++i) {
        const std::string id = "p" + std::to_string(p) + "-" + std::to_string(i);
        ok = ok && library_csv::Upsert(t.path(), id, id + ",x\n").ok();
      }
      ::_exit(ok ? 0 : 1);
    }
    kids.push_back(pid);
  }
  for (pid_t pid : kids) {
    int status = 0;
    ASSERT_EQ(::waitpid(pid, &status, 0), pid);
    EXPECT_TRUE(WIFEXITED(status) && WEXITSTATUS(status) == 0);
  }
  const std::string text = *ReadFile(t.path() + "/library.csv");
  EXPECT_EQ(std::count(text.begin(), text.end(), '\n'), 2 * kEach + 1) << text;
}

}  // namespace
}  // namespace aggscan
