// Turntable interface: absolute position moves with in-position status.
//
// Modelled on motor controllers reached over Modbus or USB: commands start a
// motion and return at once; the caller polls ReadStatus() until in_position
// (or alarm) and owns every deadline. Angles are absolute and cumulative in
// degrees (720 = two turns from home), so multi-turn schedules such as the
// study's 30 x 30 deg need no wrap-around logic.
//
// States:   Closed --Open()--> Open   (motion state is in TurntableStatus)
//           any --Close()--> Closed
#pragma once

#include <mutex>
#include <string>

#include "common/error.h"

namespace aggscan {

struct TurntableStatus {
  bool enabled = false;
  bool moving = false;
  bool in_position = false;  // the commanded move/home has completed
  bool homed = false;
  bool alarm = false;
  int alarm_code = 0;
  std::string alarm_text;
  double angle_deg = 0.0;  // measured (encoder/step count) absolute angle
  // False where nothing measures the angle (a table turned by hand): angle_deg
  // is then the plan's, and the worker measures each view's angle from the
  // labels on the disc.
  bool angle_measured = true;
};

struct TurntableInfo {
  std::string id;
  std::string backend;
  std::string model;
};

class Turntable {
 public:
  virtual ~Turntable() = default;
  Turntable(const Turntable&) = delete;
  Turntable& operator=(const Turntable&) = delete;

  Status Open();
  /// Starts homing (angle 0 is the reference after homing).
  Status StartHome();
  /// Starts a move to an absolute angle in degrees. Requires homed.
  Status StartMoveTo(double angle_deg);
  /// Stops any motion (abort).
  Status Stop();
  /// Reads the controller's status. Errors: kTimeout, kDisconnected, ...
  Result<TurntableStatus> ReadStatus();
  void Close();

  bool is_open() const;
  /// Last commanded target angle.
  double target_deg() const;
  virtual TurntableInfo Info() const = 0;

 protected:
  Turntable() = default;
  virtual Status DoOpen() = 0;
  virtual Status DoStartHome() = 0;
  virtual Status DoStartMoveTo(double angle_deg) = 0;
  virtual Status DoStop() = 0;
  virtual Result<TurntableStatus> DoReadStatus() = 0;
  virtual void DoClose() = 0;

 private:
  mutable std::mutex mu_;
  bool open_ = false;
  double target_deg_ = 0.0;
};

}  // namespace aggscan
