// The QA reports end to end: ten simulated rocks reconstructed into a state
// directory, a batch of them, `aggscan report` for the batch and for one
// rock. The PDF's text (pdftotext) must carry the numbers of the morphology
// files, its pages (pdftoppm) must not be blank, and every figure must have
// its axes and a point per rock.
#include <gtest/gtest.h>
#include <sys/wait.h>

#include <array>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>
#include <regex>
#include <sstream>
#include <string>
#include <vector>

#include "common/fsutil.h"
#include "pipeline/worker/reconstruct.h"
#include "store/batches.h"
#include "store/layout.h"
#include "store/sample_store.h"
#include "tests/reconstruct/sim_sample.h"
#include "tests/util/temp_dir.h"

namespace aggscan {
namespace {

namespace fs = std::filesystem;
using nlohmann::json;

constexpr int kRocks = 10;

struct Ran {
  int rc = -1;
  std::string out;
};

// Runs a shell command line, its stdout and stderr together.
Ran Shell(const std::string& cmd) {
  Ran r;
  FILE* p = ::popen((cmd + " 2>&1").c_str(), "r");
  if (p == nullptr) return r;
  std::array<char, 4096> buf{};
  size_t n = 0;
  while ((n = std::fread(buf.data(), 1, buf.size(), p)) > 0) r.out.append(buf.data(), n);
  const int status = ::pclose(p);
  r.rc = WIFEXITED(status) ? WEXITSTATUS(status) : -1;
  return r;
}

std::string Aggscan() { return std::string(AGGSCAN_BINARY_DIR) + "/cli/aggscan"; }

std::string Fixed(double v, int decimals) {
  char b[64];
  std::snprintf(b, sizeof b, "%.*f", decimals, v);
  return b;
}

// The figures of a report's HTML: each <img> data URI, decoded when SVG.
std::vector<std::string> Svgs(const std::string& html) {
  std::vector<std::string> out;
  const std::string tag = "data:image/svg+xml;base64,";
  for (size_t at = html.find(tag); at != std::string::npos; at = html.find(tag, at + 1)) {
    const size_t b = at + tag.size();
    const size_t e = html.find('"', b);
    const std::string b64 = html.substr(b, e - b);
    // Decoded by the same tool an engineer would use.
    const std::string tmp = fs::temp_directory_path() / "aggscan-report-test.b64";
    std::ofstream(tmp) << b64;
    const Ran d = Shell("base64 -d " + tmp);
    fs::remove(tmp);
    out.push_back(d.out);
  }
  return out;
}

int Count(const std::string& s, const std::string& what) {
  int n = 0;
  for (size_t at = s.find(what); at != std::string::npos; at = s.find(what, at + 1)) ++n;
  return n;
}

class Reports : public ::testing::Test {
 public:
  // Per test, not per suite: a failure here then fails the test (gtest skips
  // the tests of a suite whose SetUpTestSuite failed, and ctest counts that as
  // a skip). There is one test.
  void SetUp() override {
    dir_ = new test::TempDir();
    state_ = dir_->path() + "/state";
    SampleStore store(state_);
    ASSERT_TRUE(store.Init());
    for (int i = 1; i <= kRocks; ++i) {
      const std::string id = "rock-" + std::to_string(i);
      // Small and quick: 2 sides x 12 views at 1008 x 756, the sim's exact
      // calibration and its masks.
      const std::string cfg = dir_->path() + "/cfg.toml";
      std::ofstream(cfg) << "[capture]\nprofile = \"custom\"\nsides = 2\nviews_per_side = 12\n"
                            "step_deg = 30.0\n";
      SimCaptureOptions o;
      o.seed = static_cast<uint64_t>(i);
      o.out = store.SampleDir(id);
      o.config_path = cfg;
      o.width = 1008;
      o.height = 756;
      std::ostringstream out, err;
      ASSERT_EQ(RunSimCapture(o, out, err), 0) << err.str();
      Config c;
      c.sim.seed = *o.seed;
      sim::SimWorld world(c);
      ASSERT_TRUE(SaveCalibration(o.out + "/calibration.json", world.TruthCalibration(1008, 756)));
      test::PlaceTruthMasks(o.out, 2, 12);
      // The description as a QA engineer gives it; rock 10 is another lot.
      json meta = {
          {"lot", i == kRocks ? "L-2" : "L-1"},
          {"operator", "M. Rossi"},
          {"material", {{"name", "granite"}, {"specific_gravity", 2.65}, {"basis", "bulk-ssd"}}}};
      // Reference volumes (water displacement) for the first six: the truth.
      if (i <= 6) {
        std::ifstream t(store.SampleDir(id) + "/truth.json");
        const json truth = json::parse(t);
        meta["reference"] = {{"volume_mm3", truth["volume_mm3"].get<double>()},
                             {"method", "water displacement"}};
      }
      ASSERT_TRUE(store.EditMeta(id, meta, "test")) << id;
      ReconstructOptions opts;
      opts.state_dir = state_;
      opts.bundle_adjust = false;
      opts.photo_refine = false;
      auto st = ReconstructSample(store.SampleDir(id), opts);
      ASSERT_TRUE(st) << id << ": " << st.error().ToString();
    }
    BatchStore batches(state_);
    ASSERT_TRUE(
        batches.Put(*BatchFromRequest("lot-1", {{"lot", "L-1"}, {"samples", {"rock-10"}}})));
  }
  void TearDown() override {
    delete dir_;
    dir_ = nullptr;
  }

  static json Morphology(int i) {
    std::ifstream f(SampleStore(state_).SampleDir("rock-" + std::to_string(i)) +
                    "/results/morphology.json");
    return json::parse(f);
  }

  static test::TempDir* dir_;
  static std::string state_;
};
test::TempDir* Reports::dir_ = nullptr;
std::string Reports::state_;

void BatchReportCarriesTheFiguresAndEveryFigureHasItsPoints(const test::TempDir& work,
                                                            const std::string& state) {
  const std::string html = work.path() + "/batch.html", pdf = work.path() + "/batch.pdf";
  const Ran r = Shell(Aggscan() + " report --batch lot-1 --state-dir " + state +
                      " --spec en13383-lma5-40 --html " + html + " --pdf " + pdf);
  ASSERT_EQ(r.rc, 0) << r.out;
  std::printf("%s", r.out.c_str());
  // To look at: AGGSCAN_KEEP_REPORTS=DIR keeps them.
  if (const char* keep = std::getenv("AGGSCAN_KEEP_REPORTS"); keep != nullptr && *keep != '\0') {
    fs::copy_file(pdf, std::string(keep) + "/batch.pdf", fs::copy_options::overwrite_existing);
    fs::copy_file(html, std::string(keep) + "/batch.html", fs::copy_options::overwrite_existing);
  }
  const Ran text = Shell("pdftotext -layout " + pdf + " -");
  ASSERT_EQ(text.rc, 0) << text.out;
  // Every rock's Table 1 row: the numbers of its morphology file.
  for (int i = 1; i <= kRocks; ++i) {
    const json d = Reports::Morphology(i)["morphology_3d"];
    const std::string id = "rock-" + std::to_string(i);
    EXPECT_NE(text.out.find(id), std::string::npos) << id;
    const double v_cm3 = d["volume_mm3"].get<double>() / 1000.0;
    for (const std::string& want :
         {Fixed(v_cm3, 2), Fixed(d["a_mm"].get<double>(), 1), Fixed(d["b_mm"].get<double>(), 1),
          Fixed(d["c_mm"].get<double>(), 1), Fixed(d["sphericity"].get<double>(), 3),
          Fixed(v_cm3 * 2.65 / 1000.0, 3)}) {
      EXPECT_NE(text.out.find(want), std::string::npos) << id << ": " << want;
    }
  }
  for (const char* want : {"Gradation by mass", "W50", "D50", "EN 13383-1 LMA 5-40", "ASTM D4791",
                           "MPE", "MAPE", "3D FER over mean 2D FER"}) {
    EXPECT_NE(text.out.find(want), std::string::npos) << want;
  }
  // Ten rocks of ~0.1-1 kg: too light for LMA 5-40, and the report says so.
  EXPECT_NE(text.out.find("does NOT meet"), std::string::npos);
  // Every page drawn, none blank.
  const Ran pages = Shell("pdftoppm -r 30 -png " + pdf + " " + work.path() + "/page");
  ASSERT_EQ(pages.rc, 0) << pages.out;
  int n_pages = 0;
  for (const auto& e : fs::directory_iterator(work.path())) {
    const std::string n = e.path().filename().string();
    if (n.rfind("page", 0) != 0 || e.path().extension() != ".png") continue;
    ++n_pages;
    const cv::Mat g = cv::imread(e.path().string(), cv::IMREAD_GRAYSCALE);
    ASSERT_FALSE(g.empty()) << n;
    const double ink = static_cast<double>(cv::countNonZero(g < 200)) / g.total();
    EXPECT_GT(ink, 0.002) << n << " is blank";
  }
  EXPECT_GE(n_pages, 3);
  // Each figure: axes, and at least a marker per rock (Figure 6: the six
  // with reference volumes).
  std::string page;
  ASSERT_TRUE(ReadFile(html).ok());
  page = *ReadFile(html);
  const std::vector<std::string> svgs = Svgs(page);
  ASSERT_EQ(svgs.size(), 6u);  // gradation, distributions, Figures 7a, 7b, 8 and 6
  for (size_t k = 0; k < svgs.size(); ++k) {
    const std::string& s = svgs[k];
    EXPECT_NE(s.find("id=\"axes_1\""), std::string::npos) << "figure " << k << " has no axes";
    EXPECT_NE(s.find("matplotlib.axis"), std::string::npos) << "figure " << k << ": no axis";
    const int markers = Count(s, "<use xlink:href=\"#");
    const int bars = Count(s, "id=\"patch_");
    EXPECT_GE(markers + bars, 6) << "figure " << k << ": " << markers << " markers, " << bars
                                 << " bars";
  }
}

void RockReportHasItsFiguresPhotosAndModel(const test::TempDir& work, const std::string& state) {
  const std::string html = work.path() + "/rock.html", pdf = work.path() + "/rock.pdf";
  const Ran r = Shell(Aggscan() + " report rock-3 --state-dir " + state + " --html " + html +
                      " --pdf " + pdf);
  ASSERT_EQ(r.rc, 0) << r.out;
  const Ran text = Shell("pdftotext -layout " + pdf + " -");
  ASSERT_EQ(text.rc, 0);
  const json m = Reports::Morphology(3);
  const json& d = m["morphology_3d"];
  for (const std::string& want :
       {std::string("rock-3"), std::string("L-1"), std::string("M. Rossi"),
        Fixed(d["volume_mm3"].get<double>() / 1000.0, 2), Fixed(d["b_mm"].get<double>(), 1),
        Fixed(d["fer_3d"].get<double>(), 3), std::string("Quality"),
        m["software"]["version"].get<std::string>()}) {
    EXPECT_NE(text.out.find(want), std::string::npos) << want;
  }
  const std::string page = *ReadFile(html);
  // Two photos a side and the model from three directions.
  EXPECT_EQ(Count(page, "data:image/png;base64,"), 5);
  EXPECT_EQ(Svgs(page).size(), 2u);  // Figures 7 and 8
}

void WhatCannotMakeAReportIsAClearError(const test::TempDir& work, const std::string& state) {
  SampleStore store(state);
  // A rock without a specific gravity: no mass, no gradation.
  ASSERT_TRUE(store.EditMeta("rock-10", {{"material", nullptr}}, "test"));
  Ran r = Shell(Aggscan() + " report --batch lot-1 --state-dir " + state + " --pdf " + work.path() +
                "/x.pdf");
  EXPECT_EQ(r.rc, 1) << r.out;
  EXPECT_NE(r.out.find("no specific gravity for rock-10"), std::string::npos) << r.out;
  EXPECT_NE(r.out.find("aggscan meta"), std::string::npos) << r.out;
  EXPECT_FALSE(fs::exists(work.path() + "/x.pdf"));
  ASSERT_TRUE(store.EditMeta(
      "rock-10", {{"material", {{"specific_gravity", 2.65}, {"basis", "bulk-ssd"}}}}, "test"));
  r = Shell(Aggscan() + " report --batch lot-1 --state-dir " + state + " --spec no-such-spec");
  EXPECT_EQ(r.rc, 1) << r.out;
  EXPECT_NE(r.out.find("unknown gradation specification 'no-such-spec'"), std::string::npos)
      << r.out;
  EXPECT_NE(r.out.find("en13383-lma10-60"), std::string::npos) << r.out;
  r = Shell(Aggscan() + " report --batch nope --state-dir " + state);
  EXPECT_EQ(r.rc, 1) << r.out;
  EXPECT_NE(r.out.find("no batch \"nope\""), std::string::npos) << r.out;
  r = Shell(Aggscan() + " report rock-99 --state-dir " + state);
  EXPECT_EQ(r.rc, 1) << r.out;
  EXPECT_NE(r.out.find("no sample rock-99"), std::string::npos) << r.out;
}

// One test: its ten reconstructed rocks (about three minutes) are made once.
TEST_F(Reports, BatchAndRockReportsAndWhatCannotMakeOne) {
  {
    SCOPED_TRACE("batch report");
    BatchReportCarriesTheFiguresAndEveryFigureHasItsPoints(*dir_, state_);
  }
  {
    SCOPED_TRACE("rock report");
    RockReportHasItsFiguresPhotosAndModel(*dir_, state_);
  }
  {
    SCOPED_TRACE("errors");
    WhatCannotMakeAReportIsAClearError(*dir_, state_);
  }
}

}  // namespace
}  // namespace aggscan
