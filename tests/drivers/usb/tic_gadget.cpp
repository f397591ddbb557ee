// A Pololu Tic stepper controller on the device side of a USB gadget
// (FunctionFS): answers the Tic's native USB protocol on endpoint 0 (vendor
// control requests, Tic user's guide section 11) and simulates the motor.
//
//   tic_gadget --ffs DIR [--ready FILE] [--home-switch-at STEPS] [--start-at STEPS]
//              [--steps-per-rev N] [--command-timeout-ms MS]
//
// DIR is a mounted functionfs instance; the gadget writes its descriptors to
// DIR/ep0 (with FUNCTIONFS_ALL_CTRL_RECIP, so device-recipient vendor requests
// reach this program) and then creates FILE: the configfs gadget can then be
// bound to a UDC. SIGUSR1 injects a motor driver error (the Tic's error bit 1);
// SIGTERM ends it.
//
// The simulated Tic: position moves toward the target with a trapezoidal
// profile at the max speed / acceleration / deceleration set over USB (its
// units: microsteps per 10000 s and per 100 s^2); it starts de-energized in
// safe start with its position uncertain; "Go home" runs at max speed in the
// given direction until the platter's home switch (one per revolution, at
// --home-switch-at microsteps of the platter's physical position) is reached,
// then sets position 0; "Halt and hold" stops at once; the command timeout
// (default 1000 ms, the Tic's default) raises its error when no command came.
#include <fcntl.h>
#include <linux/usb/ch9.h>
#include <linux/usb/functionfs.h>
#include <poll.h>
#include <signal.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <atomic>
#include <cerrno>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <string>

#include "drivers/usb/tic_protocol.h"

namespace {

using namespace aggscan::tic;

std::atomic<bool> g_stop{false};
std::atomic<bool> g_driver_error{false};

double NowS() {
  return std::chrono::duration<double>(std::chrono::steady_clock::now().time_since_epoch()).count();
}

class SimTic {
 public:
  SimTic(double steps_per_rev, double home_switch_at, double start_at, double command_timeout_s)
      : rev_(steps_per_rev), switch_(home_switch_at), command_timeout_s_(command_timeout_s) {
    physical_ = start_at;  // the platter where it was left; position 0 there
    PowerUp();
    last_t_ = last_cmd_t_ = NowS();
  }

  // Runs the motor up to now, in 0.5 ms steps.
  void Advance(double now) {
    constexpr double kDt = 0.0005;
    while (last_t_ + kDt <= now) {
      last_t_ += kDt;
      Step(kDt);
    }
  }

  // A host-to-device command; false = not a command this Tic knows (stall).
  bool Command(uint8_t cmd, uint16_t w_value, uint16_t w_index) {
    const uint32_t data = w_value | (static_cast<uint32_t>(w_index) << 16);
    last_cmd_t_ = last_t_;
    errors_ &= ~Bit(kErrCommandTimeout);  // any command clears it (and restarts the timer)
    switch (cmd) {
      case kCmdSetTargetPosition:
        if (homing_) return true;  // ignored while homing
        target_ = static_cast<int32_t>(data);
        planning_ = kPlanningTargetPosition;
        return true;
      case kCmdHaltAndSetPosition:
        vel_ = 0;
        pos_ = static_cast<int32_t>(data);
        planning_ = 0;
        homing_ = false;
        uncertain_ = false;
        offset_ = physical_ - pos_;
        return true;
      case kCmdHaltAndHold:
        vel_ = 0;
        planning_ = 0;
        homing_ = false;
        uncertain_ = true;
        return true;
      case kCmdGoHome:
        if (w_value > 1) return false;
        homing_ = true;
        home_dir_ = w_value == 1 ? 1 : -1;
        planning_ = 0;
        uncertain_ = true;
        return true;
      case kCmdResetCommandTimeout:
        return true;
      case kCmdDeenergize:
        errors_ |= Bit(kErrIntentionallyDeenergized);
        vel_ = 0;
        planning_ = 0;
        homing_ = false;
        uncertain_ = true;
        return true;
      case kCmdEnergize:
        errors_ &= ~Bit(kErrIntentionallyDeenergized);
        return true;
      case kCmdExitSafeStart:
        errors_ &= ~Bit(kErrSafeStartViolation);
        return true;
      case kCmdEnterSafeStart:
        errors_ |= Bit(kErrSafeStartViolation);
        return true;
      case kCmdReset:
        PowerUp();
        return true;
      case kCmdClearDriverError:
        errors_ &= ~Bit(kErrMotorDriver);
        return true;
      case kCmdSetMaxSpeed:
        if (data > kMaxSpeedLimit) return false;
        max_speed_ = data;
        return true;
      case kCmdSetStartingSpeed:
        return data <= kMaxSpeedLimit;
      case kCmdSetMaxAccel:
        if (data < kMinAccelLimit || data > kMaxAccelLimit) return false;
        max_accel_ = data;
        return true;
      case kCmdSetMaxDecel:
        if (data < kMinAccelLimit || data > kMaxAccelLimit) return false;
        max_decel_ = data;
        return true;
      case kCmdSetStepMode:
        return w_value <= 9;
      default:
        return false;
    }
  }

  // The variable block as the Tic lays it out (user's guide section 7).
  std::array<uint8_t, 0x58> Variables() const {
    std::array<uint8_t, 0x58> b{};
    const bool energized = !(errors_ & Bit(kErrIntentionallyDeenergized));
    b[kVarOperationState] = !energized ? kStateDeenergized
                            : errors_  ? kStateSoftError
                                       : kStateNormal;
    b[kVarMiscFlags1] = static_cast<uint8_t>((energized ? kFlagEnergized : 0) |
                                             (uncertain_ ? kFlagPositionUncertain : 0) |
                                             (homing_ ? kFlagHomingActive : 0));
    b[kVarErrorStatus] = static_cast<uint8_t>(errors_ & 0xFF);
    b[kVarErrorStatus + 1] = static_cast<uint8_t>(errors_ >> 8);
    WriteU32(b, kVarErrorsOccurred, errors_);
    b[kVarPlanningMode] = planning_;
    WriteU32(b, kVarTargetPosition, static_cast<uint32_t>(target_));
    WriteU32(b, kVarMaxSpeed, max_speed_);
    WriteU32(b, kVarMaxDecel, max_decel_);
    WriteU32(b, kVarMaxAccel, max_accel_);
    WriteU32(b, kVarCurrentPosition,
             static_cast<uint32_t>(static_cast<int32_t>(std::lround(pos_))));
    WriteU32(
        b, kVarCurrentVelocity,
        static_cast<uint32_t>(static_cast<int32_t>(std::lround(vel_ * kSpeedUnitsPerStepPerS))));
    return b;
  }

 private:
  static uint16_t Bit(int b) { return static_cast<uint16_t>(1u << b); }

  // Power-up / "Reset": settings reloaded, position 0 and uncertain, safe start.
  void PowerUp() {
    offset_ = physical_ - 0.0;
    pos_ = 0;
    vel_ = 0;
    target_ = 0;
    planning_ = 0;
    homing_ = false;
    uncertain_ = true;
    errors_ = static_cast<uint16_t>((errors_ & Bit(kErrIntentionallyDeenergized)) |
                                    Bit(kErrSafeStartViolation));
    if (!initialized_) errors_ |= Bit(kErrIntentionallyDeenergized);
    initialized_ = true;
    max_speed_ = 2'000'000;            // the Tic's default settings: 200 steps/s
    max_accel_ = max_decel_ = 40'000;  // 400 steps/s^2
  }

  void Step(double dt) {
    if (g_driver_error.exchange(false)) {
      errors_ |= Bit(kErrMotorDriver);
      vel_ = 0;  // the driver stops driving the coils: an abrupt stop
      uncertain_ = true;
    }
    if (command_timeout_s_ > 0 && last_t_ - last_cmd_t_ > command_timeout_s_) {
      errors_ |= Bit(kErrCommandTimeout);
    }
    const double vmax = max_speed_ / kSpeedUnitsPerStepPerS;
    const double acc = max_accel_ / kAccelUnitsPerStepPerS2;
    const double dec = max_decel_ / kAccelUnitsPerStepPerS2;
    if (errors_) {
      // Soft error response "decelerate to hold" (the Tic's default).
      homing_ = false;
      const double dv = std::min(std::fabs(vel_), dec * dt);
      vel_ -= std::copysign(dv, vel_);
    } else if (homing_) {
      vel_ += home_dir_ * acc * dt;
      vel_ = std::clamp(vel_, -vmax, vmax);
    } else if (planning_ == kPlanningTargetPosition) {
      const double d = target_ - pos_;
      if (std::fabs(d) <= std::fabs(vel_) * dt + 1e-9 && std::fabs(vel_) <= dec * dt * 2 + 1e-9) {
        pos_ = target_;
        vel_ = 0;
        return;
      }
      const double dir = d > 0 ? 1 : -1;
      const double stop_dist = vel_ * vel_ / (2 * dec);
      if (vel_ * dir < 0) {
        vel_ += dir * dec * dt;  // moving away: turn round
      } else if (std::fabs(d) <= stop_dist) {
        vel_ -= dir * dec * dt;
        if (vel_ * dir < 0) vel_ = 0;
      } else {
        vel_ += dir * acc * dt;
        vel_ = std::clamp(vel_, -vmax, vmax);
      }
    } else {
      vel_ = 0;
    }
    const double before = physical_;
    pos_ += vel_ * dt;
    physical_ = pos_ + offset_;
    if (planning_ == kPlanningTargetPosition && !errors_ && !homing_) {
      const double d = target_ - pos_;
      if (vel_ != 0 && d * vel_ < 0 && std::fabs(d) < 1.0) {  // passed it
        pos_ = target_;
        vel_ = 0;
        physical_ = pos_ + offset_;
      }
    }
    if (homing_ &&
        std::floor((before - switch_) / rev_) != std::floor((physical_ - switch_) / rev_)) {
      // The home switch: the Tic backs off it slowly and calls the spot 0.
      vel_ = 0;
      homing_ = false;
      uncertain_ = false;
      pos_ = 0;
      offset_ = physical_;
    }
  }

  const double rev_, switch_, command_timeout_s_;
  double physical_ = 0, offset_ = 0;
  double pos_ = 0, vel_ = 0;  // microsteps, microsteps/s
  int32_t target_ = 0;
  uint8_t planning_ = 0;
  bool homing_ = false, uncertain_ = true, initialized_ = false;
  int home_dir_ = -1;
  uint16_t errors_ = 0;
  uint32_t max_speed_ = 0, max_accel_ = 0, max_decel_ = 0;
  double last_t_ = 0, last_cmd_t_ = 0;
};

// FunctionFS descriptors: one vendor-specific interface without endpoints
// (the Tic's native interface: everything goes over endpoint 0), full and
// high speed; ALL_CTRL_RECIP hands device-recipient requests to us.
struct __attribute__((packed)) Descriptors {
  usb_functionfs_descs_head_v2 header;
  uint32_t fs_count;
  uint32_t hs_count;
  usb_interface_descriptor fs_intf;
  usb_interface_descriptor hs_intf;
};
struct __attribute__((packed)) Strings {
  usb_functionfs_strings_head header;
};

bool WriteAll(int fd, const void* p, size_t n, const char* what) {
  if (write(fd, p, n) != static_cast<ssize_t>(n)) {
    std::fprintf(stderr, "tic_gadget: writing %s to ep0: %s\n", what, std::strerror(errno));
    return false;
  }
  return true;
}

}  // namespace

int main(int argc, char** argv) {
  std::string ffs, ready;
  double switch_at = 0, start_at = 400, steps_per_rev = 1600, timeout_ms = 1000;
  for (int i = 1; i + 1 < argc; i += 2) {
    const std::string a = argv[i];
    if (a == "--ffs")
      ffs = argv[i + 1];
    else if (a == "--ready")
      ready = argv[i + 1];
    else if (a == "--home-switch-at")
      switch_at = std::atof(argv[i + 1]);
    else if (a == "--start-at")
      start_at = std::atof(argv[i + 1]);
    else if (a == "--steps-per-rev")
      steps_per_rev = std::atof(argv[i + 1]);
    else if (a == "--command-timeout-ms")
      timeout_ms = std::atof(argv[i + 1]);
    else {
      std::fprintf(stderr, "tic_gadget: unknown option %s\n", a.c_str());
      return 2;
    }
  }
  if (ffs.empty()) {
    std::fprintf(stderr, "usage: tic_gadget --ffs DIR [--ready FILE] ...\n");
    return 2;
  }
  struct sigaction sa {};
  sa.sa_handler = [](int sig) {
    if (sig == SIGUSR1)
      g_driver_error = true;
    else
      g_stop = true;
  };
  sigaction(SIGUSR1, &sa, nullptr);
  sigaction(SIGTERM, &sa, nullptr);
  sigaction(SIGINT, &sa, nullptr);

  const int ep0 = open((ffs + "/ep0").c_str(), O_RDWR);
  if (ep0 < 0) {
    std::fprintf(stderr, "tic_gadget: open %s/ep0: %s\n", ffs.c_str(), std::strerror(errno));
    return 1;
  }
  Descriptors d{};
  d.header.magic = FUNCTIONFS_DESCRIPTORS_MAGIC_V2;
  d.header.length = sizeof(d);
  d.header.flags = FUNCTIONFS_HAS_FS_DESC | FUNCTIONFS_HAS_HS_DESC | FUNCTIONFS_ALL_CTRL_RECIP;
  d.fs_count = d.hs_count = 1;
  for (usb_interface_descriptor* intf : {&d.fs_intf, &d.hs_intf}) {
    intf->bLength = USB_DT_INTERFACE_SIZE;
    intf->bDescriptorType = USB_DT_INTERFACE;
    intf->bInterfaceNumber = kNativeInterface;
    intf->bNumEndpoints = 0;
    intf->bInterfaceClass = USB_CLASS_VENDOR_SPEC;
  }
  Strings s{};
  s.header.magic = FUNCTIONFS_STRINGS_MAGIC;
  s.header.length = sizeof(s);
  if (!WriteAll(ep0, &d, sizeof(d), "descriptors") || !WriteAll(ep0, &s, sizeof(s), "strings")) {
    return 1;
  }
  if (!ready.empty()) {
    if (FILE* f = std::fopen(ready.c_str(), "w")) std::fclose(f);
  }

  SimTic tic(steps_per_rev, switch_at, start_at, timeout_ms / 1000.0);
  int exit_code = 0;
  while (!g_stop) {
    pollfd p{ep0, POLLIN, 0};
    if (poll(&p, 1, 50) <= 0) {
      tic.Advance(NowS());
      continue;
    }
    std::array<usb_functionfs_event, 4> ev{};
    const ssize_t n = read(ep0, ev.data(), sizeof(ev));
    if (n < 0) {
      if (errno == EINTR || errno == EAGAIN) continue;
      if (errno == EL2HLT) {
        // The host dropped an IN request we could not answer (a write that
        // failed as the cable was pulled): FunctionFS stalls it on this read
        // and says so; the next read carries on with the events.
        std::fprintf(stderr, "tic_gadget: a request left unanswered was stalled\n");
        continue;
      }
      if (errno == EIDRM) {
        // A setup request was cancelled before we answered it (the host gave
        // up on it, or another event came first): FunctionFS says so once;
        // the host has moved on, and so do we.
        std::fprintf(stderr, "tic_gadget: a request was cancelled before it was answered\n");
        continue;
      }
      std::fprintf(stderr, "tic_gadget: read ep0: %s; stopping\n", std::strerror(errno));
      exit_code = 1;
      break;
    }
    for (size_t i = 0; i < static_cast<size_t>(n) / sizeof(usb_functionfs_event); ++i) {
      if (ev[i].type != FUNCTIONFS_SETUP) {
        // Bind, enable, disable, suspend, resume: no state here, but the log
        // tells a failing run's story.
        static const char* const kNames[] = {"bind",  "unbind",  "enable", "disable",
                                             "setup", "suspend", "resume"};
        std::fprintf(stderr, "tic_gadget: %.3f s: %s\n", NowS(),
                     ev[i].type < 7 ? kNames[ev[i].type] : "unknown event");
        continue;
      }
      const usb_ctrlrequest& r = ev[i].u.setup;
      const uint16_t value = le16toh(r.wValue), index = le16toh(r.wIndex),
                     length = le16toh(r.wLength);
      tic.Advance(NowS());
      if (r.bRequestType == kRequestTypeIn && r.bRequest == kCmdGetVariable) {
        const auto vars = tic.Variables();
        if (index < vars.size() && length >= 1 && length <= kMaxBlockRead) {
          const size_t len = std::min<size_t>(length, vars.size() - index);
          if (write(ep0, vars.data() + index, len) < 0) {
            std::fprintf(stderr, "tic_gadget: answering a variable read: %s\n",
                         std::strerror(errno));
          }
          continue;
        }
        (void)!read(ep0, nullptr, 0);  // IN request: a read stalls it
        continue;
      }
      if (r.bRequestType == kRequestTypeOut && length == 0 &&
          tic.Command(r.bRequest, value, index)) {
        (void)!read(ep0, nullptr, 0);  // status stage: acknowledge
        continue;
      }
      // Unknown: stall (a write for an OUT request, a read for an IN one).
      if (r.bRequestType & USB_DIR_IN)
        (void)!read(ep0, nullptr, 0);
      else
        (void)!write(ep0, nullptr, 0);
    }
  }
  close(ep0);
  std::fprintf(stderr, "tic_gadget: %s\n", exit_code ? "ended on an error" : "stopped");
  return exit_code;
}
