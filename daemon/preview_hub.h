// The live camera view for screens. The capture service shoots preview stills
// only while someone watches (and no side runs), and hands each still, and
// each view stored during a side, to the hub; the hub's own thread scales it
// down (daemon/jpeg_scale.h), so neither the capture loop nor the camera's
// thread spends time on it, and keeps only the newest: a slow screen skips
// frames instead of queueing them.
#pragma once

#include <condition_variable>
#include <cstdint>
#include <functional>
#include <memory>
#include <mutex>
#include <string>
#include <thread>

#include "drivers/camera.h"

namespace aggscan {

struct PreviewFrame {
  uint64_t seq = 0;  // 1, 2, ... in publication order
  std::shared_ptr<const std::string> jpeg;
  int width = 0;
  int height = 0;
  int64_t utc_ns = 0;
  /// "preview" (shot for the live view) or "view" (a view stored by a side).
  std::string source;
};

class PreviewHub {
 public:
  /// Frames are scaled to at most `max_side` pixels on their longer side.
  PreviewHub(int max_side, int quality);
  ~PreviewHub();
  PreviewHub(const PreviewHub&) = delete;
  PreviewHub& operator=(const PreviewHub&) = delete;

  /// A screen starts or stops watching. `on_demand` (SetOnDemand) is called
  /// when the first one starts.
  void AddViewer();
  void RemoveViewer();
  int viewers() const;
  /// Called (from the thread of AddViewer) when the viewer count goes 0 -> 1.
  void SetOnDemand(std::function<void()> fn);
  /// Called (from the hub's thread) after each frame is published.
  void SetListener(std::function<void()> fn);

  /// Queues a full-size still to be scaled and published; replaces one still
  /// waiting. Never blocks on the scaling.
  void Submit(FramePtr frame, std::string source);
  /// The newest published frame (seq 0 when none yet).
  PreviewFrame Latest() const;

  uint64_t frames_published() const;
  uint64_t frames_failed() const;

 private:
  void Run();

  const int max_side_;
  const int quality_;
  mutable std::mutex mu_;
  std::condition_variable cv_;
  bool stopping_ = false;
  int viewers_ = 0;
  FramePtr waiting_;
  std::string waiting_source_;
  PreviewFrame latest_;
  uint64_t failed_ = 0;
  bool failing_ = false;  // the last frame failed: the next failure is not logged
  std::function<void()> on_demand_;
  std::function<void()> listener_;
  std::thread thread_;
};

}  // namespace aggscan
