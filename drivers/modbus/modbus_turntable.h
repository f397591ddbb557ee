// Modbus turntable backends: "modbus-tcp" and "modbus-rtu", through libmodbus.
//
// Everything controller-specific is in the register-map profile
// (config/turntable_profile.h, config/turntables/*.toml): where the target,
// the measured position and the status bits live, the word order of 32-bit
// values, the command registers and values, speed and acceleration scaling.
// The backend adds what the rig needs on top of any controller:
//
//  - Steps <-> degrees: steps per platter revolution = motor_steps_per_rev x
//    microsteps x gear_ratio (turntable.modbus).
//  - Requests time out after response_timeout and are repeated at most
//    `retries` times; a request never answered is kTimeout with a message that
//    names the unit, the port and the line settings. A lost TCP connection or
//    serial device is reopened once on the next request (kDisconnected if it
//    stays away). Modbus exception replies are kDeviceFault, named.
//  - Link hygiene (link_hygiene.h): after a time-out or an answer that does
//    not fit, TCP re-opens the connection and RTU waits out the late answer
//    before anything else is sent, so no answer is taken for a later
//    request's. Commands (move, home, stop, reset) are never repeated blindly:
//    when one goes unanswered the controller's state is read, and it is sent
//    again only if it did not take effect.
//  - in_position is reported only when the controller's bit says so, it is not
//    moving and the measured position is within in_position_window_deg of the
//    commanded one: a controller may still show the previous move's bit for a
//    cycle after accepting a new command.
//  - shortest_path: StartMoveTo(a) drives to the position a modulo 360 that is
//    nearest (at most 180 deg away) instead of unwinding whole turns; the
//    backend keeps the whole-turn difference, so ReadStatus() still reports a
//    (the interface's absolute cumulative angle) once there.
//  - backlash_comp_deg: every target is finally approached in the same
//    direction (backlash_approach). A move against it first goes past the
//    target by the compensation and then back; the second leg is started by
//    ReadStatus() when the first one is in position, and in_position is
//    reported only after the second.
//  - Homing is also the recovery step: StartHome() resets a pending alarm
//    first (when the profile has a reset command).
//  - Commands return at once; the caller polls ReadStatus() and owns the
//    deadlines (the capture service: capture.home_timeout, move_timeout).
//    Stall detection (moving, position not advancing) is the capture
//    service's too (capture.stall_timeout), not repeated here.
#pragma once

#include <functional>
#include <memory>
#include <mutex>
#include <string>
#include <vector>

#include "config/config.h"
#include "config/turntable_profile.h"
#include "drivers/turntable.h"

// libmodbus's modbus_t, kept out of this header.
struct _modbus;  // NOLINT(bugprone-reserved-identifier): libmodbus's own tag for modbus_t

namespace aggscan::modbus {

enum class Transport { kTcp, kRtu };

class ModbusTurntable final : public Turntable {
 public:
  ModbusTurntable(Transport transport, const TurntableConfig& config, TurntableProfile profile);
  ~ModbusTurntable() override;

  TurntableInfo Info() const override;
  /// "unit 1 on /dev/ttyUSB0 at 19200 8N1" or "unit 1 at 10.0.0.5:502".
  std::string LinkDescription() const;
  /// Clears a controller alarm with the profile's reset command.
  Status ResetAlarm();
  /// Requests sent since construction, retries included (tests, metrics).
  int requests_sent() const;

 protected:
  Status DoOpen() override;
  Status DoStartHome() override;
  Status DoStartMoveTo(double angle_deg) override;
  Status DoStop() override;
  Result<TurntableStatus> DoReadStatus() override;
  void DoClose() override;

 private:
  struct CtxDeleter {
    void operator()(_modbus* ctx) const;
  };
  using Ctx = std::unique_ptr<_modbus, CtxDeleter>;

  // Raw controller state, in steps.
  struct Raw {
    bool enabled = true, moving = false, in_position = false, homed = false, alarm = false;
    int alarm_code = 0;
    int64_t steps = 0;
  };
  enum class Phase { kNone, kHoming, kOvershoot, kFinal, kStopped };

  Status Connect();
  // Runs one request with the retry/reconnect policy; `what` names it in
  // errors. A request that went unanswered is repeated as it is, unless
  // `resend` is given (commands): then it is called first and the request is
  // repeated only if it returns true; false means it took effect after all.
  template <typename F>
  Status Transact(const std::string& what, F&& request,
                  const std::function<Result<bool>()>& resend = {});
  // Puts the link back in step after request failure `err` (errno): TCP
  // closes the connection, RTU waits out a late answer (link_hygiene.h).
  void Resync(int err);
  Status WriteRegisters(const std::vector<RegisterWrite>& writes, const std::string& what);
  // `carried_out`: whether the controller's state shows the command took
  // effect (asked only when its answer was lost).
  Status WriteCommand(const RegisterWrite& command, const std::string& what,
                      const std::function<bool(const Raw&)>& carried_out);
  Result<Raw> ReadRaw();
  Status StartLeg(int64_t target_steps);
  Status MotionWrites(std::vector<RegisterWrite>* out) const;
  Error ClassifyFailure(int err, const std::string& what, int attempts) const;
  double StepsPerDeg() const;
  // Within in_position_window_deg (at least one step) of `goal`.
  bool NearSteps(int64_t steps, int64_t goal) const;

  const Transport transport_;
  const TurntableConfig config_;
  const TurntableProfile profile_;
  std::vector<std::pair<int, int>> read_blocks_;  // (first register, count)

  mutable std::mutex mu_;  // guards everything below (one request at a time)
  Ctx ctx_;
  bool connected_ = false;
  int requests_ = 0;
  Phase phase_ = Phase::kNone;
  int64_t leg_steps_ = 0;         // target of the leg in progress
  int64_t final_steps_ = 0;       // target of the whole move
  double turn_offset_deg_ = 0.0;  // reported angle = controller angle + this (multiples of 360)
  bool homed_since_open_ = false;
  bool rs485_warned_ = false;
};

}  // namespace aggscan::modbus
