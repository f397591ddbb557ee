#include "store/sample_files.h"

#include <gtest/gtest.h>

#include <filesystem>
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

const jsonio::Source kSrc{"view sidecar", "/x/side1/view_003.json", ""};
const jsonio::Source kManSrc{"side manifest", "/x/side1/manifest.json", ""};

// A sidecar as the daemon writes it (daemon/capture_service.cpp).
json DaemonSidecar() {
  return json::parse(R"({
    "camera_backend": "sim", "camera_id": "sim-cam0", "capture_monotonic_ns": 49300076158220,
    "capture_utc": "2026-12-06T16:18:51.005Z", "commanded_angle_deg": 90.0,
    "due_monotonic_ns": 49299764117140, "exposure_us": 8000.0, "frame_sequence": 33,
    "gain": 1.0, "height": 1512, "image": "view_003.jpg", "measured_angle_deg": 89.967,
    "sample_id": "demo-1", "schedule_error_ms": 312.04, "schedule_overrun": true, "side": 1,
    "time_scale": 10.0, "trigger_monotonic_ns": 49300074900720, "view": 3, "wb_blue": 1.0,
    "wb_red": 1.0, "width": 2016})");
}

json StoreManifest() {
  return json::parse(R"({
    "completed_utc": "2026-12-06T16:19:40.120Z", "sample_id": "demo-1", "side": 2,
    "views": [
      {"bytes": 812345, "image": "view_000.jpg", "sidecar": "view_000.json", "view": 0},
      {"bytes": 799001, "image": "view_001.jpg", "sidecar": "view_001.json", "view": 1}]})");
}

json WithSchema(json j) {
  j["schema"] = kSampleFilesSchema;
  return j;
}

std::vector<unsigned char> Bytes(const std::string& s) { return {s.begin(), s.end()}; }

void WriteText(const std::string& path, const std::string& text) {
  ASSERT_TRUE(WriteFileAtomic(path, std::string_view(text)));
}

TEST(SampleFiles, SidecarRoundTrip) {
  auto c = ViewSidecar::FromJson(WithSchema(DaemonSidecar()), kSrc);
  ASSERT_TRUE(c) << c.error().ToString();
  EXPECT_EQ(c->view, 3);
  EXPECT_EQ(c->side, 1);
  EXPECT_EQ(c->image, "view_003.jpg");
  EXPECT_EQ(c->sample_id, "demo-1");
  EXPECT_DOUBLE_EQ(*c->commanded_angle_deg, 90.0);
  EXPECT_DOUBLE_EQ(*c->measured_angle_deg, 89.967);
  EXPECT_EQ(*c->due_monotonic_ns, int64_t{49299764117140});
  EXPECT_EQ(*c->trigger_monotonic_ns, int64_t{49300074900720});
  EXPECT_EQ(*c->capture_monotonic_ns, int64_t{49300076158220});
  EXPECT_EQ(c->capture_utc, "2026-12-06T16:18:51.005Z");
  EXPECT_DOUBLE_EQ(*c->schedule_error_ms, 312.04);
  EXPECT_EQ(c->schedule_overrun, true);
  EXPECT_DOUBLE_EQ(*c->exposure_us, 8000.0);
  EXPECT_DOUBLE_EQ(*c->gain, 1.0);
  EXPECT_DOUBLE_EQ(*c->wb_red, 1.0);
  EXPECT_DOUBLE_EQ(*c->wb_blue, 1.0);
  EXPECT_EQ(c->camera_id, "sim-cam0");
  EXPECT_EQ(c->camera_backend, "sim");
  EXPECT_EQ(c->width, 2016);
  EXPECT_EQ(c->height, 1512);
  EXPECT_EQ(c->frame_sequence, uint64_t{33});
  EXPECT_DOUBLE_EQ(*c->time_scale, 10.0);
  EXPECT_TRUE(c->missing_controls.empty());
  EXPECT_TRUE(c->extra.empty()) << c->extra.dump();
  EXPECT_EQ(c->ToJson(), WithSchema(DaemonSidecar()));
  // Through text, as on disk.
  auto again = ViewSidecar::FromJson(json::parse(c->ToJson().dump()), kSrc);
  ASSERT_TRUE(again) << again.error().ToString();
  EXPECT_EQ(again->ToJson(), c->ToJson());

  // The fields the daemon sets only sometimes, and a minimal sidecar.
  json j = DaemonSidecar();
  j["missing_controls"] = {"exposure", "gain"};
  c = ViewSidecar::FromJson(j, kSrc);
  ASSERT_TRUE(c) << c.error().ToString();
  EXPECT_EQ(c->missing_controls, (std::vector<std::string>{"exposure", "gain"}));
  EXPECT_EQ(c->ToJson(), WithSchema(j));
  c = ViewSidecar::FromJson({{"view", 0}, {"measured_angle_deg", 10.0}}, kSrc);
  ASSERT_TRUE(c) << c.error().ToString();
  EXPECT_FALSE(c->side || c->image || c->commanded_angle_deg || c->capture_utc);
  EXPECT_EQ(c->ToJson(), WithSchema({{"view", 0}, {"measured_angle_deg", 10.0}}));
}

TEST(SampleFiles, ManifestRoundTrip) {
  auto m = SideManifest::FromJson(WithSchema(StoreManifest()), kManSrc);
  ASSERT_TRUE(m) << m.error().ToString();
  EXPECT_EQ(m->side, 2);
  EXPECT_EQ(m->sample_id, "demo-1");
  EXPECT_EQ(m->completed_utc, "2026-12-06T16:19:40.120Z");
  ASSERT_EQ(m->views.size(), 2u);
  EXPECT_EQ(m->views[1].view, 1);
  EXPECT_EQ(m->views[1].image, "view_001.jpg");
  EXPECT_EQ(m->views[1].sidecar, "view_001.json");
  EXPECT_EQ(m->views[1].bytes, int64_t{799001});
  EXPECT_EQ(m->ToJson(), WithSchema(StoreManifest()));
  auto again = SideManifest::FromJson(json::parse(m->ToJson().dump()), kManSrc);
  ASSERT_TRUE(again) << again.error().ToString();
  EXPECT_EQ(again->ToJson(), m->ToJson());
  // A hand-made manifest: no sidecar, no bytes, no sample id, no time.
  const json bare = {{"side", 1}, {"views", {{{"view", 0}, {"image", "view_000.jpg"}}}}};
  m = SideManifest::FromJson(bare, kManSrc);
  ASSERT_TRUE(m) << m.error().ToString();
  EXPECT_FALSE(m->views[0].sidecar || m->views[0].bytes || m->sample_id || m->completed_utc);
  EXPECT_EQ(m->ToJson(), WithSchema(bare));
}

TEST(SampleFiles, FileWithoutSchemaLoadsAsVersionOne) {
  TempDir t;
  const std::string sd = t.path() + "/side1";
  std::filesystem::create_directories(sd);
  json car = DaemonSidecar();
  ASSERT_FALSE(car.contains("schema"));
  WriteText(sd + "/view_003.json", car.dump(2));
  WriteText(sd + "/manifest.json", StoreManifest().dump(2));
  auto c = ReadViewSidecar(sd, 3);
  ASSERT_TRUE(c) << c.error().ToString();
  EXPECT_DOUBLE_EQ(*c->measured_angle_deg, 89.967);
  EXPECT_EQ(c->ToJson()["schema"], kSampleFilesSchema);
  EXPECT_FALSE(c->extra.contains("schema"));
  auto m = ReadSideManifest(sd);
  ASSERT_TRUE(m) << m.error().ToString();
  EXPECT_EQ(m->views.size(), 2u);
  // "schema": 1 written out is the same.
  car["schema"] = 1;
  EXPECT_TRUE(ViewSidecar::FromJson(car, kSrc));
}

TEST(SampleFiles, NewerSchemaIsRefused) {
  TempDir t;
  const std::string sd = t.path() + "/side1";
  std::filesystem::create_directories(sd);
  json car = DaemonSidecar();
  car["schema"] = 99;
  WriteText(sd + "/view_003.json", car.dump());
  json man = StoreManifest();
  man["schema"] = 99;
  WriteText(sd + "/manifest.json", man.dump());
  auto c = ReadViewSidecar(sd, 3);
  ASSERT_FALSE(c);
  EXPECT_EQ(c.error().cls, ErrorClass::kCorrupt);
  EXPECT_NE(c.error().message.find("newer"), std::string::npos) << c.error().message;
  EXPECT_NE(c.error().message.find(sd + "/view_003.json"), std::string::npos);
  auto m = ReadSideManifest(sd);
  ASSERT_FALSE(m);
  EXPECT_NE(m.error().message.find("newer"), std::string::npos) << m.error().message;
  EXPECT_NE(m.error().message.find(sd + "/manifest.json"), std::string::npos);
  // Not a version at all.
  car["schema"] = "two";
  auto bad = ViewSidecar::FromJson(car, kSrc);
  ASSERT_FALSE(bad);
  EXPECT_NE(bad.error().message.find("\"schema\""), std::string::npos) << bad.error().message;
}

TEST(SampleFiles, MissingRequiredFieldNamesFieldAndFile) {
  TempDir t;
  const std::string sd = t.path() + "/side1";
  std::filesystem::create_directories(sd);
  json car = DaemonSidecar();
  car.erase("view");
  WriteText(sd + "/view_003.json", car.dump());
  auto c = ReadViewSidecar(sd, 3);
  ASSERT_FALSE(c);
  EXPECT_EQ(c.error().cls, ErrorClass::kCorrupt);
  EXPECT_NE(c.error().message.find("\"view\" is missing"), std::string::npos) << c.error().message;
  EXPECT_NE(c.error().message.find(sd + "/view_003.json"), std::string::npos) << c.error().message;

  const std::vector<std::pair<json, std::string>> cases = {
      {[] {
         json m = StoreManifest();
         m.erase("side");
         return m;
       }(),
       "\"side\" is missing"},
      {[] {
         json m = StoreManifest();
         m.erase("views");
         return m;
       }(),
       "\"views\" is missing"},
      {[] {
         json m = StoreManifest();
         m["views"][1].erase("image");
         return m;
       }(),
       "\"image\" is missing"},
      {[] {
         json m = StoreManifest();
         m["views"][0].erase("view");
         return m;
       }(),
       "\"view\" is missing"},
  };
  for (const auto& [m, want] : cases) {
    WriteText(sd + "/manifest.json", m.dump());
    auto r = ReadSideManifest(sd);
    ASSERT_FALSE(r) << m.dump();
    EXPECT_EQ(r.error().cls, ErrorClass::kCorrupt);
    EXPECT_NE(r.error().message.find(want), std::string::npos) << r.error().message;
    EXPECT_NE(r.error().message.find(sd + "/manifest.json"), std::string::npos)
        << r.error().message;
  }
  // The entry at fault is named too.
  json m = StoreManifest();
  m["views"][1].erase("image");
  auto r = SideManifest::FromJson(m, kManSrc);
  ASSERT_FALSE(r);
  EXPECT_NE(r.error().message.find("views[1]"), std::string::npos) << r.error().message;
}

TEST(SampleFiles, WrongTypeIsRefused) {
  const std::vector<std::pair<std::string, json>> sidecars = {
      {"view", "three"},
      {"view", -1},
      {"side", 0},
      {"measured_angle_deg", "forty"},
      {"capture_monotonic_ns", 1.5},
      {"frame_sequence", -3},
      {"schedule_overrun", 1},
      {"width", "wide"},
      {"capture_utc", 12},
      {"missing_controls", "exposure"},
  };
  for (const auto& [key, value] : sidecars) {
    json j = DaemonSidecar();
    j[key] = value;
    auto c = ViewSidecar::FromJson(j, kSrc);
    ASSERT_FALSE(c) << key << " = " << value.dump();
    EXPECT_EQ(c.error().cls, ErrorClass::kCorrupt);
    EXPECT_NE(c.error().message.find("\"" + key + "\""), std::string::npos) << c.error().message;
    EXPECT_NE(c.error().message.find(kSrc.path), std::string::npos) << c.error().message;
  }
  EXPECT_FALSE(ViewSidecar::FromJson(json::array({1, 2}), kSrc));
  EXPECT_FALSE(ViewSidecar::FromJson(json("view"), kSrc));

  const std::vector<std::pair<std::string, json>> entries = {
      {"view", "three"},      {"image", 7},  {"image", "../x.jpg"}, {"image", "sub/view_000.jpg"},
      {"sidecar", ".hidden"}, {"bytes", -1}, {"bytes", "many"},
  };
  for (const auto& [key, value] : entries) {
    json m = StoreManifest();
    m["views"][0][key] = value;
    auto r = SideManifest::FromJson(m, kManSrc);
    ASSERT_FALSE(r) << key << " = " << value.dump();
    EXPECT_NE(r.error().message.find("\"" + key + "\""), std::string::npos) << r.error().message;
  }
  json m = StoreManifest();
  m["views"] = {{"view", 0}};
  EXPECT_FALSE(SideManifest::FromJson(m, kManSrc));
  m = StoreManifest();
  m["side"] = "two";
  EXPECT_FALSE(SideManifest::FromJson(m, kManSrc));
  m = StoreManifest();
  m["views"][1]["view"] = 0;  // twice
  auto dup = SideManifest::FromJson(m, kManSrc);
  ASSERT_FALSE(dup);
  EXPECT_NE(dup.error().message.find("listed twice"), std::string::npos) << dup.error().message;
}

TEST(SampleFiles, UnknownKeysSurviveTheRoundTrip) {
  json car = DaemonSidecar();
  car["lens_temperature_c"] = 31.5;
  car["future"] = {{"nested", {1, 2, 3}}};
  auto c = ViewSidecar::FromJson(car, kSrc);
  ASSERT_TRUE(c) << c.error().ToString();
  EXPECT_EQ(c->extra, json({{"lens_temperature_c", 31.5}, {"future", {{"nested", {1, 2, 3}}}}}));
  EXPECT_EQ(c->ToJson(), WithSchema(car));

  json man = StoreManifest();
  man["operator_note"] = "re-lit";
  man["views"][0]["checksum"] = "abc";
  auto m = SideManifest::FromJson(man, kManSrc);
  ASSERT_TRUE(m) << m.error().ToString();
  EXPECT_EQ(m->extra, json({{"operator_note", "re-lit"}}));
  EXPECT_EQ(m->views[0].extra, json({{"checksum", "abc"}}));
  EXPECT_EQ(m->ToJson(), WithSchema(man));
  // Known fields win over a stale copy in extra.
  m->extra["side"] = 9;
  EXPECT_EQ(m->ToJson()["side"], 2);
}

TEST(SampleFiles, MissingFilesAreNotFound) {
  TempDir t;
  auto c = ReadViewSidecar(t.path(), 0);
  ASSERT_FALSE(c);
  EXPECT_EQ(c.error().cls, ErrorClass::kNotFound);
  auto m = ReadSideManifest(t.path() + "/side1");
  ASSERT_FALSE(m);
  EXPECT_EQ(m.error().cls, ErrorClass::kNotFound);
  EXPECT_NE(m.error().message.find("manifest.json"), std::string::npos) << m.error().message;
  // Not JSON at all.
  WriteText(t.path() + "/manifest.json", "{\"side\": 1,");
  m = ReadSideManifest(t.path());
  ASSERT_FALSE(m);
  EXPECT_EQ(m.error().cls, ErrorClass::kCorrupt);
}

TEST(SampleFiles, SidecarUnderAnotherViewsNameIsRefused) {
  TempDir t;
  WriteText(t.path() + "/" + layout::ViewSidecarName(4), DaemonSidecar().dump());  // says view 3
  auto c = ReadViewSidecar(t.path(), 4);
  ASSERT_FALSE(c);
  EXPECT_EQ(c.error().cls, ErrorClass::kCorrupt);
  EXPECT_NE(c.error().message.find("\"view\" is 3"), std::string::npos) << c.error().message;
  EXPECT_TRUE(ReadViewSidecarFile(t.path() + "/" + layout::ViewSidecarName(4)));
}

SamplePlan OneSide() {
  SamplePlan p;
  p.sides = 1;
  p.views_per_side = 2;
  p.step_deg = 180;
  return p;
}

TEST(SampleFiles, StoreWrittenFilesReadBackEqual) {
  TempDir t;
  SampleStore store(t.path());
  ASSERT_TRUE(store.Init());
  ASSERT_TRUE(store.CreateOrResume("demo-1", OneSide(), "# cfg\n"));
  ASSERT_TRUE(store.BeginSide("demo-1", 1));
  std::vector<json> given;
  for (int v = 0; v < 2; ++v) {
    json car = DaemonSidecar();
    car["view"] = v;
    car["image"] = layout::ViewImageName(v);
    car["measured_angle_deg"] = 180.0 * v + 0.04;
    if (v == 1) car["missing_controls"] = {"gain"};
    given.push_back(car);
    ASSERT_TRUE(store.WriteView("demo-1", 1, v, Bytes("jpeg" + std::to_string(v)), car));
  }
  ASSERT_TRUE(store.FinishSide("demo-1", 1));
  const std::string sd = store.SampleDir("demo-1") + "/side1";
  for (int v = 0; v < 2; ++v) {
    auto c = ReadViewSidecar(sd, v);
    ASSERT_TRUE(c) << c.error().ToString();
    auto want = ViewSidecar::FromJson(given[static_cast<size_t>(v)], kSrc);
    ASSERT_TRUE(want);
    EXPECT_EQ(c->ToJson(), want->ToJson());
    EXPECT_EQ(c->ToJson(), WithSchema(given[static_cast<size_t>(v)]));
    EXPECT_DOUBLE_EQ(*c->measured_angle_deg, 180.0 * v + 0.04);
    // On disk as written: with the schema.
    auto raw = json::parse(*ReadFile(sd + "/" + layout::ViewSidecarName(v)));
    EXPECT_EQ(raw["schema"], kSampleFilesSchema);
  }
  auto m = ReadSideManifest(sd);
  ASSERT_TRUE(m) << m.error().ToString();
  EXPECT_EQ(m->side, 1);
  EXPECT_EQ(m->sample_id, "demo-1");
  EXPECT_TRUE(m->completed_utc && !m->completed_utc->empty());
  ASSERT_EQ(m->views.size(), 2u);
  for (int v = 0; v < 2; ++v) {
    const auto& e = m->views[static_cast<size_t>(v)];
    EXPECT_EQ(e.view, v);
    EXPECT_EQ(e.image, layout::ViewImageName(v));
    EXPECT_EQ(e.sidecar, layout::ViewSidecarName(v));
    EXPECT_EQ(e.bytes, int64_t{5});
  }
  auto raw = json::parse(*ReadFile(sd + "/manifest.json"));
  EXPECT_EQ(raw["schema"], kSampleFilesSchema);
  EXPECT_EQ(raw, m->ToJson());
  // The sample record agrees with the manifest.
  auto rec = store.LoadRecord("demo-1");
  ASSERT_TRUE(rec);
  EXPECT_EQ((*rec)["sides"][0]["views"], 2);
  EXPECT_EQ((*rec)["sides"][0]["completed_utc"], *m->completed_utc);
  // Describe reads the typed sidecars.
  auto d = store.Describe("demo-1");
  ASSERT_TRUE(d) << d.error().ToString();
  const json& dv = (*d)["sides"][0]["captured_views"][1];
  EXPECT_DOUBLE_EQ(dv["measured_angle_deg"].get<double>(), 180.04);
  EXPECT_EQ(dv["capture_utc"], "2026-12-06T16:18:51.005Z");
  EXPECT_FALSE(dv.contains("sidecar_problem"));
}

TEST(SampleFiles, StoreFillsItsCoordinatesAndRefusesABadSidecar) {
  TempDir t;
  SampleStore store(t.path());
  ASSERT_TRUE(store.Init());
  ASSERT_TRUE(store.CreateOrResume("r", OneSide(), "# cfg\n"));
  ASSERT_TRUE(store.BeginSide("r", 1));
  const std::string sd = store.SampleDir("r") + "/side1";
  // Nothing but the angle: the store adds sample, side, view and image.
  ASSERT_TRUE(store.WriteView("r", 1, 0, Bytes("x"), {{"measured_angle_deg", 1.5}}));
  auto c = ReadViewSidecar(sd, 0);
  ASSERT_TRUE(c) << c.error().ToString();
  EXPECT_EQ(c->sample_id, "r");
  EXPECT_EQ(c->side, 1);
  EXPECT_EQ(c->image, "view_000.jpg");
  EXPECT_DOUBLE_EQ(*c->measured_angle_deg, 1.5);
  // A wrongly typed field, another view's index or a list: refused, nothing stored.
  for (const json& bad :
       {json{{"view", "one"}}, json{{"view", 2}}, json{{"side", 2}}, json{{"sample_id", "other"}},
        json{{"exposure_us", "long"}}, json::array({1})}) {
    Status s = store.WriteView("r", 1, 1, Bytes("y"), bad);
    ASSERT_FALSE(s) << bad.dump();
    EXPECT_EQ(s.error().cls, ErrorClass::kInvalidArgument);
    EXPECT_NE(s.error().message.find(sd + "/view_001.json"), std::string::npos)
        << s.error().message;
    EXPECT_FALSE(PathExists(sd + "/view_001.jpg")) << bad.dump();
    EXPECT_FALSE(PathExists(sd + "/view_001.json")) << bad.dump();
  }
  ASSERT_TRUE(store.WriteView("r", 1, 1, Bytes("y"), {}));
  EXPECT_TRUE(ReadViewSidecar(sd, 1));
}

TEST(SampleFiles, DescribeShowsWhatADamagedSidecarStillHolds) {
  TempDir t;
  SampleStore store(t.path());
  ASSERT_TRUE(store.Init());
  ASSERT_TRUE(store.CreateOrResume("r", OneSide(), "# cfg\n"));
  ASSERT_TRUE(store.BeginSide("r", 1));
  ASSERT_TRUE(store.WriteView("r", 1, 0, Bytes("x"), {}));
  const std::string path = store.SampleDir("r") + "/side1/view_000.json";
  WriteText(path,
            R"({"view": 0, "commanded_angle_deg": "zero", "measured_angle_deg": 30.5,
                "capture_utc": 12})");
  auto d = store.Describe("r");
  ASSERT_TRUE(d) << d.error().ToString();
  const json& view = (*d)["sides"][0]["captured_views"][0];
  EXPECT_EQ(view["commanded_angle_deg"], 0.0);
  EXPECT_EQ(view["measured_angle_deg"], 30.5);
  EXPECT_EQ(view["capture_utc"], "");
  EXPECT_NE(view.value("sidecar_problem", "").find("\"commanded_angle_deg\""), std::string::npos)
      << view.dump();
}

}  // namespace
}  // namespace aggscan
