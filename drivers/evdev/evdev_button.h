// Start button on a key of an input device (backend "evdev"): a USB foot
// pedal or keypad, through libevdev.
//
// Start() opens the device (a path, or a name under /dev/input/by-id or
// /dev/input/by-path, which stay the same across reboots and ports), checks
// that it has the configured key (EVIOCGBIT, through libevdev) and optionally
// grabs it (EVIOCGRAB) so the key does not also reach the console. A thread
// polls the fd with a 100 ms timeout (Stop() is prompt); a press is the key's
// value 1 (down); releases (0) and autorepeat (2) are not presses, other
// keys are ignored. An unplugged device (ENODEV) is a kDisconnected fault.
#pragma once

#include <atomic>
#include <string>
#include <thread>

#include "common/clock.h"
#include "config/config.h"
#include "drivers/button.h"

struct libevdev;

namespace aggscan::evdev {

class EvdevButton final : public Button {
 public:
  /// `clock` must outlive the button.
  EvdevButton(Clock& clock, const ButtonConfig& config);
  ~EvdevButton() override;
  std::string Describe() const override;
  /// Key-down events of other keys seen since Start() (tests, diagnostics).
  int other_keys() const { return other_keys_.load(); }
  /// The device path Start() opened.
  const std::string& path() const { return path_; }

 protected:
  Status DoStart() override;
  void DoStop() override;

 private:
  void Run();
  void CloseDevice();

  const EvdevButtonConfig config_;
  int code_ = -1;
  std::string path_;
  std::string name_;  // the device's name, for messages
  int fd_ = -1;
  libevdev* dev_ = nullptr;
  std::atomic<bool> stop_{false};
  std::atomic<int> other_keys_{0};
  std::thread thread_;
};

}  // namespace aggscan::evdev
