#include <gtest/gtest.h>
#include <sqlite3.h>
#include <unistd.h>

#include <filesystem>
#include <thread>

#include "common/fsutil.h"
#include "store/layout.h"
#include "store/queue.h"
#include "store/sample_store.h"
#include "tests/util/temp_dir.h"

namespace aggscan {
namespace {

namespace fs = std::filesystem;

using test::TempDir;

std::vector<unsigned char> Bytes(const std::string& s) { return {s.begin(), s.end()}; }

SamplePlan SmallPlan() {
  SamplePlan p;
  p.sides = 2;
  p.views_per_side = 3;
  p.step_deg = 120;
  return p;
}

TEST(Layout, SampleIdValidation) {
  for (const char* ok : {"rock-1", "RR3_2026.11.22", "a", "0123456789"})
    EXPECT_TRUE(layout::IsValidSampleId(ok)) << ok;
  for (const char* bad : {"", "..", "../x", "a/b", ".hidden", "-x", "a b", "a\nb", "x%2f", "é"}) {
    EXPECT_FALSE(layout::IsValidSampleId(bad)) << bad;
  }
  EXPECT_FALSE(layout::IsValidSampleId(std::string(65, 'a')));
  EXPECT_EQ(layout::ViewImageName(7), "view_007.jpg");
}

TEST(FsUtil, AtomicWriteNoReplaceKeepsOriginal) {
  TempDir t;
  const std::string p = t.path() + "/f.txt";
  ASSERT_TRUE(WriteFileAtomic(p, std::string_view("first")));
  Status s = WriteFileAtomic(p, std::string_view("second"), /*no_replace=*/true);
  ASSERT_FALSE(s.ok());
  EXPECT_EQ(s.error().cls, ErrorClass::kConflict);
  EXPECT_EQ(*ReadFile(p), "first");
  ASSERT_TRUE(WriteFileAtomic(p, std::string_view("third")));
  EXPECT_EQ(*ReadFile(p), "third");
  // No temporary files are left behind.
  int n = 0;
  for (auto& e : fs::directory_iterator(t.path()))
    n += e.path().filename().string().rfind(".tmp-", 0) == 0;
  EXPECT_EQ(n, 0);
}

// The operator's description given at arming is kept in the record and
// listed; a resume keeps what it does not give again.
TEST(SampleStore, ArmDescriptionIsKeptAndMergedOnResume) {
  TempDir t;
  SampleStore store(t.path());
  ASSERT_TRUE(store.Init());
  ASSERT_TRUE(store.CreateOrResume("rock-m", SmallPlan(), "# cfg\n",
                                   {{"operator", "M. Rossi"}, {"lot", "lot-7"}, {"notes", "wet"}}));
  ASSERT_TRUE(store.CreateOrResume("rock-m", SmallPlan(), "# cfg\n", {{"notes", "dried"}}));
  auto rec = store.Describe("rock-m");
  ASSERT_TRUE(rec.ok());
  EXPECT_EQ((*rec)["meta"],
            (nlohmann::json{{"operator", "M. Rossi"}, {"lot", "lot-7"}, {"notes", "dried"}}));
  auto list = store.List();
  ASSERT_TRUE(list.ok());
  ASSERT_EQ(list->size(), 1u);
  EXPECT_EQ((*list)[0]["meta"]["lot"], "lot-7");
  // Without a description the record has none and the list says so plainly.
  ASSERT_TRUE(store.CreateOrResume("rock-n", SmallPlan(), "# cfg\n"));
  list = store.List();
  ASSERT_TRUE(list.ok());
  ASSERT_EQ(list->size(), 2u);
  for (const auto& s : *list) {
    if (s["id"] == "rock-n") {
      EXPECT_EQ(s["meta"], nlohmann::json::object());
    }
  }
}

TEST(SampleStore, FullSampleLifecycle) {
  TempDir t;
  SampleStore store(t.path());
  ASSERT_TRUE(store.Init());
  ASSERT_EQ(*store.PrepareArm("rock-1", SmallPlan()), 1);
  ASSERT_TRUE(store.CreateOrResume("rock-1", SmallPlan(), "# cfg\n"));
  for (int side = 1; side <= 2; ++side) {
    ASSERT_TRUE(store.BeginSide("rock-1", side));
    for (int v = 0; v < 3; ++v) {
      ASSERT_TRUE(
          store.WriteView("rock-1", side, v, Bytes("jpeg" + std::to_string(v)), {{"view", v}}));
    }
    ASSERT_TRUE(store.FinishSide("rock-1", side));
  }
  ASSERT_TRUE(store.SetSampleState("rock-1", "captured"));
  auto rec = store.Describe("rock-1");
  ASSERT_TRUE(rec.ok());
  EXPECT_EQ((*rec)["state"], "captured");
  EXPECT_EQ((*rec)["sides"][1]["captured_views"].size(), 3u);
  EXPECT_EQ((*rec)["sides"][0]["state"], "done");
  // A complete sample cannot be re-armed, and views cannot be overwritten.
  auto again = store.PrepareArm("rock-1", SmallPlan());
  ASSERT_FALSE(again.ok());
  EXPECT_EQ(again.error().cls, ErrorClass::kConflict);
  Status over = store.WriteView("rock-1", 1, 0, Bytes("other"), {});
  EXPECT_EQ(over.error().cls, ErrorClass::kConflict);
  EXPECT_EQ(*ReadFile(store.SampleDir("rock-1") + "/side1/view_000.jpg"), "jpeg0");
  EXPECT_TRUE(PathExists(store.SampleDir("rock-1") + "/config.toml"));
  auto list = store.List();
  ASSERT_EQ(list->size(), 1u);
  EXPECT_EQ((*list)[0]["views"], 6);
}

TEST(SampleStore, InterruptedSideIsMarkedAndReshotWithoutLoss) {
  TempDir t;
  SampleStore store(t.path());
  ASSERT_TRUE(store.Init());
  ASSERT_TRUE(store.CreateOrResume("r", SmallPlan(), "cfg"));
  ASSERT_TRUE(store.BeginSide("r", 1));
  ASSERT_TRUE(store.WriteView("r", 1, 0, Bytes("v0"), {{"view", 0}}));
  // A crash mid-write leaves a temporary file and an image without sidecar.
  ASSERT_TRUE(
      WriteFileAtomic(store.SampleDir("r") + "/side1/view_001.jpg", std::string_view("half")));
  {
    std::FILE* f =
        std::fopen((store.SampleDir("r") + "/side1/.tmp-view_002.jpg.1234").c_str(), "w");
    std::fputs("partial", f);
    std::fclose(f);
  }
  SampleStore restarted(t.path());
  auto rep = restarted.Recover();
  ASSERT_TRUE(rep.ok());
  EXPECT_EQ(rep->sides_interrupted, 1);
  EXPECT_EQ(rep->temp_files_removed, 1);
  ASSERT_EQ(rep->interrupted_samples.size(), 1u);
  auto rec = restarted.LoadRecord("r");
  EXPECT_EQ((*rec)["state"], "interrupted");
  EXPECT_EQ((*rec)["sides"][0]["state"], "interrupted");
  EXPECT_EQ((*rec)["sides"][0]["views_found"], 1);  // view 1 had no sidecar: incomplete
  // Re-arming resumes at side 1 and moves the old attempt aside intact.
  ASSERT_EQ(*restarted.PrepareArm("r", SmallPlan()), 1);
  ASSERT_TRUE(restarted.CreateOrResume("r", SmallPlan(), "cfg2"));
  ASSERT_TRUE(restarted.BeginSide("r", 1));
  EXPECT_EQ(*ReadFile(restarted.SampleDir("r") + "/side1.interrupted-1/view_000.jpg"), "v0");
  EXPECT_FALSE(PathExists(restarted.SampleDir("r") + "/side1/view_000.jpg"));
  auto desc = restarted.Describe("r");
  EXPECT_EQ((*desc)["sides"][0]["interrupted_attempts"][0]["views"], 1);
  // A different plan for the same id is refused.
  SamplePlan other = SmallPlan();
  other.views_per_side = 5;
  EXPECT_EQ(restarted.PrepareArm("r", other).error().cls, ErrorClass::kConflict);
}

TEST(SampleStore, ResumeAfterFirstSideStartsAtSecond) {
  TempDir t;
  SampleStore store(t.path());
  ASSERT_TRUE(store.Init());
  ASSERT_TRUE(store.CreateOrResume("r", SmallPlan(), "cfg"));
  ASSERT_TRUE(store.BeginSide("r", 1));
  for (int v = 0; v < 3; ++v) ASSERT_TRUE(store.WriteView("r", 1, v, Bytes("x"), {}));
  ASSERT_TRUE(store.FinishSide("r", 1));
  ASSERT_TRUE(store.SetSampleState("r", "awaiting_pose"));
  ASSERT_TRUE(SampleStore(t.path()).Recover());
  EXPECT_EQ(*store.PrepareArm("r", SmallPlan()), 2);
}

// Killed right after the last manifest, before the record said "captured":
// start-up completes the sample (both sides done, "captured"), so its sample
// job is queued (CapturedWork) instead of the rock being lost.
TEST(SampleStore, CrashAfterLastManifestCompletesTheSample) {
  TempDir t;
  SampleStore store(t.path());
  ASSERT_TRUE(store.Init());
  ASSERT_TRUE(store.CreateOrResume("r", SmallPlan(), "cfg"));
  for (int side = 1; side <= 2; ++side) {
    ASSERT_TRUE(store.BeginSide("r", side));
    for (int v = 0; v < 3; ++v)
      ASSERT_TRUE(store.WriteView("r", side, v, Bytes("s" + std::to_string(side)), {}));
    ASSERT_TRUE(store.FinishSide("r", side));
    if (side == 1) {
      ASSERT_TRUE(store.SetSampleState("r", "awaiting_pose"));
    }
  }
  // The record still says "capturing": the kill came before "captured".
  EXPECT_EQ((*store.LoadRecord("r"))["state"], "capturing");
  EXPECT_EQ(store.CapturedWork().size(), 2u);  // the sample job would be missing
  SampleStore restarted(t.path());
  auto rep = restarted.Recover();
  ASSERT_TRUE(rep.ok()) << rep.error().ToString();
  EXPECT_EQ(rep->sides_interrupted, 0);
  EXPECT_TRUE(rep->interrupted_samples.empty());
  ASSERT_EQ(rep->completed_samples.size(), 1u);
  EXPECT_EQ(rep->completed_samples[0], "r");
  auto rec = restarted.LoadRecord("r");
  EXPECT_EQ((*rec)["state"], "captured");
  EXPECT_EQ((*rec)["sides"][1]["state"], "done");
  auto work = restarted.CapturedWork();
  ASSERT_EQ(work.size(), 3u);
  EXPECT_EQ(work[2], std::make_pair(std::string("r"), 0));
  // A second start-up changes nothing.
  auto again = SampleStore(t.path()).Recover();
  EXPECT_TRUE(again->completed_samples.empty());
  EXPECT_EQ(again->sides_completed, 0);
}

// Every view of the last side stored, killed (or out of space) before its
// manifest: the manifest is written from the stored views, nothing is re-shot
// or moved aside, and the sample is captured.
TEST(SampleStore, SideWithEveryViewStoredIsCompletedNotReshot) {
  TempDir t;
  SampleStore store(t.path());
  ASSERT_TRUE(store.Init());
  ASSERT_TRUE(store.CreateOrResume("r", SmallPlan(), "cfg"));
  ASSERT_TRUE(store.BeginSide("r", 1));
  for (int v = 0; v < 3; ++v)
    ASSERT_TRUE(store.WriteView("r", 1, v, Bytes("a" + std::to_string(v)), {}));
  ASSERT_TRUE(store.FinishSide("r", 1));
  ASSERT_TRUE(store.BeginSide("r", 2));
  for (int v = 0; v < 3; ++v)
    ASSERT_TRUE(store.WriteView("r", 2, v, Bytes("bb" + std::to_string(v)), {}));
  // Manifest missing. The running daemon would have marked it interrupted on the fault.
  ASSERT_TRUE(store.SetSampleState("r", "interrupted", 2, "interrupted"));
  auto done = store.CompleteStored("r");
  ASSERT_TRUE(done.ok()) << done.error().ToString();
  ASSERT_EQ(done->sides_completed.size(), 1u);
  EXPECT_EQ(done->sides_completed[0], 2);
  EXPECT_TRUE(done->sample_captured);
  EXPECT_TRUE(done->sample_completed_now);
  auto man = nlohmann::json::parse(*ReadFile(store.SampleDir("r") + "/side2/manifest.json"));
  ASSERT_EQ(man["views"].size(), 3u);
  EXPECT_EQ(man["views"][2]["bytes"], 3);
  EXPECT_EQ(*ReadFile(store.SampleDir("r") + "/side2/view_002.jpg"), "bb2");
  EXPECT_FALSE(PathExists(store.SampleDir("r") + "/side2.interrupted-1"));
  auto rec = store.LoadRecord("r");
  EXPECT_EQ((*rec)["state"], "captured");
  EXPECT_EQ((*rec)["sides"][1]["state"], "done");
  EXPECT_EQ((*rec)["sides"][1]["views"], 3);
  EXPECT_EQ(store.PrepareArm("r", SmallPlan()).error().cls, ErrorClass::kConflict);
  // Repeating it is harmless.
  auto twice = store.CompleteStored("r");
  EXPECT_TRUE(twice->sides_completed.empty());
  EXPECT_FALSE(twice->sample_completed_now);
}

// A side with a view missing is not completed: it stays re-armable from there.
TEST(SampleStore, SideWithAViewMissingStaysReArmable) {
  TempDir t;
  SampleStore store(t.path());
  ASSERT_TRUE(store.Init());
  ASSERT_TRUE(store.CreateOrResume("r", SmallPlan(), "cfg"));
  ASSERT_TRUE(store.BeginSide("r", 1));
  ASSERT_TRUE(store.WriteView("r", 1, 0, Bytes("x"), {}));
  ASSERT_TRUE(store.WriteView("r", 1, 2, Bytes("z"), {}));  // view 1 never stored
  // Image of view 1 without its sidecar: incomplete.
  ASSERT_TRUE(WriteFileAtomic(store.SampleDir("r") + "/side1/view_001.jpg", std::string_view("y")));
  auto rep = SampleStore(t.path()).Recover();
  ASSERT_TRUE(rep.ok());
  EXPECT_EQ(rep->sides_interrupted, 1);
  EXPECT_EQ(rep->sides_completed, 0);
  EXPECT_FALSE(PathExists(store.SampleDir("r") + "/side1/manifest.json"));
  EXPECT_EQ((*store.LoadRecord("r"))["state"], "interrupted");
  EXPECT_EQ(*store.PrepareArm("r", SmallPlan()), 1);
}

// Killed between side 1's manifest and its record update: the record is
// mended to "done" and re-arming resumes at side 2.
TEST(SampleStore, ManifestWithoutRecordUpdateIsDone) {
  TempDir t;
  SampleStore store(t.path());
  ASSERT_TRUE(store.Init());
  ASSERT_TRUE(store.CreateOrResume("r", SmallPlan(), "cfg"));
  ASSERT_TRUE(store.BeginSide("r", 1));
  for (int v = 0; v < 3; ++v) ASSERT_TRUE(store.WriteView("r", 1, v, Bytes("x"), {}));
  ASSERT_TRUE(store.FinishSide("r", 1));
  // What a record that lags behind looks like (the daemon's fault path marked it).
  ASSERT_TRUE(store.SetSampleState("r", "interrupted"));
  {
    auto rec = *store.LoadRecord("r");
    rec["sides"][0]["state"] = "interrupted";
    ASSERT_TRUE(
        WriteFileAtomic(store.SampleDir("r") + "/sample.json", std::string_view(rec.dump())));
  }
  auto rep = SampleStore(t.path()).Recover();
  ASSERT_TRUE(rep.ok());
  auto rec = store.LoadRecord("r");
  EXPECT_EQ((*rec)["sides"][0]["state"], "done");
  EXPECT_EQ((*rec)["state"], "interrupted");
  EXPECT_EQ(*store.PrepareArm("r", SmallPlan()), 2);
}

TEST(SampleStore, BadIdsNeverTouchTheFilesystem) {
  TempDir t;
  SampleStore store(t.path());
  ASSERT_TRUE(store.Init());
  EXPECT_EQ(store.PrepareArm("../../etc", SmallPlan()).error().cls, ErrorClass::kInvalidArgument);
  EXPECT_EQ(store.CreateOrResume("a/b", SmallPlan(), "").error().cls, ErrorClass::kInvalidArgument);
  EXPECT_EQ(store.LoadRecord("..").error().cls, ErrorClass::kInvalidArgument);
  EXPECT_EQ(store.LoadRecord("nope").error().cls, ErrorClass::kNotFound);
}

TEST(SampleStore, DamagedRecordIsRefusedNotThrown) {
  TempDir t;
  SampleStore store(t.path());
  ASSERT_TRUE(store.Init());
  ASSERT_TRUE(store.CreateOrResume("r", SmallPlan(), "cfg"));
  for (const char* bad :
       {R"({"state": "armed"})", R"({"state": "armed", "plan": 3, "sides": []})",
        R"({"state": "armed", "plan": {"sides": 2, "views_per_side": 3}, "sides": [{"x": 1}]})",
        "[1,2]", "{not json"}) {
    ASSERT_TRUE(WriteFileAtomic(store.SampleDir("r") + "/sample.json", std::string_view(bad)));
    auto rec = store.LoadRecord("r");
    ASSERT_FALSE(rec.ok()) << bad;
    EXPECT_EQ(rec.error().cls, ErrorClass::kCorrupt) << bad;
    EXPECT_EQ(store.PrepareArm("r", SmallPlan()).error().cls, ErrorClass::kCorrupt);
    EXPECT_TRUE(store.Recover().ok());  // start-up survives it
    EXPECT_EQ((*store.List())[0]["state"], "unreadable");
  }
}

TEST(SampleStore, WronglyTypedRecordFieldsAreRefusedNotThrown) {
  // Found by the sample_json fuzzer (tests/fuzz/corpus/sample_json/): a field
  // of the wrong type made json::value throw on the capture loop.
  TempDir t;
  SampleStore store(t.path());
  ASSERT_TRUE(store.Init());
  ASSERT_TRUE(store.CreateOrResume("r", SmallPlan(), "cfg"));
  const std::string plan = R"("plan": {"sides": 2, "views_per_side": 3, "step_deg": 120})";
  const std::vector<std::pair<std::string, std::string>> cases = {
      {R"({"state": "armed", "plan": {"sides": "2", "views_per_side": 3}, "sides": []})",
       "plan.sides"},
      {R"({"state": "armed", "plan": {"sides": 2, "views_per_side": 3, "step_deg": "x"}, "sides": []})",
       "plan.step_deg"},
      {R"({"state": "armed", "plan": {"sides": 18446744073709551615, "views_per_side": 3}, "sides": []})",
       "plan.sides"},
      {R"({"state": "armed", )" + plan + R"(, "sides": [{"side": 1, "state": 5}]})",
       "side's state"},
      {R"({"state": "armed", )" + plan + R"(, "sides": [{"side": 1, "attempts": 2147483647}]})",
       "attempts"},
      {R"({"state": "armed", "resumes": "1", )" + plan + R"(, "sides": []})", "resumes"},
      {R"({"state": "armed", "created_utc": 7, )" + plan + R"(, "sides": []})", "created_utc"},
  };
  for (const auto& [bad, field] : cases) {
    ASSERT_TRUE(WriteFileAtomic(store.SampleDir("r") + "/sample.json", std::string_view(bad)));
    auto rec = store.LoadRecord("r");
    ASSERT_FALSE(rec.ok()) << bad;
    EXPECT_EQ(rec.error().cls, ErrorClass::kCorrupt) << bad;
    EXPECT_NE(rec.error().message.find(field), std::string::npos) << rec.error().message;
    EXPECT_EQ(store.PrepareArm("r", SmallPlan()).error().cls, ErrorClass::kCorrupt);
    EXPECT_FALSE(store.CreateOrResume("r", SmallPlan(), "cfg").ok());
    EXPECT_TRUE(store.Recover().ok());
    EXPECT_EQ((*store.List())[0]["state"], "unreadable");
    EXPECT_TRUE(store.CapturedWork().empty());
  }
}

// A sidecar with a field of the wrong type is refused before anything of the
// view is stored (a damaged one on disk is described as far as it reads:
// SampleFiles.DescribeShowsWhatADamagedSidecarStillHolds).
TEST(SampleStore, AWronglyTypedSidecarIsRefusedAndNothingLands) {
  TempDir t;
  SampleStore store(t.path());
  ASSERT_TRUE(store.Init());
  ASSERT_TRUE(store.CreateOrResume("r", SmallPlan(), "cfg"));
  ASSERT_TRUE(store.BeginSide("r", 1));
  const Status s = store.WriteView(
      "r", 1, 0, Bytes("x"),
      {{"commanded_angle_deg", "zero"}, {"measured_angle_deg", 30.5}, {"capture_utc", 12}});
  ASSERT_FALSE(s.ok());
  EXPECT_NE(s.error().message.find("commanded_angle_deg"), std::string::npos) << s.error().message;
  EXPECT_FALSE(PathExists(store.SampleDir("r") + "/side1/view_000.jpg"));
  EXPECT_FALSE(PathExists(store.SampleDir("r") + "/side1/view_000.json"));
}

TEST(SampleStore, DamagedCalibrationWithBytesThatAreNotUtf8IsRecordedNotThrown) {
  // Found by the sample_json fuzzer: the parser's message quotes the damaged
  // file's bytes, and the record holding that reason could not be written.
  TempDir t;
  SampleStore store(t.path());
  ASSERT_TRUE(store.Init());
  ASSERT_TRUE(WriteFileAtomic(t.path() + "/calibration.json",
                              std::string_view("{\"format\": \"\xff\xfe\"}")));
  ASSERT_TRUE(store.CreateOrResume("r", SmallPlan(), "cfg"));
  auto rec = store.LoadRecord("r");
  ASSERT_TRUE(rec.ok()) << rec.error().ToString();
  EXPECT_TRUE((*rec)["calibration"]["file"].is_null());
  const std::string reason = (*rec)["calibration"]["reason"].get<std::string>();
  EXPECT_NE(reason.find("not valid JSON"), std::string::npos) << reason;
  EXPECT_NE(reason.find("\xEF\xBF\xBD"), std::string::npos) << reason;  // U+FFFD for the bad bytes
  EXPECT_FALSE(PathExists(store.SampleDir("r") + "/calibration.json"));
}

TEST(SampleStore, DirectoryWithoutRecordIsArmable) {
  // A crash between creating the directory and writing the record.
  TempDir t;
  SampleStore store(t.path());
  ASSERT_TRUE(store.Init());
  ASSERT_TRUE(MakeDirsDurable(store.SampleDir("orphan")));
  EXPECT_EQ(*store.PrepareArm("orphan", SmallPlan()), 1);
  ASSERT_TRUE(store.CreateOrResume("orphan", SmallPlan(), "cfg"));
  EXPECT_EQ((*store.LoadRecord("orphan"))["state"], "armed");
}

TEST(SampleStore, CapturedWorkListsFinishedSidesAndSamples) {
  TempDir t;
  SampleStore store(t.path());
  ASSERT_TRUE(store.Init());
  ASSERT_TRUE(store.CreateOrResume("a", SmallPlan(), "cfg"));
  ASSERT_TRUE(store.BeginSide("a", 1));
  ASSERT_TRUE(store.WriteView("a", 1, 0, Bytes("x"), {}));
  ASSERT_TRUE(store.FinishSide("a", 1));
  ASSERT_TRUE(store.BeginSide("a", 2));
  ASSERT_TRUE(store.WriteView("a", 2, 0, Bytes("y"), {}));  // side 2 unfinished
  auto work = store.CapturedWork();
  ASSERT_EQ(work.size(), 1u);
  EXPECT_EQ(work[0], std::make_pair(std::string("a"), 1));
  ASSERT_TRUE(store.FinishSide("a", 2));
  ASSERT_TRUE(store.SetSampleState("a", "captured"));
  EXPECT_EQ(store.CapturedWork().size(), 3u);
}

TEST(JobQueue, OrderClaimCompleteAndRequeue) {
  TempDir t;
  auto q = JobQueue::Open(t.path() + "/queue.db");
  ASSERT_TRUE(q.ok()) << q.error().ToString();
  auto& queue = **q;
  auto a = queue.Enqueue("r1", 1);
  auto b = queue.Enqueue("r1", 2);
  auto dup = queue.Enqueue("r1", 1);
  ASSERT_TRUE(a.ok() && b.ok() && dup.ok());
  EXPECT_EQ(*dup, *a);  // not queued twice
  queue.Enqueue("r1", 0).value();
  EXPECT_EQ(*queue.Depth(), 3);
  auto j1 = queue.ClaimNext();
  ASSERT_TRUE(j1.ok() && j1->has_value());
  EXPECT_EQ((*j1)->side, 1);
  EXPECT_EQ((*j1)->state, "running");
  EXPECT_EQ((*j1)->attempts, 0);  // claiming is no attempt
  // The worker is killed: the running job goes back to the queue, uncounted.
  auto rq = queue.RequeueRunning(10);
  ASSERT_TRUE(rq.ok());
  EXPECT_EQ(rq->requeued, 1);
  EXPECT_EQ(rq->failed, 0);
  auto j1b = queue.ClaimNext();
  EXPECT_EQ((*j1b)->id, (*j1)->id);
  EXPECT_EQ((*j1b)->attempts, 0);
  EXPECT_EQ((*j1b)->interruptions, 1);
  ASSERT_TRUE(queue.Complete((*j1b)->id));
  auto j2 = queue.ClaimNext();
  EXPECT_EQ((*j2)->side, 2);
  ASSERT_TRUE(queue.Fail((*j2)->id, "bad image", /*requeue=*/false));
  auto j3 = queue.ClaimNext();
  EXPECT_EQ((*j3)->side, 0);
  ASSERT_TRUE(queue.Complete((*j3)->id));
  EXPECT_FALSE(queue.ClaimNext()->has_value());
  EXPECT_EQ(*queue.Depth(), 0);
  auto jobs = queue.JobsForSample("r1");
  ASSERT_EQ(jobs->size(), 3u);
  EXPECT_EQ((*jobs)[0].interruptions, 0);  // completion ends the run of interruptions
  EXPECT_EQ((*jobs)[1].state, "failed");
  EXPECT_EQ((*jobs)[1].error, "bad image");
  EXPECT_EQ((*jobs)[1].attempts, 1);
  EXPECT_EQ(queue.Complete(999).error().cls, ErrorClass::kNotFound);
}

// Attempts count failures and crashes; stops and kills do not.
TEST(JobQueue, AttemptsCountFailuresNotStopsOrKills) {
  TempDir t;
  auto q = JobQueue::Open(t.path() + "/queue.db");
  ASSERT_TRUE(q.ok()) << q.error().ToString();
  auto& queue = **q;
  const int64_t id = queue.Enqueue("r1", 1).value();
  for (int i = 0; i < 5; ++i) {  // stopped by SIGTERM five times
    auto j = queue.ClaimNext();
    ASSERT_TRUE(j.ok() && j->has_value());
    ASSERT_TRUE(queue.Release(id));
  }
  for (int i = 0; i < 5; ++i) {  // the whole worker killed five times
    ASSERT_TRUE(queue.ClaimNext()->has_value());
    ASSERT_EQ(queue.RequeueRunning(10)->requeued, 1);
  }
  auto j = queue.ClaimNext();
  ASSERT_TRUE(j->has_value());
  EXPECT_EQ((*j)->attempts, 0);
  EXPECT_EQ((*j)->interruptions, 5);
  // A release of a job that is not running is refused.
  ASSERT_TRUE(queue.Fail(id, "crashed with SIGABRT in stage masks side 1", /*requeue=*/true));
  EXPECT_EQ(queue.Release(id).error().cls, ErrorClass::kNotFound);
  j = queue.ClaimNext();
  EXPECT_EQ((*j)->attempts, 1);
  EXPECT_EQ((*j)->interruptions, 0);  // an attempt that ended resets the interruptions
  EXPECT_EQ((*j)->error, "crashed with SIGABRT in stage masks side 1");
  ASSERT_TRUE(queue.Fail(id, "second", true));
  ASSERT_TRUE(queue.ClaimNext()->has_value());
  ASSERT_TRUE(queue.Fail(id, "third", false));
  auto jobs = queue.JobsForSample("r1");
  ASSERT_EQ(jobs->size(), 1u);
  EXPECT_EQ((*jobs)[0].state, "failed");
  EXPECT_EQ((*jobs)[0].attempts, 3);
  EXPECT_EQ((*jobs)[0].error, "third");
}

// A job that gets the whole worker killed every time (OOM) is failed after
// max_interruptions starts in a row, and the queue moves on.
TEST(JobQueue, RepeatedInterruptionsFailTheJob) {
  TempDir t;
  auto q = JobQueue::Open(t.path() + "/queue.db");
  ASSERT_TRUE(q.ok()) << q.error().ToString();
  auto& queue = **q;
  const int64_t id = queue.Enqueue("r1", 1).value();
  queue.Enqueue("r2", 1).value();
  for (int i = 1; i <= 4; ++i) {
    auto j = queue.ClaimNext();
    ASSERT_TRUE(j->has_value());
    EXPECT_EQ((*j)->id, id);
    auto rq = queue.RequeueRunning(4);
    ASSERT_TRUE(rq.ok());
    EXPECT_EQ(rq->requeued, i < 4 ? 1 : 0) << i;
    EXPECT_EQ(rq->failed, i < 4 ? 0 : 1) << i;
  }
  auto jobs = queue.JobsForSample("r1");
  EXPECT_EQ((*jobs)[0].state, "failed");
  EXPECT_EQ((*jobs)[0].attempts, 0);
  EXPECT_NE((*jobs)[0].error.find("interrupted 4 times"), std::string::npos) << (*jobs)[0].error;
  EXPECT_NE((*jobs)[0].error.find("out of memory"), std::string::npos) << (*jobs)[0].error;
  auto next = queue.ClaimNext();
  ASSERT_TRUE(next->has_value());
  EXPECT_EQ((*next)->sample_id, "r2");
}

TEST(JobQueue, RetryRequeuesFailedJobsWithAttemptsReset) {
  TempDir t;
  auto q = JobQueue::Open(t.path() + "/queue.db");
  ASSERT_TRUE(q.ok()) << q.error().ToString();
  auto& queue = **q;
  const int64_t s1 = queue.Enqueue("r1", 1).value();
  const int64_t s2 = queue.Enqueue("r1", 2).value();
  queue.Enqueue("r2", 1).value();
  ASSERT_TRUE(queue.ClaimNext()->has_value());
  ASSERT_TRUE(queue.Fail(s1, "bad photo", false));
  ASSERT_TRUE(queue.ClaimNext()->has_value());
  ASSERT_TRUE(queue.Complete(s2));
  EXPECT_EQ(*queue.FailedCount(), 1);
  auto failed = queue.FailedJobs(10);
  ASSERT_TRUE(failed.ok());
  ASSERT_EQ(failed->size(), 1u);
  EXPECT_EQ((*failed)[0].sample_id, "r1");
  EXPECT_EQ((*failed)[0].side, 1);
  EXPECT_EQ((*failed)[0].error, "bad photo");
  // Nothing failed for r2: refused, saying so.
  auto none = queue.Retry("r2");
  ASSERT_FALSE(none.ok());
  EXPECT_EQ(none.error().cls, ErrorClass::kNotFound);
  EXPECT_NE(none.error().message.find("no failed job"), std::string::npos) << none.error().message;
  auto n = queue.Retry("r1");
  ASSERT_TRUE(n.ok()) << n.error().ToString();
  EXPECT_EQ(*n, 1);
  EXPECT_EQ(*queue.FailedCount(), 0);
  auto jobs = queue.JobsForSample("r1");
  EXPECT_EQ((*jobs)[0].state, "queued");
  EXPECT_EQ((*jobs)[0].attempts, 0);
  EXPECT_EQ((*jobs)[0].error, "");
  EXPECT_EQ((*jobs)[1].state, "done");   // untouched
  EXPECT_FALSE(queue.Retry("r1").ok());  // nothing failed any more
}

// A queue written before the interruption counter existed opens, keeps its
// jobs, and gets the column.
TEST(JobQueue, OldQueueDatabaseIsMigrated) {
  TempDir t;
  const std::string path = t.path() + "/queue.db";
  {
    sqlite3* db = nullptr;
    ASSERT_EQ(sqlite3_open(path.c_str(), &db), SQLITE_OK);
    ASSERT_EQ(
        sqlite3_exec(
            db,
            "CREATE TABLE jobs (id INTEGER PRIMARY KEY AUTOINCREMENT, sample_id TEXT NOT NULL,"
            " side INTEGER NOT NULL, state TEXT NOT NULL CHECK (state IN "
            "('queued','running','done','failed')), attempts INTEGER NOT NULL DEFAULT 0, error "
            "TEXT,"
            " created_utc TEXT NOT NULL, updated_utc TEXT NOT NULL);"
            "INSERT INTO jobs(sample_id, side, state, attempts, created_utc, updated_utc) VALUES "
            "('old', 1, 'running', 2, 'x', 'x');",
            nullptr, nullptr, nullptr),
        SQLITE_OK);
    sqlite3_close(db);
  }
  for (int open = 0; open < 2; ++open) {  // the second open finds the column there
    auto q = JobQueue::Open(path);
    ASSERT_TRUE(q.ok()) << q.error().ToString();
    auto jobs = (*q)->JobsForSample("old");
    ASSERT_TRUE(jobs.ok()) << jobs.error().ToString();
    ASSERT_EQ(jobs->size(), 1u);
    EXPECT_EQ((*jobs)[0].attempts, 2);
    EXPECT_EQ((*jobs)[0].interruptions, open);
    ASSERT_EQ((*q)->RequeueRunning(10)->requeued, 1);
    ASSERT_TRUE((*q)->ClaimNext()->has_value());
  }
}

TEST(JobQueue, TwoProcessesShareTheQueue) {
  TempDir t;
  const std::string path = t.path() + "/queue.db";
  auto producer = JobQueue::Open(path);
  auto consumer = JobQueue::Open(path);
  ASSERT_TRUE(producer.ok() && consumer.ok());
  std::thread prod([&] {
    for (int i = 0; i < 50; ++i) (*producer)->Enqueue("s" + std::to_string(i), 1).value();
  });
  int claimed = 0;
  for (int spins = 0; claimed < 50 && spins < 100000; ++spins) {
    auto j = (*consumer)->ClaimNext();
    ASSERT_TRUE(j.ok()) << j.error().ToString();
    if (j->has_value()) {
      EXPECT_EQ((*j)->sample_id, "s" + std::to_string(claimed));
      ASSERT_TRUE((*consumer)->Complete((*j)->id));
      ++claimed;
    }
  }
  prod.join();
  EXPECT_EQ(claimed, 50);
}

// The worker's report: read back as written, aged on the boot clock by the
// reader (another connection, as aggscand's is), replaced by the next one,
// and not taken for this boot's when an earlier boot wrote it.
TEST(JobQueue, WorkerReportIsReadBackWithItsAge) {
  TempDir t;
  const std::string path = t.path() + "/queue.db";
  auto worker = JobQueue::Open(path);
  auto daemon = JobQueue::Open(path);
  ASSERT_TRUE(worker.ok() && daemon.ok());
  auto none = (*daemon)->Worker();
  ASSERT_TRUE(none.ok()) << none.error().ToString();
  EXPECT_FALSE(none->has_value());

  const int64_t t0 = BootTimeNs();
  WorkerReport r;
  r.pid = 4242;
  r.state = "busy";
  r.job_id = 7;
  r.sample_id = "rock-3";
  r.side = 2;
  r.stage = "masks side 2 view 5";
  r.done = 4;
  r.total = 30;
  r.started_boot_ns = t0 - 60'000'000'000;      // a minute ago
  r.job_started_boot_ns = t0 - 12'000'000'000;  // 12 s ago
  r.stage_since_boot_ns = t0 - 2'000'000'000;   // 2 s ago
  ASSERT_TRUE((*worker)->ReportWorker(r).ok());
  auto seen = (*daemon)->Worker();
  ASSERT_TRUE(seen.ok() && seen->has_value());
  const WorkerSeen& w = **seen;
  EXPECT_TRUE(w.this_boot);
  EXPECT_EQ(w.report.pid, 4242);
  EXPECT_EQ(w.report.state, "busy");
  EXPECT_EQ(w.report.job_id, 7);
  EXPECT_EQ(w.report.sample_id, "rock-3");
  EXPECT_EQ(w.report.side, 2);
  EXPECT_EQ(w.report.stage, "masks side 2 view 5");
  EXPECT_EQ(w.report.done, 4);
  EXPECT_EQ(w.report.total, 30);
  EXPECT_GE(w.heard_s_ago, 0.0);
  EXPECT_LT(w.heard_s_ago, 5.0);
  EXPECT_NEAR(w.up_s, 60.0, 5.0);
  EXPECT_NEAR(w.job_s, 12.0, 5.0);
  EXPECT_NEAR(w.stage_s, 2.0, 5.0);
  EXPECT_EQ(w.heard_utc.size(), std::string("2026-01-01T00:00:00.000Z").size()) << w.heard_utc;

  r.state = "idle";
  r.job_id = 0;
  ASSERT_TRUE((*worker)->ReportWorker(r).ok());
  seen = (*daemon)->Worker();
  ASSERT_TRUE(seen.ok() && seen->has_value());
  EXPECT_EQ((*seen)->report.state, "idle");
  EXPECT_EQ((*seen)->report.job_id, 0);

  // The connection goes on with jobs after a report.
  ASSERT_TRUE((*worker)->Enqueue("rock-4", 1).ok());
  ASSERT_TRUE((*worker)->ClaimNext()->has_value());
  sqlite3* db = nullptr;
  ASSERT_EQ(sqlite3_open(path.c_str(), &db), SQLITE_OK);
  ASSERT_EQ(
      sqlite3_exec(db, "UPDATE worker SET boot_id='an-earlier-boot'", nullptr, nullptr, nullptr),
      SQLITE_OK);
  sqlite3_close(db);
  seen = (*daemon)->Worker();
  ASSERT_TRUE(seen.ok() && seen->has_value());
  EXPECT_FALSE((*seen)->this_boot);
  EXPECT_EQ((*seen)->heard_s_ago, 0.0);
}

TEST(JobQueue, UnwritableLocationIsAClearError) {
  auto q = JobQueue::Open("/nonexistent-dir/queue.db");
  ASSERT_FALSE(q.ok());
  EXPECT_NE(q.error().message.find("/nonexistent-dir/queue.db"), std::string::npos);
}

}  // namespace
}  // namespace aggscan
