#include "drivers/v4l2/v4l2_camera.h"

#include <fcntl.h>
#include <linux/videodev2.h>
#include <poll.h>
#include <sys/ioctl.h>
#include <sys/mman.h>
#include <time.h>
#include <unistd.h>

#include <cerrno>
#include <cmath>
#include <cstring>
#include <span>
#include <utility>

#include "common/log.h"

namespace aggscan::v4l2 {
namespace {

constexpr const char* kLog = "v4l2";

// ioctl restarted on EINTR, as every V4L2 client must.
int Xioctl(int fd, unsigned long req, void* arg) {
  int r;
  do {
    r = ::ioctl(fd, req, arg);
  } while (r < 0 && errno == EINTR);
  return r;
}

}  // namespace

UniqueFd& UniqueFd::operator=(UniqueFd&& o) noexcept {
  if (this != &o) {
    Reset();
    fd_ = o.Release();
  }
  return *this;
}
int UniqueFd::Release() { return std::exchange(fd_, -1); }
void UniqueFd::Reset() {
  if (fd_ >= 0) ::close(fd_);
  fd_ = -1;
}

MappedBuffer::~MappedBuffer() {
  if (addr_ != nullptr) ::munmap(addr_, length_);
}

V4l2Camera::V4l2Camera(Clock& clock, const CameraConfig& config) : clock_(clock), config_(config) {}

V4l2Camera::~V4l2Camera() { DoClose(); }

CameraInfo V4l2Camera::Info() const {
  return {config_.id, "v4l2", model_.empty() ? config_.device : model_};
}

std::string V4l2Camera::device_path() const { return path_; }

V4l2Negotiated V4l2Camera::negotiated() const { return neg_; }

Error V4l2Camera::Fail(const std::string& what, int err) const {
  return V4l2Error(path_.empty() ? config_.device : path_, what, err,
                   streaming_ || !model_.empty());
}

Status V4l2Camera::DoOpen() {
  Result<std::string> path = ResolveDevice(config_.device);
  if (!path) return path.error();
  path_ = *path;
  const int fd = ::open(path_.c_str(), O_RDWR | O_NONBLOCK | O_CLOEXEC);
  if (fd < 0) {
    const int err = errno;
    return V4l2Error(path_, "open", err, false);
  }
  UniqueFd owned(fd);
  v4l2_capability cap{};
  if (Xioctl(owned.get(), VIDIOC_QUERYCAP, &cap) < 0) {
    const int err = errno;
    if (err == ENOTTY)
      return MakeError(ErrorClass::kInvalidConfig, "camera " + path_ + " is not a V4L2 device");
    return V4l2Error(path_, "VIDIOC_QUERYCAP", err, false);
  }
  const uint32_t caps =
      (cap.capabilities & V4L2_CAP_DEVICE_CAPS) ? cap.device_caps : cap.capabilities;
  if (!(caps & V4L2_CAP_VIDEO_CAPTURE) || !(caps & V4L2_CAP_STREAMING)) {
    char hex[16];
    std::snprintf(hex, sizeof hex, "0x%08x", caps);
    return MakeError(ErrorClass::kInvalidConfig,
                     "camera " + path_ + " (" + reinterpret_cast<const char*>(cap.card) +
                         ") is not a streaming single-planar capture node (caps " + hex +
                         "); pick its capture node, e.g. with v4l2-ctl --list-devices");
  }
  model_ = std::string(reinterpret_cast<const char*>(cap.card)) + " (" +
           reinterpret_cast<const char*>(cap.driver) + ", " +
           reinterpret_cast<const char*>(cap.bus_info) + ")";
  fd_ = std::move(owned);
  worker_.Start(kLog, path_, [this](const Job& job) { return Capture(job); });
  AGG_LOGI(kLog, "opened %s: %s", path_.c_str(), model_.c_str());
  return OkStatus();
}

std::optional<ControlRange> V4l2Camera::Query(uint32_t id) const {
  v4l2_queryctrl q{};
  q.id = id;
  if (Xioctl(fd_.get(), VIDIOC_QUERYCTRL, &q) < 0) return std::nullopt;
  if (q.flags & V4L2_CTRL_FLAG_DISABLED) return std::nullopt;
  return ControlRange{q.minimum, q.maximum, q.step, q.default_value};
}

Result<int64_t> V4l2Camera::Get(uint32_t id) const {
  v4l2_control c{};
  c.id = id;
  if (Xioctl(fd_.get(), VIDIOC_G_CTRL, &c) < 0) return Fail("VIDIOC_G_CTRL", errno);
  return static_cast<int64_t>(c.value);
}

Status V4l2Camera::SetAndVerify(uint32_t id, const char* what, int64_t value) {
  v4l2_control c{};
  c.id = id;
  c.value = static_cast<int32_t>(value);
  if (Xioctl(fd_.get(), VIDIOC_S_CTRL, &c) < 0) return Fail(std::string("setting ") + what, errno);
  Result<int64_t> back = Get(id);
  if (!back) return back.error();
  if (*back != value) {
    return MakeError(ErrorClass::kDeviceFault, "camera " + path_ + " did not keep " + what +
                                                   ": set " + std::to_string(value) +
                                                   ", reads back " + std::to_string(*back) +
                                                   " (an automatic mode may still be on)");
  }
  return OkStatus();
}

Status V4l2Camera::ApplyControls(const CameraSettings& s, std::vector<std::string>* missing) {
  gain_range_.reset();
  red_range_.reset();
  blue_range_.reset();
  gain_id_ = 0;
  // Found in either mode, so frames report the gain and balance in effect.
  for (uint32_t id :
       {static_cast<uint32_t>(V4L2_CID_GAIN), static_cast<uint32_t>(V4L2_CID_ANALOGUE_GAIN)}) {
    if (auto r = Query(id)) {
      gain_range_ = r;
      gain_id_ = id;
      break;
    }
  }
  if (!s.manual_exposure) {
    red_range_ = Query(V4L2_CID_RED_BALANCE);
    blue_range_ = Query(V4L2_CID_BLUE_BALANCE);
  }
  // Automatic modes off first: their values are volatile while they run.
  auto set_if_present = [&](uint32_t id, const char* what, int64_t v) -> Status {
    if (!Query(id)) return OkStatus();
    return SetAndVerify(id, what, v);
  };
  if (s.manual_exposure) {
    if (Status st = set_if_present(V4L2_CID_EXPOSURE_AUTO, "auto exposure mode (manual)",
                                   V4L2_EXPOSURE_MANUAL);
        !st)
      return st;
    // UVC: do not let the camera stretch the exposure by lowering the frame rate.
    if (Status st =
            set_if_present(V4L2_CID_EXPOSURE_AUTO_PRIORITY, "exposure auto priority (off)", 0);
        !st)
      return st;
    if (auto r = Query(V4L2_CID_EXPOSURE_ABSOLUTE)) {
      Result<int64_t> v = QuantizeControl(*r, ExposureUsToV4l2(s.exposure_us), "exposure");
      if (!v) return v.error();
      if (Status st = SetAndVerify(V4L2_CID_EXPOSURE_ABSOLUTE, "exposure", *v); !st) return st;
    } else {
      missing->push_back("exposure");
    }
    if (Status st = set_if_present(V4L2_CID_AUTOGAIN, "auto gain (off)", 0); !st) return st;
    if (gain_range_) {
      Result<double> dv = UnitlessToDevice(*gain_range_, s.gain, config_.v4l2.gain_unit, "gain");
      if (!dv) return dv.error();
      Result<int64_t> v = QuantizeControl(*gain_range_, *dv, "gain");
      if (!v) return v.error();
      if (Status st = SetAndVerify(gain_id_, "gain", *v); !st) return st;
    } else {
      missing->push_back("gain");
    }
    if (Status st = set_if_present(V4L2_CID_AUTO_WHITE_BALANCE, "auto white balance (off)", 0); !st)
      return st;
    struct Wb {
      uint32_t id;
      double factor;
      const char* name;
      std::optional<ControlRange>* range;
    };
    for (const Wb& wb : {Wb{V4L2_CID_RED_BALANCE, s.wb_red, "wb_red", &red_range_},
                         Wb{V4L2_CID_BLUE_BALANCE, s.wb_blue, "wb_blue", &blue_range_}}) {
      auto r = Query(wb.id);
      if (!r) {
        missing->push_back(wb.name);
        continue;
      }
      Result<double> dv = UnitlessToDevice(*r, wb.factor, 0, wb.name);
      if (!dv) return dv.error();
      Result<int64_t> v = QuantizeControl(*r, *dv, wb.name);
      if (!v) return v.error();
      if (Status st = SetAndVerify(wb.id, wb.name, *v); !st) return st;
      *wb.range = r;
    }
  } else {
    // Automatic exposure wanted: switch the automatic modes on where they exist;
    // UVC cameras often accept only aperture priority as "auto".
    if (Query(V4L2_CID_EXPOSURE_AUTO) &&
        !SetAndVerify(V4L2_CID_EXPOSURE_AUTO, "auto exposure", V4L2_EXPOSURE_AUTO).ok()) {
      (void)SetAndVerify(V4L2_CID_EXPOSURE_AUTO, "auto exposure", V4L2_EXPOSURE_APERTURE_PRIORITY);
    }
    if (Status st = set_if_present(V4L2_CID_AUTOGAIN, "auto gain (on)", 1); !st) return st;
    if (Status st = set_if_present(V4L2_CID_AUTO_WHITE_BALANCE, "auto white balance (on)", 1); !st)
      return st;
  }
  if (config_.v4l2.focus >= 0) {
    if (Status st = set_if_present(V4L2_CID_FOCUS_AUTO, "autofocus (off)", 0); !st) return st;
    if (auto r = Query(V4L2_CID_FOCUS_ABSOLUTE)) {
      Result<int64_t> v = QuantizeControl(*r, config_.v4l2.focus, "focus");
      if (!v) return v.error();
      if (Status st = SetAndVerify(V4L2_CID_FOCUS_ABSOLUTE, "focus", *v); !st) return st;
    } else {
      missing->push_back("focus");
    }
  }
  if (!missing->empty()) {
    std::string list;
    for (const auto& m : *missing) list += (list.empty() ? "" : ", ") + m;
    if (config_.v4l2.strict_controls) {
      return MakeError(
          ErrorClass::kInvalidConfig,
          "camera " + path_ + " (" + model_ + ") has no control for " + list +
              ", so those settings cannot be locked; use a camera that has them or set "
              "camera.v4l2.strict_controls = false to shoot with the device's own values");
    }
    AGG_LOGW(kLog, "%s has no control for %s; frames report these as missing", path_.c_str(),
             list.c_str());
  }
  return OkStatus();
}

V4l2Camera::ReadBack V4l2Camera::ReadControls() const {
  ReadBack rb;
  if (Query(V4L2_CID_EXPOSURE_ABSOLUTE)) {
    if (auto v = Get(V4L2_CID_EXPOSURE_ABSOLUTE)) rb.exposure_us = V4l2ToExposureUs(*v);
  }
  auto factor = [&](uint32_t id, const std::optional<ControlRange>& r, int unit, double* out) {
    if (!r || id == 0) return;
    const double ref = unit > 0 ? unit : static_cast<double>(r->default_value);
    if (auto v = Get(id); v && ref > 0) *out = static_cast<double>(*v) / ref;
  };
  factor(gain_id_, gain_range_, config_.v4l2.gain_unit, &rb.gain);
  factor(V4L2_CID_RED_BALANCE, red_range_, 0, &rb.wb_red);
  factor(V4L2_CID_BLUE_BALANCE, blue_range_, 0, &rb.wb_blue);
  return rb;
}

Status V4l2Camera::DoConfigure(const CameraSettings& settings) {
  if (!fd_.valid()) return MakeError(ErrorClass::kInvalidState, "camera is not open");
  StopStreaming();  // a second Configure renegotiates from scratch

  V4l2Negotiated neg;
  for (uint32_t i = 0;; ++i) {
    v4l2_fmtdesc d{};
    d.index = i;
    d.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    if (Xioctl(fd_.get(), VIDIOC_ENUM_FMT, &d) < 0) {
      if (errno == EINVAL) break;  // end of the list
      return Fail("VIDIOC_ENUM_FMT", errno);
    }
    neg.offered.push_back(d.pixelformat);
  }
  Result<uint32_t> fourcc = ChooseFormat(neg.offered, config_.v4l2.pixel_format);
  if (!fourcc) return fourcc.error();

  v4l2_format f{};
  f.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
  f.fmt.pix.width = static_cast<uint32_t>(settings.width);
  f.fmt.pix.height = static_cast<uint32_t>(settings.height);
  f.fmt.pix.pixelformat = *fourcc;
  f.fmt.pix.field = V4L2_FIELD_NONE;
  if (Xioctl(fd_.get(), VIDIOC_S_FMT, &f) < 0) return Fail("VIDIOC_S_FMT", errno);
  v4l2_format g{};
  g.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
  if (Xioctl(fd_.get(), VIDIOC_G_FMT, &g) < 0) return Fail("VIDIOC_G_FMT", errno);
  neg.fourcc = g.fmt.pix.pixelformat;
  neg.width = static_cast<int>(g.fmt.pix.width);
  neg.height = static_cast<int>(g.fmt.pix.height);
  neg.bytes_per_line = static_cast<int>(g.fmt.pix.bytesperline);
  neg.size_image = g.fmt.pix.sizeimage;
  if (neg.fourcc != *fourcc || neg.width != settings.width || neg.height != settings.height) {
    return MakeError(ErrorClass::kInvalidConfig,
                     "camera " + path_ + " cannot deliver " + FourCcName(*fourcc) + " " +
                         std::to_string(settings.width) + "x" + std::to_string(settings.height) +
                         "; it offers " + FourCcName(neg.fourcc) + " " + std::to_string(neg.width) +
                         "x" + std::to_string(neg.height) +
                         " instead: set camera.width/height to a size it has "
                         "(v4l2-ctl --list-formats-ext)");
  }
  if (g.fmt.pix.field != V4L2_FIELD_NONE && g.fmt.pix.field != V4L2_FIELD_ANY) {
    return MakeError(
        ErrorClass::kInvalidConfig,
        "camera " + path_ + " delivers interlaced fields; a progressive camera is needed");
  }

  Status ctl = ApplyControls(settings, &neg.missing_controls);
  if (!ctl) return ctl;

  frame_period_ns_ = 0;
  v4l2_streamparm parm{};
  parm.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
  if (Xioctl(fd_.get(), VIDIOC_G_PARM, &parm) == 0 &&
      parm.parm.capture.timeperframe.denominator > 0) {
    frame_period_ns_ = static_cast<int64_t>(parm.parm.capture.timeperframe.numerator) *
                       1'000'000'000 / parm.parm.capture.timeperframe.denominator;
  }

  active_ = settings;
  neg_ = neg;
  Status st = StartStreaming();
  if (!st) return st;
  AGG_LOGI(kLog, "%s: %s %dx%d (bytesperline %d), %zu buffers", path_.c_str(),
           FourCcName(neg_.fourcc).c_str(), neg_.width, neg_.height, neg_.bytes_per_line,
           buffers_.size());
  return OkStatus();
}

Status V4l2Camera::StartStreaming() {
  v4l2_requestbuffers rb{};
  rb.count = static_cast<uint32_t>(config_.v4l2.buffers);
  rb.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
  rb.memory = V4L2_MEMORY_MMAP;
  if (Xioctl(fd_.get(), VIDIOC_REQBUFS, &rb) < 0) return Fail("VIDIOC_REQBUFS", errno);
  if (rb.count < 2) {
    StopStreaming();
    return MakeError(ErrorClass::kDeviceFault, "camera " + path_ + " granted only " +
                                                   std::to_string(rb.count) + " buffer(s)");
  }
  for (uint32_t i = 0; i < rb.count; ++i) {
    v4l2_buffer b{};
    b.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    b.memory = V4L2_MEMORY_MMAP;
    b.index = i;
    if (Xioctl(fd_.get(), VIDIOC_QUERYBUF, &b) < 0) {
      Error e = Fail("VIDIOC_QUERYBUF", errno);
      StopStreaming();
      return e;
    }
    void* p = ::mmap(nullptr, b.length, PROT_READ | PROT_WRITE, MAP_SHARED, fd_.get(), b.m.offset);
    if (p == MAP_FAILED) {
      Error e = Fail("mmap", errno);
      StopStreaming();
      return e;
    }
    buffers_.emplace_back(p, b.length);
    // Queued as soon as it is mapped: the driver fills it once streaming.
    if (Xioctl(fd_.get(), VIDIOC_QBUF, &b) < 0) {
      Error e = Fail("VIDIOC_QBUF", errno);
      StopStreaming();
      return e;
    }
  }
  int type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
  if (Xioctl(fd_.get(), VIDIOC_STREAMON, &type) < 0) {
    Error e = Fail("VIDIOC_STREAMON", errno);
    StopStreaming();
    return e;
  }
  streaming_ = true;
  return OkStatus();
}

void V4l2Camera::StopStreaming() {
  if (!fd_.valid()) {
    buffers_.clear();
    streaming_ = false;
    return;
  }
  if (streaming_) {
    int type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    (void)Xioctl(fd_.get(), VIDIOC_STREAMOFF, &type);  // fails harmlessly on a vanished device
    streaming_ = false;
  }
  buffers_.clear();  // munmap before the driver frees the buffers
  v4l2_requestbuffers rb{};
  rb.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
  rb.memory = V4L2_MEMORY_MMAP;
  rb.count = 0;
  (void)Xioctl(fd_.get(), VIDIOC_REQBUFS, &rb);
}

Status V4l2Camera::DoRequestStill(const StillRequest& req, FrameCallback done) {
  return worker_.Post(req, std::move(done), streaming_);
}

void V4l2Camera::DoClose() {
  worker_.Stop();
  StopStreaming();
  fd_.Reset();
  neg_ = {};
}

Result<FramePtr> V4l2Camera::Capture(const Job& job) {
  const int64_t deadline = job.requested_mono_ns + config_.v4l2.frame_timeout;
  auto requeue = [&](v4l2_buffer& b) -> Status {
    if (Xioctl(fd_.get(), VIDIOC_QBUF, &b) < 0) return Fail("VIDIOC_QBUF", errno);
    return OkStatus();
  };
  for (;;) {
    {
      std::lock_guard<std::mutex> l(mu_);
      if (worker_.stopping_locked())
        return MakeError(ErrorClass::kInvalidState, "camera closed while a still was pending");
    }
    const int64_t now = MonotonicNs();
    if (now >= deadline) {
      return MakeError(ErrorClass::kTimeout,
                       "camera " + path_ + ": no frame within " +
                           SecondsText(config_.v4l2.frame_timeout) +
                           " of the still request — check the camera and its cable");
    }
    // Short slices so Close() is never kept waiting for long.
    const int wait_ms = static_cast<int>(std::min<int64_t>((deadline - now) / 1'000'000 + 1, 50));
    pollfd p{fd_.get(), POLLIN, 0};
    const int pr = ::poll(&p, 1, wait_ms);
    if (pr < 0) {
      if (errno == EINTR) continue;
      return Fail("poll", errno);
    }
    if (pr == 0) continue;
    v4l2_buffer b{};
    b.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    b.memory = V4L2_MEMORY_MMAP;
    if (Xioctl(fd_.get(), VIDIOC_DQBUF, &b) < 0) {
      const int err = errno;
      if (err == EAGAIN) {
        // POLLERR without a buffer: the driver put the queue in an error
        // state (a vanished device answers DQBUF with ENODEV instead).
        if (p.revents & (POLLERR | POLLHUP))
          return MakeError(ErrorClass::kDeviceFault,
                           "camera " + path_ +
                               ": the driver stopped the stream with an error — "
                               "the camera is reconfigured on reset");
        continue;
      }
      return Fail("VIDIOC_DQBUF", err);
    }
    if (b.index >= buffers_.size())
      return MakeError(ErrorClass::kInternal, "driver returned an unknown buffer index");
    const bool mono = (b.flags & V4L2_BUF_FLAG_TIMESTAMP_MASK) == V4L2_BUF_FLAG_TIMESTAMP_MONOTONIC;
    int64_t ts =
        static_cast<int64_t>(b.timestamp.tv_sec) * 1'000'000'000 + b.timestamp.tv_usec * 1000;
    // Most drivers stamp the end of the frame: its start is one frame period
    // earlier (the best estimate V4L2 gives).
    if ((b.flags & V4L2_BUF_FLAG_TSTAMP_SRC_MASK) == V4L2_BUF_FLAG_TSTAMP_SRC_EOF)
      ts -= frame_period_ns_;
    // A corrupted frame, or one whose exposure started before the request
    // (stale in the queue): hand the buffer back and wait for the next.
    if ((b.flags & V4L2_BUF_FLAG_ERROR) || (mono && ts < job.requested_mono_ns)) {
      ++((b.flags & V4L2_BUF_FLAG_ERROR) ? corrupt_frames_ : stale_frames_);
      if (Status s = requeue(b); !s) return s.error();
      continue;
    }
    Result<FramePtr> frame = MakeFrame(job, buffers_[b.index].data(),
                                       std::min<size_t>(b.bytesused, buffers_[b.index].length()),
                                       mono ? ts : MonotonicNs(), b.sequence);
    if (Status s = requeue(b); !s) return s.error();
    return frame;
  }
}

Result<FramePtr> V4l2Camera::MakeFrame(const Job& job, const uint8_t* data, size_t bytes,
                                       int64_t ts_mono_ns, uint64_t sequence) {
  // MJPEG: the camera's own JPEG is the still, no decode and no second compression.
  Result<std::shared_ptr<Frame>> made = EncodeStillFrame(
      path_, neg_.fourcc, std::span<const uint8_t>(data, bytes), neg_.width, neg_.height,
      neg_.bytes_per_line, active_.jpeg_quality, job.req.request_id, sequence);
  if (!made) return made.error();
  std::shared_ptr<Frame> frame = std::move(*made);
  StampExposure(frame.get(), clock_, ts_mono_ns);
  const ReadBack rb = ReadControls();
  frame->exposure_us = rb.exposure_us;
  frame->gain = rb.gain;
  frame->wb_red = rb.wb_red;
  frame->wb_blue = rb.wb_blue;
  frame->missing_controls = neg_.missing_controls;
  return FramePtr(std::move(frame));
}

}  // namespace aggscan::v4l2
