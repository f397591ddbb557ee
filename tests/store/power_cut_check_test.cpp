// power_cut_check against state dirs built here: a whole one passes, and each
// kind of damage a power cut could leave is named.
#include <gtest/gtest.h>
#include <sqlite3.h>
#include <turbojpeg.h>

#include <cstdio>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

namespace {

namespace fs = std::filesystem;
using nlohmann::json;

std::string Jpeg(int w, int h) {
  std::vector<unsigned char> px(static_cast<size_t>(w) * h * 3);
  for (size_t i = 0; i < px.size(); ++i) px[i] = static_cast<unsigned char>(i * 7);
  tjhandle tj = tjInitCompress();
  unsigned char* buf = nullptr;
  unsigned long size = 0;
  EXPECT_EQ(tjCompress2(tj, px.data(), w, 0, h, TJPF_RGB, &buf, &size, TJSAMP_420, 90, 0), 0);
  std::string out(reinterpret_cast<char*>(buf), size);
  tjFree(buf);
  tjDestroy(tj);
  return out;
}

void Write(const fs::path& p, const std::string& s) {
  fs::create_directories(p.parent_path());
  std::ofstream(p, std::ios::binary) << s;
}

struct CheckRun {
  int rc;
  std::string out;
};

CheckRun Check(const std::string& args) {
  const std::string cmd =
      std::string(AGGSCAN_BINARY_DIR) + "/tests/store/power_cut_check " + args + " 2>&1";
  FILE* p = ::popen(cmd.c_str(), "r");
  std::string out;
  char buf[4096];
  while (size_t n = std::fread(buf, 1, sizeof buf, p)) out.append(buf, n);
  const int st = ::pclose(p);
  return {WEXITSTATUS(st), out};
}

class PowerCutCheck : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = fs::temp_directory_path() / ("power_cut_check_test." + std::to_string(::getpid()));
    fs::remove_all(dir_);
    side_ = dir_ / "state/samples/r1/side1";
    json views = json::array();
    for (int v = 0; v < 3; ++v) {
      char stem[16];
      std::snprintf(stem, sizeof stem, "view_%03d", v);
      const std::string img = Jpeg(64, 48);
      Write(side_ / (std::string(stem) + ".jpg"), img);
      Write(side_ / (std::string(stem) + ".json"),
            json{{"view", v}, {"width", 64}, {"height", 48}}.dump());
      views.push_back({{"view", v}, {"image", std::string(stem) + ".jpg"}, {"bytes", img.size()}});
    }
    Write(side_ / "manifest.json", json{{"views", views}}.dump());
    Write(dir_ / "state/samples/r1/sample.json",
          json{{"state", "captured"}, {"plan", {{"sides", 1}}}}.dump());
    Write(side_ / ".tmp-view_003.jpg.0123456789abcdef", "half a file");
    Write(dir_ / "expect.txt", "view r1 1 0\nview r1 1 2\nmanifest r1 1\ncaptured r1\n");
  }
  void TearDown() override { fs::remove_all(dir_); }
  std::string Files() {
    return "files " + (dir_ / "state").string() + " " + (dir_ / "expect.txt").string();
  }

  fs::path dir_, side_;
};

TEST_F(PowerCutCheck, AWholeStateDirPasses) {
  const CheckRun r = Check(Files());
  EXPECT_EQ(r.rc, 0) << r.out;
  EXPECT_NE(r.out.find("views=3 orphan_images=0 manifests=1 json=5"), std::string::npos) << r.out;
  EXPECT_NE(r.out.find("temp=1 expected=4"), std::string::npos) << r.out;
}

TEST_F(PowerCutCheck, ATruncatedImageWithASidecarIsNamed) {
  const std::string img = Jpeg(64, 48);
  Write(side_ / "view_001.jpg", img.substr(0, img.size() / 2));
  const CheckRun r = Check(Files());
  EXPECT_EQ(r.rc, 1);
  EXPECT_NE(
      r.out.find("image of a complete view does not decode: " + (side_ / "view_001.jpg").string()),
      std::string::npos)
      << r.out;
  // The manifest's byte count no longer matches either.
  EXPECT_NE(r.out.find("lists view_001.jpg with " + std::to_string(img.size()) + " bytes"),
            std::string::npos)
      << r.out;
}

TEST_F(PowerCutCheck, BrokenJsonAMissingReportedViewAndALostCaptureAreNamed) {
  Write(side_ / "view_002.json", "{\"view\": 2, \"wid");
  fs::remove(side_ / "view_000.jpg");
  Write(dir_ / "state/samples/r1/sample.json",
        json{{"state", "capturing"}, {"plan", {{"sides", 1}}}}.dump());
  const CheckRun r = Check(Files());
  EXPECT_EQ(r.rc, 1);
  EXPECT_NE(r.out.find("not valid JSON: " + (side_ / "view_002.json").string()), std::string::npos)
      << r.out;
  EXPECT_NE(r.out.find("view reported stored before the cut is missing: " +
                       (side_ / "view_000").string()),
            std::string::npos)
      << r.out;
  EXPECT_NE(r.out.find("sample reported captured before the cut is not: r1 state capturing"),
            std::string::npos)
      << r.out;
}

TEST_F(PowerCutCheck, ACapturedSampleWithoutItsJobIsNamed) {
  sqlite3* db = nullptr;
  ASSERT_EQ(sqlite3_open((dir_ / "state/queue.db").c_str(), &db), SQLITE_OK);
  ASSERT_EQ(
      sqlite3_exec(
          db,
          "CREATE TABLE jobs (id INTEGER PRIMARY KEY, sample_id TEXT, side INTEGER, state TEXT);"
          "INSERT INTO jobs(sample_id, side, state) VALUES('r1', 1, 'done');",
          nullptr, nullptr, nullptr),
      SQLITE_OK);
  sqlite3_close(db);
  CheckRun r = Check("queue " + (dir_ / "state").string());
  EXPECT_EQ(r.rc, 1) << r.out;
  EXPECT_NE(r.out.find("sample r1 is captured but has no sample job"), std::string::npos) << r.out;
  EXPECT_NE(r.out.find("jobs=1 needed=2 problems=1"), std::string::npos) << r.out;
  // The side's job is there: no finding about side 1; the files check sees a sound queue.
  EXPECT_EQ(r.out.find("side 1 of r1"), std::string::npos) << r.out;
  r = Check(Files());
  EXPECT_EQ(r.rc, 0) << r.out;
  EXPECT_NE(r.out.find("jobs=1 problems=0"), std::string::npos) << r.out;
}

}  // namespace
