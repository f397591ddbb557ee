#include "drivers/still_worker.h"

#include <algorithm>
#include <cstdio>
#include <utility>

#include "common/log.h"

namespace aggscan {

std::string SecondsText(TimeNs t) {
  char b[32];
  std::snprintf(b, sizeof b, "%.3g s", static_cast<double>(t) / 1e9);
  return b;
}

void StampExposure(Frame* frame, Clock& clock, int64_t ts_mono_ns) {
  const int64_t age = std::max<int64_t>(0, MonotonicNs() - ts_mono_ns);
  // A virtual clock does not advance with real time: the frame is "now" on it.
  frame->exposure_start =
      clock.Now() -
      static_cast<TimeNs>(static_cast<double>(age) * (clock.IsVirtual() ? 0.0 : clock.Scale()));
  frame->utc_ns = clock.UtcNs() - age;
}

void StillWorker::Start(const char* log_category, std::string name, CaptureFn capture) {
  Stop();
  {
    std::lock_guard<std::mutex> l(mu_);
    stop_ = false;
    job_.reset();
  }
  log_category_ = log_category;
  name_ = std::move(name);
  capture_ = std::move(capture);
  thread_ = std::thread([this] { Loop(); });
}

Status StillWorker::Post(const StillRequest& req, FrameCallback done, bool ready) {
  std::lock_guard<std::mutex> l(mu_);
  if (!thread_.joinable() || stop_ || !ready)
    return MakeError(ErrorClass::kInvalidState, "camera is not streaming");
  job_ = Job{req, std::move(done), MonotonicNs()};
  cv_.notify_all();
  return OkStatus();
}

void StillWorker::Stop() {
  {
    std::lock_guard<std::mutex> l(mu_);
    stop_ = true;
  }
  cv_.notify_all();
  if (thread_.joinable()) thread_.join();  // delivers the in-flight still (or an error) first
}

void StillWorker::Loop() {
  for (;;) {
    Job job;
    {
      std::unique_lock<std::mutex> l(mu_);
      cv_.wait(l, [this] { return stop_ || job_.has_value(); });
      if (!job_) return;
      job = std::move(*job_);
      job_.reset();
    }
    Result<FramePtr> r = capture_(job);
    if (!r)
      AGG_LOGW(log_category_, "%s: still %llu: %s", name_.c_str(),
               static_cast<unsigned long long>(job.req.request_id), r.error().ToString().c_str());
    job.done(std::move(r));
  }
}

}  // namespace aggscan
