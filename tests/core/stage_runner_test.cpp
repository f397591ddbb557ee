// The stage runner: a declared list of stages over a sample directory, each
// kept only while its fingerprint matches the ledger's.
#include "pipeline/core/stage_runner.h"

#include <gtest/gtest.h>

#include <atomic>
#include <filesystem>
#include <map>
#include <string>
#include <vector>

#include "common/fsutil.h"
#include "tests/util/temp_dir.h"

namespace aggscan {
namespace {

namespace fs = std::filesystem;

class StageRunnerTest : public ::testing::Test {
 protected:
  void SetUp() override { fs::create_directories(dir_ + "/results"); }

  // Three stages a -> b -> c, each writing results/<name>.txt holding its
  // fingerprint and counting its runs; b also writes partial work and
  // can be made to fail once.
  std::vector<StageDecl> Job(const std::map<std::string, std::string>& fp) {
    std::vector<StageDecl> job;
    for (const std::string name : {"a", "b", "c"}) {
      job.push_back(
          {name,
           name == "b" ? "b-family" : "",
           fp.at(name),
           {"results/" + name + ".txt"},
           name == "b" ? std::vector<std::string>{"work/b"} : std::vector<std::string>{},
           [this, name, f = fp.at(name)](StageContext& ctx) -> Status {
             seen_reused_[name] = ctx.reused();
             if (ctx.reused()) return OkStatus();
             ++runs_[name];
             if (name == "b") {
               fs::create_directories(dir_ + "/work/b");
               partial_at_start_ = PathExists(dir_ + "/work/b/partial");
               if (Status s = WriteFileAtomic(dir_ + "/work/b/partial", std::string_view("x"));
                   !s) {
                 return s;
               }
               if (fail_b_) {
                 fail_b_ = false;
                 return MakeError(ErrorClass::kIo, "b failed");
               }
             }
             if (name == "c" && cancel_in_c_) cancel_ = true;
             if (Status s = ctx.CheckCancelled("in the middle"); !s) return s;
             return WriteFileAtomic(dir_ + "/results/" + name + ".txt", std::string_view(f));
           }});
    }
    return job;
  }

  test::TempDir tmp_;
  std::string dir_ = tmp_.path();
  std::map<std::string, int> runs_;
  std::map<std::string, bool> seen_reused_;
  bool fail_b_ = false;
  bool cancel_in_c_ = false;
  bool partial_at_start_ = false;
  std::atomic<bool> cancel_{false};
};

const std::map<std::string, std::string> kFp = {{"a", "1"}, {"b", "2"}, {"c", "3"}};

TEST_F(StageRunnerTest, FinishedStagesWithTheSameFingerprintAreKept) {
  auto first = RunStages(dir_, Job(kFp), {});
  ASSERT_TRUE(first.ok()) << first.error().ToString();
  EXPECT_EQ(first->ran, (std::vector<std::string>{"a", "b", "c"}));
  auto second = RunStages(dir_, Job(kFp), {});
  ASSERT_TRUE(second.ok()) << second.error().ToString();
  EXPECT_TRUE(second->ran.empty());
  EXPECT_EQ(second->kept, (std::vector<std::string>{"a", "b", "c"}));
  EXPECT_EQ(runs_["a"], 1);
  EXPECT_EQ(runs_["c"], 1);
  EXPECT_TRUE(seen_reused_["c"]);  // the kept stage was still called, to load its result
  auto ledger = ReadStageLedger(dir_);
  ASSERT_TRUE(ledger.ok());
  EXPECT_EQ((*ledger)["stages"]["b"]["fingerprint"], "2");
  EXPECT_TRUE((*ledger)["stages"]["b"]["finished"].get<bool>());
  EXPECT_TRUE(second->seconds.contains("b"));
}

TEST_F(StageRunnerTest, AChangedFingerprintRerunsThatStageAndEveryLaterOne) {
  ASSERT_TRUE(RunStages(dir_, Job(kFp), {}).ok());
  auto fp = kFp;
  fp["b"] = "2'";  // other options for b only: c's own fingerprint is unchanged
  auto r = RunStages(dir_, Job(fp), {});
  ASSERT_TRUE(r.ok()) << r.error().ToString();
  EXPECT_EQ(r->kept, (std::vector<std::string>{"a"}));
  EXPECT_EQ(r->ran, (std::vector<std::string>{"b", "c"}));
  EXPECT_EQ(runs_["b"], 2);
  EXPECT_EQ(runs_["c"], 2);
  // The earlier run's work was removed before b ran afresh.
  EXPECT_FALSE(partial_at_start_);
  EXPECT_EQ(*ReadFile(dir_ + "/results/b.txt"), "2'");
}

TEST_F(StageRunnerTest, AMissingOutputOrFromRerunsFromThere) {
  ASSERT_TRUE(RunStages(dir_, Job(kFp), {}).ok());
  fs::remove(dir_ + "/results/c.txt");
  auto r = RunStages(dir_, Job(kFp), {});
  ASSERT_TRUE(r.ok());
  EXPECT_EQ(r->ran, (std::vector<std::string>{"c"}));

  StageRunOptions from;
  from.from = "b-family";  // a family names its stages
  r = RunStages(dir_, Job(kFp), from);
  ASSERT_TRUE(r.ok());
  EXPECT_EQ(r->ran, (std::vector<std::string>{"b", "c"}));
  from.from = "a";
  r = RunStages(dir_, Job(kFp), from);
  ASSERT_TRUE(r.ok());
  EXPECT_EQ(r->ran, (std::vector<std::string>{"a", "b", "c"}));

  from.from = "colour";
  r = RunStages(dir_, Job(kFp), from);
  ASSERT_FALSE(r.ok());
  EXPECT_EQ(r.error().cls, ErrorClass::kInvalidArgument);
  EXPECT_NE(r.error().message.find("a, b-family, c"), std::string::npos) << r.error().message;
}

TEST_F(StageRunnerTest, TheLogSaysWhyEachStageRunsAgain) {
  ASSERT_TRUE(RunStages(dir_, Job(kFp), {}).ok());
  auto fp = kFp;
  fp["a"] = "1'";  // a's options changed; b and c are the same but follow a
  StageRunOptions from;
  from.from = "c";  // asked for c only: a and b run for their own reasons
  testing::internal::CaptureStderr();
  auto r = RunStages(dir_, Job(fp), from);
  const std::string log = testing::internal::GetCapturedStderr();
  ASSERT_TRUE(r.ok()) << r.error().ToString();
  EXPECT_EQ(r->ran, (std::vector<std::string>{"a", "b", "c"}));
  EXPECT_NE(log.find("a: runs again (other options or inputs)"), std::string::npos) << log;
  EXPECT_NE(log.find("b: runs again (an earlier stage ran again)"), std::string::npos) << log;
  EXPECT_NE(log.find("c: runs again (asked from c)"), std::string::npos) << log;

  fs::remove(dir_ + "/results/b.txt");
  testing::internal::CaptureStderr();
  r = RunStages(dir_, Job(fp), {});
  const std::string log2 = testing::internal::GetCapturedStderr();
  ASSERT_TRUE(r.ok()) << r.error().ToString();
  EXPECT_NE(log2.find("b: runs again (an output is missing)"), std::string::npos) << log2;
  EXPECT_NE(log2.find("c: runs again (an earlier stage ran again)"), std::string::npos) << log2;
}

TEST_F(StageRunnerTest, AStageThatStoppedResumesInPlaceWithItsPartialWork) {
  fail_b_ = true;
  auto r = RunStages(dir_, Job(kFp), {});
  ASSERT_FALSE(r.ok());
  EXPECT_EQ(r.error().message, "b failed");
  auto ledger = ReadStageLedger(dir_);
  ASSERT_TRUE(ledger.ok());
  EXPECT_FALSE((*ledger)["stages"]["b"]["finished"].get<bool>());
  EXPECT_FALSE((*ledger)["stages"].contains("c"));

  r = RunStages(dir_, Job(kFp), {});
  ASSERT_TRUE(r.ok()) << r.error().ToString();
  EXPECT_EQ(r->kept, (std::vector<std::string>{"a"}));
  EXPECT_EQ(r->resumed, (std::vector<std::string>{"b"}));
  EXPECT_EQ(r->ran, (std::vector<std::string>{"c"}));
  EXPECT_TRUE(partial_at_start_);  // the same fingerprint: b's partial work kept
  EXPECT_EQ(runs_["a"], 1);
}

TEST_F(StageRunnerTest, CancellationIsItsOwnErrorClassAndResumes) {
  cancel_in_c_ = true;
  StageRunOptions o;
  o.cancel = &cancel_;
  auto r = RunStages(dir_, Job(kFp), o);
  ASSERT_FALSE(r.ok());
  EXPECT_EQ(r.error().cls, ErrorClass::kCancelled);
  EXPECT_NE(r.error().message.find("stage c"), std::string::npos) << r.error().message;
  // Cancelled before a stage starts.
  r = RunStages(dir_, Job(kFp), o);
  ASSERT_FALSE(r.ok());
  EXPECT_EQ(r.error().cls, ErrorClass::kCancelled);
  EXPECT_NE(r.error().message.find("before stage a"), std::string::npos) << r.error().message;

  cancel_in_c_ = false;
  cancel_ = false;
  r = RunStages(dir_, Job(kFp), o);
  ASSERT_TRUE(r.ok()) << r.error().ToString();
  EXPECT_EQ(r->resumed, (std::vector<std::string>{"c"}));
}

TEST_F(StageRunnerTest, AnExceptionInAStageIsAnErrorNamingIt) {
  std::vector<StageDecl> job = {{"boom", "", "1", {}, {}, [](StageContext&) -> Status {
                                   throw std::runtime_error("library said no");
                                 }}};
  auto r = RunStages(dir_, job, {});
  ASSERT_FALSE(r.ok());
  EXPECT_NE(r.error().ToString().find("boom"), std::string::npos) << r.error().ToString();
  EXPECT_NE(r.error().ToString().find("library said no"), std::string::npos);
}

// Results without a ledger entry (made before the ledger, or put in place
// by hand): every such stage continues from them, none is kept as it is;
// an unrecorded stage without results, and every one after it, runs afresh.
TEST_F(StageRunnerTest, UnrecordedResultsAreContinuedFrom) {
  ASSERT_TRUE(RunStages(dir_, Job(kFp), {}).ok());
  ASSERT_TRUE(WriteFileAtomic(dir_ + "/results/stages.json", std::string_view("{not json")).ok());
  auto r = RunStages(dir_, Job(kFp), {});
  ASSERT_TRUE(r.ok());
  EXPECT_EQ(r->resumed, (std::vector<std::string>{"a", "b", "c"}));
  EXPECT_TRUE(r->kept.empty());
  EXPECT_TRUE(partial_at_start_);  // b's earlier work there to continue from

  // Neither b's result nor its work: b runs afresh, and so does c, whose
  // result was made from an older b.
  fs::remove(dir_ + "/results/stages.json");
  fs::remove(dir_ + "/results/b.txt");
  fs::remove_all(dir_ + "/work/b");
  r = RunStages(dir_, Job(kFp), {});
  ASSERT_TRUE(r.ok());
  EXPECT_EQ(r->resumed, (std::vector<std::string>{"a"}));
  EXPECT_EQ(r->ran, (std::vector<std::string>{"b", "c"}));
  EXPECT_FALSE(partial_at_start_);
  EXPECT_EQ(runs_["c"], 3);
}

// A stage that resumes (it stopped with these options): a later stage the
// ledger holds as finished is not kept, since it may be older than what the
// resumed stage finishes now; it runs afresh.
TEST_F(StageRunnerTest, AfterAResumedStageRecordedLaterStagesRunAfresh) {
  ASSERT_TRUE(RunStages(dir_, Job(kFp), {}).ok());
  // b asked for again and stopped: a's and c's entries still say finished.
  fail_b_ = true;
  StageRunOptions from;
  from.from = "b";
  ASSERT_FALSE(RunStages(dir_, Job(kFp), from).ok());
  auto r = RunStages(dir_, Job(kFp), {});
  ASSERT_TRUE(r.ok()) << r.error().ToString();
  EXPECT_EQ(r->kept, (std::vector<std::string>{"a"}));
  EXPECT_EQ(r->resumed, (std::vector<std::string>{"b"}));
  EXPECT_EQ(r->ran, (std::vector<std::string>{"c"}));
  EXPECT_EQ(runs_["c"], 2);
}

TEST(Fingerprint, FieldsAreDelimitedAndFilesCount) {
  EXPECT_NE(Fingerprint().Add("x", std::string_view("ab")).Add("y", std::string_view("c")).Hex(),
            Fingerprint().Add("x", std::string_view("a")).Add("y", std::string_view("bc")).Hex());
  EXPECT_EQ(Fingerprint().Add("x", nlohmann::json{{"k", 1}}).Hex(),
            Fingerprint().Add("x", nlohmann::json{{"k", 1}}).Hex());
  EXPECT_EQ(Fingerprint().Hex().size(), 16u);
  const std::string f = (fs::temp_directory_path() / "fp-file-test").string();
  fs::remove(f);
  Fingerprint absent, one, two;
  ASSERT_TRUE(absent.AddFile("f", f).ok());
  ASSERT_TRUE(WriteFileAtomic(f, std::string_view("1")).ok());
  ASSERT_TRUE(one.AddFile("f", f).ok());
  ASSERT_TRUE(WriteFileAtomic(f, std::string_view("2")).ok());
  ASSERT_TRUE(two.AddFile("f", f).ok());
  EXPECT_NE(absent.Hex(), one.Hex());
  EXPECT_NE(one.Hex(), two.Hex());
  fs::remove(f);
}

}  // namespace
}  // namespace aggscan
