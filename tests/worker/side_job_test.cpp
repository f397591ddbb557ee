#include "pipeline/worker/side_job.h"

#include <gtest/gtest.h>

#include <atomic>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <string>

#include "common/fsutil.h"
#include "store/layout.h"
#include "store/queue.h"
#include "tests/util/synth_scene.h"

namespace aggscan {
namespace {

namespace fs = std::filesystem;
using nlohmann::json;

// A sample directory with `sides` sides of `views` synthetic views each, as
// the daemon leaves it (images, sidecars, manifest written last).
class SideJobTest : public ::testing::Test {
 protected:
  void SetUp() override {
    root_ = fs::temp_directory_path() /
            ("aggscan_sidejob_" + std::to_string(::getpid()) + "_" +
             ::testing::UnitTest::GetInstance()->current_test_info()->name());
    fs::remove_all(root_);
    dir_ = (root_ / "samples" / "S-0001").string();
    fs::create_directories(dir_);
  }
  void TearDown() override { fs::remove_all(root_); }

  void MakeSide(int side, int views = 3) {
    const std::string sd = dir_ + "/" + layout::SideDirName(side);
    fs::create_directories(sd);
    json jviews = json::array();
    for (int v = 0; v < views; ++v) {
      testing::SceneParams p;
      p.size = {640, 480};
      p.seed = 100 + side * 10 + v;
      p.turntable_deg = 30.0 * v;
      const auto sc = testing::MakeScene(p);
      Write(sd + "/" + layout::ViewImageName(v), std::string(sc.jpeg.begin(), sc.jpeg.end()));
      Write(sd + "/" + layout::ViewSidecarName(v), json{{"view", v},
                                                        {"commanded_angle_deg", 30.0 * v},
                                                        {"measured_angle_deg", 30.0 * v + 0.02}}
                                                       .dump());
      jviews.push_back({{"view", v},
                        {"image", layout::ViewImageName(v)},
                        {"sidecar", layout::ViewSidecarName(v)},
                        {"bytes", sc.jpeg.size()}});
    }
    manifest_ = {{"sample_id", "S-0001"},
                 {"side", side},
                 {"views", jviews},
                 {"completed_utc", "2026-01-01T00:00:00.000Z"}};
    Write(sd + "/" + layout::kManifest, manifest_.dump());
  }
  static void Write(const std::string& path, const std::string& data) {
    std::ofstream(path, std::ios::binary) << data;
  }
  static json ReadJson(const std::string& path) {
    std::ifstream f(path);
    return json::parse(f);
  }

  fs::path root_;
  std::string dir_;
  json manifest_;
};

TEST_F(SideJobTest, ProcessesSidesAndSample) {
  MakeSide(1);
  MakeSide(2);
  ASSERT_TRUE(ProcessSide(dir_, 1).ok());
  for (int v = 0; v < 3; ++v) {
    const cv::Mat m = cv::imread(ViewMaskPath(dir_, 1, v), cv::IMREAD_UNCHANGED);
    ASSERT_FALSE(m.empty()) << v;
    EXPECT_EQ(m.type(), CV_8UC1);
    EXPECT_EQ(m.size(), cv::Size(640, 480));
    EXPECT_GT(cv::countNonZero(m), 1000);
  }
  const json r = ReadJson(SideResultPath(dir_, 1));
  EXPECT_EQ(r["sample_id"], "S-0001");
  EXPECT_EQ(r["side"], 1);
  ASSERT_EQ(r["views"].size(), 3u);
  for (const auto& v : r["views"]) {
    for (const char* k :
         {"l_max_px", "l_min_px", "fer_2d", "area_px", "perimeter_px", "circularity",
          "mask_area_fraction", "commanded_angle_deg", "measured_angle_deg", "timing_ms"})
      EXPECT_TRUE(v.contains(k) && v[k].is_number()) << k;
    EXPECT_GT(v["fer_2d"].get<double>(), 1.0);
    EXPECT_GT(v["circularity"].get<double>(), 0.5);
    EXPECT_LE(v["circularity"].get<double>(), 1.05);
    EXPECT_GT(v["mask_area_fraction"].get<double>(), 0.01);
  }
  for (const char* f : {"fer_2d", "circularity", "l_max_px", "l_min_px"})
    for (const char* k : {"mean", "min", "max", "std", "cov"})
      EXPECT_TRUE(r["stats"][f][k].is_number()) << f << k;
  EXPECT_EQ(r["stats"]["fer_2d"]["n"], 3);
  EXPECT_TRUE(r["timing_ms"].is_number());

  // The sample job processes side 2 itself if its job has not run yet.
  ASSERT_TRUE(ProcessSample(dir_).ok());
  EXPECT_TRUE(PathExists(SideResultPath(dir_, 2)));
  const json s = ReadJson(SampleResultPath(dir_));
  ASSERT_EQ(s["sides"].size(), 2u);
  EXPECT_EQ(s["overall"]["views_ok"], 6);
  EXPECT_EQ(s["overall"]["stats"]["fer_2d"]["n"], 6);
  EXPECT_NEAR(s["sides"][0]["stats"]["circularity"]["mean"].get<double>(),
              r["stats"]["circularity"]["mean"].get<double>(), 1e-12);
}

// A side result as the stages after the side job read it.
records::SideResult Typed(const json& j) {
  auto r = records::SideResult::FromJson(j, {"side result", "test", ""});
  EXPECT_TRUE(r.ok()) << r.error().ToString();
  return r.ok() ? *r : records::SideResult{};
}

// The empty-turntable photos linked into a sample are matched to its views
// by the measured angle: a view with one within the tolerance is masked
// against it (the stone on the disc the frame's border does not show is
// found), a view without one, or with one of another size, is masked without
// and named in the side result.
TEST_F(SideJobTest, EmptyTurntablePhotosAreMatchedByAngle) {
  const std::string sd = dir_ + "/" + layout::SideDirName(1);
  const std::string staging = root_.string() + "/staging";
  fs::create_directories(sd);
  fs::create_directories(staging);
  const double angles[] = {0.0, 90.0, 180.0, 270.0};  // measured angle of each view
  json jviews = json::array();
  EmptyTurntableSet set;
  set.id = "test-set";
  set.width = 1008;
  set.height = 756;
  std::vector<std::string> photos;
  std::vector<cv::Mat> truth;
  for (int v = 0; v < 4; ++v) {
    const testing::FloorScene sc = testing::MakeFloorScene(20 + v);
    truth.push_back(sc.truth);
    cv::imwrite(sd + "/" + layout::ViewImageName(v), sc.photo);
    Write(sd + "/" + layout::ViewSidecarName(v), json{{"view", v},
                                                      {"commanded_angle_deg", angles[v]},
                                                      {"measured_angle_deg", angles[v] + 0.03}}
                                                     .dump());
    jviews.push_back({{"view", v},
                      {"image", layout::ViewImageName(v)},
                      {"sidecar", layout::ViewSidecarName(v)}});
    // The set: views 0 and 1 shot 0.2 deg off theirs; view 2's photo is of
    // another camera mode; nothing near view 3's 270 deg.
    if (v == 3) continue;
    cv::Mat empty = sc.empty;
    if (v == 2) cv::resize(empty, empty, cv::Size(640, 480), 0, 0, cv::INTER_AREA);
    const std::string name = "e" + std::to_string(v) + ".jpg";
    cv::imwrite(staging + "/" + name, empty);
    photos.push_back(staging + "/" + name);
    set.views.push_back({name, angles[v] - 0.2});
  }
  Write(sd + "/" + layout::kManifest,
        json{{"sample_id", "S-0001"}, {"side", 1}, {"views", jviews}}.dump());
  ASSERT_TRUE(WriteEmptyTurntableSet(dir_ + "/" + layout::kEmptyDir, set, photos).ok());

  ASSERT_TRUE(ProcessSide(dir_, 1).ok());
  const json r = ReadJson(SideResultPath(dir_, 1));
  EXPECT_EQ(r["mask_empty_turntable"], "test-set");
  EXPECT_EQ(r["mask_empty_turntable_views"], 2);
  ASSERT_TRUE(r.contains("mask_empty_turntable_problems")) << r.dump();
  const std::string problems = r["mask_empty_turntable_problems"].dump();
  EXPECT_NE(
      problems.find("view_002: the empty-turntable photo e2.jpg is 640x480, the view 1008x756"),
      std::string::npos)
      << problems;
  EXPECT_NE(problems.find("view_003: the nearest empty-turntable photo was shot 89.77 deg away"),
            std::string::npos)
      << problems;
  for (int v : {0, 1}) {
    const cv::Mat m = cv::imread(ViewMaskPath(dir_, 1, v), cv::IMREAD_GRAYSCALE);
    ASSERT_FALSE(m.empty());
    EXPECT_GE(testing::MaskIoU(m, truth[static_cast<size_t>(v)]), 0.97) << "view " << v;
  }
}

// A tighter tolerance than the set was shot to leaves every view without.
TEST_F(SideJobTest, EmptyTurntableToleranceIsTheWorkersOption) {
  const std::string sd = dir_ + "/" + layout::SideDirName(1);
  fs::create_directories(sd);
  const testing::FloorScene sc = testing::MakeFloorScene(30);
  cv::imwrite(sd + "/" + layout::ViewImageName(0), sc.photo);
  Write(sd + "/" + layout::ViewSidecarName(0),
        json{{"view", 0}, {"measured_angle_deg", 10.0}}.dump());
  Write(sd + "/" + layout::kManifest,
        json{{"sample_id", "S-0001"},
             {"side", 1},
             {"views", json::array({{{"view", 0},
                                     {"image", layout::ViewImageName(0)},
                                     {"sidecar", layout::ViewSidecarName(0)}}})}}
            .dump());
  const std::string staging = root_.string() + "/e0.jpg";
  cv::imwrite(staging, sc.empty);
  EmptyTurntableSet set;
  set.id = "loose";
  set.width = 1008;
  set.height = 756;
  set.views.push_back({"e0.jpg", 10.3});
  ASSERT_TRUE(WriteEmptyTurntableSet(dir_ + "/" + layout::kEmptyDir, set, {staging}).ok());
  WorkerOptions o;
  o.empty_turntable_max_angle_deg = 0.1;
  ASSERT_TRUE(ProcessSide(dir_, 1, o).ok());
  const json r = ReadJson(SideResultPath(dir_, 1));
  EXPECT_EQ(r["mask_empty_turntable_views"], 0);
  EXPECT_NE(r["mask_empty_turntable_problems"].dump().find("0.30 deg away (more than 0.10)"),
            std::string::npos)
      << r.dump();
}

TEST_F(SideJobTest, FinishedSideIsSkippedAndMasksAreReused) {
  MakeSide(1);
  // Leftover of a crashed attempt: ignored and cleaned up.
  fs::create_directories(dir_ + "/results");
  Write(dir_ + "/results/.tmp-side1_morph2d.json.123", "{garbage");
  ASSERT_TRUE(ProcessSide(dir_, 1).ok());
  EXPECT_FALSE(fs::exists(dir_ + "/results/.tmp-side1_morph2d.json.123"));
  const json first = ReadJson(SideResultPath(dir_, 1));

  // A finished side result means done: not recomputed.
  Write(SideResultPath(dir_, 1), R"({"marker": "untouched"})");
  ASSERT_TRUE(ProcessSide(dir_, 1).ok());
  EXPECT_EQ(ReadJson(SideResultPath(dir_, 1))["marker"], "untouched");

  // Crash after the masks but before the result: masks are reused, same figures.
  fs::remove(SideResultPath(dir_, 1));
  for (int v = 0; v < 3; ++v) fs::remove(dir_ + "/side1/" + layout::ViewImageName(v));
  Write(dir_ + "/side1/" + layout::kManifest, [&] {
    json m = manifest_;
    for (auto& v : m["views"]) v.erase("bytes");
    return m.dump();
  }());
  for (int v = 0; v < 3; ++v)
    Write(dir_ + "/side1/" + layout::ViewImageName(v), "x");  // not decodable
  ASSERT_TRUE(ProcessSide(dir_, 1).ok());
  const json again = ReadJson(SideResultPath(dir_, 1));
  for (int v = 0; v < 3; ++v)
    EXPECT_DOUBLE_EQ(again["views"][v]["fer_2d"].get<double>(),
                     first["views"][v]["fer_2d"].get<double>());
}

// A rock cut by the photo's edge, or lost by the segmentation, must not
// carve the model or enter the 2D statistics: such views are left out and
// the side result says which and what to do.
TEST_F(SideJobTest, MasksCutByTheFrameOrLostAreLeftOut) {
  MakeSide(1, 4);
  ASSERT_TRUE(ProcessSide(dir_, 1).ok());
  const json first = ReadJson(SideResultPath(dir_, 1));
  EXPECT_EQ(first["views_ok"], 4);
  EXPECT_EQ(first["mask_problems"], "");
  for (const auto& v : first["views"]) EXPECT_EQ(v["mask_frame_px"], 0) << v["view"];

  // View 1: the rock reaches the top edge; view 2: a speck of the usual size's 5 %.
  cv::Mat cut = cv::imread(ViewMaskPath(dir_, 1, 1), cv::IMREAD_GRAYSCALE);
  ASSERT_FALSE(cut.empty());
  cv::rectangle(cut, cv::Rect(250, 0, 140, 200), cv::Scalar(255), cv::FILLED);
  ASSERT_TRUE(cv::imwrite(ViewMaskPath(dir_, 1, 1), cut));
  cv::Mat speck = cv::Mat::zeros(cut.size(), CV_8UC1);
  const int side_px =
      static_cast<int>(std::sqrt(0.05 * first["views"][0]["area_px"].get<double>()));
  cv::rectangle(speck, cv::Rect(300, 240, side_px, side_px), cv::Scalar(255), cv::FILLED);
  ASSERT_TRUE(cv::imwrite(ViewMaskPath(dir_, 1, 2), speck));
  fs::remove(SideResultPath(dir_, 1));
  ASSERT_TRUE(ProcessSide(dir_, 1).ok());  // reuses the masks

  const json r = ReadJson(SideResultPath(dir_, 1));
  EXPECT_EQ(r["views_ok"], 2);
  EXPECT_EQ(r["stats"]["fer_2d"]["n"], 2);
  EXPECT_TRUE(r["views"][0]["ok"].get<bool>());
  EXPECT_TRUE(r["views"][3]["ok"].get<bool>());
  EXPECT_FALSE(r["views"][1]["ok"].get<bool>());
  EXPECT_GE(r["views"][1]["mask_frame_px"].get<int>(), 140);
  EXPECT_NE(r["views"][1]["error"].get<std::string>().find("edge of the photo"), std::string::npos);
  EXPECT_FALSE(r["views"][2]["ok"].get<bool>());
  EXPECT_NE(r["views"][2]["error"].get<std::string>().find("lost the rock"), std::string::npos);
  const std::string problems = r["mask_problems"].get<std::string>();
  EXPECT_NE(problems.find("edge of the photo in view 1 "), std::string::npos) << problems;
  EXPECT_NE(problems.find("move the camera back"), std::string::npos) << problems;
  EXPECT_NE(problems.find("segmentation in view 2 "), std::string::npos) << problems;
  // Half the views left out: the side cannot give a model, and says why.
  const Status enough = SideHasEnoughWholeViews(Typed(r));
  ASSERT_FALSE(enough.ok());
  EXPECT_EQ(enough.error().cls, ErrorClass::kCorrupt);
  EXPECT_NE(enough.error().message.find("side 1: only 2 of 4 views"), std::string::npos)
      << enough.error().message;
  EXPECT_NE(enough.error().message.find("move the camera back"), std::string::npos)
      << enough.error().message;
  EXPECT_TRUE(SideHasEnoughWholeViews(Typed(first)).ok());
}

TEST(CheckSideMasks, ThresholdsAndMessages) {
  auto view = [](int v, double area, int frame) {
    records::View2D r;
    r.view = v;
    r.ok = true;
    r.mask = "masks/side1/" + std::to_string(v) + ".png";
    r.mask_area_fraction = area;
    r.mask_frame_px = frame;
    return r;
  };
  std::vector<records::View2D> views = {view(0, 0.20, 0),
                                        view(1, 0.20 * kMaskMinAreaOfLargest * 1.01, 0),
                                        view(2, 0.20 * kMaskMinAreaOfLargest * 0.99, 0),
                                        view(3, 0.18, kMaskFrameMinPx - 1),
                                        view(4, 0.19, kMaskFrameMinPx),
                                        view(5, 0.19, 0)};
  views[5].ok = false;  // already without a rock: untouched
  const std::string msg = CheckSideMasks(&views);
  std::vector<bool> ok;
  for (const auto& v : views) ok.push_back(v.ok);
  EXPECT_EQ(ok, (std::vector<bool>{true, true, false, true, false, false}));
  EXPECT_TRUE(views[5].error.empty());
  EXPECT_NE(msg.find("view 4 "), std::string::npos) << msg;
  EXPECT_NE(msg.find("view 2 "), std::string::npos) << msg;

  std::vector<records::View2D> fine = {view(0, 0.2, 0), view(1, 0.1, 0)};
  EXPECT_EQ(CheckSideMasks(&fine), "");
  // A view without the mask's figures (a record of an older worker): its
  // area counts as none, its frame pixels as none.
  std::vector<records::View2D> bare = {view(0, 0.2, 0), view(1, 0.2, 0)};
  bare[1].mask_area_fraction.reset();
  bare[1].mask_frame_px.reset();
  EXPECT_NE(CheckSideMasks(&bare).find("segmentation in view 1 "), std::string::npos);
}

// A side result read back from disk with a field of another type (as in
// tests/fuzz/corpus/worker_json/side_result_types.json) is refused with the
// field named, not read as something else.
TEST(SideHasEnoughWholeViews, CountsAndRecordsOfAnotherType) {
  records::SideResult huge;
  huge.mask_problems = "cut";
  huge.views_total = huge.views_ok = 2147483647;
  EXPECT_TRUE(SideHasEnoughWholeViews(huge).ok());
  records::SideResult few;
  few.mask_problems = "cut";
  few.views_total = 30;
  few.views_ok = 19;
  const Status s = SideHasEnoughWholeViews(few);
  ASSERT_FALSE(s.ok());
  EXPECT_NE(s.error().message.find("only 19 of 30 views"), std::string::npos) << s.error().message;
  few.mask_problems.clear();
  EXPECT_TRUE(SideHasEnoughWholeViews(few).ok());  // no problems named

  const json typed = {
      {"side", "1"}, {"mask_problems", "cut"}, {"views_total", 30}, {"views_ok", "30"}};
  auto r = records::SideResult::FromJson(typed, {"side result", "side1_morph2d.json", ""});
  ASSERT_FALSE(r.ok());
  EXPECT_NE(r.error().message.find("\"side\" is not a whole number"), std::string::npos)
      << r.error().message;
}

TEST_F(SideJobTest, SampleStageRefusesAWronglyTypedSideResult) {
  MakeSide(1);
  ASSERT_TRUE(ProcessSide(dir_, 1).ok());
  fs::create_directories(dir_ + "/side2");
  Write(
      SideResultPath(dir_, 2),
      R"({"side": 2, "views_total": 3, "views_ok": 2, "views": [{"view": 0, "ok": 1, "fer_2d": 1.5}, 3]})");
  const Status s = ProcessSample(dir_);
  ASSERT_FALSE(s.ok());
  EXPECT_EQ(s.error().cls, ErrorClass::kCorrupt);
  EXPECT_NE(s.error().message.find("side2_morph2d.json"), std::string::npos) << s.error().message;
  EXPECT_NE(s.error().message.find("\"ok\" is not true or false"), std::string::npos)
      << s.error().message;
  EXPECT_NE(s.error().message.find("delete it to recompute"), std::string::npos)
      << s.error().message;
  EXPECT_FALSE(PathExists(SampleResultPath(dir_)));
}

TEST_F(SideJobTest, CancelStopsBetweenViewsAndResumes) {
  MakeSide(1);
  std::atomic<bool> cancel{true};
  WorkerOptions o;
  o.cancel = &cancel;
  Status s = ProcessSide(dir_, 1, o);
  ASSERT_FALSE(s.ok());
  EXPECT_EQ(s.error().cls, ErrorClass::kCancelled);
  EXPECT_FALSE(PathExists(SideResultPath(dir_, 1)));
  cancel = false;
  EXPECT_TRUE(ProcessSide(dir_, 1, o).ok());
}

TEST_F(SideJobTest, BadManifestsAreRefused) {
  auto expect = [&](ErrorClass cls, const std::string& why) {
    Status s = ProcessSide(dir_, 1);
    ASSERT_FALSE(s.ok()) << why;
    EXPECT_EQ(s.error().cls, cls) << why << ": " << s.error().ToString();
    EXPECT_FALSE(PathExists(SideResultPath(dir_, 1))) << why;
  };
  expect(ErrorClass::kNotFound, "no side directory");
  MakeSide(1, 2);
  const std::string mpath = dir_ + "/side1/" + layout::kManifest;
  auto with = [&](auto edit) {
    json m = manifest_;
    edit(m);
    Write(mpath, m.dump());
  };
  fs::remove(mpath);
  expect(ErrorClass::kNotFound, "no manifest");
  Write(mpath, "{\"side\": 1, \"views\": [");
  expect(ErrorClass::kCorrupt, "truncated JSON");
  with([](json& m) { m["side"] = 2; });
  expect(ErrorClass::kCorrupt, "wrong side");
  with([](json& m) { m["views"] = json::array(); });
  expect(ErrorClass::kCorrupt, "no views");
  with([](json& m) { m["views"][0]["bytes"] = 12; });
  expect(ErrorClass::kCorrupt, "size mismatch");
  with([](json& m) { m["views"][1]["image"] = "view_009.jpg"; });
  expect(ErrorClass::kCorrupt, "missing image");
  with([](json& m) { m["views"][1]["image"] = "../../etc/passwd"; });
  expect(ErrorClass::kCorrupt, "path escape");
  with([](json& m) { m["views"][1]["view"] = 0; });
  expect(ErrorClass::kCorrupt, "duplicate view");
  with([](json& m) { m["sample_id"] = "other"; });
  expect(ErrorClass::kCorrupt, "other sample");
  EXPECT_FALSE(ProcessSide(dir_, 0).ok());
}

// Photos that cannot be used (truncated, a 1x1 frame, a strip) are left
// out of the side and named with what to do; the side is still measured
// from the others, and refused for its model when too few are left.
TEST_F(SideJobTest, UnusablePhotosAreLeftOutAndNamed) {
  MakeSide(1, 6);
  const std::string sd = dir_ + "/side1/";
  auto replace = [&](int v, const std::string& bytes) {
    Write(sd + layout::ViewImageName(v), bytes);
    manifest_["views"][v]["bytes"] = bytes.size();
  };
  const std::string good = *ReadFile(sd + layout::ViewImageName(1));
  replace(1, good.substr(0, good.size() / 2));
  std::vector<unsigned char> tiny;
  ASSERT_TRUE(cv::imencode(".jpg", cv::Mat(1, 1, CV_8UC3, cv::Scalar(128, 128, 128)), tiny));
  replace(3, std::string(tiny.begin(), tiny.end()));
  Write(sd + layout::kManifest, manifest_.dump());
  Status st = ProcessSide(dir_, 1);
  ASSERT_TRUE(st.ok()) << st.error().ToString();
  const json r = ReadJson(SideResultPath(dir_, 1));
  EXPECT_EQ(r["views_ok"].get<int>(), 4);
  EXPECT_FALSE(r["views"][1]["ok"].get<bool>());
  EXPECT_NE(r["views"][1]["error"].get<std::string>().find("Premature end of JPEG file"),
            std::string::npos)
      << r["views"][1].dump();
  EXPECT_NE(r["views"][3]["error"].get<std::string>().find("is 1x1: too small to measure"),
            std::string::npos)
      << r["views"][3].dump();
  const std::string problems = r["image_problems"].get<std::string>();
  EXPECT_NE(problems.find("the photo of views 1, 3 cannot be used"), std::string::npos) << problems;
  EXPECT_NE(problems.find("re-shoot the side"), std::string::npos) << problems;
  EXPECT_FALSE(PathExists(ViewMaskPath(dir_, 1, 1)));
  // 4 of 6 left: enough (two thirds); one more lost is not.
  EXPECT_TRUE(SideHasEnoughWholeViews(Typed(r)).ok());
  json fewer = r;
  fewer["views_ok"] = 3;
  Status s = SideHasEnoughWholeViews(Typed(fewer));
  ASSERT_FALSE(s.ok());
  EXPECT_NE(s.error().message.find("the photo of views 1, 3 cannot be used"), std::string::npos)
      << s.error().message;
}

TEST_F(SideJobTest, SampleWithoutSidesIsNotFound) {
  Status s = ProcessSample(dir_);
  ASSERT_FALSE(s.ok());
  EXPECT_EQ(s.error().cls, ErrorClass::kNotFound);
}

// The real aggscan-worker binary on a queue with a good sample and a bad job.
TEST_F(SideJobTest, WorkerBinaryDrainsTheQueue) {
  MakeSide(1);
  {
    auto q = JobQueue::Open(layout::QueuePath(root_.string()));
    ASSERT_TRUE(q.ok()) << q.error().ToString();
    ASSERT_TRUE((*q)->Enqueue("S-0001", 1).ok());
    ASSERT_TRUE((*q)->Enqueue("S-0001", 0).ok());
  }
  const std::string bin = std::string(AGGSCAN_BINARY_DIR) + "/pipeline/aggscan-worker";
  const std::string log = root_.string() + "/worker.log";
  const std::string cmd = bin + " --state-dir " + root_.string() + " --once --poll-ms 10 2>" + log;
  ASSERT_EQ(std::system(cmd.c_str()), 0) << std::ifstream(log).rdbuf();
  EXPECT_TRUE(PathExists(SideResultPath(dir_, 1)));
  EXPECT_TRUE(PathExists(SampleResultPath(dir_)));
  {
    auto q = JobQueue::Open(layout::QueuePath(root_.string()));
    ASSERT_TRUE(q.ok());
    auto jobs = (*q)->JobsForSample("S-0001");
    ASSERT_TRUE(jobs.ok());
    ASSERT_EQ(jobs->size(), 2u);
    for (const auto& j : *jobs) EXPECT_EQ(j.state, "done") << j.side << " " << j.error;
    // A job whose side was never captured fails three times, then stays failed.
    ASSERT_TRUE((*q)->Enqueue("S-0001", 2).ok());
  }
  EXPECT_NE(std::system(cmd.c_str()), 0);
  auto q = JobQueue::Open(layout::QueuePath(root_.string()));
  ASSERT_TRUE(q.ok());
  auto jobs = (*q)->JobsForSample("S-0001");
  ASSERT_TRUE(jobs.ok());
  bool seen = false;
  for (const auto& j : *jobs)
    if (j.side == 2) {
      seen = true;
      EXPECT_EQ(j.state, "failed");
      EXPECT_EQ(j.attempts, 3);
      EXPECT_NE(j.error.find("manifest"), std::string::npos) << j.error;
    }
  EXPECT_TRUE(seen);
  std::string text((std::istreambuf_iterator<char>(std::ifstream(log).rdbuf())),
                   std::istreambuf_iterator<char>());
  EXPECT_NE(text.find("S-0001"), std::string::npos) << "log lines carry the sample id";
}

}  // namespace
}  // namespace aggscan
