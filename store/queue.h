// Persistent job queue shared by aggscand (producer) and aggscan-worker
// (consumer): SQLite in WAL mode with synchronous=FULL, so an enqueued job
// survives power loss and the two processes never see a half-written row.
// A side job (side >= 1) is queued as soon as that side is captured; a sample
// job (side == 0) when the whole sample is. Jobs are taken in id order.
#pragma once

#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "common/error.h"

struct sqlite3;

namespace aggscan {

/// What a job is about: a rock (a sample's side or the sample) or a capture
/// of the calibration board (layout::kCalibrationCollection) to solve.
inline constexpr const char* kJobRock = "rock";
inline constexpr const char* kJobCalibration = "calibration";

struct Job {
  int64_t id = 0;
  std::string kind = kJobRock;
  std::string sample_id;
  int side = 0;           // 1..N for a side job, 0 for the sample job
  std::string state;      // queued | running | done | failed
  int attempts = 0;       // runs that ended in a failure or a crash (not kills or stops)
  int interruptions = 0;  // consecutive runs cut off with the whole worker (kill, power loss)
  std::string error;      // last failure message
  std::string created_utc;
  std::string updated_utc;
};

/// What the worker last told the daemon about itself (one row in the queue
/// database: the two processes share no other channel). Times are on the
/// machine's boot clock (CLOCK_BOOTTIME), which neither an NTP step nor a
/// suspend can make run backwards, tagged with the boot they belong to.
struct WorkerReport {
  int64_t pid = 0;
  std::string state;   // idle | busy | stopped
  int64_t job_id = 0;  // busy: the job it runs
  std::string sample_id;
  int side = 0;       // of that job: 1..N a side, 0 the sample stage
  std::string stage;  // innermost stage, e.g. "masks side 1 view 7" ("" between stages)
  int done = 0;       // progress of that stage: done of total units; total 0 when unknown
  int total = 0;
  int64_t started_boot_ns = 0;      // the worker process started
  int64_t job_started_boot_ns = 0;  // busy: the job started
  int64_t stage_since_boot_ns = 0;  // the stage started
};

/// The worker's report as read by the daemon, with its age on the same clock.
struct WorkerSeen {
  WorkerReport report;
  std::string heard_utc;   // wall-clock time of the report, for people
  bool this_boot = false;  // written since this machine last booted
  double heard_s_ago = 0;  // this_boot: seconds since the report
  double job_s = 0;        // busy: seconds since the job started
  double stage_s = 0;      // seconds since the stage started
  double up_s = 0;         // seconds since the worker started
};

/// CLOCK_BOOTTIME in nanoseconds, and this boot's id (the kernel's boot_id).
int64_t BootTimeNs();
const std::string& BootId();

class JobQueue {
 public:
  /// Opens (creating if needed) the queue database at `path`.
  static Result<std::unique_ptr<JobQueue>> Open(const std::string& path);
  ~JobQueue();
  JobQueue(const JobQueue&) = delete;
  JobQueue& operator=(const JobQueue&) = delete;

  /// Queues a job unless an identical one (sample, side) is queued or running.
  /// Capture ids are unique across kinds (calibration captures have their own
  /// prefix, see layout::kCalibrationIdPrefix).
  Result<int64_t> Enqueue(const std::string& sample_id, int side,
                          const std::string& kind = kJobRock);
  /// Takes the oldest queued job and marks it running; nullopt when empty.
  /// Claiming counts nothing: a run that is killed or stopped is no attempt.
  Result<std::optional<Job>> ClaimNext();
  Status Complete(int64_t job_id);
  /// One attempt of the job failed (an error or a crash): counts it and
  /// records the reason; requeue=true puts it back, false marks it failed.
  Status Fail(int64_t job_id, const std::string& error, bool requeue);
  /// The worker was asked to stop during the job: back to queued, uncounted.
  Status Release(int64_t job_id);

  struct Requeued {
    int requeued = 0;  // back to queued
    int failed = 0;    // failed: interrupted max_interruptions times in a row
  };
  /// Worker start-up: jobs left running by a worker that was killed (or lost
  /// power) go back to queued without counting an attempt; each such return
  /// counts an interruption, and a job interrupted `max_interruptions` times
  /// in a row (a job that gets the worker OOM-killed every time) is failed.
  Result<Requeued> RequeueRunning(int max_interruptions);
  /// Puts the failed jobs of a sample back in the queue with their attempts
  /// reset (after the cause was fixed); the number requeued. kNotFound when
  /// the sample has no failed job.
  Result<int> Retry(const std::string& sample_id);
  /// Number of queued + running jobs.
  Result<int> Depth();
  Result<std::vector<Job>> JobsForSample(const std::string& sample_id);
  /// The failed jobs, newest first, at most `limit`.
  Result<std::vector<Job>> FailedJobs(int limit);
  /// Number of failed jobs.
  Result<int> FailedCount();

  /// The worker's heartbeat: replaces its report, stamped with the time now.
  /// Not synced to disk on its own (a report lost in a power cut is of no
  /// use after it), so it costs no fsync of the queue's journal.
  Status ReportWorker(const WorkerReport& r);
  /// The worker's last report; nullopt when none was ever written.
  Result<std::optional<WorkerSeen>> Worker();

 private:
  explicit JobQueue(sqlite3* db) : db_(db) {}
  Status Exec(const char* sql);
  Status Migrate();
  sqlite3* db_;
};

}  // namespace aggscan
