// Non-virtual halves of the driver interfaces: argument and state checks,
// then the backend's Do... hook.
#include <cmath>

#include "drivers/button.h"
#include "drivers/camera.h"
#include "drivers/turntable.h"

namespace aggscan {

const char* CameraStateName(Camera::State s) {
  switch (s) {
    case Camera::State::kClosed:
      return "closed";
    case Camera::State::kOpened:
      return "opened";
    case Camera::State::kReady:
      return "ready";
    case Camera::State::kBusy:
      return "busy";
  }
  return "?";
}

Camera::State Camera::state() const {
  std::lock_guard<std::mutex> l(mu_);
  return state_;
}

Status Camera::Open() {
  {
    std::lock_guard<std::mutex> l(mu_);
    if (state_ != State::kClosed)
      return MakeError(ErrorClass::kInvalidState, "camera is already open");
  }
  Status s = DoOpen();
  if (!s) return s;
  std::lock_guard<std::mutex> l(mu_);
  state_ = State::kOpened;
  return OkStatus();
}

Status Camera::Configure(const CameraSettings& settings) {
  if (settings.width < 16 || settings.height < 16 || settings.width > 16384 ||
      settings.height > 16384) {
    return MakeError(ErrorClass::kInvalidArgument,
                     "camera resolution " + std::to_string(settings.width) + "x" +
                         std::to_string(settings.height) + " is out of range 16..16384");
  }
  if (settings.jpeg_quality < 1 || settings.jpeg_quality > 100) {
    return MakeError(ErrorClass::kInvalidArgument, "jpeg_quality must be 1..100");
  }
  if (settings.manual_exposure && (settings.exposure_us <= 0 || settings.gain <= 0)) {
    return MakeError(ErrorClass::kInvalidArgument,
                     "manual exposure needs exposure_us > 0 and gain > 0");
  }
  {
    std::lock_guard<std::mutex> l(mu_);
    if (state_ != State::kOpened && state_ != State::kReady) {
      return MakeError(ErrorClass::kInvalidState,
                       std::string("camera cannot be configured while ") + CameraStateName(state_));
    }
  }
  Status s = DoConfigure(settings);
  std::lock_guard<std::mutex> l(mu_);
  if (!s) {
    // The backend may have stopped the old stream before refusing (V4L2 and
    // libcamera renegotiate from scratch): no longer ready to shoot.
    if (state_ == State::kReady) state_ = State::kOpened;
    return s;
  }
  settings_ = settings;
  state_ = State::kReady;
  return OkStatus();
}

Status Camera::RequestStill(const StillRequest& req, FrameCallback done) {
  {
    std::lock_guard<std::mutex> l(mu_);
    if (state_ != State::kReady) {
      return MakeError(ErrorClass::kInvalidState,
                       std::string("camera cannot take a still while ") + CameraStateName(state_));
    }
    state_ = State::kBusy;
  }
  auto wrapped = [this, done = std::move(done)](Result<FramePtr> r) {
    {
      std::lock_guard<std::mutex> l(mu_);
      if (state_ == State::kBusy) state_ = State::kReady;
    }
    done(std::move(r));
  };
  Status s = DoRequestStill(req, std::move(wrapped));
  if (!s) {
    std::lock_guard<std::mutex> l(mu_);
    if (state_ == State::kBusy) state_ = State::kReady;
  }
  return s;
}

void Camera::Close() {
  {
    std::lock_guard<std::mutex> l(mu_);
    if (state_ == State::kClosed) return;
  }
  DoClose();
  std::lock_guard<std::mutex> l(mu_);
  state_ = State::kClosed;
}

bool Turntable::is_open() const {
  std::lock_guard<std::mutex> l(mu_);
  return open_;
}

double Turntable::target_deg() const {
  std::lock_guard<std::mutex> l(mu_);
  return target_deg_;
}

Status Turntable::Open() {
  if (is_open()) return MakeError(ErrorClass::kInvalidState, "turntable is already open");
  Status s = DoOpen();
  if (!s) return s;
  std::lock_guard<std::mutex> l(mu_);
  open_ = true;
  return OkStatus();
}

Status Turntable::StartHome() {
  if (!is_open()) return MakeError(ErrorClass::kInvalidState, "turntable is not open");
  Status s = DoStartHome();
  if (s) {
    std::lock_guard<std::mutex> l(mu_);
    target_deg_ = 0.0;
  }
  return s;
}

Status Turntable::StartMoveTo(double angle_deg) {
  if (!std::isfinite(angle_deg) || std::fabs(angle_deg) > 1e6) {
    return MakeError(ErrorClass::kInvalidArgument,
                     "turntable target angle is not a finite angle in range");
  }
  if (!is_open()) return MakeError(ErrorClass::kInvalidState, "turntable is not open");
  Status s = DoStartMoveTo(angle_deg);
  if (s) {
    std::lock_guard<std::mutex> l(mu_);
    target_deg_ = angle_deg;
  }
  return s;
}

Status Turntable::Stop() {
  if (!is_open()) return MakeError(ErrorClass::kInvalidState, "turntable is not open");
  return DoStop();
}

Result<TurntableStatus> Turntable::ReadStatus() {
  if (!is_open()) return MakeError(ErrorClass::kInvalidState, "turntable is not open");
  return DoReadStatus();
}

void Turntable::Close() {
  if (!is_open()) return;
  DoClose();
  std::lock_guard<std::mutex> l(mu_);
  open_ = false;
}

Status Button::Start(PressCallback on_press) {
  {
    std::lock_guard<std::mutex> l(mu_);
    if (started_) return MakeError(ErrorClass::kInvalidState, "button already started");
    cb_ = std::move(on_press);
    fault_.reset();
  }
  Status s = DoStart();
  if (s) {
    std::lock_guard<std::mutex> l(mu_);
    started_ = true;
  }
  return s;
}

void Button::Stop() {
  {
    std::lock_guard<std::mutex> l(mu_);
    if (!started_) return;
    started_ = false;
  }
  DoStop();
}

void Button::InjectPress(const std::string& source) { DeliverPress(source); }

Status Button::Health() const {
  std::lock_guard<std::mutex> l(mu_);
  if (fault_) return *fault_;
  if (!started_) return MakeError(ErrorClass::kInvalidState, "button is not started");
  return OkStatus();
}

void Button::ReportFault(Error error) {
  std::lock_guard<std::mutex> l(mu_);
  if (started_ && !fault_) fault_ = std::move(error);
}

void Button::DeliverPress(const std::string& source) {
  PressCallback cb;
  ButtonPress p;
  {
    std::lock_guard<std::mutex> l(mu_);
    if (!started_ || !cb_) return;
    const TimeNs now = clock_.Now();
    if (have_last_ && now - last_press_ < debounce_) return;
    have_last_ = true;
    last_press_ = now;
    p.time = now;
    p.source = source;
    cb = cb_;
  }
  cb(p);
}

}  // namespace aggscan
