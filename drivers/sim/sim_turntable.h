// Simulated turntable: a real backend of the Turntable interface whose motion
// is a pure function of clock time, so it runs on a VirtualClock at any speed
// without a thread.
//
// Motion model (degrees, absolute and cumulative like the real controllers):
//  - moves follow a trapezoidal profile limited by max_speed_deg_s and
//    accel_deg_s2 (triangular when the move is too short to reach top speed);
//  - each move ends at target + error: a Gaussian of sigma repeatability_deg
//    plus backlash_deg whenever the platter approaches its target in the
//    negative direction (homing approaches in the positive direction, so the
//    error changes by the backlash when the direction reverses);
//  - the MEASURED angle (ReadStatus, like a step count/encoder) follows the
//    profile and is exactly target + error once the move has ended;
//  - the PHYSICAL platter angle (what the sim camera sees) additionally leads
//    the motor during deceleration and rings after the move ends:
//    dir * settle_amplitude_deg * exp(-t/settle_time_constant) * cos(2 pi f t).
// Homing takes home_duration and ends at angle 0, homed.
//
// Faults (TurntableConfig.faults): stall_at_deg freezes a move that crosses
// that angle (status keeps moving=true, never in_position); timeout_every_n
// makes every n-th StartMoveTo and every later call fail with kTimeout until
// StartHome or Open; disconnect_after makes every call from Open()+t fail with
// kDisconnected. Deterministic for a given seed. Thread-safe.
#pragma once

#include <cstdint>
#include <functional>
#include <memory>

#include "common/clock.h"
#include "config/config.h"
#include "drivers/turntable.h"

namespace aggscan::sim {

class SimTurntable final : public Turntable {
 public:
  /// `clock` must outlive this object and every PhysicalAngleFunction().
  SimTurntable(Clock& clock, const TurntableConfig& config, uint64_t seed);
  ~SimTurntable() override;

  TurntableInfo Info() const override;

  /// Physical platter angle at clock time t (deg), settling oscillation
  /// included. Times before the last few commands are answered from the
  /// oldest one kept.
  double PhysicalAngleAt(TimeNs t) const;
  /// Measured (encoder) angle at clock time t, what ReadStatus reports.
  double MeasuredAngleAt(TimeNs t) const;
  /// Measured angle now.
  double MeasuredAngle() const;
  /// PhysicalAngleAt as a function that stays valid after this object is
  /// destroyed (it then reports the last motion), for the sim camera.
  std::function<double(TimeNs)> PhysicalAngleFunction() const;

 protected:
  Status DoOpen() override;
  Status DoStartHome() override;
  Status DoStartMoveTo(double angle_deg) override;
  Status DoStop() override;
  Result<TurntableStatus> DoReadStatus() override;
  void DoClose() override;

 private:
  struct Model;
  std::shared_ptr<Model> m_;
};

}  // namespace aggscan::sim
