#include "daemon/preview_hub.h"

#include <span>
#include <utility>

#include "common/log.h"
#include "daemon/jpeg_scale.h"

namespace aggscan {

namespace {
constexpr const char* kCat = "preview";
}

PreviewHub::PreviewHub(int max_side, int quality)
    : max_side_(max_side), quality_(quality), thread_([this] { Run(); }) {}

PreviewHub::~PreviewHub() {
  {
    std::lock_guard<std::mutex> lock(mu_);
    stopping_ = true;
  }
  cv_.notify_all();
  thread_.join();
}

void PreviewHub::AddViewer() {
  std::function<void()> demand;
  {
    std::lock_guard<std::mutex> lock(mu_);
    if (viewers_++ == 0) demand = on_demand_;
  }
  if (demand) demand();
}

void PreviewHub::RemoveViewer() {
  std::lock_guard<std::mutex> lock(mu_);
  if (viewers_ > 0) --viewers_;
}

int PreviewHub::viewers() const {
  std::lock_guard<std::mutex> lock(mu_);
  return viewers_;
}

void PreviewHub::SetOnDemand(std::function<void()> fn) {
  std::lock_guard<std::mutex> lock(mu_);
  on_demand_ = std::move(fn);
}

void PreviewHub::SetListener(std::function<void()> fn) {
  std::lock_guard<std::mutex> lock(mu_);
  listener_ = std::move(fn);
}

void PreviewHub::Submit(FramePtr frame, std::string source) {
  if (!frame) return;
  {
    std::lock_guard<std::mutex> lock(mu_);
    waiting_ = std::move(frame);
    waiting_source_ = std::move(source);
  }
  cv_.notify_one();
}

PreviewFrame PreviewHub::Latest() const {
  std::lock_guard<std::mutex> lock(mu_);
  return latest_;
}

uint64_t PreviewHub::frames_published() const {
  std::lock_guard<std::mutex> lock(mu_);
  return latest_.seq;
}

uint64_t PreviewHub::frames_failed() const {
  std::lock_guard<std::mutex> lock(mu_);
  return failed_;
}

void PreviewHub::Run() {
  std::unique_lock<std::mutex> lock(mu_);
  for (;;) {
    cv_.wait(lock, [this] { return stopping_ || waiting_ != nullptr; });
    if (stopping_) return;
    FramePtr frame = std::move(waiting_);
    std::string source = std::move(waiting_source_);
    waiting_.reset();
    lock.unlock();
    Result<ScaledJpeg> scaled =
        ScaleJpeg(std::span<const unsigned char>(frame->data), max_side_, quality_);
    std::function<void()> listener;
    lock.lock();
    if (!scaled) {
      // Logged once per run of failures: a camera sending bad JPEGs would
      // otherwise fill the journal at the preview rate.
      ++failed_;
      if (!failing_)
        AGG_LOGW(kCat, "cannot scale a %s frame for the live view: %s", source.c_str(),
                 scaled.error().ToString().c_str());
      failing_ = true;
      continue;
    }
    failing_ = false;
    latest_.seq += 1;
    latest_.jpeg = std::make_shared<const std::string>(std::move(scaled->jpeg));
    latest_.width = scaled->width;
    latest_.height = scaled->height;
    latest_.utc_ns = frame->utc_ns;
    latest_.source = std::move(source);
    listener = listener_;
    lock.unlock();
    if (listener) listener();
    lock.lock();
  }
}

}  // namespace aggscan
