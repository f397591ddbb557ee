#include "drivers/status_light.h"

#include <chrono>

namespace aggscan {

const char* LightPatternName(LightPattern p) {
  switch (p) {
    case LightPattern::kOff:
      return "off";
    case LightPattern::kReady:
      return "ready";
    case LightPattern::kCapturing:
      return "capturing";
    case LightPattern::kFlip:
      return "flip";
    case LightPattern::kFault:
      return "fault";
    case LightPattern::kTurn:
      return "turn";
  }
  return "?";
}

const std::vector<LightStep>& PatternSteps(LightPattern p) {
  static const std::vector<LightStep> kOff = {{false, kNsPerSec}};
  static const std::vector<LightStep> kReady = {{true, kNsPerSec}};
  static const std::vector<LightStep> kCapturing = {{true, 500 * kNsPerMs},
                                                    {false, 500 * kNsPerMs}};
  static const std::vector<LightStep> kFlip = {{true, 150 * kNsPerMs}, {false, 150 * kNsPerMs}};
  static const std::vector<LightStep> kFault = {{true, 150 * kNsPerMs},
                                                {false, 150 * kNsPerMs},
                                                {true, 150 * kNsPerMs},
                                                {false, 1050 * kNsPerMs}};
  // A hand-turned table: "turn it now", faster than any other pattern; the
  // side's slow blink comes back when the hands must be off.
  static const std::vector<LightStep> kTurn = {{true, 70 * kNsPerMs}, {false, 70 * kNsPerMs}};
  switch (p) {
    case LightPattern::kReady:
      return kReady;
    case LightPattern::kCapturing:
      return kCapturing;
    case LightPattern::kFlip:
      return kFlip;
    case LightPattern::kFault:
      return kFault;
    case LightPattern::kTurn:
      return kTurn;
    case LightPattern::kOff:
      break;
  }
  return kOff;
}

StatusLight::~StatusLight() {
  // Backends must Close() in their own destructor (DoClose is theirs); this
  // only guards against a thread left running.
  std::unique_lock<std::mutex> l(mu_);
  stop_ = true;
  cv_.notify_all();
  l.unlock();
  if (thread_.joinable()) thread_.join();
}

Status StatusLight::Open() {
  {
    std::lock_guard<std::mutex> l(mu_);
    if (open_) return MakeError(ErrorClass::kInvalidState, "status light is already open");
  }
  Status s = DoOpen();
  if (!s) return s;
  if (Status d = DoSet(false); !d) {
    DoClose();
    return d;
  }
  std::lock_guard<std::mutex> l(mu_);
  open_ = true;
  stop_ = false;
  fault_.reset();
  thread_ = std::thread([this] { Run(); });
  return OkStatus();
}

void StatusLight::Close() {
  {
    std::lock_guard<std::mutex> l(mu_);
    if (!open_) return;
    open_ = false;
    stop_ = true;
  }
  cv_.notify_all();
  if (thread_.joinable()) thread_.join();
  (void)DoSet(false);  // best effort: a lost link cannot be switched off
  DoClose();
}

void StatusLight::Show(LightPattern p) {
  {
    std::lock_guard<std::mutex> l(mu_);
    if (pattern_ == p) return;
    pattern_ = p;
    ++generation_;
  }
  cv_.notify_all();
}

LightPattern StatusLight::pattern() const {
  std::lock_guard<std::mutex> l(mu_);
  return pattern_;
}

Status StatusLight::Health() const {
  std::lock_guard<std::mutex> l(mu_);
  if (fault_) return *fault_;
  return OkStatus();
}

void StatusLight::Run() {
  std::unique_lock<std::mutex> l(mu_);
  // What the output was last set to: Open() left it dark. (Unknown here, the
  // thread wrote "dark" a second time, racing the caller's first pattern.)
  std::optional<bool> level = false;
  while (!stop_) {
    const uint64_t gen = generation_;
    const std::vector<LightStep>& steps = PatternSteps(pattern_);
    for (size_t i = 0; !stop_ && gen == generation_; i = (i + 1) % steps.size()) {
      const LightStep step = steps[i];
      // Write on a change only, and retry a failed write on the next step:
      // a Modbus coil is a request on a shared link.
      if (level != step.on) {
        l.unlock();
        Status s = DoSet(step.on);
        l.lock();
        if (s) {
          level = step.on;
          fault_.reset();
        } else {
          level.reset();
          fault_ = s.error();
        }
      }
      cv_.wait_for(l, std::chrono::nanoseconds(step.duration),
                   [&] { return stop_ || gen != generation_; });
    }
  }
}

}  // namespace aggscan
