// The real aggscan-worker binary on the real queue: a job whose photos make
// a library throw or the process crash ends failed with a named reason after
// [worker] max_attempts runs and the queue moves on; kills and stops of the
// worker count no attempt; a failed job retried after the fix completes.
#include <gtest/gtest.h>
#include <signal.h>
#include <sys/prctl.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>
#include <optional>
#include <regex>
#include <set>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "common/fsutil.h"
#include "pipeline/worker/side_job.h"
#include "store/layout.h"
#include "store/queue.h"
#include "tests/util/synth_scene.h"

namespace aggscan {
namespace {

namespace fs = std::filesystem;
using nlohmann::json;

class WorkerSupervisionTest : public ::testing::Test {
 protected:
  void SetUp() override {
    root_ = (fs::temp_directory_path() /
             ("aggscan_supervise_" + std::to_string(::getpid()) + "_" +
              ::testing::UnitTest::GetInstance()->current_test_info()->name()))
                .string();
    fs::remove_all(root_);
    fs::create_directories(root_ + "/samples");
    log_ = root_ + "/worker.log";
  }
  void TearDown() override {
    if (!HasFailure()) fs::remove_all(root_);
  }

  std::string SampleDir(const std::string& id) const { return layout::SampleDir(root_, id); }

  // One captured side of synthetic 640x480 views, as the daemon leaves it.
  void MakeSide(const std::string& id, int side, int views) {
    const std::string sd = SampleDir(id) + "/" + layout::SideDirName(side);
    fs::create_directories(sd);
    json jviews = json::array();
    for (int v = 0; v < views; ++v) {
      testing::SceneParams p;
      p.size = {640, 480};
      p.seed = 300 + side * 20 + v;
      p.turntable_deg = 360.0 * v / views;
      const auto sc = testing::MakeScene(p);
      Write(sd + "/" + layout::ViewImageName(v), std::string(sc.jpeg.begin(), sc.jpeg.end()));
      Write(sd + "/" + layout::ViewSidecarName(v), json{{"view", v},
                                                        {"commanded_angle_deg", p.turntable_deg},
                                                        {"measured_angle_deg", p.turntable_deg}}
                                                       .dump());
      jviews.push_back({{"view", v},
                        {"image", layout::ViewImageName(v)},
                        {"sidecar", layout::ViewSidecarName(v)},
                        {"bytes", sc.jpeg.size()}});
    }
    Write(sd + "/" + layout::kManifest, json{{"sample_id", id},
                                             {"side", side},
                                             {"views", jviews},
                                             {"completed_utc", "2026-01-01T00:00:00.000Z"}}
                                            .dump());
  }

  // Replaces the photos of a side by `bytes` (the manifest's sizes follow,
  // as if the camera had delivered those files).
  void ReplacePhotos(const std::string& id, int side, const std::string& bytes) {
    const std::string sd = SampleDir(id) + "/" + layout::SideDirName(side);
    std::ifstream f(sd + "/" + layout::kManifest);
    json m = json::parse(f);
    for (json& v : m["views"]) {
      Write(sd + "/" + v["image"].get<std::string>(), bytes);
      v["bytes"] = bytes.size();
    }
    Write(sd + "/" + layout::kManifest, m.dump());
  }

  static void Write(const std::string& path, const std::string& data) {
    std::ofstream(path, std::ios::binary | std::ios::trunc) << data;
  }
  static std::string ReadText(const std::string& path) {
    std::ifstream f(path);
    std::stringstream ss;
    ss << f.rdbuf();
    return ss.str();
  }

  std::unique_ptr<JobQueue> Queue() {
    auto q = JobQueue::Open(layout::QueuePath(root_));
    EXPECT_TRUE(q.ok()) << q.error().ToString();
    return q.ok() ? std::move(*q) : nullptr;
  }
  Job JobOf(const std::string& id, int side) {
    auto jobs = Queue()->JobsForSample(id);
    EXPECT_TRUE(jobs.ok());
    for (const Job& j : *jobs)
      if (j.side == side) return j;
    ADD_FAILURE() << "no job for " << id << " side " << side;
    return {};
  }

  // Starts the worker; `env` entries ("K=V") are added to its environment.
  pid_t StartWorker(const std::vector<std::string>& extra_args,
                    const std::vector<std::string>& env = {}) {
    std::vector<std::string> argv = {std::string(AGGSCAN_BINARY_DIR) + "/pipeline/aggscan-worker",
                                     "--state-dir", root_, "--poll-ms", "20"};
    argv.insert(argv.end(), extra_args.begin(), extra_args.end());
    const pid_t pid = ::fork();
    if (pid == 0) {
      FILE* f = std::fopen(log_.c_str(), "a");
      if (f) {
        ::dup2(fileno(f), 1);
        ::dup2(fileno(f), 2);
      }
      for (const std::string& e : env) ::putenv(const_cast<char*>(e.c_str()));
      std::vector<char*> a;
      for (const auto& s : argv) a.push_back(const_cast<char*>(s.c_str()));
      a.push_back(nullptr);
      ::execv(a[0], a.data());
      ::_exit(127);
    }
    return pid;
  }
  // Exit code, or 128 + signal.
  static int Wait(pid_t pid) {
    int st = 0;
    if (::waitpid(pid, &st, 0) != pid) return -1;
    return WIFEXITED(st) ? WEXITSTATUS(st) : 128 + WTERMSIG(st);
  }
  int RunOnce(const std::vector<std::string>& extra_args = {},
              const std::vector<std::string>& env = {}) {
    std::vector<std::string> a = {"--once"};
    a.insert(a.end(), extra_args.begin(), extra_args.end());
    return Wait(StartWorker(a, env));
  }

  std::string root_;
  std::string log_;
};

std::string OneByOneJpeg() {
  std::vector<unsigned char> buf;
  EXPECT_TRUE(cv::imencode(".jpg", cv::Mat(1, 1, CV_8UC3, cv::Scalar(200, 200, 200)), buf));
  return std::string(buf.begin(), buf.end());
}

// A side of 1x1 photos: the stage's failure is a named failure of that job,
// counted three times (the default), and the sample behind it is processed.
TEST_F(WorkerSupervisionTest, OneByOnePhotosFailTheJobByNameAndTheQueueMovesOn) {
  MakeSide("bad-1x1", 1, 3);
  ReplacePhotos("bad-1x1", 1, OneByOneJpeg());
  MakeSide("good", 1, 3);
  {
    auto q = Queue();
    ASSERT_TRUE(q->Enqueue("bad-1x1", 1).ok());
    ASSERT_TRUE(q->Enqueue("good", 1).ok());
  }
  // Exit 1: a job failed for good.
  EXPECT_EQ(RunOnce(), 1) << ReadText(log_);
  const Job bad = JobOf("bad-1x1", 1);
  RecordProperty("reason", bad.error);
  EXPECT_EQ(bad.state, "failed");
  EXPECT_EQ(bad.attempts, 3);
  EXPECT_EQ(bad.interruptions, 0);
  EXPECT_TRUE(bad.error.find("side 1") != std::string::npos ||
              bad.error.find("side1") != std::string::npos)
      << bad.error;
  EXPECT_EQ(bad.error.find("crashed"), std::string::npos)
      << "a named failure, not a crash: " << bad.error;
  EXPECT_EQ(JobOf("good", 1).state, "done");
  EXPECT_TRUE(PathExists(SideResultPath(SampleDir("good"), 1)));
  const std::string log = ReadText(log_);
  EXPECT_NE(log.find("giving up after 3 attempts: fix the cause, then run `aggscan retry bad-1x1`"),
            std::string::npos)
      << log;
}

// Zero-byte photos (a truncated file the manifest agrees with): OpenCV's
// decoder asserts on an empty buffer; the stage boundary names it.
TEST_F(WorkerSupervisionTest, ZeroBytePhotosFailTheJobByName) {
  MakeSide("empty", 1, 2);
  ReplacePhotos("empty", 1, "");
  MakeSide("good", 1, 2);
  {
    auto q = Queue();
    ASSERT_TRUE(q->Enqueue("empty", 1).ok());
    ASSERT_TRUE(q->Enqueue("good", 1).ok());
  }
  Write(root_ + "/worker.toml", "[worker]\nmax_attempts = 2\n");
  EXPECT_EQ(RunOnce({"--config", root_ + "/worker.toml"}), 1) << ReadText(log_);
  const Job bad = JobOf("empty", 1);
  RecordProperty("reason", bad.error);
  EXPECT_EQ(bad.state, "failed");
  EXPECT_EQ(bad.attempts, 2);  // [worker] max_attempts
  EXPECT_NE(bad.error.find("view"), std::string::npos) << bad.error;
  EXPECT_EQ(bad.error.find("crashed"), std::string::npos) << bad.error;
  EXPECT_EQ(JobOf("good", 1).state, "done");
}

// A job whose process aborts (as a library's failed assertion or a
// std::terminate on one of its threads would) is counted and failed with the
// signal and the stage, never looped; the next sample is processed.
TEST_F(WorkerSupervisionTest, CrashingJobIsCountedAndFailedNotLooped) {
  MakeSide("crash", 1, 3);
  MakeSide("good", 1, 3);
  {
    auto q = Queue();
    ASSERT_TRUE(q->Enqueue("crash", 1).ok());
    ASSERT_TRUE(q->Enqueue("good", 1).ok());
  }
  // Views are masked two at a time: view 2 starts when view 0 or 1 is done.
  EXPECT_EQ(RunOnce({}, {"AGGSCAN_WORKER_TEST_ABORT=crash/masks side 1 view 2"}), 1)
      << ReadText(log_);
  const Job bad = JobOf("crash", 1);
  RecordProperty("reason", bad.error);
  EXPECT_EQ(bad.state, "failed");
  EXPECT_EQ(bad.attempts, 3);
  EXPECT_NE(bad.error.find("crashed with SIGABRT"), std::string::npos) << bad.error;
  // The stage names the view that crashed, with any view in flight beside it.
  const std::regex stage(
      R"(in stage "(masks side 1 view [01] & )?masks side 1 view 2( & masks side 1 view [01])?")");
  EXPECT_TRUE(std::regex_search(bad.error, stage)) << bad.error;
  EXPECT_EQ(JobOf("good", 1).state, "done");
  // A view finished before the crash is kept for the next attempt.
  EXPECT_TRUE(PathExists(ViewMaskPath(SampleDir("crash"), 1, 0)) ||
              PathExists(ViewMaskPath(SampleDir("crash"), 1, 1)));
  EXPECT_FALSE(PathExists(ViewMaskPath(SampleDir("crash"), 1, 2)));

  // The cause removed (here: the hook), a retry completes the job.
  auto n = Queue()->Retry("crash");
  ASSERT_TRUE(n.ok()) << n.error().ToString();
  EXPECT_EQ(*n, 1);
  EXPECT_EQ(RunOnce(), 0) << ReadText(log_);
  const Job fixed = JobOf("crash", 1);
  EXPECT_EQ(fixed.state, "done");
  EXPECT_EQ(fixed.attempts, 0);
  EXPECT_TRUE(PathExists(SideResultPath(SampleDir("crash"), 1)));
}

// Number of view masks the side has written so far.
int MasksWritten(const std::string& sample_dir, int side, int views) {
  int n = 0;
  for (int v = 0; v < views; ++v) n += PathExists(ViewMaskPath(sample_dir, side, v)) ? 1 : 0;
  return n;
}

// SIGKILL, SIGTERM, SIGKILL of the worker in the middle of a job: no attempt
// is counted, the job's process dies with the worker, and the job completes
// afterwards, resuming from the masks already written.
TEST_F(WorkerSupervisionTest, KilledAndStoppedWorkerCountsNoAttempt) {
  // Orphans (the job's process of a killed worker) come to this process, so
  // the test sees that they end.
  ASSERT_EQ(::prctl(PR_SET_CHILD_SUBREAPER, 1), 0);
  constexpr int kViews = 12;
  MakeSide("long", 1, kViews);
  ASSERT_TRUE(Queue()->Enqueue("long", 1).ok());
  const std::string dir = SampleDir("long");
  for (int sig : {SIGKILL, SIGTERM, SIGKILL}) {
    const int before = MasksWritten(dir, 1, kViews);
    const pid_t pid = StartWorker({});
    // Generous: the first view waits for the process start on a loaded machine.
    const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(120);
    while (MasksWritten(dir, 1, kViews) <= before && std::chrono::steady_clock::now() < deadline)
      std::this_thread::sleep_for(std::chrono::milliseconds(5));
    ASSERT_GT(MasksWritten(dir, 1, kViews), before) << "no progress before the kill\n"
                                                    << ReadText(log_);
    ASSERT_EQ(::kill(pid, sig), 0);
    const int rc = Wait(pid);
    if (sig == SIGTERM) {
      EXPECT_EQ(rc, 0) << ReadText(log_);  // the side stops between views; the worker exits cleanly
    } else {
      EXPECT_EQ(rc, 128 + SIGKILL);
    }
    // The job's process ends too (PR_SET_PDEATHSIG, or the forwarded SIGTERM);
    // reaped here as an orphan or already reaped by the worker.
    const auto reap_deadline = std::chrono::steady_clock::now() + std::chrono::seconds(60);
    int st;
    while (::waitpid(-1, &st, WNOHANG) >= 0 && std::chrono::steady_clock::now() < reap_deadline)
      std::this_thread::sleep_for(std::chrono::milliseconds(10));
    EXPECT_EQ(::waitpid(-1, &st, WNOHANG), -1) << "the job's process outlived the worker";
    const Job j = JobOf("long", 1);
    EXPECT_NE(j.state, "done") << "killed too late to test anything";
    EXPECT_NE(j.state, "failed") << j.error;
    EXPECT_EQ(j.attempts, 0);
    EXPECT_EQ(j.state, sig == SIGTERM ? "queued" : "running");
  }
  ASSERT_LT(MasksWritten(dir, 1, kViews), kViews);
  EXPECT_EQ(RunOnce(), 0) << ReadText(log_);
  const Job j = JobOf("long", 1);
  EXPECT_EQ(j.state, "done");
  EXPECT_EQ(j.attempts, 0);
  EXPECT_EQ(j.interruptions, 0);
  std::ifstream f(SideResultPath(dir, 1));
  const json result = json::parse(f);
  EXPECT_EQ(result["views_total"], kViews);
  const std::string log = ReadText(log_);
  EXPECT_NE(log.find("interrupted, will resume"), std::string::npos) << log;
  EXPECT_NE(log.find("requeued 1 job(s) cut off"), std::string::npos) << log;
}

// What the worker tells aggscand through the queue: idle, then busy with the
// side's job in its masks stage with the views done counting up to the
// side's, idle again when it is done, stopped after SIGTERM; heard from at
// least every heartbeat interval throughout.
TEST_F(WorkerSupervisionTest, ReportsItsJobStageAndProgressThroughTheQueue) {
  constexpr int kViews = 24;
  MakeSide("watched", 1, kViews);
  const std::string cfg = root_ + "/worker.toml";
  Write(cfg, "[worker]\nheartbeat_interval = \"300ms\"\nsilent_after = \"2s\"\n");
  auto q = Queue();
  ASSERT_TRUE(q);
  const pid_t pid = StartWorker({"--config", cfg});
  // Idle first (no job queued yet).
  auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(60);
  std::optional<WorkerSeen> seen;
  while (std::chrono::steady_clock::now() < deadline) {
    auto w = q->Worker();
    ASSERT_TRUE(w.ok()) << w.error().ToString();
    if (w->has_value() && (*w)->report.pid == pid) {
      seen = **w;
      break;
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  }
  ASSERT_TRUE(seen) << ReadText(log_);
  EXPECT_EQ(seen->report.state, "idle");
  EXPECT_TRUE(seen->this_boot);

  auto job_id = q->Enqueue("watched", 1);
  ASSERT_TRUE(job_id.ok());
  std::set<int> done_seen;
  std::set<std::string> stages;
  double longest_silence_s = 0;
  bool busy_seen = false;
  deadline = std::chrono::steady_clock::now() + std::chrono::seconds(240);
  while (std::chrono::steady_clock::now() < deadline) {
    auto w = q->Worker();
    ASSERT_TRUE(w.ok() && w->has_value());
    const WorkerSeen& now = **w;
    longest_silence_s = std::max(longest_silence_s, now.heard_s_ago);
    if (now.report.state == "busy") {
      busy_seen = true;
      EXPECT_EQ(now.report.job_id, *job_id);
      EXPECT_EQ(now.report.sample_id, "watched");
      EXPECT_EQ(now.report.side, 1);
      stages.insert(now.report.stage);
      if (now.report.stage.rfind("masks side 1", 0) == 0) {
        EXPECT_EQ(now.report.total, kViews) << now.report.stage;
        done_seen.insert(now.report.done);
      }
    } else if (busy_seen && now.report.state == "idle") {
      break;
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  }
  ASSERT_TRUE(busy_seen) << ReadText(log_);
  EXPECT_EQ(q->Worker()->value().report.state, "idle") << ReadText(log_);
  EXPECT_EQ(JobOf("watched", 1).state, "done");
  // Views of 640x480 take a fraction of a second each: several of the 24
  // counts show at two reports a second.
  RecordProperty("progress_counts_seen", static_cast<int>(done_seen.size()));
  EXPECT_GE(done_seen.size(), 3u) << ::testing::PrintToString(done_seen);
  EXPECT_LE(*done_seen.rbegin(), kViews - 1);
  bool view_stage = false;
  for (const std::string& st : stages)
    view_stage = view_stage || st.find(" view ") != std::string::npos;
  EXPECT_TRUE(view_stage) << ::testing::PrintToString(stages);
  // A report at least every 300 ms, read on a loaded machine.
  EXPECT_LT(longest_silence_s, 1.5);

  ASSERT_EQ(::kill(pid, SIGTERM), 0);
  EXPECT_EQ(Wait(pid), 0) << ReadText(log_);
  auto last = q->Worker();
  ASSERT_TRUE(last.ok() && last->has_value());
  EXPECT_EQ((*last)->report.state, "stopped");
}

// The photos fixed after the job failed: `retry` puts it back with its
// attempts reset and the worker completes it.
TEST_F(WorkerSupervisionTest, RetryAfterFixingThePhotosCompletesTheJob) {
  MakeSide("fixme", 1, 3);
  const std::string sd = SampleDir("fixme") + "/" + layout::SideDirName(1);
  const std::string good_manifest = ReadText(sd + "/" + layout::kManifest);
  std::vector<std::string> good_photos;
  for (int v = 0; v < 3; ++v) good_photos.push_back(ReadText(sd + "/" + layout::ViewImageName(v)));
  ReplacePhotos("fixme", 1, "");
  ASSERT_TRUE(Queue()->Enqueue("fixme", 1).ok());
  EXPECT_EQ(RunOnce(), 1) << ReadText(log_);
  ASSERT_EQ(JobOf("fixme", 1).state, "failed");
  // Retrying before the fix only fails again; the operator fixes the files.
  for (int v = 0; v < 3; ++v) Write(sd + "/" + layout::ViewImageName(v), good_photos[v]);
  Write(sd + "/" + layout::kManifest, good_manifest);
  auto n = Queue()->Retry("fixme");
  ASSERT_TRUE(n.ok()) << n.error().ToString();
  EXPECT_EQ(RunOnce(), 0) << ReadText(log_);
  const Job j = JobOf("fixme", 1);
  EXPECT_EQ(j.state, "done");
  EXPECT_EQ(j.attempts, 0);
  EXPECT_EQ(j.error, "");
  std::ifstream f(SideResultPath(SampleDir("fixme"), 1));
  EXPECT_EQ(json::parse(f)["views_ok"], 3);
}

}  // namespace
}  // namespace aggscan
