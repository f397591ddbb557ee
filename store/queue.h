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

struct Job {
  int64_t id = 0;
  std::string sample_id;
  int side = 0;             // 1..N for a side job, 0 for the sample job
  std::string state;        // queued | running | done | failed
  int attempts = 0;
  std::string error;        // last failure message
  std::string created_utc;
  std::string updated_utc;
};

class JobQueue {
 public:
  /// Opens (creating if needed) the queue database at `path`.
  static Result<std::unique_ptr<JobQueue>> Open(const std::string& path);
  ~JobQueue();
  JobQueue(const JobQueue&) = delete;
  JobQueue& operator=(const JobQueue&) = delete;

  /// Queues a job unless an identical one (sample, side) is queued or running.
  Result<int64_t> Enqueue(const std::string& sample_id, int side);
  /// Takes the oldest queued job and marks it running; nullopt when empty.
  Result<std::optional<Job>> ClaimNext();
  Status Complete(int64_t job_id);
  /// Marks failed with the reason; requeue=true puts it back (bounded by caller).
  Status Fail(int64_t job_id, const std::string& error, bool requeue);
  /// Worker start-up: jobs left running by a crashed worker go back to queued.
  Result<int> RequeueRunning();
  /// Number of queued + running jobs.
  Result<int> Depth();
  Result<std::vector<Job>> JobsForSample(const std::string& sample_id);

 private:
  explicit JobQueue(sqlite3* db) : db_(db) {}
  Status Exec(const char* sql);
  sqlite3* db_;
};

}  // namespace aggscan
