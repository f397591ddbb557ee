// What the real camera backends (V4L2, libcamera) share: the one-still job
// slot served on the backend's own thread, and the stamping of a frame's
// exposure time from the kernel's CLOCK_MONOTONIC onto the daemon's clock.
//
// The worker uses the backend's mutex and condition variable, so a backend
// waiting for its device under that lock sees Stop() at once
// (stopping_locked()) and its own device events wake the same waiters.
#pragma once

#include <condition_variable>
#include <cstdint>
#include <functional>
#include <mutex>
#include <optional>
#include <string>
#include <thread>

#include "common/clock.h"
#include "common/error.h"
#include "drivers/camera.h"

namespace aggscan {

// MonotonicNs() (common/clock.h) is the clock V4L2 and libcamera stamp frames with.
/// "0.6 s", "2 s": a timeout as messages show it.
std::string SecondsText(TimeNs t);
/// Sets exposure_start (daemon clock) and utc_ns of a frame whose exposure
/// began at `ts_mono_ns` (CLOCK_MONOTONIC), by its age now.
void StampExposure(Frame* frame, Clock& clock, int64_t ts_mono_ns);

class StillWorker {
 public:
  struct Job {
    StillRequest req;
    FrameCallback done;
    int64_t requested_mono_ns = 0;  // CLOCK_MONOTONIC when the still was asked for
  };
  /// Runs on the worker thread; returns the still or why there is none.
  using CaptureFn = std::function<Result<FramePtr>(const Job&)>;

  StillWorker(std::mutex& mu, std::condition_variable& cv) : mu_(mu), cv_(cv) {}
  ~StillWorker() { Stop(); }
  StillWorker(const StillWorker&) = delete;
  StillWorker& operator=(const StillWorker&) = delete;

  /// Starts the thread; `log_category`/`name` prefix the warning logged for a failed still.
  void Start(const char* log_category, std::string name, CaptureFn capture);
  /// Hands one still to the thread. kInvalidState when not running or when
  /// `ready` is false (the backend is not streaming). Takes the lock.
  Status Post(const StillRequest& req, FrameCallback done, bool ready);
  /// Wakes every waiter, lets the in-flight still finish (its `done` is
  /// called), and joins the thread. Takes the lock; idempotent.
  void Stop();
  /// True once Stop() began. Call with the backend's mutex held.
  bool stopping_locked() const { return stop_; }

 private:
  void Loop();

  std::mutex& mu_;
  std::condition_variable& cv_;
  std::optional<Job> job_;  // guarded by mu_
  bool stop_ = false;       // guarded by mu_
  const char* log_category_ = "camera";
  std::string name_;
  CaptureFn capture_;
  std::thread thread_;
};

}  // namespace aggscan
