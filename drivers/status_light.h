// Optional status light (a lamp or stack light on a GPIO line or a Modbus
// coil) that tells the operator what the rig wants, from across the quarry:
//
//   pattern    shown while                                   lamp
//   off        aggscand is not running                       dark
//   ready      idle or armed, every device healthy           steady on
//   capturing  a side is being shot (homing .. storing)      slow blink, 0.5 s on / 0.5 s off
//   flip       waiting for the operator to flip the rock     fast blink, 0.15 s on / 0.15 s off
//   fault      faulted, or a device is unhealthy             double flash, then 1.05 s dark
//   turn       a hand-turned table: turn it to the next view  very fast, 0.07 s on / 0.07 s off
//              (then back to capturing: hands off, the camera shoots)
//
// The base runs the pattern on its own thread in real time (a lamp is for
// people, not for the daemon's clock); backends only switch the output.
#pragma once

#include <condition_variable>
#include <mutex>
#include <optional>
#include <string>
#include <thread>
#include <vector>

#include "common/clock.h"
#include "common/error.h"

namespace aggscan {

enum class LightPattern { kOff, kReady, kCapturing, kFlip, kFault, kTurn };
const char* LightPatternName(LightPattern p);

/// One step of a pattern: the output level held for `duration` (real time).
struct LightStep {
  bool on = false;
  TimeNs duration = 0;
};
/// The repeating steps of a pattern (one step = steady).
const std::vector<LightStep>& PatternSteps(LightPattern p);

class StatusLight {
 public:
  virtual ~StatusLight();
  StatusLight(const StatusLight&) = delete;
  StatusLight& operator=(const StatusLight&) = delete;

  /// Opens the output (dark) and starts the pattern thread.
  Status Open();
  /// Dark, then closed; the thread ends.
  void Close();
  /// Shows `p` from now on (restarts the pattern at its first step).
  void Show(LightPattern p);
  LightPattern pattern() const;
  /// Ok while the last output write worked; that write's error otherwise.
  Status Health() const;
  virtual std::string Describe() const = 0;

 protected:
  StatusLight() = default;
  virtual Status DoOpen() = 0;
  /// Sets the lamp (true = lit); called from the pattern thread only.
  virtual Status DoSet(bool on) = 0;
  virtual void DoClose() = 0;

 private:
  void Run();

  mutable std::mutex mu_;
  std::condition_variable cv_;
  std::thread thread_;
  bool open_ = false;
  bool stop_ = false;
  uint64_t generation_ = 0;  // bumped by Show(): the thread restarts the pattern
  LightPattern pattern_ = LightPattern::kOff;
  std::optional<Error> fault_;
};

}  // namespace aggscan
