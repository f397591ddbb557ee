// USB turntable backend "usb-tic": a Pololu Tic stepper controller on its
// native USB interface (vendor control transfers on endpoint 0, see
// tic_protocol.h), through libusb.
//
//  - Selection: the Tic with turntable.usb.serial_number, or the only Tic
//    attached (vendor_id / product_id; product_id 0 = any Tic model). None:
//    kDeviceMissing naming VID:PID and serial; no permission: kDeviceMissing
//    naming the udev rule; several and no serial: kInvalidConfig listing them.
//  - Open sets the step mode (turntable.usb.microsteps), max speed and
//    acceleration/deceleration (converted to the Tic's units), exits safe
//    start and energizes. Close de-energizes.
//  - Every ReadStatus also resets the Tic's command timeout: if aggscan stops
//    polling during a move, the Tic's own timeout stops the motor.
//  - Errors: a vanished device (unplugged, hub reset, the gadget unbound) is
//    kDisconnected and the handle is dropped; the next request looks the Tic
//    up again (re-plug) and, found, sets it up again and reports homed = false
//    (its position is no longer known). A transfer that does not complete in
//    turntable.usb.timeout is kTimeout; a stalled (refused) request is
//    kDeviceFault. Where libusb delivers hotplug events (a udev daemon runs)
//    the backend also listens for departures of the Tic's vendor ID, so an
//    unplug is reported at the next call without waiting for a transfer to
//    fail. Arrival needs no event: every request without a handle searches.
//  - Homing: the Tic's own homing procedure ("Go home", limit switch) in the
//    configured direction, or home = "here" (Halt and set position 0). It is
//    also the recovery step: a motor driver error is cleared first.
//  - Stop is the Tic's "Halt and hold" (an abrupt stop). The Tic then flags
//    its position as uncertain; the backend keeps its homed state (a stop by
//    aggscan at the rig's modest speeds loses no steps) until the Tic is
//    de-energized, reset or reconnected.
//  - Angles: microsteps per platter revolution = motor_steps_per_rev x
//    microsteps x gear_ratio; shortest_path as in the Modbus backend (the
//    backend keeps the whole-turn offset, ReadStatus reports cumulative
//    angles); backlash_comp_deg / backlash_approach as in the Modbus backend
//    (drivers/turntable_legs.h): a move against the approach direction first
//    goes past the target by the compensation; ReadStatus starts the leg back
//    once the Tic is there, and reports in_position only after that leg.
#pragma once

#include <atomic>
#include <mutex>
#include <string>

#include "config/config.h"
#include "drivers/turntable.h"
#include "drivers/usb/tic_protocol.h"

struct libusb_context;
struct libusb_device_handle;

namespace aggscan::usb {

class UsbTicTurntable final : public Turntable {
 public:
  explicit UsbTicTurntable(const TurntableConfig& config);
  ~UsbTicTurntable() override;

  TurntableInfo Info() const override;
  /// "Tic (USB 1ffb:any Tic model, serial 00123456)" — what the selection asks for.
  std::string SelectionDescription() const;
  /// Sends the Tic's "Reset" command: it forgets its state as after power-up
  /// (position 0 and uncertain, de-energized, safe start). Needs homing after.
  Status ResetController();
  /// Departures of the open Tic that libusb's hotplug events reported (they
  /// need a udev daemon; without one a failing transfer tells).
  int hotplug_departures() const;

 protected:
  Status DoOpen() override;
  Status DoStartHome() override;
  Status DoStartMoveTo(double angle_deg) override;
  Status DoStop() override;
  Result<TurntableStatus> DoReadStatus() override;
  void DoClose() override;

 private:
  // kOvershoot: the first leg of a backlash-compensated move; kMoving: the
  // move's (last) leg to target_steps_.
  enum class Phase { kNone, kHoming, kOvershoot, kMoving, kStopped };

  Status Connect();
  Status SetUp();  // step mode, limits, safe start, energize on a fresh handle
  Status EnsureConnected();
  void DropHandle();
  void ExitContext();  // the handle first
  void PollHotplug();
  Status Command(uint8_t cmd, uint32_t value, const std::string& what);
  Result<tic::Variables> ReadVariables();
  Error TransferError(int rc, const std::string& what);
  Status Prepare();  // before a motion command: command timeout, safe start, energize
  Status StartLeg(int64_t target_steps);  // sets the Tic's target position
  double StepsPerDeg() const { return usb_.steps_per_rev() / 360.0; }
  friend struct HotplugBridge;  // libusb's callback (in the .cpp) sets departed_

  const TurntableConfig config_;
  const UsbTicConfig usb_;

  mutable std::mutex mu_;  // guards everything below (one transfer at a time)
  libusb_context* ctx_ = nullptr;
  libusb_device_handle* handle_ = nullptr;
  int hotplug_ = 0;                    // libusb hotplug callback handle, 0 = none
  std::atomic<bool> departed_{false};  // set from the hotplug callback
  uint16_t product_id_ = 0;            // of the opened device
  std::string serial_;                 // of the opened device
  bool lost_ = false;                  // the device went away while open
  int hotplug_departures_ = 0;
  Phase phase_ = Phase::kNone;
  bool homed_ = false;
  int64_t target_steps_ = 0;      // target of the whole move
  int64_t leg_steps_ = 0;         // target of the leg in progress
  double turn_offset_deg_ = 0.0;  // reported angle = controller angle + this (multiples of 360)
};

}  // namespace aggscan::usb
