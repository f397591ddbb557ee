// Start button interface: GPIO line, input-device key, Modbus input, or the
// sim. Presses are delivered through the callback on the driver's thread
// (post an event, touch nothing). The base debounces: presses closer than the
// debounce time to the previous accepted one are dropped. A backend whose
// device goes away while it runs (unplugged pedal, lost Modbus link) records
// the error with ReportFault(); Health() shows it until the next Start().
#pragma once

#include <functional>
#include <mutex>
#include <optional>
#include <string>

#include "common/clock.h"
#include "common/error.h"

namespace aggscan {

struct ButtonPress {
  TimeNs time = 0;     // on the daemon's clock
  std::string source;  // "gpio", "api", "cli", "sim", ...
};
using PressCallback = std::function<void(const ButtonPress&)>;

class Button {
 public:
  virtual ~Button() = default;
  Button(const Button&) = delete;
  Button& operator=(const Button&) = delete;

  /// Starts watching the input; presses go to `on_press`.
  Status Start(PressCallback on_press);
  void Stop();
  /// A press from software (API, CLI, tests): same path as the hardware.
  void InjectPress(const std::string& source);
  virtual std::string Describe() const = 0;
  /// Ok while started and working; the backend's runtime fault otherwise
  /// (kDisconnected, kTimeout, ...), with a message naming what to check.
  Status Health() const;

 protected:
  Button(Clock& clock, TimeNs debounce) : clock_(clock), debounce_(debounce) {}
  /// Backends call this for every hardware press; the base debounces.
  void DeliverPress(const std::string& source);
  /// Backends call this from their thread when the device fails while started.
  void ReportFault(Error error);
  virtual Status DoStart() = 0;
  virtual void DoStop() = 0;

 private:
  Clock& clock_;
  TimeNs debounce_;
  mutable std::mutex mu_;
  PressCallback cb_;
  std::optional<Error> fault_;
  bool started_ = false;
  bool have_last_ = false;
  TimeNs last_press_ = 0;
};

}  // namespace aggscan
