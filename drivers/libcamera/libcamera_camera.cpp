#include "drivers/libcamera/libcamera_camera.h"

#include <libcamera/control_ids.h>
#include <libcamera/property_ids.h>
#include <libcamera/stream.h>
#include <sys/mman.h>
#include <sys/stat.h>

#include <algorithm>
#include <cerrno>
#include <cstring>
#include <filesystem>
#include <span>
#include <utility>

#include "common/log.h"

namespace aggscan::lc {
namespace {

constexpr const char* kLog = "libcamera";

std::string SizeText(const libcamera::PixelFormat& f, unsigned w, unsigned h) {
  return f.toString() + " " + std::to_string(w) + "x" + std::to_string(h);
}

// A camera that vanished while running, with its requests and the allocator
// owning their buffers. libcamera 0.0.3 cannot stop it (stop() is refused
// after a disconnect, or aborts on requests stuck in the vanished device) and
// aborts when it destroys a camera still running (its IPA thread is never
// joined), while its pipeline keeps pointers to our requests. So all of it is
// kept for the life of the process: a few objects and one idle thread per
// unplug, against a crash.
struct Abandoned {
  std::vector<std::unique_ptr<libcamera::Request>> requests;
  std::unique_ptr<libcamera::FrameBufferAllocator> allocator;
  std::shared_ptr<libcamera::Camera> camera;
};
void Abandon(Abandoned a) {
  static std::mutex mu;
  static auto* kept = new std::vector<Abandoned>;  // never freed, on purpose
  std::lock_guard<std::mutex> l(mu);
  kept->push_back(std::move(a));
}

}  // namespace

Result<std::shared_ptr<libcamera::CameraManager>> SharedCameraManager() {
  static std::mutex mu;
  static std::weak_ptr<libcamera::CameraManager> weak;
  std::lock_guard<std::mutex> l(mu);
  if (auto m = weak.lock()) return m;
  std::shared_ptr<libcamera::CameraManager> m(new libcamera::CameraManager,
                                              [](libcamera::CameraManager* p) {
                                                p->stop();
                                                delete p;
                                              });
  if (const int r = m->start(); r < 0) {
    return MakeError(ErrorClass::kDeviceFault,
                     "libcamera's camera manager did not start — check that /dev/media* and "
                     "/dev/video* are readable and udev is running",
                     std::strerror(-r));
  }
  weak = m;
  return m;
}

LibcameraCamera::LibcameraCamera(Clock& clock, const CameraConfig& config)
    : clock_(clock), config_(config) {}

LibcameraCamera::~LibcameraCamera() { DoClose(); }

CameraInfo LibcameraCamera::Info() const {
  return {config_.id, "libcamera", model_.empty() ? id_ : model_};
}

Status LibcameraCamera::DoOpen() {
  Result<std::shared_ptr<libcamera::CameraManager>> m = SharedCameraManager();
  if (!m) return m.error();
  manager_ = *m;
  std::vector<std::string> ids;
  for (const auto& c : manager_->cameras()) ids.push_back(c->id());
  Result<std::string> id = PickCamera(ids, config_.libcamera.camera_id, config_.libcamera.index);
  if (!id) {
    manager_.reset();
    return id.error();
  }
  std::shared_ptr<libcamera::Camera> cam = manager_->get(*id);
  if (!cam) {  // removed between the listing and now
    manager_.reset();
    return MakeError(ErrorClass::kDeviceMissing, "camera " + *id + " went away while opening");
  }
  if (const int r = cam->acquire(); r < 0) {
    manager_.reset();
    return LibcameraError(*id, "acquire", r, false);
  }
  camera_ = std::move(cam);
  id_ = *id;
  nodes_.clear();
  std::error_code ec;
  for (const auto& e : std::filesystem::directory_iterator("/dev", ec)) {
    const std::string path = e.path().string();
    struct stat st {};
    if (path.rfind("/dev/video", 0) != 0 || ::stat(path.c_str(), &st) != 0 || !S_ISCHR(st.st_mode))
      continue;
    if (manager_->get(st.st_rdev) == camera_) nodes_.push_back({path, st.st_rdev});
  }
  const auto model = camera_->properties().get(libcamera::properties::Model);
  model_ = (model ? *model + " (" : "(") + id_ + ")";
  {
    std::lock_guard<std::mutex> l(mu_);
    disconnected_ = false;
  }
  camera_->requestCompleted.connect(this, &LibcameraCamera::OnRequestCompleted);
  camera_->disconnected.connect(this, &LibcameraCamera::OnDisconnected);
  worker_.Start(kLog, id_, [this](const Job& job) { return Capture(job); });
  std::string on;
  for (const Node& n : nodes_) on += " " + n.path;
  AGG_LOGI(kLog, "opened %s%s%s", model_.c_str(), on.empty() ? "" : " on", on.c_str());
  return OkStatus();
}

bool LibcameraCamera::NodesGone() const {
  for (const Node& n : nodes_) {
    struct stat st {};
    if (::stat(n.path.c_str(), &st) != 0 || st.st_rdev != n.rdev) return true;
  }
  return false;
}

void LibcameraCamera::OnRequestCompleted(libcamera::Request* request) {
  {
    std::lock_guard<std::mutex> l(mu_);
    completed_.push_back(request);
    --in_flight_;
  }
  cv_.notify_all();
}

void LibcameraCamera::OnDisconnected() {
  {
    std::lock_guard<std::mutex> l(mu_);
    disconnected_ = true;
  }
  cv_.notify_all();
}

Status LibcameraCamera::DoConfigure(const CameraSettings& settings) {
  if (!camera_) return MakeError(ErrorClass::kInvalidState, "camera is not open");
  StopCamera();  // a second Configure renegotiates from scratch
  {
    std::lock_guard<std::mutex> l(mu_);
    if (disconnected_ || NodesGone())
      return MakeError(ErrorClass::kDisconnected,
                       "camera " + id_ + " went away; it is reopened on reset");
  }
  const libcamera::StreamRole role = *RoleFromName(config_.libcamera.role);
  std::unique_ptr<libcamera::CameraConfiguration> cfg = camera_->generateConfiguration({role});
  if (!cfg || cfg->empty()) {
    return MakeError(ErrorClass::kInvalidConfig,
                     "camera " + id_ + " cannot give a \"" + config_.libcamera.role +
                         "\" stream; set camera.libcamera.role to still, video, viewfinder or raw");
  }
  libcamera::StreamConfiguration& sc = cfg->at(0);
  LibcameraNegotiated neg;
  neg.offered = sc.formats().pixelformats();
  Result<libcamera::PixelFormat> fmt =
      ChoosePixelFormat(neg.offered, sc.pixelFormat, config_.libcamera.pixel_format);
  if (!fmt) {
    Error e = fmt.error();
    e.message = "camera " + id_ + ": " + e.message;
    return e;
  }
  sc.pixelFormat = *fmt;
  sc.size = libcamera::Size(static_cast<unsigned>(settings.width),
                            static_cast<unsigned>(settings.height));
  if (config_.libcamera.buffers > 0)
    sc.bufferCount = static_cast<unsigned>(config_.libcamera.buffers);
  const libcamera::CameraConfiguration::Status vs = cfg->validate();
  if (vs == libcamera::CameraConfiguration::Invalid) {
    return MakeError(ErrorClass::kInvalidConfig,
                     "camera " + id_ + " refuses " +
                         SizeText(*fmt, settings.width, settings.height) + " for a \"" +
                         config_.libcamera.role + "\" stream");
  }
  if (sc.pixelFormat != *fmt || sc.size.width != static_cast<unsigned>(settings.width) ||
      sc.size.height != static_cast<unsigned>(settings.height)) {
    return MakeError(ErrorClass::kInvalidConfig,
                     "camera " + id_ + " cannot deliver " +
                         SizeText(*fmt, settings.width, settings.height) + "; it offers " +
                         SizeText(sc.pixelFormat, sc.size.width, sc.size.height) +
                         " instead: set camera.width/height to a size it has");
  }
  if (const int r = camera_->configure(cfg.get()); r < 0)
    return LibcameraError(id_, "configure", r, false);
  Result<ControlPlan> plan = PlanControls(camera_->controls(), settings);
  if (!plan) {
    Error e = plan.error();
    e.message = "camera " + id_ + ": " + e.message;
    return e;
  }
  for (const auto& [id, info] : camera_->controls()) neg.controls.push_back(id->name());
  std::sort(neg.controls.begin(), neg.controls.end());
  neg.missing_controls = plan->missing;
  if (!plan->missing.empty()) {
    std::string list;
    for (const auto& m : plan->missing) list += (list.empty() ? "" : ", ") + m;
    if (config_.libcamera.strict_controls) {
      return MakeError(
          ErrorClass::kInvalidConfig,
          "camera " + model_ + " has no control for " + list +
              ", so those settings cannot be locked; use a camera that has them or set "
              "camera.libcamera.strict_controls = false to shoot with the camera's own values");
    }
    AGG_LOGW(kLog, "%s has no control for %s; frames report these as missing", id_.c_str(),
             list.c_str());
  }
  neg.format = sc.pixelFormat;
  neg.width = static_cast<int>(sc.size.width);
  neg.height = static_cast<int>(sc.size.height);
  neg.stride = static_cast<int>(sc.stride);
  stream_ = sc.stream();
  lc_config_ = std::move(cfg);
  active_ = settings;
  neg_ = neg;
  Status st = StartCamera(*plan);
  if (!st) return st;
  AGG_LOGI(kLog, "%s: %s (stride %d), %u buffers", id_.c_str(),
           SizeText(neg_.format, neg_.width, neg_.height).c_str(), neg_.stride, neg_.buffers);
  return OkStatus();
}

Status LibcameraCamera::StartCamera(const ControlPlan& plan) {
  allocator_ = std::make_unique<libcamera::FrameBufferAllocator>(camera_);
  if (const int r = allocator_->allocate(stream_); r < 0) {
    StopCamera();
    return LibcameraError(id_, "allocating frame buffers", r, false);
  }
  const auto& buffers = allocator_->buffers(stream_);
  std::vector<libcamera::Request*> idle;
  for (size_t i = 0; i < buffers.size(); ++i) {
    libcamera::FrameBuffer* fb = buffers[i].get();
    // Each plane's dmabuf mapped once, from its start: plane offsets need
    // not be page aligned, so the mapping covers offset + length.
    MappedFrame mf;
    std::map<int, size_t> map_of_fd;
    for (const auto& p : fb->planes()) {
      const int fd = p.fd.get();
      size_t end = 0;
      for (const auto& q : fb->planes())
        if (q.fd.get() == fd) end = std::max<size_t>(end, size_t{q.offset} + q.length);
      auto [it, fresh] = map_of_fd.emplace(fd, mf.maps.size());
      if (fresh) {
        void* a = ::mmap(nullptr, end, PROT_READ, MAP_SHARED, fd, 0);
        if (a == MAP_FAILED) {
          const int err = errno;
          StopCamera();
          return LibcameraError(id_, "mmap of a frame buffer", -err, false);
        }
        mf.maps.emplace_back(a, end);
      }
      mf.planes.push_back(mf.maps[it->second].data() + p.offset);
    }
    mapped_.emplace(fb, std::move(mf));
    std::unique_ptr<libcamera::Request> req = camera_->createRequest(i);
    if (!req) {
      StopCamera();
      return MakeError(ErrorClass::kDeviceFault, "camera " + id_ + ": creating a request failed");
    }
    if (const int r = req->addBuffer(stream_, fb); r < 0) {
      StopCamera();
      return LibcameraError(id_, "adding a buffer to a request", r, false);
    }
    idle.push_back(req.get());
    requests_.push_back(std::move(req));
  }
  neg_.buffers = static_cast<unsigned>(buffers.size());
  request_controls_ = plan.controls;
  if (const int r = camera_->start(&plan.controls); r < 0) {
    StopCamera();
    return LibcameraError(id_, "start", r, false);
  }
  started_ = true;
  std::lock_guard<std::mutex> l(mu_);
  completed_.clear();
  idle_ = std::move(idle);
  return OkStatus();
}

void LibcameraCamera::StopCamera() {
  if (started_ && camera_) {
    bool gone = NodesGone();
    {
      std::lock_guard<std::mutex> l(mu_);
      gone = gone || disconnected_;
    }
    // stop() completes (cancels) every queued request. A camera that went
    // away cannot be stopped (see Abandoned): the requests its pipeline fails
    // to queue come back cancelled (waited for briefly, so its thread is not
    // mid-signal when we disconnect), then it is abandoned running.
    if (!gone) {
      (void)camera_->stop();
    } else {
      {
        std::unique_lock<std::mutex> l(mu_);
        cv_.wait_for(l, std::chrono::seconds(2), [this] { return in_flight_ <= 0; });
        AGG_LOGW(kLog, "%s went away while running: abandoned (%d request(s) never came back)",
                 id_.c_str(), in_flight_);
      }
      Abandon({std::move(requests_), std::move(allocator_), camera_});
      requests_.clear();
      abandoned_ = true;
    }
  }
  started_ = false;
  {
    std::lock_guard<std::mutex> l(mu_);
    completed_.clear();
    idle_.clear();
    in_flight_ = 0;
  }
  mapped_.clear();  // munmap before the buffers are freed
  requests_.clear();
  allocator_.reset();
  lc_config_.reset();
  stream_ = nullptr;
}

void LibcameraCamera::ReleaseCamera() {
  if (!camera_) return;
  camera_->requestCompleted.disconnect(this);
  camera_->disconnected.disconnect(this);
  if (!abandoned_) (void)camera_->release();  // an abandoned camera is still running
  abandoned_ = false;
  camera_.reset();
}

Status LibcameraCamera::DoRequestStill(const StillRequest& req, FrameCallback done) {
  return worker_.Post(req, std::move(done), started_);
}

void LibcameraCamera::DoClose() {
  worker_.Stop();
  StopCamera();
  ReleaseCamera();
  manager_.reset();
  neg_ = {};
}

Status LibcameraCamera::QueueStill(libcamera::Request* request) {
  request->reuse(libcamera::Request::ReuseBuffers);
  // The locked values ride on every request, so no frame of the rock can be
  // shot with anything else, whatever the pipeline did in between.
  for (const auto& [id, value] : request_controls_) request->controls().set(id, value);
  {
    std::lock_guard<std::mutex> l(mu_);
    ++in_flight_;  // before queueing: the completion may come first
  }
  if (const int r = camera_->queueRequest(request); r < 0) {
    std::lock_guard<std::mutex> l(mu_);
    --in_flight_;
    idle_.push_back(request);
    const bool gone = disconnected_ || r == -ENODEV || NodesGone();
    return LibcameraError(id_, "queueing a request", gone ? -ENODEV : r, true);
  }
  return OkStatus();
}

// Pipelines need several requests in flight to stream at all (vimc's
// capture node starts only with two buffers queued), so while a still is
// pending every idle request is queued, and the first good frame whose
// exposure began after the request is the still. Between stills the
// requests drain and the pipeline idles; what completed meanwhile is stale.
Result<FramePtr> LibcameraCamera::Capture(const Job& job) {
  const int64_t deadline = job.requested_mono_ns + config_.libcamera.frame_timeout;
  std::string unsettled;   // why the last fresh frame was not the still
  bool cancelled = false;  // the pipeline cancelled a request: queue nothing more
  uint64_t bad = 0;        // frames flagged bad during this still
  for (;;) {
    std::vector<libcamera::Request*> to_queue;
    std::deque<libcamera::Request*> got;
    {
      std::unique_lock<std::mutex> l(mu_);
      for (;;) {
        if (worker_.stopping_locked())
          return MakeError(ErrorClass::kInvalidState, "camera closed while a still was pending");
        if (disconnected_ || (cancelled && NodesGone()))
          return MakeError(ErrorClass::kDisconnected,
                           "camera " + id_ +
                               " went away while a still was pending — check the cable; it is "
                               "reopened on reset");
        if (!completed_.empty()) {
          got.swap(completed_);
          break;
        }
        // After a cancellation nothing is queued again: a camera that went
        // away says so (disconnected) before the deadline, else it is a fault.
        if (!cancelled && !idle_.empty()) {
          to_queue.swap(idle_);
          break;
        }
        const int64_t now = MonotonicNs();
        if (now >= deadline && NodesGone()) {
          disconnected_ = true;
          continue;  // reported as disconnected above
        }
        if (now >= deadline) {
          const std::string within = " within " + SecondsText(config_.libcamera.frame_timeout);
          if (cancelled)
            return MakeError(ErrorClass::kDeviceFault,
                             "camera " + id_ +
                                 ": the pipeline cancelled the still's requests — the camera is "
                                 "reconfigured on reset");
          if (!unsettled.empty())
            return MakeError(ErrorClass::kDeviceFault,
                             "camera " + id_ + " did not apply the locked settings" + within +
                                 ": its last frame had " + unsettled);
          if (bad > 0)
            return MakeError(ErrorClass::kDeviceFault,
                             "camera " + id_ + ": only frames flagged bad (" + std::to_string(bad) +
                                 ")" + within + " of the still request");
          return MakeError(ErrorClass::kTimeout,
                           "camera " + id_ + ": no frame" + within +
                               " of the still request — check the camera and its cable");
        }
        // After a cancellation, look for the vanished node now and then: it
        // goes a moment after the device stops answering.
        const int64_t slice =
            cancelled ? std::min<int64_t>(deadline - now, 50'000'000) : deadline - now;
        cv_.wait_for(l, std::chrono::nanoseconds(slice));
      }
    }
    for (size_t i = 0; i < to_queue.size(); ++i) {
      if (Status s = QueueStill(to_queue[i]); !s) {
        std::lock_guard<std::mutex> l(mu_);
        idle_.insert(idle_.end(), to_queue.begin() + static_cast<std::ptrdiff_t>(i) + 1,
                     to_queue.end());
        return s.error();
      }
    }
    libcamera::Request* still = nullptr;
    ReadBack still_rb;
    for (libcamera::Request* r : got) {
      if (still != nullptr) continue;  // frames after the still: back to the pool below
      if (r->status() == libcamera::Request::RequestCancelled) {
        cancelled = true;  // a stop or disconnected_ tell why, else the deadline does
        continue;
      }
      const libcamera::FrameBuffer* fb = r->findBuffer(stream_);
      if (fb == nullptr || fb->metadata().status != libcamera::FrameMetadata::FrameSuccess) {
        ++corrupt_frames_;
        ++bad;
        continue;
      }
      if (FrameTimestamp(r) < job.requested_mono_ns) {
        ++stale_frames_;
        continue;
      }
      const ReadBack rb = ReadMetadata(r->metadata());
      if (std::string why = UnsettledReason(rb, active_, neg_.missing_controls); !why.empty()) {
        ++unsettled_frames_;
        unsettled = why;
        continue;
      }
      still = r;
      still_rb = rb;
    }
    Result<FramePtr> frame = MakeError(ErrorClass::kInternal, "no still");
    if (still != nullptr) frame = MakeFrame(job, still, still_rb);
    {
      std::lock_guard<std::mutex> l(mu_);
      idle_.insert(idle_.end(), got.begin(), got.end());
    }
    if (still != nullptr) return frame;
  }
}

int64_t LibcameraCamera::FrameTimestamp(libcamera::Request* request) const {
  // SensorTimestamp: start of exposure of the first line, CLOCK_MONOTONIC;
  // else the buffer's own timestamp (same clock).
  if (const auto ts = request->metadata().get(libcamera::controls::SensorTimestamp)) return *ts;
  const libcamera::FrameBuffer* fb = request->findBuffer(stream_);
  return fb ? static_cast<int64_t>(fb->metadata().timestamp) : 0;
}

Result<FramePtr> LibcameraCamera::MakeFrame(const Job& job, libcamera::Request* request,
                                            const ReadBack& rb) {
  const libcamera::FrameBuffer* fb = request->findBuffer(stream_);
  const libcamera::FrameMetadata& md = fb->metadata();
  const MappedFrame& mf = mapped_.at(fb);
  // One plane is encoded in place; several (NV12 on some pipelines) are
  // joined first, in the layout the converter expects (plane after plane).
  std::vector<uint8_t> joined;
  std::span<const uint8_t> bytes;
  const auto planes = md.planes();
  if (fb->planes().size() == 1) {
    bytes = std::span<const uint8_t>(mf.planes[0],
                                     std::min<size_t>(planes[0].bytesused, fb->planes()[0].length));
  } else {
    for (size_t i = 0; i < fb->planes().size(); ++i)
      joined.insert(joined.end(), mf.planes[i],
                    mf.planes[i] + std::min<size_t>(planes[i].bytesused, fb->planes()[i].length));
    bytes = joined;
  }
  Result<std::shared_ptr<Frame>> made =
      v4l2::EncodeStillFrame(id_, V4l2FourCcFor(neg_.format), bytes, neg_.width, neg_.height,
                             neg_.stride, active_.jpeg_quality, job.req.request_id, md.sequence);
  if (!made) return made.error();
  std::shared_ptr<Frame> frame = std::move(*made);
  StampExposure(frame.get(), clock_, FrameTimestamp(request));
  // The metadata's values where the pipeline reports them; else, for manual
  // exposure, the values the camera accepted as controls (a setting without
  // a control, or an automatic one not reported, reads 0 / 1).
  auto has = [&](const char* name) {
    return active_.manual_exposure &&
           std::find(neg_.missing_controls.begin(), neg_.missing_controls.end(), name) ==
               neg_.missing_controls.end();
  };
  frame->exposure_us = rb.has_exposure ? rb.exposure_us : has("exposure") ? active_.exposure_us : 0;
  frame->gain = rb.has_gain ? rb.gain : has("gain") ? active_.gain : 0;
  frame->wb_red = rb.has_wb ? rb.wb_red : has("wb_red") ? active_.wb_red : 1;
  frame->wb_blue = rb.has_wb ? rb.wb_blue : has("wb_blue") ? active_.wb_blue : 1;
  frame->missing_controls = neg_.missing_controls;
  return FramePtr(std::move(frame));
}

}  // namespace aggscan::lc
