#include "drivers/usb/usb_tic_turntable.h"

#include <libusb-1.0/libusb.h>

#include <array>
#include <cmath>
#include <cstdio>
#include <vector>

#include "common/log.h"
#include "drivers/turntable_legs.h"

namespace aggscan::usb {
namespace {

constexpr const char* kLog = "turntable";

std::string Hex4(int v) {
  char buf[8];
  std::snprintf(buf, sizeof(buf), "%04x", v & 0xFFFF);
  return buf;
}

// Errors a Tic can stop the motor with that aggscan's own commands clear
// (Prepare() sends exit safe start, energize and reset command timeout): not
// alarms while the table is idle.
constexpr uint16_t kClearedByPrepare = (1u << tic::kErrIntentionallyDeenergized) |
                                       (1u << tic::kErrCommandTimeout) |
                                       (1u << tic::kErrSafeStartViolation);

unsigned TimeoutMs(TimeNs t) { return static_cast<unsigned>(std::max<TimeNs>(1, t / kNsPerMs)); }

}  // namespace

// libusb's hotplug callback runs inside libusb_handle_events*(), which only
// PollHotplug() calls, with mu_ held: it must not lock.
struct HotplugBridge {
  static int LIBUSB_CALL Callback(libusb_context*, libusb_device* dev, libusb_hotplug_event event,
                                  void* user) {
    auto* self = static_cast<UsbTicTurntable*>(user);
    if (event == LIBUSB_HOTPLUG_EVENT_DEVICE_LEFT && self->handle_ &&
        libusb_get_device(self->handle_) == dev) {
      self->departed_ = true;
    }
    return 0;  // stay registered
  }
};

UsbTicTurntable::UsbTicTurntable(const TurntableConfig& config)
    : config_(config), usb_(config.usb) {}

UsbTicTurntable::~UsbTicTurntable() {
  std::lock_guard<std::mutex> l(mu_);
  DropHandle();
  ExitContext();
}

void UsbTicTurntable::ExitContext() {
  if (!ctx_) return;
  if (hotplug_) libusb_hotplug_deregister_callback(ctx_, hotplug_);
  hotplug_ = 0;
  libusb_exit(ctx_);
  ctx_ = nullptr;
}

std::string UsbTicTurntable::SelectionDescription() const {
  std::string s = "Tic (USB " + Hex4(usb_.vendor_id) + ":" +
                  (usb_.product_id ? Hex4(usb_.product_id) : std::string("any Tic model"));
  if (!usb_.serial_number.empty()) s += ", serial " + usb_.serial_number;
  return s + ")";
}

TurntableInfo UsbTicTurntable::Info() const {
  std::lock_guard<std::mutex> l(mu_);
  TurntableInfo info;
  info.backend = "usb-tic";
  const std::string serial = serial_.empty() ? usb_.serial_number : serial_;
  info.id = "usb:" + Hex4(usb_.vendor_id) + ":" +
            Hex4(product_id_ ? product_id_ : usb_.product_id) +
            (serial.empty() ? std::string() : "/" + serial);
  const char* name =
      tic::ProductName(product_id_ ? product_id_ : static_cast<uint16_t>(usb_.product_id));
  info.model = name ? name : "Pololu Tic";
  return info;
}

void UsbTicTurntable::DropHandle() {
  if (!handle_) return;
  libusb_release_interface(handle_, tic::kNativeInterface);
  libusb_close(handle_);
  handle_ = nullptr;
  departed_ = false;
}

void UsbTicTurntable::PollHotplug() {
  if (!ctx_ || !hotplug_) return;
  timeval zero{0, 0};
  libusb_handle_events_timeout_completed(ctx_, &zero, nullptr);
  if (departed_ && handle_) {
    AGG_LOGW(kLog, "%s left the USB bus (hotplug event)", SelectionDescription().c_str());
    DropHandle();
    lost_ = true;
    ++hotplug_departures_;
  }
}

int UsbTicTurntable::hotplug_departures() const {
  std::lock_guard<std::mutex> l(mu_);
  return hotplug_departures_;
}

Status UsbTicTurntable::Connect() {
  // A fresh libusb context for every search: with hotplug support libusb
  // lists devices from the cache its hotplug monitor keeps, and where no udev
  // daemon runs (containers, minimal systems) that cache never learns of a
  // re-plugged device. A new context enumerates sysfs afresh.
  ExitContext();
  {
    const int rc = libusb_init(&ctx_);
    if (rc != 0) {
      ctx_ = nullptr;
      return MakeError(ErrorClass::kDeviceMissing,
                       "USB is not available on this machine, so " + SelectionDescription() +
                           " cannot be found — check that /dev/bus/usb exists (usbfs) and the "
                           "service may use it",
                       libusb_strerror(rc));
    }
    if (libusb_has_capability(LIBUSB_CAP_HAS_HOTPLUG)) {
      libusb_hotplug_register_callback(ctx_, LIBUSB_HOTPLUG_EVENT_DEVICE_LEFT,
                                       LIBUSB_HOTPLUG_NO_FLAGS, usb_.vendor_id,
                                       LIBUSB_HOTPLUG_MATCH_ANY, LIBUSB_HOTPLUG_MATCH_ANY,
                                       &HotplugBridge::Callback, this, &hotplug_);
    }
  }
  libusb_device** list = nullptr;
  const ssize_t n = libusb_get_device_list(ctx_, &list);
  if (n < 0) {
    return MakeError(ErrorClass::kDeviceMissing,
                     "cannot list USB devices to find " + SelectionDescription(),
                     libusb_strerror(static_cast<int>(n)));
  }
  struct Found {
    libusb_device_handle* handle;
    uint16_t pid;
    std::string serial;
  };
  std::vector<Found> found;
  std::string denied;  // "bus 1 device 4" of a matching device we may not open
  for (ssize_t i = 0; i < n; ++i) {
    libusb_device_descriptor d{};
    if (libusb_get_device_descriptor(list[i], &d) != 0) continue;
    if (d.idVendor != usb_.vendor_id) continue;
    if (usb_.product_id ? d.idProduct != usb_.product_id
                        : (usb_.vendor_id == tic::kVendorId && !tic::ProductName(d.idProduct))) {
      continue;
    }
    const std::string where = "bus " + std::to_string(libusb_get_bus_number(list[i])) + " device " +
                              std::to_string(libusb_get_device_address(list[i]));
    libusb_device_handle* h = nullptr;
    const int rc = libusb_open(list[i], &h);
    if (rc == LIBUSB_ERROR_ACCESS) {
      denied = where;
      continue;
    }
    if (rc != 0) continue;  // vanished between listing and opening
    std::array<unsigned char, 64> sn{};
    const int len = d.iSerialNumber
                        ? libusb_get_string_descriptor_ascii(h, d.iSerialNumber, sn.data(),
                                                             static_cast<int>(sn.size()))
                        : 0;
    std::string serial = len > 0 ? std::string(reinterpret_cast<char*>(sn.data()), len) : "";
    if (!usb_.serial_number.empty() && serial != usb_.serial_number) {
      libusb_close(h);
      continue;
    }
    found.push_back({h, d.idProduct, std::move(serial)});
  }
  libusb_free_device_list(list, 1);

  if (found.size() > 1) {
    std::string serials;
    for (auto& f : found) {
      serials += (serials.empty() ? "" : ", ") + (f.serial.empty() ? "(no serial)" : f.serial);
      libusb_close(f.handle);
    }
    return MakeError(ErrorClass::kInvalidConfig,
                     std::to_string(found.size()) + " Tics are attached (serial numbers " +
                         serials + "); set turntable.usb.serial_number to the turntable's");
  }
  if (found.empty()) {
    if (!denied.empty()) {
      return MakeError(ErrorClass::kDeviceMissing,
                       "no permission to open " + SelectionDescription() + " at " + denied +
                           " — install systemd/70-aggscan.rules (vendor " + Hex4(usb_.vendor_id) +
                           ": group plugdev) and add the user to plugdev, then re-plug");
    }
    return MakeError(ErrorClass::kDeviceMissing,
                     SelectionDescription() +
                         " not found — check the USB cable and that the Tic is powered; `lsusb "
                         "-d " +
                         Hex4(usb_.vendor_id) +
                         ":` should list it (check "
                         "turntable.usb.serial_number / vendor_id / product_id)");
  }
  libusb_device_handle* h = found[0].handle;
  const int rc = libusb_claim_interface(h, tic::kNativeInterface);
  if (rc != 0) {
    libusb_close(h);
    if (rc == LIBUSB_ERROR_BUSY) {
      return MakeError(ErrorClass::kDeviceMissing,
                       SelectionDescription() +
                           " is in use by another program (the Tic Control Center or ticcmd?) — "
                           "close it",
                       libusb_strerror(rc));
    }
    if (rc == LIBUSB_ERROR_NO_DEVICE) {
      return MakeError(ErrorClass::kDeviceMissing,
                       SelectionDescription() + " went away while it was being opened",
                       libusb_strerror(rc));
    }
    return MakeError(ErrorClass::kDeviceMissing,
                     "cannot claim the native USB interface of " + SelectionDescription(),
                     libusb_strerror(rc));
  }
  handle_ = h;
  departed_ = false;
  product_id_ = found[0].pid;
  serial_ = found[0].serial;
  return OkStatus();
}

Error UsbTicTurntable::TransferError(int rc, const std::string& what) {
  const std::string dev = SelectionDescription();
  if (rc == LIBUSB_ERROR_NO_DEVICE || rc == LIBUSB_ERROR_IO || rc == LIBUSB_ERROR_NOT_FOUND) {
    // Gone (unplugged, powered off, hub reset): drop the handle; the next
    // request looks the Tic up again.
    DropHandle();
    lost_ = true;
    return MakeError(ErrorClass::kDisconnected,
                     dev + " disconnected while " + what +
                         " — check the USB cable and the Tic's power; it is reopened when it is "
                         "back (home again then)",
                     libusb_strerror(rc));
  }
  if (rc == LIBUSB_ERROR_TIMEOUT) {
    return MakeError(ErrorClass::kTimeout,
                     dev + " did not complete " + what + " within turntable.usb.timeout " +
                         FormatDuration(usb_.timeout) + " — check the Tic (its LEDs) and the cable",
                     libusb_strerror(rc));
  }
  if (rc == LIBUSB_ERROR_PIPE) {
    return MakeError(ErrorClass::kDeviceFault,
                     dev + " refused " + what +
                         " (control request stalled) — is it a Tic with current firmware, and is "
                         "its control mode Serial / I2C / USB?",
                     libusb_strerror(rc));
  }
  return MakeError(ErrorClass::kDeviceFault, dev + ": " + what + " failed", libusb_strerror(rc));
}

Status UsbTicTurntable::EnsureConnected() {
  PollHotplug();
  if (handle_) return OkStatus();
  Status s = Connect();
  if (!s) {
    if (lost_ && s.error().cls == ErrorClass::kDeviceMissing) {
      return MakeError(ErrorClass::kDisconnected, s.error().message, s.error().detail);
    }
    return s;
  }
  s = SetUp();
  if (!s) return s;
  if (lost_) {
    AGG_LOGW(kLog, "%s is back; its position is unknown until it is homed again",
             SelectionDescription().c_str());
    lost_ = false;
    homed_ = false;
    phase_ = Phase::kNone;
  }
  return OkStatus();
}

Status UsbTicTurntable::Command(uint8_t cmd, uint32_t value, const std::string& what) {
  Status s = EnsureConnected();
  if (!s) return s;
  // Section 11 of the Tic user's guide: 32-bit data split into wValue (low
  // half) and wIndex (high half); quick and 7-bit commands use wValue only.
  const int rc = libusb_control_transfer(
      handle_, tic::kRequestTypeOut, cmd, static_cast<uint16_t>(value & 0xFFFFu),
      static_cast<uint16_t>(value >> 16), nullptr, 0, TimeoutMs(usb_.timeout));
  if (rc < 0) return TransferError(rc, what);
  return OkStatus();
}

Result<tic::Variables> UsbTicTurntable::ReadVariables() {
  Status s = EnsureConnected();
  if (!s) return s.error();
  std::array<uint8_t, tic::kStatusBlockSize> buf{};
  const int rc =
      libusb_control_transfer(handle_, tic::kRequestTypeIn, tic::kCmdGetVariable, 0, 0, buf.data(),
                              static_cast<uint16_t>(buf.size()), TimeoutMs(usb_.timeout));
  if (rc < 0) return TransferError(rc, "reading its variables");
  return tic::ParseVariables(std::span<const uint8_t>(buf.data(), static_cast<size_t>(rc)));
}

Status UsbTicTurntable::SetUp() {
  const double spr = usb_.steps_per_rev();
  Result<uint32_t> speed = tic::SpeedUnits(config_.max_speed_deg_s, spr);
  if (!speed) return speed.error();
  Result<uint32_t> accel = tic::AccelUnits(config_.accel_deg_s2, spr);
  if (!accel) return accel.error();
  const std::optional<uint8_t> mode = tic::StepModeCode(usb_.microsteps);
  if (!mode) {
    return MakeError(ErrorClass::kInvalidConfig,
                     "turntable.usb.microsteps " + std::to_string(usb_.microsteps) +
                         " is not a Tic step mode (1, 2, 4, 8, 16, 32; 36v4 also 64, 128, 256)");
  }
  if (*mode > 5 && product_id_ != 0x00CB) {
    return MakeError(
        ErrorClass::kInvalidConfig,
        "turntable.usb.microsteps " + std::to_string(usb_.microsteps) + " needs a Tic 36v4; this " +
            std::string(tic::ProductName(product_id_) ? tic::ProductName(product_id_) : "Tic") +
            " goes to 32");
  }
  struct Step {
    uint8_t cmd;
    uint32_t value;
    const char* what;
  };
  const Step steps[] = {
      {tic::kCmdSetStepMode, *mode, "setting the step mode"},
      {tic::kCmdSetMaxSpeed, *speed, "setting the max speed"},
      {tic::kCmdSetMaxAccel, *accel, "setting the max acceleration"},
      {tic::kCmdSetMaxDecel, *accel, "setting the max deceleration"},
  };
  for (const Step& st : steps) {
    const int rc = libusb_control_transfer(
        handle_, tic::kRequestTypeOut, st.cmd, static_cast<uint16_t>(st.value & 0xFFFFu),
        static_cast<uint16_t>(st.value >> 16), nullptr, 0, TimeoutMs(usb_.timeout));
    if (rc < 0) return TransferError(rc, st.what);
  }
  return OkStatus();
}

Status UsbTicTurntable::Prepare() {
  Status s = Command(tic::kCmdResetCommandTimeout, 0, "resetting the command timeout");
  if (s) s = Command(tic::kCmdExitSafeStart, 0, "exiting safe start");
  if (s) s = Command(tic::kCmdEnergize, 0, "energizing the motor");
  return s;
}

Status UsbTicTurntable::DoOpen() {
  std::lock_guard<std::mutex> l(mu_);
  phase_ = Phase::kNone;
  homed_ = false;
  lost_ = false;
  turn_offset_deg_ = 0.0;
  // Limits that do not fit the Tic: refuse before talking to it.
  Result<uint32_t> speed = tic::SpeedUnits(config_.max_speed_deg_s, usb_.steps_per_rev());
  if (!speed) return speed.error();
  Result<uint32_t> accel = tic::AccelUnits(config_.accel_deg_s2, usb_.steps_per_rev());
  if (!accel) return accel.error();
  Status s = EnsureConnected();
  if (s) s = Prepare();
  if (s) {
    Result<tic::Variables> v = ReadVariables();  // it must answer, or Open fails with the reason
    if (!v) s = v.error();
  }
  if (!s) DropHandle();
  lost_ = false;
  return s;
}

void UsbTicTurntable::DoClose() {
  std::lock_guard<std::mutex> l(mu_);
  if (handle_) {
    // Best effort: leave the motor without current when aggscan is not using it.
    libusb_control_transfer(handle_, tic::kRequestTypeOut, tic::kCmdDeenergize, 0, 0, nullptr, 0,
                            TimeoutMs(usb_.timeout));
  }
  DropHandle();
  phase_ = Phase::kNone;
  lost_ = false;
}

Status UsbTicTurntable::ResetController() {
  if (!is_open()) return MakeError(ErrorClass::kInvalidState, "turntable is not open");
  std::lock_guard<std::mutex> l(mu_);
  Status s = Command(tic::kCmdReset, 0, "resetting the controller");
  if (!s) return s;
  homed_ = false;
  phase_ = Phase::kNone;
  turn_offset_deg_ = 0.0;
  // The reset reloads the Tic's settings: apply ours again.
  return SetUp();
}

Status UsbTicTurntable::DoStartHome() {
  std::lock_guard<std::mutex> l(mu_);
  Result<tic::Variables> v = ReadVariables();
  if (!v) return v.error();
  Status s = OkStatus();
  if (v->has_error(tic::kErrMotorDriver)) {
    s = Command(tic::kCmdClearDriverError, 0, "clearing the motor driver error");
    if (!s) return s;
  }
  s = Prepare();
  if (!s) return s;
  if (usb_.home == "here") {
    s = Command(tic::kCmdHaltAndSetPosition, 0, "setting the home position");
  } else {
    s = Command(tic::kCmdGoHome, usb_.home == "forward" ? 1 : 0, "starting the homing run");
  }
  if (!s) return s;
  phase_ = Phase::kHoming;
  homed_ = false;
  turn_offset_deg_ = 0.0;
  target_steps_ = 0;
  return OkStatus();
}

Status UsbTicTurntable::DoStartMoveTo(double angle_deg) {
  std::lock_guard<std::mutex> l(mu_);
  Result<tic::Variables> v = ReadVariables();
  if (!v) return v.error();
  if (!homed_) return MakeError(ErrorClass::kInvalidState, "turntable is not homed; home first");
  const uint16_t alarm = v->error_status & ~kClearedByPrepare;
  if (alarm) {
    return MakeError(ErrorClass::kDeviceFault,
                     "the Tic reports " + tic::ErrorStatusText(alarm) +
                         "; remove the cause, then home again (homing clears a driver error)");
  }
  const double spd = StepsPerDeg();
  const ControllerTarget target = PlanControllerTarget(
      angle_deg, turn_offset_deg_, v->current_position, spd, usb_.shortest_path);
  const MoveLegs legs = PlanBacklashLegs(v->current_position, target.steps,
                                         std::llround(usb_.backlash_comp_deg * spd),
                                         ParseBacklashApproach(usb_.backlash_approach));
  if (!legs.fit_int32()) {
    return MakeError(ErrorClass::kInvalidArgument,
                     "target " + std::to_string(angle_deg) +
                         " deg is beyond the Tic's int32 position range at " +
                         std::to_string(usb_.steps_per_rev()) + " microsteps/rev");
  }
  Status s = Prepare();
  if (!s) return s;
  s = StartLeg(legs.first);
  if (!s) return s;
  turn_offset_deg_ = target.turn_offset_deg;
  target_steps_ = legs.final;
  phase_ = legs.two_legs() ? Phase::kOvershoot : Phase::kMoving;
  return OkStatus();
}

Status UsbTicTurntable::StartLeg(int64_t target_steps) {
  Status s =
      Command(tic::kCmdSetTargetPosition, static_cast<uint32_t>(static_cast<int32_t>(target_steps)),
              "setting the target position");
  if (s) leg_steps_ = target_steps;
  return s;
}

Status UsbTicTurntable::DoStop() {
  std::lock_guard<std::mutex> l(mu_);
  Status s = Command(tic::kCmdHaltAndHold, 0, "halting");
  if (s) phase_ = Phase::kStopped;
  return s;
}

Result<TurntableStatus> UsbTicTurntable::DoReadStatus() {
  std::lock_guard<std::mutex> l(mu_);
  // Keeps the Tic's command timeout from stopping a move aggscan is watching.
  Status s = Command(tic::kCmdResetCommandTimeout, 0, "resetting the command timeout");
  if (!s) return s.error();
  Result<tic::Variables> r = ReadVariables();
  if (!r) return r.error();
  const tic::Variables& v = *r;
  // De-energized (power loss, reset, an error response): steps may be lost.
  if (!v.energized()) homed_ = false;

  TurntableStatus st;
  st.enabled = v.energized();
  const bool planning = v.planning_mode == tic::kPlanningTargetPosition &&
                        v.current_position != v.target_position && v.error_status == 0;
  st.moving = v.current_velocity != 0 || planning || v.homing_active();
  // Errors aggscan's commands clear are alarms only while a commanded motion
  // cannot go on because of them.
  const bool in_motion_phase =
      phase_ == Phase::kHoming || phase_ == Phase::kOvershoot || phase_ == Phase::kMoving;
  const uint16_t alarm =
      in_motion_phase && !st.moving ? v.error_status : v.error_status & ~kClearedByPrepare;
  st.alarm = alarm != 0;
  st.alarm_code = alarm;
  if (st.alarm) {
    st.alarm_text = "Tic error: " + tic::ErrorStatusText(alarm) + " (operation state " +
                    tic::OperationStateName(v.operation_state) + ")";
  }
  const double window = std::max(1.0, usb_.in_position_window_deg * StepsPerDeg());
  const bool settled = !st.moving && !st.alarm && v.energized();
  auto near = [&](int64_t goal) {
    return std::fabs(static_cast<double>(v.current_position - goal)) <= window;
  };
  switch (phase_) {
    case Phase::kNone:
      st.in_position = settled && homed_;
      break;
    case Phase::kStopped:
      st.in_position = false;
      break;
    case Phase::kHoming:
      st.in_position = settled && !v.position_uncertain() && near(0);
      if (st.in_position) {
        homed_ = true;
        phase_ = Phase::kNone;
      }
      break;
    case Phase::kOvershoot:
      st.in_position = false;
      if (settled && near(leg_steps_)) {
        // Past the target: now approach it in the compensation's direction.
        s = StartLeg(target_steps_);
        if (!s) return s.error();
        phase_ = Phase::kMoving;
        st.moving = true;
      }
      break;
    case Phase::kMoving:
      st.in_position = settled && near(target_steps_);
      break;
  }
  st.homed = homed_;
  st.angle_deg = v.current_position / StepsPerDeg() + turn_offset_deg_;
  return st;
}

}  // namespace aggscan::usb
