#include "pipeline/core/stage.h"

#include <gtest/gtest.h>

#include <condition_variable>
#include <mutex>
#include <new>
#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>
#include <stdexcept>
#include <string>
#include <thread>
#include <vector>

namespace aggscan {
namespace {

std::vector<std::string> g_seen;
void Record(const char* stage, int, int) { g_seen.emplace_back(stage); }

std::vector<std::string> g_progress;  // "stage done/total"
void RecordProgress(const char* stage, int done, int total) {
  g_progress.push_back(std::string(stage) + " " + std::to_string(done) + "/" +
                       std::to_string(total));
}

TEST(RunStage, LibraryExceptionsBecomeNamedErrors) {
  // A real OpenCV assertion: a blur kernel on an empty image.
  Status cv_err = RunStage("masks side 1 view 3", []() -> Status {
    cv::Mat empty, out;
    cv::GaussianBlur(empty, out, cv::Size(5, 5), 0);
    return OkStatus();
  });
  ASSERT_FALSE(cv_err.ok());
  EXPECT_EQ(cv_err.error().cls, ErrorClass::kCorrupt);
  EXPECT_NE(
      cv_err.error().message.find("stage \"masks side 1 view 3\" failed: OpenCV refused its data"),
      std::string::npos)
      << cv_err.error().message;
  EXPECT_NE(cv_err.error().message.find("retry the sample"), std::string::npos)
      << cv_err.error().message;
  EXPECT_NE(cv_err.error().detail.find("Assertion failed"), std::string::npos)
      << cv_err.error().detail;

  Result<int> oom = RunStage("surface", []() -> Result<int> { throw std::bad_alloc(); });
  ASSERT_FALSE(oom.ok());
  EXPECT_NE(oom.error().message.find("stage \"surface\" failed: out of memory"), std::string::npos)
      << oom.error().message;

  // std::vector's own check of an absurd count (what a mesh header of 2^63 faces gives).
  Status len = RunStage("morphology", []() -> Status {
    std::vector<double> v;
    v.reserve(v.max_size() + 1);
    return OkStatus();
  });
  ASSERT_FALSE(len.ok());
  EXPECT_EQ(len.error().cls, ErrorClass::kCorrupt);
  EXPECT_NE(len.error().message.find("stage \"morphology\" failed: a size out of range"),
            std::string::npos)
      << len.error().message;

  Status other =
      RunStage("poses side 2", []() -> Status { throw std::runtime_error("ceres: bad residual"); });
  ASSERT_FALSE(other.ok());
  EXPECT_EQ(other.error().cls, ErrorClass::kInternal);
  EXPECT_NE(other.error().message.find(
                "stage \"poses side 2\" failed: unexpected library error (ceres: bad residual)"),
            std::string::npos)
      << other.error().message;

  Status odd = RunStage("stitch", []() -> Status { throw 42; });
  ASSERT_FALSE(odd.ok());
  EXPECT_NE(odd.error().message.find("stage \"stitch\" failed: unknown exception"),
            std::string::npos);

  // Error values pass through unchanged.
  Status value =
      RunStage("stitch", [] { return Status(MakeError(ErrorClass::kNotFound, "no markers")); });
  ASSERT_FALSE(value.ok());
  EXPECT_EQ(value.error().message, "no markers");
}

TEST(RunStage, InnermostStageIsNamedAndObserved) {
  g_seen.clear();
  SetStageObserver(Record);
  Status st = RunStage("job", []() -> Status {
    Status inner = RunStage("masks side 1", []() -> Status {
      const StageScope view("masks side 1 view 4");
      EXPECT_EQ(CurrentStage(), "masks side 1 view 4");
      throw std::length_error("vector");
    });
    EXPECT_EQ(CurrentStage(), "job");
    return inner;
  });
  SetStageObserver(nullptr);
  ASSERT_FALSE(st.ok());
  EXPECT_NE(st.error().message.find("stage \"masks side 1 view 4\" failed"), std::string::npos)
      << st.error().message;
  EXPECT_EQ(CurrentStage(), "");
  EXPECT_EQ(g_seen, (std::vector<std::string>{"job", "masks side 1", "masks side 1 view 4",
                                              "masks side 1", "job", ""}));
}

// Views masked side by side on two threads: while both run, the innermost
// stage is both of them (a crash names every view in flight); each ends its
// own frame whatever the order; progress goes to the stage around them.
TEST(RunStage, ConcurrentStagesAreNamedTogetherAndEndInAnyOrder) {
  const StageScope side("masks side 1");
  ReportStageProgress(0, 4);
  std::mutex mu;
  std::condition_variable cv;
  int step = 0;
  auto wait_for = [&](int s) {
    std::unique_lock<std::mutex> lock(mu);
    cv.wait(lock, [&] { return step >= s; });
  };
  auto advance = [&] {
    std::lock_guard<std::mutex> lock(mu);
    ++step;
    cv.notify_all();
  };
  std::string both, after_first_ended;
  std::thread a([&] {
    const StageScope view("masks side 1 view 6", /*concurrent=*/true);
    advance();  // 1: view 6 runs
    wait_for(2);
    both = CurrentStage();
    ReportStageProgress(1, 4);
    advance();  // 3: view 6 ends first though it started first
  });
  std::thread b([&] {
    wait_for(1);
    {
      const StageScope view("masks side 1 view 7", /*concurrent=*/true);
      advance();  // 2: view 7 runs beside it
      wait_for(3);
    }
  });
  wait_for(3);
  a.join();
  // view 6 has ended while view 7 may still be running.
  after_first_ended = CurrentStage();
  b.join();
  EXPECT_EQ(both, "masks side 1 view 6 & masks side 1 view 7");
  EXPECT_TRUE(after_first_ended == "masks side 1 view 7" || after_first_ended == "masks side 1")
      << after_first_ended;
  EXPECT_EQ(CurrentStage(), "masks side 1");
}

// A stage's own log lines carry the sample and the stage they were written
// in: on a view's thread its view, on a loop's helper thread that opened no
// stage the stage around the loop, outside any stage nothing.
TEST(RunStage, StageLogNamesTheStageOfTheWritingThread) {
  ::testing::internal::CaptureStderr();
  StageLog(LogLevel::kWarning, "worker", "S-7", "before");
  Status st = RunStage("stitch", []() -> Status {
    StageLog(LogLevel::kWarning, "worker", "S-7", "markers located");
    std::thread helper([] { StageLog(LogLevel::kWarning, "worker", "S-7", "on a helper"); });
    helper.join();
    std::thread view([] {
      const StageScope v("stitch view 3", /*concurrent=*/true);
      StageLog(LogLevel::kWarning, "worker", "S-7", "view done");
    });
    view.join();
    return OkStatus();
  });
  const std::string err = ::testing::internal::GetCapturedStderr();
  ASSERT_TRUE(st.ok());
  EXPECT_NE(err.find("worker: [S-7] before\n"), std::string::npos) << err;
  EXPECT_NE(err.find("worker: [S-7] stitch: markers located\n"), std::string::npos) << err;
  EXPECT_NE(err.find("worker: [S-7] stitch: on a helper\n"), std::string::npos) << err;
  EXPECT_NE(err.find("worker: [S-7] stitch view 3: view done\n"), std::string::npos) << err;
}

// A stage's progress shows in the stages nested in it and ends with it; the
// figures are clamped to 0..total.
TEST(RunStage, ProgressIsTheInnermostReportingStages) {
  g_progress.clear();
  SetStageObserver(RecordProgress);
  Status st = RunStage("job", []() -> Status {
    return RunStage("masks side 1", []() -> Status {
      for (int v = 0; v < 2; ++v) {
        ReportStageProgress(v, 2);
        const StageScope view("view " + std::to_string(v + 1));
      }
      ReportStageProgress(5, 2);
      return OkStatus();
    });
  });
  SetStageObserver(nullptr);
  ASSERT_TRUE(st.ok());
  EXPECT_EQ(g_progress, (std::vector<std::string>{
                            "job 0/0", "masks side 1 0/0", "masks side 1 0/2", "view 1 0/2",
                            "masks side 1 0/2", "masks side 1 1/2", "view 2 1/2",
                            "masks side 1 1/2", "masks side 1 2/2", "job 0/0", " 0/0"}));
}

}  // namespace
}  // namespace aggscan
