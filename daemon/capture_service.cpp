#include "daemon/capture_service.h"

#include <sys/statvfs.h>

#include <algorithm>
#include <atomic>
#include <cerrno>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <future>
#include <sstream>

#include "common/fsutil.h"
#include "common/json_io.h"
#include "common/log.h"
#include "daemon/calibration_check.h"
#include "store/batches.h"
#include "store/layout.h"
#include "store/library_csv.h"
#include "store/sample_meta.h"

namespace aggscan {

using nlohmann::json;
namespace cs = capture;

namespace {
// A shot later than its due time by more than this counts as a schedule overrun.
constexpr TimeNs kOverrunTolerance = 50 * kNsPerMs;
// Motion smaller than this between polls counts as "not advancing" (stall detection).
constexpr double kStallEpsilonDeg = 0.01;
// The longest an API call waits for the loop (a call's own deadline may be
// sooner): below the CLI's 30 s read timeout, so a client always learns
// whether its command ran.
constexpr auto kApiWait = std::chrono::seconds(5);
// Failed jobs listed in the status (newest first); the total is counted too.
constexpr int kStatusFailedJobs = 20;

// One worker job as the status, sample and retry answers show it.
json JobJson(const Job& j) {
  return {{"sample_id", j.sample_id},
          {"side", j.side},
          {"state", j.state},
          {"attempts", j.attempts},
          {"interruptions", j.interruptions},
          {"error", j.error},
          {"updated_utc", j.updated_utc}};
}

SamplePlan PlanFromConfig(const Config& c) {
  SamplePlan p;
  p.profile = c.capture.profile;
  p.sides = c.capture.sides;
  p.views_per_side = c.capture.views_per_side;
  p.step_deg = c.capture.step_deg;
  p.interval_ms = c.capture.interval / kNsPerMs;
  return p;
}

std::string Deg(double d) {
  char b[32];
  std::snprintf(b, sizeof b, "%.2f", d);
  return b;
}

// Why a motion that came to rest never counted as finished: where the platter
// stood against the target and the key of the backend's in-position window.
std::string RestedOutOfPosition(const TurntableConfig& tt, double angle_deg, double target_deg) {
  const double off = angle_deg - target_deg;
  std::string key;
  double window_deg = 0, steps_per_rev = 0;
  if (tt.backend == "modbus-tcp" || tt.backend == "modbus-rtu") {
    key = "turntable.modbus.in_position_window_deg";
    window_deg = tt.modbus.in_position_window_deg;
    steps_per_rev = tt.modbus.steps_per_rev();
  } else if (tt.backend == "usb-tic") {
    key = "turntable.usb.in_position_window_deg";
    window_deg = tt.usb.in_position_window_deg;
    steps_per_rev = tt.usb.steps_per_rev();
  }
  char b[256];
  std::snprintf(b, sizeof b, "the platter came to rest at %.3f deg, %+.3f deg from the target",
                angle_deg, off);
  std::string msg = b;
  if (steps_per_rev > 0) {
    std::snprintf(b, sizeof b, " (%+lld steps at %.0f steps per turn)",
                  std::llround(off * steps_per_rev / 360.0), steps_per_rev);
    msg += b;
    window_deg =
        std::max(window_deg, 360.0 / steps_per_rev);  // the backends' window is at least a step
  }
  if (key.empty()) return msg;
  if (std::fabs(off) > window_deg) {
    std::snprintf(b, sizeof b, "%.3f", window_deg);
    msg += ", outside " + key + " = " + b + " deg: if the drive cannot settle closer, raise " + key;
    std::snprintf(b, sizeof b, "%.3f", std::fabs(off));
    msg +=
        std::string(" above ") + b + " deg, else check the drive's tuning and the gear's backlash";
  } else {
    msg += ", inside " + key +
           ", but the controller never reported in position: check its own in-position "
           "setting";
  }
  return msg;
}

std::string Mb(int64_t bytes) {
  char b[32];
  std::snprintf(b, sizeof b, "%.1f MB", static_cast<double>(bytes) / 1e6);
  return b;
}

// JPEG bytes per pixel of a rig view: a side of 30 views at 2016x1512 takes
// about 9.3 MB (sim rig, default quality), i.e. 0.102 B/px. Used until the
// sample has views of its own to measure.
constexpr double kJpegBytesPerPixel = 9.3e6 / (2016.0 * 1512.0 * 30.0);
// A view's sidecar JSON (about 1 kB) rounded up to a filesystem block.
constexpr int64_t kSidecarBytes = 4096;
// JPEG size follows the scene (a textured rock, a flipped pose): the side is
// only started with half as much again free, plus room for the manifest,
// the record rewrites and the queue's journal.
constexpr double kSideMargin = 1.5;
constexpr int64_t kSideFixedBytes = 1 << 20;
}  // namespace

CaptureService::CaptureService(EventLoop& loop, Config config, std::string effective_config_toml,
                               RigDevices devices, SampleStore& store, JobQueue* queue)
    : loop_(loop),
      config_(std::move(config)),
      config_toml_(std::move(effective_config_toml)),
      dev_(std::move(devices)),
      store_(store),
      cal_store_(store.state_dir(), layout::kCalibrationCollection),
      reports_(store.state_dir()),
      queue_(queue) {
  started_real_ = MonotonicNs();
  // The status shows the latest calibration capture, also after a restart.
  if (Result<json> cals = cal_store_.List(); cals && cals->is_array()) {
    for (const json& c : *cals) {
      const std::string id = c.value("id", "");
      if (id.rfind(layout::kCalibrationIdPrefix, 0) == 0) cal_last_id_ = id;
    }
  }
  for (const char* name : {"camera", "turntable", "button"}) {
    health_[name].message = std::string(name) + ": not opened yet";
  }
  if (dev_.light) health_["light"].message = "light: not opened yet";
}

CaptureService::~CaptureService() {
  if (preview_ != nullptr) preview_->SetOnDemand({});
  if (dev_.light) dev_.light->Close();
  if (dev_.button) dev_.button->Stop();
  if (dev_.camera) dev_.camera->Close();
  if (dev_.turntable) dev_.turntable->Close();
}

// What an API call answers when the loop cannot (stopping, or a bug).
template <typename R>
R Unavailable() {
  if constexpr (std::is_same_v<R, json>) {
    return json{{"state", "unavailable"}, {"status_line", "aggscand is stopping or busy"}};
  } else if constexpr (std::is_same_v<R, std::string>) {
    return std::string("# aggscand is stopping or busy\n");
  } else {
    return MakeError(ErrorClass::kInternal,
                     "aggscand could not run this request (stopping, or an internal error)");
  }
}

// What an API call answers when it was dropped without running: `why` says why.
template <typename R>
R NotRun(ErrorClass cls, const std::string& why) {
  if constexpr (std::is_same_v<R, json>) {
    return json{{"state", "unavailable"}, {"status_line", why}};
  } else if constexpr (std::is_same_v<R, std::string>) {
    return "# " + why + "\n";
  } else {
    return MakeError(cls, why);
  }
}

template <typename F>
auto CaptureService::OnLoop(F fn, const CallContext& ctx) -> decltype(fn()) {
  using R = decltype(fn());
  using Clock = std::chrono::steady_clock;
  // The closure and the waiter race for the call: whichever moves it out of
  // kPending decides whether it runs. A waiter that gave up has moved it to
  // kDropped, so the closure, however late the loop gets to it, never runs fn.
  enum Stage : int { kPending, kStarted, kDropped };
  struct Call {
    std::atomic<int> stage{kPending};
    std::promise<R> prom;
  };
  if (loop_.stopped())
    return NotRun<R>(ErrorClass::kInternal, "aggscand is stopping: the request was not run");
  const auto deadline = std::min(Clock::now() + kApiWait, ctx.deadline);
  const double budget_s = std::chrono::duration<double>(deadline - Clock::now()).count();
  char budget[32];
  std::snprintf(budget, sizeof budget, "%.1f", std::max(0.0, budget_s));
  const std::string late =
      std::string("the capture loop was busy and did not start this request within ") + budget +
      " s: it was dropped and will not run later; check the status and try again";
  auto call = std::make_shared<Call>();
  std::future<R> fut = call->prom.get_future();
  loop_.Post([call, fn, deadline, late, gone = ctx.client_gone]() mutable {
    int expected = kPending;
    if (!call->stage.compare_exchange_strong(expected, kStarted))
      return;  // the waiter gave up on it
    if (Clock::now() >= deadline) {
      call->prom.set_value(NotRun<R>(ErrorClass::kTimeout, late));
      return;
    }
    if (gone && gone()) {
      call->prom.set_value(NotRun<R>(
          ErrorClass::kTimeout, "the client disconnected before the request ran: it was dropped"));
      return;
    }
    try {
      call->prom.set_value(fn());
    } catch (const std::exception& e) {
      // A bug must not take the capture loop down with it.
      AGG_LOGE("capture", "API call failed with an exception: %s", e.what());
      call->prom.set_value(Unavailable<R>());
    }
  });
  // Wait in slices: a daemon that is stopping answers at once.
  for (;;) {
    const auto slice = std::min(deadline, Clock::now() + std::chrono::milliseconds(100));
    if (fut.wait_until(slice) == std::future_status::ready) return fut.get();
    if (!loop_.stopped() && Clock::now() < deadline) continue;
    int expected = kPending;
    if (call->stage.compare_exchange_strong(expected, kDropped)) {
      return loop_.stopped()
                 ? NotRun<R>(ErrorClass::kInternal, "aggscand is stopping: the request was not run")
                 : NotRun<R>(ErrorClass::kTimeout, late);
    }
    // Started just now: it runs to the end on the loop, so its answer is the truth.
    if (fut.wait_for(kApiWait) == std::future_status::ready) return fut.get();
    return NotRun<R>(
        ErrorClass::kTimeout,
        "the request started but gave no answer in time; check the status before repeating it");
  }
}

// ------------------------------------------------------------- live view --

void CaptureService::SetPreviewHub(PreviewHub* hub) {
  if (preview_ != nullptr) preview_->SetOnDemand({});
  preview_ = hub;
  if (hub != nullptr) hub->SetOnDemand([this] { loop_.Post([this] { StartPreview(); }); });
}

void CaptureService::StartPreview() {
  if (preview_ == nullptr || preview_ticking_ || config_.daemon.preview_interval <= 0) return;
  preview_ticking_ = true;
  PreviewTick();
}

void CaptureService::PreviewTick() {
  if (preview_->viewers() == 0 || loop_.stopped()) {
    preview_ticking_ = false;  // the next viewer starts it again
    return;
  }
  // Real time: the live view is for people, whatever the sim clock does.
  loop_.AddRealTimer(MonotonicNs() + config_.daemon.preview_interval, [this] { PreviewTick(); });
  if (preview_in_flight_ || SideRunning() || !dev_.camera) return;
  auto h = health_.find("camera");
  if (h == health_.end() || !h->second.healthy || dev_.camera->state() != Camera::State::kReady)
    return;
  preview_in_flight_ = true;
  const uint64_t gen = preview_generation_;
  StillRequest req{next_request_id_++, state_.sample_id, std::max(1, state_.side), 0};
  req.board = calibration_capture_ && state_.Active();
  Status s = dev_.camera->RequestStill(req, [this, gen](Result<FramePtr> r) {
    loop_.Post([this, gen, r = std::move(r)]() mutable { OnPreviewFrame(gen, std::move(r)); });
  });
  if (!s) OnPreviewFrame(gen, s.error());
}

void CaptureService::OnPreviewFrame(uint64_t generation, Result<FramePtr> frame) {
  if (generation != preview_generation_) return;  // the camera was reopened since
  preview_in_flight_ = false;
  if (frame.ok()) {
    ++previews_shot_;
    preview_log_.Clear("camera", "live view: camera stills arrive again");
    if (preview_ != nullptr) preview_->Submit(*frame, "preview");
  } else {
    ++preview_failures_;
    preview_log_.Error("camera",
                       "live view: the camera gave no still: " + frame.error().ToString() +
                           " (captures are not affected "
                           "unless their stills fail too)");
  }
  if (shot_waits_for_preview_) {
    shot_waits_for_preview_ = false;
    if (state_.phase == cs::Phase::kCapturing && holding_) {
      if (Status s = ShootView(); !s) Fault(s.error().cls, "camera: " + s.error().ToString());
    }
  }
}

Status CaptureService::ShootView() {
  StillRequest req{pending_.request_id, state_.sample_id, pending_.side, pending_.view};
  req.board = calibration_capture_;
  const uint64_t ep = epoch_;
  const uint64_t rid = pending_.request_id;
  Status s = dev_.camera->RequestStill(req, [this, ep, rid](Result<FramePtr> r) {
    loop_.Post([this, ep, rid, r = std::move(r)]() mutable {
      if (ep == epoch_ && rid == pending_.request_id && holding_) {
        holding_ = false;
        loop_.Release();
      }
      if (ep != epoch_ || rid != pending_.request_id) return;  // late answer of an aborted shot
      if (!r.ok()) {
        Fault(r.error().cls, "camera: " + r.error().ToString());
        return;
      }
      pending_.frame = *r;
      Dispatch(cs::FrameReady{});
    });
  });
  if (!s && holding_) {
    holding_ = false;
    loop_.Release();
  }
  return s;
}

// ---------------------------------------------------------------- devices --

void CaptureService::Start() {
  OpenDevices();
  if (config_.daemon.health_probe_interval > 0) {
    loop_.AddRealTimer(MonotonicNs() + config_.daemon.health_probe_interval,
                       [this] { ProbeDevices(); });
  }
  if (queue_ && (config_.worker.silent_after > 0 || events_)) WatchWorker();
  NotifyStatus();
}

void CaptureService::Publish(const std::string& type, json data) {
  if (events_) events_->Publish(type, std::move(data));
}

void CaptureService::WatchWorker() {
  const json w = WorkerOnLoop();
  if (w.is_object()) {
    // Ages tick on every read: what changed is the state, job, stage and progress.
    const json key = {w["state"], w["job"].is_object() ? w["job"]["id"] : json(nullptr), w["stage"],
                      w["progress"]};
    const std::string said = key.dump();
    if (said != published_worker_) {
      published_worker_ = said;
      Publish("worker", w);
    }
    const bool healthy = w.value("healthy", false);
    if (healthy != worker_healthy_) {
      worker_healthy_ = healthy;
      LogLine(healthy ? LogLevel::kNotice : LogLevel::kWarning, "worker", "",
              healthy ? "aggscan-worker is reporting again: " + w.value("message", std::string())
                      : w.value("message", std::string()));
      Publish("health", {{"device", "worker"},
                         {"healthy", healthy},
                         {"state", w["state"]},
                         {"message", w["message"]}});
    }
  }
  // Twice a second while events are followed (the worker's progress);
  // otherwise a quarter of the silence allowed, within 1..5 s: the change is
  // logged soon after it is due without reading the queue often.
  const TimeNs period =
      events_ ? 500 * kNsPerMs
              : std::clamp<TimeNs>(config_.worker.silent_after / 4, kNsPerSec, 5 * kNsPerSec);
  WatchCalibration();
  loop_.AddRealTimer(MonotonicNs() + period, [this] { WatchWorker(); });
}

bool CaptureService::SideRunning() const {
  return state_.Active() && state_.phase != cs::Phase::kArmed &&
         state_.phase != cs::Phase::kAwaitingPose;
}

void CaptureService::ProbeDevices() {
  ProbeButtonAndLight();
  DeviceHealth& h = health_["turntable"];
  if (dev_.turntable && h.healthy && !SideRunning() && dev_.turntable->is_open()) {
    Result<TurntableStatus> st = dev_.turntable->ReadStatus();
    if (st) {
      probe_failures_ = 0;
      h.last_ok_utc_ns = std::chrono::duration_cast<std::chrono::nanoseconds>(
                             std::chrono::system_clock::now().time_since_epoch())
                             .count();
    } else if (++probe_failures_ > config_.capture.comm_retries ||
               st.error().cls == ErrorClass::kDisconnected) {
      probe_failures_ = 0;
      MarkUnhealthy("turntable", st.error().cls, "turntable: " + st.error().ToString());
      ScheduleReopen("turntable");
      NotifyStatus();
    }
  }
  loop_.AddRealTimer(MonotonicNs() + config_.daemon.health_probe_interval,
                     [this] { ProbeDevices(); });
}

void CaptureService::OpenDevices() {
  for (const char* name : {"camera", "turntable", "button", "light"}) {
    if (health_.count(name) && !health_[name].healthy) TryOpen(name);
  }
}

// The button's and the light's threads record a device lost while running
// (unplugged pedal, lost link); here that becomes the device's health, and
// the usual backoff reopens it.
void CaptureService::ProbeButtonAndLight() {
  struct Probe {
    const char* name;
    Status health;
  };
  std::vector<Probe> probes;
  if (dev_.button && health_["button"].healthy) probes.push_back({"button", dev_.button->Health()});
  if (dev_.light && health_["light"].healthy) probes.push_back({"light", dev_.light->Health()});
  for (const Probe& p : probes) {
    if (p.health) continue;
    if (std::string(p.name) == "button") dev_.button->Stop();
    MarkUnhealthy(p.name, p.health.error().cls,
                  std::string(p.name) + ": " + p.health.error().ToString());
    ScheduleReopen(p.name);
    NotifyStatus();
  }
}

Status CaptureService::OpenDevice(const std::string& name) {
  if (name == "camera") {
    if (!dev_.camera)
      return MakeError(ErrorClass::kInvalidConfig, "camera: none configured; check [camera]");
    if (dev_.camera->state() != Camera::State::kClosed) dev_.camera->Close();
    // A live-view still of the closed device never counts.
    ++preview_generation_;
    preview_in_flight_ = false;
    Status s = dev_.camera->Open();
    if (s) s = dev_.camera->Configure(CameraSettingsFor(config_));
    if (!s) dev_.camera->Close();
    return s;
  }
  if (name == "turntable") {
    if (!dev_.turntable)
      return MakeError(ErrorClass::kInvalidConfig, "turntable: none configured; check [turntable]");
    dev_.turntable->Close();
    return dev_.turntable->Open();
  }
  if (name == "light") {
    dev_.light->Close();
    return dev_.light->Open();
  }
  if (!dev_.button)
    return MakeError(ErrorClass::kInvalidConfig, "button: none configured; check [button]");
  dev_.button->Stop();  // a reopen after a runtime fault
  return dev_.button->Start([this](const ButtonPress& p) {
    const std::string src = p.source;
    loop_.Post([this, src] {
      LogLine(LogLevel::kInfo, "capture", state_.sample_id, "start button pressed (" + src + ")");
      // A side must not start with a device it needs unhealthy: it would fault
      // at once, or worse, half-way. The API's press is refused the same way.
      if (state_.phase == cs::Phase::kArmed || state_.phase == cs::Phase::kAwaitingPose) {
        if (Status ok = CheckDevicesHealthy({"camera", "turntable"}); !ok) {
          LogLine(LogLevel::kWarning, "capture", state_.sample_id, ok.error().message);
          return;
        }
        if (Status room = CheckStorageForSide(); !room) {
          LogLine(LogLevel::kWarning, "capture", state_.sample_id, room.error().message);
          return;
        }
      }
      Dispatch(cs::ButtonPressed{});
    });
  });
}

void CaptureService::TryOpen(const std::string& name) {
  DeviceHealth& h = health_[name];
  if (h.retry_timer != 0) {
    loop_.CancelTimer(h.retry_timer);
    h.retry_timer = 0;
    h.next_retry_real = 0;
  }
  Status s = OpenDevice(name);
  h.tried = true;
  if (s) {
    MarkHealthy(name);
    return;
  }
  MarkUnhealthy(name, s.error().cls, name + ": " + s.error().ToString());
  ++h.retries;
  ScheduleReopen(name);
}

void CaptureService::MarkHealthy(const std::string& name) {
  DeviceHealth& h = health_[name];
  const int64_t now = std::chrono::duration_cast<std::chrono::nanoseconds>(
                          std::chrono::system_clock::now().time_since_epoch())
                          .count();
  if (!h.healthy) {
    h.since_utc_ns = now;
    device_log_.ClearPrefix(name + "/", name + ": ok again after " + std::to_string(h.retries) +
                                            " failed open attempt" + (h.retries == 1 ? "" : "s"));
    Publish("health", {{"device", name}, {"healthy", true}, {"state", "ok"}, {"message", "ok"}});
  }
  h.healthy = true;
  h.message = "ok";
  h.last_ok_utc_ns = now;
  h.retries = 0;
  if (h.retry_timer != 0) loop_.CancelTimer(h.retry_timer);
  h.retry_timer = 0;
  h.next_retry_real = 0;
}

void CaptureService::MarkUnhealthy(const std::string& name, ErrorClass cls,
                                   const std::string& message) {
  DeviceHealth& h = health_[name];
  if (h.healthy || h.cls != cls || h.since_utc_ns == 0) {
    h.since_utc_ns = std::chrono::duration_cast<std::chrono::nanoseconds>(
                         std::chrono::system_clock::now().time_since_epoch())
                         .count();
    Publish("health", {{"device", name},
                       {"healthy", false},
                       {"state", ErrorClassName(cls)},
                       {"message", message}});
  }
  h.healthy = false;
  h.cls = cls;
  h.message = message;
  // Once per device and class: a missing turntable retried every 30 s for a
  // night must not fill the journal; a change of class (missing -> timeout)
  // is news and is logged.
  device_log_.Error(name + "/" + ErrorClassName(cls), message + " [" + ErrorClassName(cls) + "]");
}

void CaptureService::ScheduleReopen(const std::string& name) {
  DeviceHealth& h = health_[name];
  if (h.retry_timer != 0) return;
  // Backoff in real time, doubling from reopen_backoff_min to reopen_backoff_max.
  const TimeNs lo = config_.daemon.reopen_backoff_min;
  const TimeNs hi = std::max(lo, config_.daemon.reopen_backoff_max);
  TimeNs delay = lo;
  for (int i = 1; i < h.retries && delay < hi; ++i) delay *= 2;
  delay = std::min(delay, hi);
  h.next_retry_real = MonotonicNs() + delay;
  h.retry_timer = loop_.AddRealTimer(h.next_retry_real, [this, name] {
    DeviceHealth& d = health_[name];
    d.retry_timer = 0;
    d.next_retry_real = 0;
    if (d.healthy) return;
    if (SideRunning()) {
      // Never reopen a device under a running side; try again later.
      ScheduleReopen(name);
    } else {
      TryOpen(name);
    }
    NotifyStatus();
  });
}

StorageHealth CaptureService::CheckStorage() const {
  StorageHealth h;
  const Config& c = config_;
  const int views = std::max(1, c.capture.views_per_side);
  int64_t per_view = static_cast<int64_t>(kJpegBytesPerPixel * c.camera.width * c.camera.height);
  std::string basis = "from the camera resolution " + std::to_string(c.camera.width) + "x" +
                      std::to_string(c.camera.height);
  if (!state_.sample_id.empty()) {
    // The directory scan runs only between sides: status is polled while a
    // side is shot, and its loop must keep the schedule.
    if (!SideRunning() || view_bytes_.first != state_.sample_id) {
      view_bytes_ = {state_.sample_id, StoreOf(state_.sample_id).StoredViewBytes(state_.sample_id)};
    }
    const auto [n, bytes] = view_bytes_.second;
    if (n > 0) {
      per_view = bytes / n;
      basis = "from the " + std::to_string(n) + " views " + state_.sample_id + " has stored";
    }
  }
  h.side_needs_bytes =
      static_cast<int64_t>(kSideMargin * static_cast<double>(views * (per_view + kSidecarBytes))) +
      kSideFixedBytes;
  // Each view is two files (image, sidecar), each written to a temporary name first.
  h.side_needs_files = 2 * views + 16;
  const std::string& dir = c.daemon.state_dir;
  struct statvfs vfs {};
  if (::statvfs(dir.c_str(), &vfs) != 0) {
    const int err = errno;
    h.cls = ErrorClass::kIo;
    h.message = "storage: cannot read the free space of " + dir + ": " + std::strerror(err);
  } else {
    h.free_bytes = static_cast<int64_t>(vfs.f_bavail) * static_cast<int64_t>(vfs.f_frsize);
    h.total_bytes = static_cast<int64_t>(vfs.f_blocks) * static_cast<int64_t>(vfs.f_frsize);
    // Filesystems without an inode limit (btrfs, some tmpfs) report 0 files.
    h.free_inodes = vfs.f_files == 0 ? -1 : static_cast<int64_t>(vfs.f_favail);
    const std::string need = "a side needs about " + Mb(h.side_needs_bytes) + " (" +
                             std::to_string(views) + " views of ~" +
                             std::to_string(per_view / 1000) + " kB " + basis + ", with margin)";
    if (h.free_bytes < h.side_needs_bytes) {
      h.cls = ErrorClass::kDiskFull;
      h.message = "storage: " + Mb(h.free_bytes) + " free on " + dir + ", " + need +
                  "; free space (move finished samples off the rig)";
    } else if (h.free_inodes >= 0 && h.free_inodes < h.side_needs_files) {
      h.cls = ErrorClass::kDiskFull;
      h.message = "storage: only " + std::to_string(h.free_inodes) +
                  " more files can be created on " + dir + ", a side needs " +
                  std::to_string(h.side_needs_files) +
                  "; free space (move finished samples off the rig)";
    } else {
      h.healthy = true;
      h.message = "storage: " + Mb(h.free_bytes) + " free on " + dir + ", " + need;
    }
  }
  if (store_fault_) {
    // The capture is faulted on the store: that is the storage's state until reset.
    h.healthy = false;
    h.cls = store_fault_->cls;
    h.message = "storage: " + store_fault_->message;
  }
  return h;
}

Status CaptureService::CheckStorageForSide() const {
  StorageHealth h = CheckStorage();
  if (h.healthy) return OkStatus();
  return MakeError(h.cls, "cannot start side " + std::to_string(state_.side) + ": " + h.message);
}

Status CaptureService::CompleteAndQueue(const std::string& sample_id) {
  if (!PathExists(StoreOf(sample_id).SampleDir(sample_id) + "/" + layout::kSampleRecord))
    return OkStatus();
  Result<Completion> done = StoreOf(sample_id).CompleteStored(sample_id);
  if (!done) {
    // A damaged record is PrepareArm's to explain; anything else is a store failure.
    if (done.error().cls == ErrorClass::kCorrupt) return OkStatus();
    return MakeError(done.error().cls, "cannot complete the stored sides of \"" + sample_id +
                                           "\": " + done.error().ToString());
  }
  for (int side : done->sides_completed) {
    LogLine(
        LogLevel::kNotice, "capture", sample_id,
        "side " + std::to_string(side) + " had every view stored: manifest written, not re-shot");
  }
  if (queue_) {
    for (const auto& [id, side] : StoreOf(sample_id).CapturedWork(sample_id)) {
      auto jobs = queue_->JobsForSample(id);
      if (!jobs)
        return MakeError(jobs.error().cls, "cannot read the job queue: " + jobs.error().ToString());
      bool have = false;
      for (const Job& j : *jobs) have = have || j.side == side;
      if (have) continue;
      auto q = queue_->Enqueue(id, side);
      if (!q)
        return MakeError(q.error().cls,
                         "cannot queue \"" + id + "\" for the worker: " + q.error().ToString());
      LogLine(LogLevel::kNotice, "capture", id,
              "queued " + (side ? "side " + std::to_string(side) : std::string("the sample job")));
    }
  }
  if (done->sample_captured) {
    if (done->sample_completed_now) ++samples_completed_;
    return MakeError(ErrorClass::kConflict,
                     "sample \"" + sample_id +
                         "\" is complete: every side is stored and it is queued for the "
                         "worker; choose a new id for a new rock");
  }
  return OkStatus();
}

Status CaptureService::CheckDevicesHealthy(std::initializer_list<const char*> names) const {
  for (const char* name : names) {
    auto it = health_.find(name);
    if (it != health_.end() && !it->second.healthy) {
      return MakeError(it->second.cls, "cannot start a capture: " + it->second.message);
    }
  }
  return OkStatus();
}

// ------------------------------------------------------------ dispatching --

void CaptureService::Dispatch(cs::Event e) {
  pending_events_.push_back(std::move(e));
  if (dispatching_) return;  // effects may raise events: handled in order below
  dispatching_ = true;
  while (!pending_events_.empty()) {
    cs::Event ev = std::move(pending_events_.front());
    pending_events_.pop_front();
    const cs::StepResult r = cs::Step(state_, ev);
    if (!r.accepted) {
      ++rejected_events_[cs::EventName(ev)];
      LogLine(LogLevel::kWarning, "capture", state_.sample_id,
              std::string("dropped event ") + cs::EventName(ev) + " in state " +
                  cs::PhaseName(state_.phase) + ": " + r.reason);
      continue;
    }
    if (const auto* f = std::get_if<cs::StoreFailed>(&ev))
      store_fault_ = *f;  // storage health shows it
    const cs::Phase before = state_.phase;
    const std::string sample = state_.sample_id.empty() ? r.next.sample_id : state_.sample_id;
    state_ = r.next;
    if (before != state_.phase) {
      LogLine(LogLevel::kDebug, "capture", sample,
              std::string(cs::PhaseName(before)) + " -> " + cs::PhaseName(state_.phase) + " on " +
                  cs::EventName(ev));
    }
    // Effects refer to the sample of the transition, even when it ends in idle.
    const std::string keep_id = state_.sample_id;
    state_.sample_id = sample;
    for (const auto& eff : r.effects) Execute(eff);
    if (state_.phase == cs::Phase::kIdle) state_.sample_id = keep_id;
    if (on_transition_) on_transition_(state_);
    if (events_) {
      const std::string now = std::string(cs::PhaseName(state_.phase)) + "/" + state_.sample_id +
                              "/" + std::to_string(state_.side);
      if (now != published_state_) {
        published_state_ = now;
        Publish("state",
                {{"state", cs::PhaseName(state_.phase)},
                 {"sample_id", state_.sample_id.empty() ? json(nullptr) : json(state_.sample_id)},
                 {"side", state_.side},
                 {"views_per_side", config_.capture.views_per_side},
                 {"sides", state_.Active() ? state_.plan.sides : config_.capture.sides},
                 {"capture_kind", calibration_capture_ ? "calibration" : "rock"},
                 {"status_line", StatusLine()}});
        if (state_.phase == cs::Phase::kFaulted && before != cs::Phase::kFaulted) {
          Publish("fault", {{"class", ErrorClassName(state_.fault_class)},
                            {"message", state_.fault_message},
                            {"sample_id", sample},
                            {"side", state_.side}});
        }
      }
    }
    NotifyStatus();
  }
  dispatching_ = false;
}

uint64_t CaptureService::AddEpochTimer(TimeNs at, std::function<void()> fn) {
  const uint64_t ep = epoch_;
  return loop_.AddTimer(at, [this, ep, fn = std::move(fn)] {
    if (ep == epoch_) fn();
  });
}

void CaptureService::Fault(ErrorClass cls, const std::string& message) {
  Dispatch(cs::DeviceFault{cls, message});
}

void CaptureService::Execute(const cs::Effect& eff) {
  // One Run() overload per effect: an effect without a step does not compile.
  std::visit([this](const auto& e) { Run(e); }, eff);
}

void CaptureService::Run(const cs::CreateSample& e) {
  Status s =
      StoreOf(e.sample_id).CreateOrResume(e.sample_id, CurrentPlan(), config_toml_, arm_meta_);
  if (!s) {
    pending_events_.push_back(
        cs::StoreFailed{s.error().cls, "cannot create sample: " + s.error().ToString()});
    return;
  }
  LogLine(LogLevel::kInfo, "capture", e.sample_id,
          calibration_capture_
              ? "armed for calibration: lay the board flat on the disc (no rock) and "
                "press the start button"
              : "armed: place the rock and press the start button");
}

void CaptureService::Run(const cs::Home& /*e*/) {
  Clock& clock = loop_.clock();
  turn_prompt_ = false;  // a side starts with the table where it is
  Status s = dev_.turntable->StartHome();
  if (!s) {
    pending_events_.push_back(
        cs::DeviceFault{s.error().cls, "turntable: cannot start homing: " + s.error().ToString()});
    return;
  }
  motion_ = MotionWatch{true, true,        0.0, clock.Now() + config_.capture.home_timeout,
                        0.0,  clock.Now(), 0,   {}};
  AddEpochTimer(clock.Now() + config_.capture.poll_interval,
                [this, ep = epoch_] { PollMotion(ep); });
}

bool CaptureService::ManualTurntable() const {
  return dev_.turntable && dev_.turntable->Info().backend == "manual";
}

// The study's protocol without a motor: right after a shot the operator is
// told to turn the table by the step (event stream, the console's beep, the
// light's fast blink) until the hands-off moment before the next view is due.
void CaptureService::PromptTurn(int side, int view, double from_deg, double to_deg) {
  const TimeNs due = side_t0_ + static_cast<TimeNs>(view) * config_.capture.interval;
  const TimeNs hands_off = due - config_.turntable.manual_hands_off;
  const TimeNs now = loop_.clock().Now();
  const double by = to_deg - from_deg;
  // A still rock and a walked camera: the same prompt, to move the camera.
  const bool walk = config_.capture.mode == "moving_camera";
  Publish("turn", {{"sample_id", state_.sample_id},
                   {"side", side},
                   {"view", view},
                   {"number", view + 1},
                   {"views_per_side", config_.capture.views_per_side},
                   {"move", walk ? "camera" : "table"},
                   {"by_deg", by},
                   {"hands_off_in_ms", std::max<TimeNs>(0, hands_off - now) / kNsPerMs},
                   {"due_in_ms", std::max<TimeNs>(0, due - now) / kNsPerMs}});
  const std::string what =
      walk ? "move the camera on round the rock (about " + Deg(std::abs(by)) +
                 " deg, another height than the last view; keep the rock and the labels in view)"
           : "turn the table by " + Deg(by) + " deg";
  LogLine(LogLevel::kInfo, "capture", state_.sample_id,
          what + " now for view " + std::to_string(view + 1) + " (hands off in " +
              FormatDuration(std::max<TimeNs>(0, hands_off - now)) + ")");
  turn_prompt_ = true;
  const uint64_t my = ++turn_epoch_;
  NotifyStatus();
  auto end_prompt = [this, my] {
    if (turn_epoch_ != my || !turn_prompt_) return;
    turn_prompt_ = false;
    NotifyStatus();
  };
  if (hands_off <= now) {
    end_prompt();
  } else {
    AddEpochTimer(hands_off, end_prompt);
  }
}

void CaptureService::Run(const cs::MoveTo& e) {
  Clock& clock = loop_.clock();
  if (ManualTurntable() && e.angle_deg != dev_.turntable->target_deg()) {
    PromptTurn(e.side, e.view, dev_.turntable->target_deg(), e.angle_deg);
  }
  Status s = dev_.turntable->StartMoveTo(e.angle_deg);
  if (!s) {
    pending_events_.push_back(cs::DeviceFault{
        s.error().cls,
        "turntable: cannot start move to " + Deg(e.angle_deg) + " deg: " + s.error().ToString()});
    return;
  }
  motion_ = MotionWatch{true,
                        false,
                        e.angle_deg,
                        clock.Now() + config_.capture.move_timeout,
                        motion_.last_angle,
                        clock.Now(),
                        0,
                        {}};
  AddEpochTimer(clock.Now() + config_.capture.poll_interval,
                [this, ep = epoch_] { PollMotion(ep); });
}

void CaptureService::Run(const cs::BeginSide& e) {
  const std::string& id = state_.sample_id;
  Status s = StoreOf(id).BeginSide(id, e.side);
  if (!s) {
    pending_events_.push_back(
        cs::StoreFailed{s.error().cls, "cannot start side: " + s.error().ToString()});
    return;
  }
  side_t0_ = loop_.clock().Now() + config_.capture.settle;
  LogLine(LogLevel::kInfo, "capture", id, "side " + std::to_string(e.side) + " started");
}

void CaptureService::Run(const cs::StartSettle& /*e*/) {
  AddEpochTimer(loop_.clock().Now() + config_.capture.settle,
                [this] { Dispatch(cs::SettleDone{}); });
}

void CaptureService::Run(const cs::WaitUntilDue& e) {
  const TimeNs due = side_t0_ + static_cast<TimeNs>(e.view) * config_.capture.interval;
  pending_.due = due;
  if (due <= loop_.clock().Now()) {
    pending_events_.push_back(cs::ViewDue{});
  } else {
    AddEpochTimer(due, [this] { Dispatch(cs::ViewDue{}); });
  }
}

void CaptureService::Run(const cs::TriggerCapture& e) {
  Clock& clock = loop_.clock();
  Result<TurntableStatus> st = dev_.turntable->ReadStatus();
  if (!st) {
    pending_events_.push_back(
        cs::DeviceFault{st.error().cls, "turntable: " + st.error().ToString()});
    return;
  }
  pending_.side = e.side;
  pending_.view = e.view;
  pending_.commanded_deg = e.commanded_deg;
  if (st->angle_measured) {
    pending_.measured_deg = st->angle_deg;
  } else {
    pending_.measured_deg.reset();
  }
  pending_.trigger = clock.Now();
  pending_.frame.reset();
  pending_.request_id = next_request_id_++;
  const uint64_t rid = pending_.request_id;
  loop_.Hold();
  holding_ = true;
  if (preview_in_flight_) {
    // The camera is finishing a live-view still: this view's is
    // requested the moment that one arrives (OnPreviewFrame).
    shot_waits_for_preview_ = true;
    ++preview_delayed_views_;
  } else if (Status s = ShootView(); !s) {
    pending_events_.push_back(cs::DeviceFault{s.error().cls, "camera: " + s.error().ToString()});
    return;
  }
  AddEpochTimer(clock.Now() + config_.capture.frame_timeout, [this, rid] {
    if (state_.phase == cs::Phase::kCapturing && pending_.request_id == rid) {
      if (holding_) {
        holding_ = false;
        loop_.Release();
      }
      Fault(ErrorClass::kTimeout, "camera: no still within " +
                                      FormatDuration(config_.capture.frame_timeout) +
                                      " of the trigger; check the camera connection");
    }
  });
}

void CaptureService::Run(const cs::StoreView& e) {
  const std::string& id = state_.sample_id;
  const FramePtr& f = pending_.frame;
  const double err_ms = static_cast<double>(f->exposure_start - pending_.due) / 1e6;
  const bool overrun = f->exposure_start - pending_.due > kOverrunTolerance;
  json car = {{"sample_id", id},
              {"side", e.side},
              {"view", e.view},
              {"image", layout::ViewImageName(e.view)},
              {"commanded_angle_deg", pending_.commanded_deg},
              {"due_monotonic_ns", pending_.due},
              {"trigger_monotonic_ns", pending_.trigger},
              {"capture_monotonic_ns", f->exposure_start},
              {"capture_utc", FormatUtc(f->utc_ns)},
              {"schedule_error_ms", err_ms},
              {"schedule_overrun", overrun},
              {"exposure_us", f->exposure_us},
              {"gain", f->gain},
              {"wb_red", f->wb_red},
              {"wb_blue", f->wb_blue},
              {"camera_id", dev_.camera->Info().id},
              {"camera_backend", dev_.camera->Info().backend},
              {"width", f->width},
              {"height", f->height},
              {"frame_sequence", f->sequence},
              {"time_scale", loop_.clock().Scale()}};
  // Nothing measured a hand-turned table's angle: the field is absent and the
  // worker measures it from the labels on the disc.
  if (pending_.measured_deg) {
    car["measured_angle_deg"] = *pending_.measured_deg;
  } else {
    car["turntable_backend"] = dev_.turntable->Info().backend;
  }
  // The worker poses a walked camera's views by SfM alone.
  if (config_.capture.mode != "turntable") car["capture_mode"] = config_.capture.mode;
  // A real camera without a control for a locked setting (V4L2
  // strict_controls = false): say so rather than let its value pass as measured.
  if (!f->missing_controls.empty()) car["missing_controls"] = f->missing_controls;
  Status s = StoreOf(id).WriteView(id, e.side, e.view, f->data, car);
  if (!s) {
    pending_events_.push_back(
        cs::StoreFailed{s.error().cls, "cannot store view: " + s.error().ToString()});
    return;
  }
  ++views_captured_;
  // Screens watching the live view see each view as it is stored.
  if (preview_ != nullptr && preview_->viewers() > 0) preview_->Submit(f, "view");
  Publish("view", {{"sample_id", id},
                   {"side", e.side},
                   {"view", e.view},
                   {"number", e.view + 1},
                   {"views_per_side", config_.capture.views_per_side},
                   {"image", layout::SideDirName(e.side) + "/" + layout::ViewImageName(e.view)},
                   {"url", ViewUrl(id, e.side, e.view)},
                   {"thumbnail", ViewUrl(id, e.side, e.view) + "/thumbnail"},
                   // Wall clock of the store: screens measure how late they show it.
                   {"stored_utc_ms", std::chrono::duration_cast<std::chrono::milliseconds>(
                                         std::chrono::system_clock::now().time_since_epoch())
                                         .count()}});
  {
    // A stored view proves both devices work: the health API's last_ok.
    const int64_t now_utc = std::chrono::duration_cast<std::chrono::nanoseconds>(
                                std::chrono::system_clock::now().time_since_epoch())
                                .count();
    for (const char* name : {"camera", "turntable"}) {
      if (health_[name].healthy) health_[name].last_ok_utc_ns = now_utc;
    }
  }
  if (overrun) {
    ++overruns_;
    LogLine(LogLevel::kWarning, "capture", id,
            "view " + std::to_string(e.view) + " taken " + Deg(err_ms) + " ms after its due time");
  }
  last_schedule_error_ms_ = err_ms;
  max_schedule_error_ms_ = std::max(max_schedule_error_ms_, std::fabs(err_ms));
  pending_.frame.reset();  // hand the buffer back
  pending_events_.push_back(cs::ViewStored{});
}

void CaptureService::Run(const cs::FinishSide& e) {
  // Every step that stores something must succeed before the side
  // counts as finished: a failure is a named fault (SideFinished is
  // never posted), and what is already stored is completed by arming
  // the sample again or by the next start-up.
  const std::string& id = state_.sample_id;
  const std::string side = "side " + std::to_string(e.side);
  const std::string again = ": free space or fix the state directory, reset, then arm " + id +
                            " again to complete it (its views are stored)";
  auto fail = [&](const std::string& what, const Error& err) {
    pending_events_.push_back(cs::StoreFailed{err.cls, what + ": " + err.ToString() + again});
  };
  if (Status s = StoreOf(id).FinishSide(id, e.side); !s)
    return fail("cannot store " + side + "'s manifest and record", s.error());
  if (queue_) {
    auto q = queue_->Enqueue(id, e.side, calibration_capture_ ? kJobCalibration : kJobRock);
    if (!q) return fail("cannot queue " + side + " for the worker", q.error());
  }
  ++sides_completed_;
  if (!e.last_side) {
    if (Status s = StoreOf(id).SetSampleState(id, "awaiting_pose"); !s) {
      return fail("cannot record " + side + " as done", s.error());
    }
    LogLine(LogLevel::kInfo, "capture", id,
            side + " done and queued: flip the rock and press the start button");
  } else {
    LogLine(LogLevel::kInfo, "capture", id, side + " done and queued");
    if (Status s = StoreOf(id).SetSampleState(id, "captured"); !s) {
      return fail("cannot mark the sample captured", s.error());
    }
    if (queue_ && !calibration_capture_) {
      auto q = queue_->Enqueue(id, 0);
      if (!q) return fail("cannot queue the sample job", q.error());
    }
    if (calibration_capture_) {
      LogLine(LogLevel::kInfo, "capture", id,
              "calibration board captured: the worker solves the rig calibration");
    } else {
      ++samples_completed_;
      LogLine(LogLevel::kInfo, "capture", id, "sample captured");
    }
  }
  pending_events_.push_back(cs::SideFinished{});
}

void CaptureService::Run(const cs::StopMotion& /*e*/) {
  ++epoch_;  // cancels every pending timer and late callback of this capture
  shot_waits_for_preview_ = false;
  turn_prompt_ = false;  // its hands-off timer was one of them
  motion_.active = false;
  if (holding_) {
    holding_ = false;
    loop_.Release();
  }
  if (dev_.turntable && dev_.turntable->is_open()) (void)dev_.turntable->Stop();
}

void CaptureService::Run(const cs::MarkInterrupted& e) {
  const std::string& id = state_.sample_id;
  if (id.empty()) return;
  Status s = StoreOf(id).SetSampleState(id, "interrupted", e.side, "interrupted");
  if (!s) {
    LogLine(LogLevel::kError, "capture", id, "cannot record interruption: " + s.error().ToString());
  }
}

void CaptureService::Run(const cs::MarkAborted& e) {
  const std::string& id = state_.sample_id;
  if (!id.empty()) {
    Status s = StoreOf(id).SetSampleState(id, "aborted", e.side, "interrupted");
    if (!s) {
      LogLine(LogLevel::kError, "capture", id, "cannot record abort: " + s.error().ToString());
    }
  }
  LogLine(LogLevel::kNotice, "capture", id, "capture aborted by the operator");
}

void CaptureService::Run(const cs::RecordFault& e) {
  const std::string& id = state_.sample_id;
  ++faults_by_class_[ErrorClassName(e.cls)];
  LogLine(LogLevel::kError, "capture", id,
          std::string("FAULT (") + ErrorClassName(e.cls) + "): " + e.message);
  if (e.cls == ErrorClass::kDisconnected || e.cls == ErrorClass::kDeviceMissing ||
      e.cls == ErrorClass::kTimeout) {
    // The device that failed is re-opened on reset.
    // Retried in the background too, so health shows when it is back.
    for (const char* name : {"turntable", "camera"}) {
      if (e.message.rfind(name, 0) != 0) continue;
      MarkUnhealthy(name, e.cls, e.message);
      ScheduleReopen(name);
    }
  }
}

void CaptureService::Run(const cs::ClearFault& /*e*/) {
  LogLine(LogLevel::kNotice, "capture", state_.sample_id, "fault cleared");
  store_fault_.reset();
  OpenDevices();
}

void CaptureService::PollMotion(uint64_t epoch) {
  if (epoch != epoch_ || !motion_.active) return;
  Clock& clock = loop_.clock();
  const TimeNs now = clock.Now();
  Result<TurntableStatus> st = dev_.turntable->ReadStatus();
  if (!st) {
    // Bounded retries: a single lost answer on a serial line is routine.
    if (++motion_.comm_errors > config_.capture.comm_retries ||
        st.error().cls == ErrorClass::kDisconnected) {
      motion_.active = false;
      Fault(st.error().cls, "turntable: " + st.error().ToString());
      return;
    }
  } else {
    motion_.comm_errors = 0;
    motion_.last_status = *st;
    const TurntableStatus& s = *st;
    if (s.alarm) {
      motion_.active = false;
      Fault(ErrorClass::kDeviceFault, "turntable: alarm " + std::to_string(s.alarm_code) + " " +
                                          s.alarm_text + "; clear the cause, then reset");
      return;
    }
    const bool done =
        motion_.homing ? (s.homed && s.in_position && !s.moving) : (s.in_position && !s.moving);
    if (done) {
      motion_.active = false;
      motion_.last_angle = s.angle_deg;
      Dispatch(motion_.homing ? cs::Event(cs::HomeDone{}) : cs::Event(cs::MoveDone{}));
      return;
    }
    if (std::fabs(s.angle_deg - motion_.last_angle) > kStallEpsilonDeg) {
      motion_.last_angle = s.angle_deg;
      motion_.last_progress = now;
    } else if (!motion_.homing && s.moving &&
               now - motion_.last_progress > config_.capture.stall_timeout) {
      // Homing is exempt: controllers often hold or reset the position count
      // while searching for the home sensor; home_timeout bounds it instead.
      motion_.active = false;
      Fault(ErrorClass::kStalled, "turntable stalled at " + Deg(s.angle_deg) +
                                      " deg while moving to " + Deg(motion_.target_deg) +
                                      " deg; check that nothing blocks the platter");
      return;
    }
  }
  if (now > motion_.deadline) {
    motion_.active = false;
    std::string why;
    const std::optional<TurntableStatus>& last = motion_.last_status;
    if (last && !last->moving && !last->in_position) {
      why = ": " + RestedOutOfPosition(config_.turntable, last->angle_deg,
                                       motion_.homing ? 0.0 : motion_.target_deg);
    }
    Fault(ErrorClass::kTimeout,
          std::string("turntable: ") +
              (motion_.homing ? "homing" : "move to " + Deg(motion_.target_deg) + " deg") +
              " did not finish within " +
              FormatDuration(motion_.homing ? config_.capture.home_timeout
                                            : config_.capture.move_timeout) +
              why);
    return;
  }
  AddEpochTimer(now + config_.capture.poll_interval, [this, ep = epoch_] { PollMotion(ep); });
}

// ---------------------------------------------------------------- control --

std::string CaptureService::StatusLine() const {
  const auto& s = state_;
  switch (s.phase) {
    case cs::Phase::kIdle:
      return "idle: arm a sample to start";
    case cs::Phase::kArmed:
      return "armed " + s.sample_id + ": place the rock and press start";
    case cs::Phase::kAwaitingPose:
      return "side " + std::to_string(s.side - 1) +
             " done: flip the rock and press start for side " + std::to_string(s.side);
    case cs::Phase::kFaulted:
      return std::string("FAULT: ") + s.fault_message;
    case cs::Phase::kHoming:
      return "side " + std::to_string(s.side) + ": homing";
    default:
      return "side " + std::to_string(s.side) + " view " + std::to_string(s.view + 1) + "/" +
             std::to_string(s.plan.views_per_side);
  }
}

void CaptureService::NotifyStatus() {
  if (dev_.light) dev_.light->Show(LightPatternFor());
  const std::string line = StatusLine();
  if (line != last_status_) {
    last_status_ = line;
    if (on_status_) on_status_(line);
  }
}

LightPattern CaptureService::LightPatternFor() const {
  if (state_.phase == cs::Phase::kFaulted) return LightPattern::kFault;
  for (const char* name : {"camera", "turntable", "button"}) {
    auto it = health_.find(name);
    if (it != health_.end() && it->second.tried && !it->second.healthy) return LightPattern::kFault;
  }
  // Not under a running side: the light must not cost the schedule a directory scan.
  if (!SideRunning() && !CheckStorage().healthy) return LightPattern::kFault;
  // Set from a hand-turned table's prompt to its hands-off moment; a fault
  // or an abort (StopMotion) clears it.
  if (turn_prompt_) return LightPattern::kTurn;
  switch (state_.phase) {
    case cs::Phase::kIdle:
    case cs::Phase::kArmed:
      return LightPattern::kReady;
    case cs::Phase::kAwaitingPose:
      return LightPattern::kFlip;
    default:
      return LightPattern::kCapturing;
  }
}

namespace {
// "ok", the error class name ("device_missing", "timeout", ...), or "opening"
// before the first attempt.
std::string HealthState(const DeviceHealth& h) {
  if (h.healthy) return "ok";
  if (!h.tried) return "opening";
  return ErrorClassName(h.cls);
}
}  // namespace

json CaptureService::HealthOnLoop() const {
  json devices = json::object();
  bool all_ok = true;
  const TimeNs now_real = MonotonicNs();
  const int64_t now_utc = std::chrono::duration_cast<std::chrono::nanoseconds>(
                              std::chrono::system_clock::now().time_since_epoch())
                              .count();
  for (const auto& [name, h] : health_) {
    all_ok = all_ok && h.healthy;
    json d = {{"state", HealthState(h)},
              {"healthy", h.healthy},
              {"message", h.message},
              {"since_utc", h.since_utc_ns ? json(FormatUtc(h.since_utc_ns)) : json(nullptr)},
              {"last_ok_utc", h.last_ok_utc_ns ? json(FormatUtc(h.last_ok_utc_ns)) : json(nullptr)},
              {"retries", h.retries},
              {"next_retry_utc", nullptr},
              {"next_retry_in_s", nullptr}};
    if (h.next_retry_real != 0) {
      const TimeNs in = std::max<TimeNs>(0, h.next_retry_real - now_real);
      d["next_retry_utc"] = FormatUtc(now_utc + in);
      d["next_retry_in_s"] = static_cast<double>(in) / 1e9;
    }
    if (name == "camera" && dev_.camera) {
      const CameraInfo info = dev_.camera->Info();
      d["backend"] = info.backend;
      d["id"] = info.id;
      d["model"] = info.model;
    } else if (name == "turntable" && dev_.turntable) {
      const TurntableInfo info = dev_.turntable->Info();
      d["backend"] = info.backend;
      d["id"] = info.id;
      d["model"] = info.model;
    } else if (name == "button" && dev_.button) {
      d["backend"] = config_.button.backend;
      d["id"] = dev_.button->Describe();
    } else if (name == "light" && dev_.light) {
      d["backend"] = config_.light.backend;
      d["id"] = dev_.light->Describe();
      d["pattern"] = LightPatternName(dev_.light->pattern());
    }
    devices[name] = std::move(d);
  }
  const StorageHealth st = CheckStorage();
  devices["storage"] = {{"state", st.healthy ? "ok" : ErrorClassName(st.cls)},
                        {"healthy", st.healthy},
                        {"message", st.message},
                        {"backend", "filesystem"},
                        {"id", config_.daemon.state_dir},
                        {"free_bytes", st.free_bytes},
                        {"total_bytes", st.total_bytes},
                        {"free_files", st.free_inodes},
                        {"side_needs_bytes", st.side_needs_bytes},
                        {"side_needs_files", st.side_needs_files}};
  all_ok = all_ok && st.healthy;
  // The worker is no device of the capture (a side is stored and queued
  // without it), but a rig whose results never come is not healthy.
  const json worker = WorkerOnLoop();
  if (worker.is_object()) all_ok = all_ok && worker.value("healthy", false);
  json fault = nullptr;
  if (state_.phase == cs::Phase::kFaulted) {
    // A capture stopped on a fault is not healthy, even once the device is back.
    all_ok = false;
    fault = {{"class", ErrorClassName(state_.fault_class)}, {"message", state_.fault_message}};
  }
  return {
      {"status", all_ok ? "ok" : (state_.phase == cs::Phase::kFaulted ? "faulted" : "unhealthy")},
      {"state", cs::PhaseName(state_.phase)},
      {"fault", fault},
      {"devices", devices},
      {"worker", worker},
      {"checked_utc", FormatUtc(now_utc)},
      {"reopen_backoff_s",
       {{"min", static_cast<double>(config_.daemon.reopen_backoff_min) / 1e9},
        {"max", static_cast<double>(config_.daemon.reopen_backoff_max) / 1e9}}}};
}

json CaptureService::WorkerOnLoop() const {
  if (!queue_) return nullptr;
  const bool watched = config_.worker.silent_after > 0;
  const double silent_after_s = static_cast<double>(config_.worker.silent_after) / 1e9;
  const double daemon_up_s = static_cast<double>(MonotonicNs() - started_real_) / 1e9;
  std::string waiting;
  if (auto d = queue_->Depth(); d && *d > 0)
    waiting = "; " + std::to_string(*d) + " job(s) wait in the queue";
  const std::string look =
      ": is it running? `systemctl status aggscan-worker`, its log `journalctl -u aggscan-worker`";
  json out = {{"watched", watched},     {"silent_after_s", silent_after_s},
              {"pid", nullptr},         {"heard_utc", nullptr},
              {"heard_s_ago", nullptr}, {"up_s", nullptr},
              {"job", nullptr},         {"stage", nullptr},
              {"stage_s", nullptr},     {"progress", nullptr}};
  auto seen = queue_->Worker();
  if (!seen) {
    out["state"] = "unknown";
    out["healthy"] = false;
    out["message"] = "cannot read the worker's report from the queue: " + seen.error().ToString();
    return out;
  }
  if (!seen->has_value() || !(*seen)->this_boot) {
    // The worker is started beside the daemon: give it the same time to say so.
    const bool healthy = !watched || daemon_up_s <= silent_after_s;
    out["state"] = "not_seen";
    out["healthy"] = healthy;
    char b[160];
    std::snprintf(b, sizeof b,
                  "no aggscan-worker has reported since this machine started (aggscand up %.0f s)",
                  daemon_up_s);
    out["message"] =
        healthy ? std::string("waiting for aggscan-worker's first report") : b + look + waiting;
    return out;
  }
  const WorkerSeen& w = **seen;
  const WorkerReport& r = w.report;
  out["pid"] = r.pid;
  out["heard_utc"] = w.heard_utc;
  out["heard_s_ago"] = w.heard_s_ago;
  out["up_s"] = w.up_s;
  const bool busy = r.state == "busy";
  std::string doing = r.state;
  if (busy) {
    out["job"] = {{"id", r.job_id},
                  {"sample_id", r.sample_id},
                  {"side", r.side},
                  {"kind", r.side > 0 ? "side" : "sample"},
                  {"running_s", w.job_s}};
    out["stage"] = r.stage;
    out["stage_s"] = w.stage_s;
    if (r.total > 0) {
      out["progress"] = {{"done", r.done},
                         {"total", r.total},
                         {"fraction", static_cast<double>(r.done) / static_cast<double>(r.total)}};
    }
    doing = "busy with job " + std::to_string(r.job_id) + " (" + r.sample_id + " " +
            (r.side > 0 ? "side " + std::to_string(r.side) : std::string("sample stage")) + ")";
    if (!r.stage.empty()) doing += ", stage \"" + r.stage + "\"";
    if (r.total > 0) doing += " " + std::to_string(r.done) + " of " + std::to_string(r.total);
  }
  const bool silent = watched && w.heard_s_ago > silent_after_s;
  out["healthy"] = !silent;
  char ago[96];
  std::snprintf(ago, sizeof ago, "%.0f s (limit %.0f s, worker.silent_after)", w.heard_s_ago,
                silent_after_s);
  if (!silent) {
    out["state"] = r.state;
    out["message"] = doing;
  } else if (r.state == "stopped") {
    out["state"] = "stopped";
    out["message"] = "aggscan-worker stopped at " + w.heard_utc + " and has not started since, " +
                     ago + ": start it (`systemctl start aggscan-worker`)" + waiting;
  } else {
    out["state"] = "silent";
    out["message"] = "aggscan-worker has not reported for " + std::string(ago) +
                     "; last heard at " + w.heard_utc + ", " + doing + look + waiting;
  }
  return out;
}

json CaptureService::StatusOnLoop() const {
  json devices = json::object();
  for (const auto& [name, h] : health_) {
    devices[name] = {{"healthy", h.healthy}, {"state", HealthState(h)}, {"message", h.message}};
  }
  const StorageHealth st = CheckStorage();
  devices["storage"] = {{"healthy", st.healthy},
                        {"state", st.healthy ? "ok" : ErrorClassName(st.cls)},
                        {"message", st.message},
                        {"free_bytes", st.free_bytes}};
  if (dev_.camera) devices["camera"]["backend"] = dev_.camera->Info().backend;
  if (dev_.turntable) devices["turntable"]["backend"] = dev_.turntable->Info().backend;
  if (dev_.button) devices["button"]["describe"] = dev_.button->Describe();
  json fault = nullptr;
  if (state_.phase == cs::Phase::kFaulted) {
    fault = {{"class", ErrorClassName(state_.fault_class)}, {"message", state_.fault_message}};
  }
  int depth = -1;
  json failed = json::array();
  int failed_total = 0;
  if (queue_) {
    auto d = queue_->Depth();
    if (d) depth = *d;
    // Failed jobs wait for an operator: shown until retried.
    if (auto f = queue_->FailedJobs(kStatusFailedJobs)) {
      for (const Job& j : *f) failed.push_back(JobJson(j));
    }
    failed_total = static_cast<int>(failed.size());
    // Counted only when the list is cut: the status is polled on the loop.
    if (failed_total == kStatusFailedJobs) {
      if (auto n = queue_->FailedCount()) failed_total = *n;
    }
  }
  return {{"state", cs::PhaseName(state_.phase)},
          {"sample_id", state_.sample_id.empty() ? json(nullptr) : json(state_.sample_id)},
          {"side", state_.side},
          // 1-based number of the view being taken; 0 when no side is running.
          {"view", (state_.Active() && state_.phase != cs::Phase::kArmed &&
                    state_.phase != cs::Phase::kAwaitingPose && state_.phase != cs::Phase::kHoming)
                       ? state_.view + 1
                       : 0},
          {"views_per_side", config_.capture.views_per_side},
          {"sides", state_.Active() ? state_.plan.sides : config_.capture.sides},
          {"profile", config_.capture.profile},
          {"fault", fault},
          {"status_line", StatusLine()},
          {"devices", devices},
          {"queue_depth", depth},
          {"failed_jobs", failed},
          {"failed_jobs_total", failed_total},
          {"views_captured", views_captured_},
          {"time_scale", loop_.clock().Scale()},
          {"uptime_s", static_cast<double>(MonotonicNs() - started_real_) / 1e9},
          {"calibration", calibration_},
          {"calibration_capture", CalibrationCaptureOnLoop()},
          {"capture_kind", calibration_capture_ ? "calibration" : "rock"},
          {"worker", WorkerOnLoop()}};
}

Status CaptureService::CheckCanArm(const std::string& what) const {
  if (state_.phase != cs::Phase::kIdle) {
    return MakeError(
        ErrorClass::kInvalidState,
        "cannot " + what + " while " + cs::PhaseName(state_.phase) +
            (state_.phase == cs::Phase::kFaulted ? ": reset the fault first"
                                                 : ": abort the current sample first"));
  }
  return CheckDevicesHealthy({"camera", "turntable", "button"});
}

Result<json> CaptureService::ArmOnLoop(const ArmRequest& request) {
  const std::string& sample_id = request.id;
  if (Status s = CheckCanArm("arm"); !s) return s.error();
  if (sample_id.rfind(layout::kCalibrationIdPrefix, 0) == 0) {
    return MakeError(ErrorClass::kInvalidArgument,
                     "sample ids starting with \"" + std::string(layout::kCalibrationIdPrefix) +
                         "\" name calibration captures: choose another id for a rock (to "
                         "calibrate, use the console's Calibrate or POST /api/v1/calibration)");
  }
  calibration_capture_ = false;
  // The store copies the calibration into the sample: show what it copies.
  if (!calibration_.is_null()) RefreshCalibration();
  if (Status c = CompleteAndQueue(sample_id); !c) return c.error();
  const SamplePlan plan = PlanFromConfig(config_);
  Result<int> first = store_.PrepareArm(sample_id, plan);
  if (!first) return first.error();
  // Kept until the record is written when the first side starts.
  arm_meta_ = request.meta.is_object() ? request.meta : json::object();
  // The config's material is the default of a new sample; a resumed one
  // keeps the material it has (SampleStore::CreateOrResume).
  if (!arm_meta_.contains("material")) {
    json m = sample_meta::MaterialFromConfig(
        config_.material.name, config_.material.specific_gravity, config_.material.basis);
    if (!m.is_null()) arm_meta_["material"] = std::move(m);
  }
  Dispatch(cs::Arm{sample_id, cs::Plan{plan.sides, plan.views_per_side, plan.step_deg}, *first});
  if (state_.phase == cs::Phase::kFaulted) {
    return MakeError(state_.fault_class, state_.fault_message);
  }
  json out = StatusOnLoop();
  out["first_side"] = *first;
  return out;
}

SamplePlan CaptureService::CurrentPlan() const {
  SamplePlan plan = PlanFromConfig(config_);
  // The board lies flat: one turn of one side is the whole capture.
  if (calibration_capture_) plan.sides = 1;
  return plan;
}

Result<json> CaptureService::ArmCalibrationOnLoop() {
  if (Status s = CheckCanArm("start a calibration"); !s) return s.error();
  if (config_.camera.backend == "sim" && config_.sim.board_image.empty()) {
    return MakeError(ErrorClass::kInvalidConfig,
                     "the sim camera has no calibration board to draw: write one with `aggscan "
                     "calibrate board --out FILE.pgm --margin-mm 0`, set sim.board_image = "
                     "\"FILE.pgm\" and restart aggscand");
  }
  if (Status s = cal_store_.Init(); !s) return s.error();
  // calibration-<UTC>, made unique if two start within a second.
  const std::string id = FreeTimedName(cal_store_.SampleDir(""), layout::kCalibrationIdPrefix);
  calibration_capture_ = true;
  const SamplePlan plan = CurrentPlan();
  Result<int> first = cal_store_.PrepareArm(id, plan);
  if (!first) {
    calibration_capture_ = false;
    return first.error();
  }
  arm_meta_ = json::object();
  cal_last_id_ = id;
  cal_reported_.clear();
  Dispatch(cs::Arm{id, cs::Plan{plan.sides, plan.views_per_side, plan.step_deg}, *first});
  if (state_.phase == cs::Phase::kFaulted)
    return MakeError(state_.fault_class, state_.fault_message);
  return StatusOnLoop();
}

json CaptureService::CalibrationCaptureOnLoop() const {
  if (cal_last_id_.empty()) return nullptr;
  const std::string dir = cal_store_.SampleDir(cal_last_id_);
  json out = {{"id", cal_last_id_}, {"state", "unknown"}, {"error", nullptr}, {"result", nullptr}};
  Result<json> rec = cal_store_.LoadRecord(cal_last_id_);
  if (rec) out["state"] = rec->value("state", "unknown");
  if (queue_) {
    if (auto jobs = queue_->JobsForSample(cal_last_id_); jobs && !jobs->empty()) {
      const Job& j = jobs->back();
      // The job's state says more than the capture's once it is captured.
      out["state"] = j.state == "running" ? "solving" : j.state;
      if (!j.error.empty()) out["error"] = j.error;
    }
  }
  Result<std::string> r = ReadFile(layout::ResultsPath(dir, layout::kCalibrationResult));
  if (r) {
    json res = json::parse(*r, nullptr, false);
    if (res.is_object()) out["result"] = res;
  }
  return out;
}

void CaptureService::WatchCalibration() {
  const json c = CalibrationCaptureOnLoop();
  if (!c.is_object()) return;
  const std::string key =
      c.value("state", "") + "|" + (c["error"].is_string() ? c["error"].get<std::string>() : "");
  if (key == cal_reported_) return;
  cal_reported_ = key;
  const std::string state = c.value("state", "");
  // The worker wrote a new state_dir/calibration.json: check it as the next
  // arm would, so the status and the console show it at once.
  if (state == "done" || state == "failed") RefreshCalibration();
  json data = c;
  data["rig"] = calibration_;
  Publish("calibration", std::move(data));
}

void CaptureService::RefreshCalibration() {
  json now =
      CheckRigCalibration(config_.daemon.state_dir, config_.camera.width, config_.camera.height);
  const std::string state = now.value("state", "");
  const bool changed = calibration_.is_null() || calibration_.value("state", "") != state ||
                       calibration_.value("created_utc", "") != now.value("created_utc", "");
  calibration_ = std::move(now);
  if (!changed) return;
  const std::string msg = calibration_.value("message", "");
  if (state == "ok") {
    AGG_LOGI("calibration", "%s", msg.c_str());
  } else {
    // Not fatal: views are still captured; the worker needs full SfM without it.
    AGG_LOGW("calibration",
             "rig calibration %s: %s; capture works, reconstruction falls back to full SfM",
             state.c_str(), msg.c_str());
  }
}

Result<json> CaptureService::AbortOnLoop() {
  cs::StepResult probe = cs::Step(state_, cs::Abort{});
  if (!probe.accepted) return MakeError(ErrorClass::kInvalidState, probe.reason);
  Dispatch(cs::Abort{});
  return StatusOnLoop();
}

Result<json> CaptureService::ResetOnLoop() {
  cs::StepResult probe = cs::Step(state_, cs::Reset{});
  if (!probe.accepted) return MakeError(ErrorClass::kInvalidState, probe.reason);
  Dispatch(cs::Reset{});
  return StatusOnLoop();
}

json CaptureService::GetStatus() {
  return OnLoop([this] { return StatusOnLoop(); });
}

json CaptureService::GetHealth() {
  return OnLoop([this] { return HealthOnLoop(); });
}

Result<json> CaptureService::Arm(const ArmRequest& request, const CallContext& ctx) {
  return OnLoop([this, request] { return ArmOnLoop(request); }, ctx);
}

Result<json> CaptureService::ArmCalibration(const CallContext& ctx) {
  return OnLoop([this] { return ArmCalibrationOnLoop(); }, ctx);
}

Result<json> CaptureService::PressOnLoop(const std::string& source) {
  // Same path as the hardware: through the button driver (debounced there).
  if (state_.phase != cs::Phase::kArmed && state_.phase != cs::Phase::kAwaitingPose) {
    return MakeError(ErrorClass::kInvalidState,
                     std::string("the start button does nothing while ") +
                         cs::PhaseName(state_.phase) +
                         (state_.phase == cs::Phase::kIdle ? ": arm a sample first" : ""));
  }
  if (!dev_.button || !health_["button"].healthy) {
    return MakeError(ErrorClass::kDeviceMissing,
                     "button input is not available: " + health_["button"].message);
  }
  if (Status ok = CheckDevicesHealthy({"camera", "turntable"}); !ok) return ok.error();
  if (Status room = CheckStorageForSide(); !room) return room.error();
  dev_.button->InjectPress(source);
  json out = StatusOnLoop();
  out["pressed"] = true;
  return out;
}

Result<json> CaptureService::Press(const std::string& source, const CallContext& ctx) {
  return OnLoop([this, source] { return PressOnLoop(source); }, ctx);
}

Result<json> CaptureService::EditMeta(const std::string& sample_id, const json& doc,
                                      const std::string& by, const CallContext& ctx) {
  // On the loop: the capture writes the same sample.json (its state) there.
  return OnLoop(
      [this, sample_id, doc, by]() -> Result<json> {
        Result<json> r = store_.EditMeta(sample_id, doc, by);
        if (r && !(*r)["changed"].empty()) {
          LogLine(LogLevel::kNotice, "capture", sample_id,
                  "description edited by " + by + ": " + (*r)["changed"].dump());
          // The library's row carries the description and the mass from it.
          const std::string mpath =
              layout::ResultsPath(store_.SampleDir(sample_id), layout::kMorphology);
          if (PathExists(mpath)) {
            Result<json> m = jsonio::ReadFile(mpath, "results");
            Status s = m ? library_csv::Upsert(store_.state_dir(), sample_id,
                                               library_csv::Row(*m, (*r)["meta"]))
                         : Status(m.error());
            if (!s) {
              LogLine(LogLevel::kWarning, "capture", sample_id,
                      "library.csv row not updated after the edit: " + s.error().ToString());
            }
          }
        }
        return r;
      },
      ctx);
}

Result<json> CaptureService::ListBatches() {
  Result<json> samples = store_.List();
  if (!samples) return samples.error();
  std::vector<std::string> problems;
  std::vector<BatchDef> defs;
  {
    std::lock_guard<std::mutex> lock(batches_mu_);
    defs = BatchStore(store_.state_dir()).List(&problems);
  }
  json out = {{"batches", json::array()}};
  for (const BatchDef& b : defs) {
    json j = b.ToJson();
    j["members"] = ResolveBatch(b, *samples).ids.size();
    out["batches"].push_back(std::move(j));
  }
  if (!problems.empty()) out["problems"] = problems;
  return out;
}

Result<json> CaptureService::GetBatch(const std::string& name) {
  Result<BatchDef> def = [&] {
    std::lock_guard<std::mutex> lock(batches_mu_);
    return BatchStore(store_.state_dir()).Get(name);
  }();
  if (!def) return def.error();
  Result<json> samples = ListSamples();
  if (!samples) return samples.error();
  const BatchMembers m = ResolveBatch(*def, *samples);
  json out = def->ToJson();
  out["members"] = json::array();
  for (const std::string& id : m.ids) {
    for (const json& s : *samples) {
      if (s.value("id", "") == id) out["members"].push_back(s);
    }
  }
  out["missing"] = m.missing;
  return out;
}

Result<json> CaptureService::PutBatch(const std::string& name, const json& doc) {
  Result<BatchDef> def = BatchFromRequest(name, doc);
  if (!def) return def.error();
  {
    std::lock_guard<std::mutex> lock(batches_mu_);
    Result<BatchDef> put = BatchStore(store_.state_dir()).Put(std::move(*def));
    if (!put) return put.error();
  }
  LogLine(LogLevel::kNotice, "capture", "", "batch " + name + " set: " + doc.dump());
  return GetBatch(name);
}

Result<json> CaptureService::DeleteBatch(const std::string& name) {
  std::lock_guard<std::mutex> lock(batches_mu_);
  if (Status s = BatchStore(store_.state_dir()).Remove(name); !s) return s.error();
  LogLine(LogLevel::kNotice, "capture", "", "batch " + name + " deleted");
  return json{{"deleted", name}};
}

Result<std::string> CaptureService::MakeReport(const ReportRequest& request) {
  // Off the loop: the report runs for seconds in a process of its own.
  Result<std::string> r = reports_.Make(request);
  if (r) {
    LogLine(LogLevel::kInfo, "capture", request.kind == "rock" ? request.name : "",
            request.kind + " report " + request.name + " (" + request.format + ") made");
  }
  return r;
}

Result<json> CaptureService::Abort(const CallContext& ctx) {
  return OnLoop([this] { return AbortOnLoop(); }, ctx);
}

Result<json> CaptureService::Reset(const CallContext& ctx) {
  return OnLoop([this] { return ResetOnLoop(); }, ctx);
}

namespace {

// Where a sample's reconstruction stands, from its jobs: "failed" (with the
// first error), "reconstructing", "queued", "done" (figures written; "result"
// holds the 3D ones when there are), or null when nothing was queued yet.
json ReconstructionOf(const std::vector<Job>& jobs, bool has_result) {
  std::string state;
  std::string error;
  for (const Job& j : jobs) {
    if (j.state == "failed" && state != "failed") {
      state = "failed";
      error = j.error;
    } else if (j.state == "running" && state != "failed") {
      state = "reconstructing";
    } else if (j.state == "queued" && state.empty()) {
      state = "queued";
    }
  }
  // Every job done: the figures are written (3D ones only with a rig
  // calibration, else the 2D ones alone).
  if (state.empty() &&
      (has_result || (!jobs.empty() && std::all_of(jobs.begin(), jobs.end(), [](const Job& j) {
         return j.state == "done";
       }) && std::any_of(jobs.begin(), jobs.end(), [](const Job& j) { return j.side == 0; }))))
    state = "done";
  if (state.empty()) return nullptr;
  json out = {{"state", state}};
  if (!error.empty()) out["error"] = error;
  return out;
}

}  // namespace

json CaptureService::ResultSummary(const std::string& sample_id, const json& meta) const {
  // The worker's figures once it has written them, with their quality: a
  // doubtful result is shown as such wherever the sample is.
  // A record that does not read (cut short, edited by hand) shows no
  // figures; one whose quality does not read is not confident.
  const std::string path = layout::ResultsPath(store_.SampleDir(sample_id), layout::kMorphology);
  Result<json> mj = jsonio::ReadFile(path, "results");
  if (!mj) return nullptr;
  const jsonio::Source src{"results", path, ""};
  Result<json> d3 = jsonio::ObjectOr(*mj, "morphology_3d", src);
  if (!d3 || d3->empty()) return nullptr;
  json r = json::object();
  for (const char* k : {"volume_mm3", "surface_area_mm2", "a_mm", "b_mm", "c_mm", "sphericity",
                        "fer_3d", "ratio_c_b", "ratio_b_a"}) {
    if (d3->contains(k) && (*d3)[k].is_number()) r[k] = (*d3)[k];
  }
  // Mass from the sample's description as it is now: an edited specific
  // gravity shows at once, without reconstructing.
  if (r.contains("volume_mm3")) {
    const sample_meta::Mass m = sample_meta::MassOf(r["volume_mm3"].get<double>(), meta);
    if (m.grams) {
      r["mass_g"] = *m.grams;
      r["mass_basis"] = m.basis;
      r["specific_gravity"] = m.specific_gravity;
    } else {
      r["mass_none"] = m.why_none;
    }
  }
  // The per-view 2D figures against the 3D ones (the study's Figure 7).
  if (Result<json> s2 = jsonio::ObjectOr(*mj, "stats_2d", src); s2 && s2->contains("overall")) {
    const json& o = (*s2)["overall"];
    json d2 = json::object();
    for (const char* k : {"fer_2d", "circularity"}) {
      if (!o.is_object() || !o.contains(k) || !o[k].is_object()) continue;
      json st = json::object();
      for (const char* f : {"mean", "min", "max", "cov", "n"}) {
        if (o[k].contains(f) && o[k][f].is_number()) st[f] = o[k][f];
      }
      d2[k] = std::move(st);
    }
    if (!d2.empty()) r["views_2d"] = std::move(d2);
  }
  if (Result<json> w = jsonio::ArrayOr(*mj, "warnings", src); w && !w->empty()) r["warnings"] = *w;
  if (mj->contains("software") && (*mj)["software"].is_object()) r["software"] = (*mj)["software"];
  Result<json> q = jsonio::ObjectOr(*mj, "quality", src);
  Result<bool> confident = q ? jsonio::BoolOr(*q, "confident", true, src) : Result<bool>(false);
  Result<json> flags = q ? jsonio::ArrayOr(*q, "flags", src) : Result<json>(json::array());
  r["confident"] = confident && *confident && flags;
  r["quality_flags"] = flags ? *flags : json::array();
  return r;
}

Result<json> CaptureService::ListSamples() {
  Result<json> list = store_.List();
  if (!list) return list;
  // Each sample's figures and reconstruction, so that a screen lists every
  // sample's state in one request.
  std::vector<std::string> ids;
  for (auto& s : *list) {
    const std::string id = s.value("id", "");
    const json r = ResultSummary(id, s.value("meta", json::object()));
    if (!r.is_null()) s["result"] = r;
    ids.push_back(id);
  }
  if (queue_) {
    auto jobs = OnLoop([this, ids]() -> Result<std::vector<std::vector<Job>>> {
      std::vector<std::vector<Job>> all;
      for (const std::string& id : ids) {
        Result<std::vector<Job>> j = queue_->JobsForSample(id);
        all.push_back(j ? std::move(*j) : std::vector<Job>{});
      }
      return all;
    });
    if (jobs && jobs->size() == list->size()) {
      for (size_t i = 0; i < jobs->size(); ++i) {
        json& s = (*list)[i];
        s["reconstruction"] = ReconstructionOf((*jobs)[i], s.contains("result"));
      }
    }
  }
  return list;
}

Result<json> CaptureService::GetSample(const std::string& sample_id) {
  Result<json> d = store_.Describe(sample_id);
  if (!d) return d;
  json out = *d;
  if (json r = ResultSummary(sample_id, out.value("meta", json::object())); !r.is_null())
    out["result"] = std::move(r);
  if (queue_) {
    // Our own queue handle is used from the loop thread only.
    auto jobs = OnLoop([this, sample_id]() -> Result<std::vector<Job>> {
      return queue_->JobsForSample(sample_id);
    });
    if (jobs) {
      json js = json::array();
      for (const Job& j : *jobs) js.push_back(JobJson(j));
      out["jobs"] = js;
      out["reconstruction"] = ReconstructionOf(*jobs, out.contains("result"));
    }
  }
  return out;
}

Result<json> CaptureService::Retry(const std::string& sample_id) {
  Result<json> d = store_.Describe(sample_id);
  if (!d) return d.error();
  if (!queue_)
    return MakeError(ErrorClass::kInvalidState,
                     "this daemon runs without a job queue: nothing to retry");
  return OnLoop([this, sample_id]() -> Result<json> {
    auto n = queue_->Retry(sample_id);
    if (!n) return n.error();
    LogLine(LogLevel::kNotice, "capture", sample_id,
            "retry: " + std::to_string(*n) + " failed job(s) back in the worker's queue");
    json out = {{"sample_id", sample_id}, {"requeued", *n}, {"jobs", json::array()}};
    if (auto jobs = queue_->JobsForSample(sample_id)) {
      for (const Job& j : *jobs) out["jobs"].push_back(JobJson(j));
    }
    return out;
  });
}

Result<std::string> CaptureService::ResultFile(const std::string& sample_id,
                                               const std::string& name) {
  const auto& names = ResultFileNames();
  if (std::find(names.begin(), names.end(), name) == names.end()) {
    return MakeError(ErrorClass::kNotFound, "no result file \"" + name +
                                                "\"; results are morphology.json, mesh.ply, "
                                                "mesh.obj and mesh.stl");
  }
  const std::string dir = store_.SampleDir(sample_id);
  if (!PathExists(dir + "/" + layout::kSampleRecord)) {
    return MakeError(ErrorClass::kNotFound, "no sample \"" + sample_id + "\"");
  }
  const std::string path = dir + "/" + layout::kResultsDir + "/" + name;
  // The mesh files are complete once the worker has written morphology.json.
  if (!PathExists(dir + "/" + layout::kResultsDir + "/morphology.json") || !PathExists(path)) {
    return MakeError(ErrorClass::kNotFound, "sample \"" + sample_id +
                                                "\" has no results yet: the worker has not "
                                                "finished it (see GET /api/v1/samples/" +
                                                sample_id + " for its jobs)");
  }
  return path;
}

Result<std::string> CaptureService::ViewFile(const std::string& sample_id, int side, int view,
                                             ViewFileKind kind) {
  // A board capture's views are shown like a rock's while they are shot.
  const std::string dir = StoreOf(sample_id).SampleDir(sample_id);
  if (!PathExists(dir + "/" + layout::kSampleRecord))
    return MakeError(ErrorClass::kNotFound, "no sample \"" + sample_id + "\"");
  const std::string what = "view " + std::to_string(view) + " of side " + std::to_string(side) +
                           " of \"" + sample_id + "\"";
  const std::string image =
      dir + "/" + layout::SideDirName(side) + "/" + layout::ViewImageName(view);
  if (side < 1 || view < 0 || !PathExists(image)) {
    return MakeError(ErrorClass::kNotFound,
                     "no " + what +
                         ": it is not captured (sides count from 1, views from 0; see "
                         "GET /api/v1/samples/" +
                         sample_id + ")");
  }
  if (kind == ViewFileKind::kImage) return image;
  const std::string mask = dir + "/" + layout::kResultsDir + "/masks/" + layout::SideDirName(side) +
                           "/" + layout::ViewStem(view) + ".png";
  if (!PathExists(mask)) {
    return MakeError(ErrorClass::kNotFound,
                     "no mask of " + what + " yet: the worker has not masked side " +
                         std::to_string(side) + " (see its job in GET /api/v1/samples/" +
                         sample_id + ")");
  }
  return mask;
}

Result<std::vector<ArchiveMember>> CaptureService::ImageArchive(const std::string& sample_id) {
  if (!PathExists(store_.SampleDir(sample_id) + "/" + layout::kSampleRecord))
    return MakeError(ErrorClass::kNotFound, "no sample \"" + sample_id + "\"");
  auto files = store_.ImageFiles(sample_id);
  if (!files) return files.error();
  std::vector<ArchiveMember> out;
  int views = 0;
  for (auto& [path, name] : *files) {
    views += name.size() > 4 && name.compare(name.size() - 4, 4, ".jpg") == 0;
    out.push_back(ArchiveMember{std::move(path), std::move(name)});
  }
  if (views == 0) {
    return MakeError(ErrorClass::kNotFound, "sample \"" + sample_id +
                                                "\" has no stored view yet: arm it and press "
                                                "START to capture");
  }
  return out;
}

std::string CaptureService::Metrics() {
  return OnLoop([this] {
    std::ostringstream m;
    m << "# HELP aggscan_views_captured_total Views captured and stored.\n"
      << "# TYPE aggscan_views_captured_total counter\n"
      << "aggscan_views_captured_total " << views_captured_ << "\n"
      << "# HELP aggscan_sides_completed_total Sides captured completely and queued.\n"
      << "# TYPE aggscan_sides_completed_total counter\n"
      << "aggscan_sides_completed_total " << sides_completed_ << "\n"
      << "# HELP aggscan_samples_completed_total Samples captured completely.\n"
      << "# TYPE aggscan_samples_completed_total counter\n"
      << "aggscan_samples_completed_total " << samples_completed_ << "\n"
      << "# HELP aggscan_schedule_overruns_total Views shot more than 50 ms after their due time.\n"
      << "# TYPE aggscan_schedule_overruns_total counter\n"
      << "aggscan_schedule_overruns_total " << overruns_ << "\n"
      << "# HELP aggscan_schedule_error_max_ms Largest absolute schedule error since start.\n"
      << "# TYPE aggscan_schedule_error_max_ms gauge\n"
      << "aggscan_schedule_error_max_ms " << max_schedule_error_ms_ << "\n"
      << "# HELP aggscan_preview_viewers Screens watching the live view.\n"
      << "# TYPE aggscan_preview_viewers gauge\n"
      << "aggscan_preview_viewers " << (preview_ != nullptr ? preview_->viewers() : 0) << "\n"
      << "# HELP aggscan_preview_stills_total Stills shot for the live view.\n"
      << "# TYPE aggscan_preview_stills_total counter\n"
      << "aggscan_preview_stills_total " << previews_shot_ << "\n"
      << "# HELP aggscan_preview_failures_total Live-view stills the camera did not give.\n"
      << "# TYPE aggscan_preview_failures_total counter\n"
      << "aggscan_preview_failures_total " << preview_failures_ << "\n"
      << "# HELP aggscan_preview_delayed_views_total Views whose still waited for a live-view "
         "still to finish.\n"
      << "# TYPE aggscan_preview_delayed_views_total counter\n"
      << "aggscan_preview_delayed_views_total " << preview_delayed_views_ << "\n"
      << "# HELP aggscan_faults_total Capture faults by class.\n"
      << "# TYPE aggscan_faults_total counter\n";
    for (const char* cls : {"timeout", "stalled", "disconnected", "device_missing", "device_fault",
                            "disk_full", "io"}) {
      auto it = faults_by_class_.find(cls);
      m << "aggscan_faults_total{class=\"" << cls << "\"} "
        << (it == faults_by_class_.end() ? 0 : it->second) << "\n";
    }
    int depth = 0, failed = 0;
    if (queue_) {
      auto d = queue_->Depth();
      if (d) depth = *d;
      auto f = queue_->FailedCount();
      if (f) failed = *f;
    }
    if (queue_) {
      const json w = WorkerOnLoop();
      auto num = [&w](const char* key) {
        return w.contains(key) && w[key].is_number() ? w[key].get<double>() : 0.0;
      };
      const bool busy = w.value("state", std::string()) == "busy";
      const json& progress = w["progress"];
      m << "# HELP aggscan_worker_up 1 when the worker has reported within worker.silent_after.\n"
        << "# TYPE aggscan_worker_up gauge\n"
        << "aggscan_worker_up " << (w.value("healthy", false) ? 1 : 0) << "\n"
        << "# HELP aggscan_worker_report_age_seconds Seconds since the worker's last report (-1: "
           "none this boot).\n"
        << "# TYPE aggscan_worker_report_age_seconds gauge\n"
        << "aggscan_worker_report_age_seconds "
        << (w["heard_s_ago"].is_number() ? num("heard_s_ago") : -1.0) << "\n"
        << "# HELP aggscan_worker_busy 1 while the worker runs a job.\n"
        << "# TYPE aggscan_worker_busy gauge\n"
        << "aggscan_worker_busy " << (busy ? 1 : 0) << "\n"
        << "# HELP aggscan_worker_stage_seconds Seconds the running job has been in its current "
           "stage.\n"
        << "# TYPE aggscan_worker_stage_seconds gauge\n"
        << "aggscan_worker_stage_seconds " << (busy ? num("stage_s") : 0.0) << "\n"
        << "# HELP aggscan_worker_stage_progress_ratio Done fraction of the running stage's units "
           "(views, steps).\n"
        << "# TYPE aggscan_worker_stage_progress_ratio gauge\n"
        << "aggscan_worker_stage_progress_ratio "
        << (busy && progress.is_object() ? progress.value("fraction", 0.0) : 0.0) << "\n";
    }
    m << "# HELP aggscan_queue_depth Side and sample jobs waiting for or in the worker.\n"
      << "# TYPE aggscan_queue_depth gauge\n"
      << "aggscan_queue_depth " << depth << "\n"
      << "# HELP aggscan_jobs_failed Jobs the worker gave up on, waiting for `aggscan retry`.\n"
      << "# TYPE aggscan_jobs_failed gauge\n"
      << "aggscan_jobs_failed " << failed << "\n"
      << "# HELP aggscan_state Current capture state (1 for the active one).\n"
      << "# TYPE aggscan_state gauge\n";
    for (auto p :
         {cs::Phase::kIdle, cs::Phase::kArmed, cs::Phase::kHoming, cs::Phase::kRotating,
          cs::Phase::kSettling, cs::Phase::kWaitingDue, cs::Phase::kCapturing, cs::Phase::kStoring,
          cs::Phase::kFinishing, cs::Phase::kAwaitingPose, cs::Phase::kFaulted}) {
      m << "aggscan_state{state=\"" << cs::PhaseName(p) << "\"} " << (state_.phase == p ? 1 : 0)
        << "\n";
    }
    return m.str();
  });
}

void CaptureService::Shutdown() {
  if (state_.Active()) {
    LogLine(LogLevel::kNotice, "capture", state_.sample_id,
            "shutting down during a capture: marked interrupted");
    Dispatch(cs::DeviceFault{ErrorClass::kInternal, "daemon stopped during the capture"});
  }
  if (dev_.button) dev_.button->Stop();
  if (dev_.camera) dev_.camera->Close();
  if (dev_.turntable) dev_.turntable->Close();
  if (dev_.light) dev_.light->Close();
}

}  // namespace aggscan
