// The worker's records (pipeline/core/records.h): records written by the
// release before records carried a schema version still load, and write back
// unchanged but for the version; bad records are refused with the file and
// the field named; keys a record does not know survive.
#include "pipeline/core/records.h"

#include <gtest/gtest.h>

#include <cmath>
#include <filesystem>
#include <fstream>

#include "common/fsutil.h"
#include "common/json_io.h"
#include "pipeline/core/pose.h"

namespace aggscan::records {
namespace {

using nlohmann::json;

const std::string kData = std::string(AGGSCAN_SOURCE_DIR) + "/tests/core/data/";

json Fixture(const std::string& name) {
  std::ifstream f(kData + name);
  EXPECT_TRUE(f.good()) << kData + name;
  return json::parse(f);
}

jsonio::Source Src(const std::string& what = "record") {
  return {what, "/x/results/" + what + ".json", "redo it"};
}

// Written back, a record read from a file of the earlier release is that
// file plus the schema version.
template <typename R>
void ExpectSameOnDisk(const std::string& name) {
  SCOPED_TRACE(name);
  const json old = Fixture(name);
  auto r = R::FromJson(old, Src());
  ASSERT_TRUE(r.ok()) << r.error().ToString();
  json back = r->ToJson();
  EXPECT_EQ(back.at("schema"), kRecordSchema);
  back.erase("schema");
  EXPECT_EQ(back, old) << json::diff(old, back).dump(1);
  // And read again, the same.
  auto again = R::FromJson(r->ToJson(), Src());
  ASSERT_TRUE(again.ok()) << again.error().ToString();
  EXPECT_EQ(again->ToJson(), r->ToJson());
}

TEST(Records, FilesOfTheEarlierReleaseLoadAndWriteBackUnchanged) {
  ExpectSameOnDisk<SideResult>("side_result_v1.json");
  ExpectSameOnDisk<PosesRecord>("poses_v1.json");
  ExpectSameOnDisk<StitchRecord>("stitch_v1.json");
  ExpectSameOnDisk<SurfaceRecord>("surface_v1.json");
  ExpectSameOnDisk<Morphology>("morphology_v1.json");
}

TEST(Records, TypedFieldsReadFromTheEarlierRelease) {
  auto sr = SideResult::FromJson(Fixture("side_result_v1.json"), Src());
  ASSERT_TRUE(sr.ok()) << sr.error().ToString();
  EXPECT_EQ(sr->side, 1);
  ASSERT_EQ(sr->views.size(), 3u);
  EXPECT_TRUE(sr->views[0].ok);
  EXPECT_EQ(sr->views[0].mask, "masks/side1/view_000.png");
  EXPECT_GT(sr->views[0].fer_2d, 1.0);
  ASSERT_TRUE(sr->views[0].measured_angle_deg.has_value());
  EXPECT_FALSE(sr->views[2].ok);
  EXPECT_NE(sr->views[2].error.find("edge of the photo"), std::string::npos);
  EXPECT_EQ(sr->stats.at("fer_2d").n, 30);

  auto po = PosesRecord::FromJson(Fixture("poses_v1.json"), Src());
  ASSERT_TRUE(po.ok()) << po.error().ToString();
  EXPECT_EQ(po->side, 2);
  EXPECT_EQ(po->method, "turntable+ba");
  ASSERT_EQ(po->views.size(), 3u);
  // The sim rig's camera, about 0.67 m from the turntable's centre.
  const double d = po->views[1].cam_from_table.translation().norm();
  EXPECT_GT(d, 600);
  EXPECT_LT(d, 750);
  EXPECT_TRUE(po->bundle_adjustment.value("refined", false));

  auto st = StitchRecord::FromJson(Fixture("stitch_v1.json"), Src());
  ASSERT_TRUE(st.ok()) << st.error().ToString();
  ASSERT_EQ(st->table_from_object.size(), 2u);
  EXPECT_TRUE(st->table_from_object.at(1).isApprox(Pose::Identity()));
  ASSERT_EQ(st->stitches.size(), 1u);
  EXPECT_EQ(st->stitches[0].source, "features");
  ASSERT_TRUE(st->stitches[0].features && st->stitches[0].features->moving_to_reference);
  // The stitch's side-2 transform is the features' estimate, inverted.
  EXPECT_TRUE(st->table_from_object.at(2).isApprox(
      st->stitches[0].features->moving_to_reference->inverse(), 1e-9));
  ASSERT_TRUE(st->rms_mm.has_value());

  auto su = SurfaceRecord::FromJson(Fixture("surface_v1.json"), Src());
  ASSERT_TRUE(su.ok()) << su.error().ToString();
  EXPECT_EQ(su->method, "visual-hull+photo");
  EXPECT_EQ(su->silhouette_iou.size(), 3u);
  EXPECT_GT(su->timings_s.at("photo_refine"), 0.0);

  auto mo = Morphology::FromJson(Fixture("morphology_v1.json"), Src());
  ASSERT_TRUE(mo.ok()) << mo.error().ToString();
  EXPECT_DOUBLE_EQ(mo->volume_mm3, 155746.50207816696);
  EXPECT_LE(mo->a_mm, mo->b_mm);
  EXPECT_LE(mo->b_mm, mo->c_mm);
  EXPECT_TRUE(mo->confident);
  EXPECT_TRUE(mo->watertight);
  EXPECT_EQ(mo->methods.at("poses"), "turntable+ba");
  ASSERT_EQ(mo->poses.size(), 2u);
  EXPECT_TRUE(mo->poses[0].figures.value("ba_refined", false));
}

TEST(Records, ANewerSchemaIsRefused) {
  json j = Fixture("stitch_v1.json");
  j["schema"] = 99;
  auto r = StitchRecord::FromJson(j, Src("stitch record"));
  ASSERT_FALSE(r.ok());
  EXPECT_EQ(r.error().cls, ErrorClass::kCorrupt);
  EXPECT_NE(r.error().message.find("newer"), std::string::npos) << r.error().message;
  EXPECT_NE(r.error().message.find("/x/results/stitch record.json"), std::string::npos);
  j["schema"] = "two";
  EXPECT_FALSE(StitchRecord::FromJson(j, Src()).ok());
  j["schema"] = kRecordSchema;
  EXPECT_TRUE(StitchRecord::FromJson(j, Src()).ok());
}

TEST(Records, AMissingOrMistypedFieldIsNamedWithTheFileAndWhatToDo) {
  json j = Fixture("poses_v1.json");
  j["views"][1].erase("cam_from_table_4x4");
  auto r = PosesRecord::FromJson(j, Src("poses record"));
  ASSERT_FALSE(r.ok());
  const std::string m = r.error().message;
  EXPECT_NE(m.find("\"cam_from_table_4x4\" is missing"), std::string::npos) << m;
  EXPECT_NE(m.find("views[1]"), std::string::npos) << m;
  EXPECT_NE(m.find("/x/results/poses record.json"), std::string::npos) << m;
  EXPECT_NE(m.find("redo it"), std::string::npos) << m;

  json s = Fixture("side_result_v1.json");
  s["views_ok"] = "thirty";
  auto sr = SideResult::FromJson(s, Src());
  ASSERT_FALSE(sr.ok());
  EXPECT_NE(sr.error().message.find("\"views_ok\" is not a whole number"), std::string::npos)
      << sr.error().message;

  // A view with figures must have all of them.
  s = Fixture("side_result_v1.json");
  s["views"][0].erase("fer_2d");
  sr = SideResult::FromJson(s, Src());
  ASSERT_FALSE(sr.ok());
  EXPECT_NE(sr.error().message.find("\"fer_2d\""), std::string::npos) << sr.error().message;

  json m3 = Fixture("morphology_v1.json");
  m3["morphology_3d"]["volume_mm3"] = nullptr;  // a non-finite volume, as nlohmann writes it
  auto mo = Morphology::FromJson(m3, Src());
  ASSERT_FALSE(mo.ok());
  EXPECT_NE(mo.error().message.find("volume_mm3"), std::string::npos) << mo.error().message;

  json st = Fixture("stitch_v1.json");
  st["sides"] = json::array();
  auto sst = StitchRecord::FromJson(st, Src());
  ASSERT_FALSE(sst.ok());
  EXPECT_NE(sst.error().message.find("lists no side"), std::string::npos);

  EXPECT_FALSE(SurfaceRecord::FromJson(json::array(), Src()).ok());
  EXPECT_FALSE(Morphology::FromJson(json("text"), Src()).ok());
}

TEST(Records, APoseMustBeRigid) {
  json j = Fixture("stitch_v1.json");
  json& T = j["sides"][1]["table_from_object_4x4"];
  T[0] = T[0].get<double>() * 1.01;  // a scaled rotation
  auto r = StitchRecord::FromJson(j, Src());
  ASSERT_FALSE(r.ok());
  EXPECT_NE(r.error().message.find("not a rotation"), std::string::npos) << r.error().message;
  j = Fixture("stitch_v1.json");
  j["sides"][1]["table_from_object_4x4"][15] = 2.0;
  EXPECT_FALSE(StitchRecord::FromJson(j, Src()).ok());
  j["sides"][1]["table_from_object_4x4"] = json::array({1, 2, 3});
  EXPECT_FALSE(StitchRecord::FromJson(j, Src()).ok());

  // Round trip of a pose to 1e-12.
  Pose p = Pose::Identity();
  p.linear() = Eigen::AngleAxisd(0.7, Eigen::Vector3d(1, 2, 3).normalized()).toRotationMatrix();
  p.translation() = Eigen::Vector3d(10.5, -3.25, 400);
  auto back = PoseFromJson(PoseToJson(p), "p", Src());
  ASSERT_TRUE(back.ok()) << back.error().ToString();
  EXPECT_TRUE(back->isApprox(p, 1e-12));
  EXPECT_TRUE(ToPose(ToRigid3(p)).isApprox(p, 0));
}

TEST(Records, KeysARecordDoesNotKnowSurvive) {
  json j = Fixture("surface_v1.json");
  j["written_by_a_newer_release"] = {{"figure", 1.5}};
  j["views_left_out"] = json::array({{{"side", 2}, {"view", 7}, {"reason", "why"}, {"iou", 0.4}}});
  auto r = SurfaceRecord::FromJson(j, Src());
  ASSERT_TRUE(r.ok()) << r.error().ToString();
  ASSERT_EQ(r->views_left_out.size(), 1u);
  EXPECT_EQ(r->views_left_out[0].reason, "why");
  json back = r->ToJson();
  EXPECT_EQ(back["written_by_a_newer_release"]["figure"], 1.5);
  EXPECT_EQ(back["views_left_out"][0]["iou"], 0.4);
}

TEST(Records, ReadAndWriteThroughFiles) {
  const std::string dir = ::testing::TempDir() + "/records_test";
  std::filesystem::create_directories(dir);
  auto missing = Read<StitchRecord>(dir + "/none.json", "stitch record", "");
  ASSERT_FALSE(missing.ok());
  EXPECT_EQ(missing.error().cls, ErrorClass::kNotFound);
  ASSERT_TRUE(WriteFileAtomic(dir + "/cut.json", std::string_view("{\"method\": \"feat")).ok());
  auto cut = Read<StitchRecord>(dir + "/cut.json", "stitch record", "run it again");
  ASSERT_FALSE(cut.ok());
  EXPECT_EQ(cut.error().cls, ErrorClass::kCorrupt);
  EXPECT_NE(cut.error().message.find("run it again"), std::string::npos);

  auto st = StitchRecord::FromJson(Fixture("stitch_v1.json"), Src());
  ASSERT_TRUE(st.ok());
  ASSERT_TRUE(Write(dir + "/stitch.json", *st).ok());
  auto back = Read<StitchRecord>(dir + "/stitch.json", "stitch record", "");
  ASSERT_TRUE(back.ok()) << back.error().ToString();
  EXPECT_EQ(back->ToJson(), st->ToJson());
  std::filesystem::remove_all(dir);
}

TEST(JsonIo, FieldsAndTheirErrors) {
  const json j = {{"n", 3}, {"x", 2.5}, {"s", "a"}, {"b", true}, {"big", 1e12}, {"null", nullptr}};
  const jsonio::Source src{"thing", "/p.json", ""};
  EXPECT_EQ(*jsonio::Int(j, "n", src), 3);
  EXPECT_FALSE(jsonio::Int(j, "x", src).ok());
  EXPECT_FALSE(jsonio::Int(j, "big", src).ok());
  EXPECT_DOUBLE_EQ(*jsonio::Number(j, "n", src), 3.0);
  EXPECT_EQ(*jsonio::String(j, "s", src), "a");
  EXPECT_FALSE(jsonio::String(j, "n", src).ok());
  EXPECT_TRUE(*jsonio::Bool(j, "b", src));
  EXPECT_EQ(*jsonio::IntOr(j, "absent", 7, src), 7);
  EXPECT_EQ(*jsonio::IntOr(j, "null", 7, src), 7);
  EXPECT_FALSE(jsonio::IntOr(j, "s", 7, src).ok());  // present with another type: refused
  EXPECT_EQ(*jsonio::SchemaVersion(j, "schema", 2, src), 1);
  EXPECT_TRUE(jsonio::Finite(std::nan("")).is_null());
  EXPECT_EQ(jsonio::Finite(1.5), 1.5);
  const auto e = jsonio::Number(j, "absent", src);
  ASSERT_FALSE(e.ok());
  EXPECT_EQ(e.error().message, "thing /p.json: \"absent\" is missing");
}

}  // namespace
}  // namespace aggscan::records
