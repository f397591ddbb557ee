// Start button on a GPIO line (backend "gpio"), through libgpiod v1.
//
// The line is requested for both edges; a thread blocks in
// gpiod_line_event_wait with a 100 ms timeout (so Stop() returns promptly)
// and reads the kernel's edge events. A press is the active edge: rising, or
// falling with active_low (a switch to ground with a pull-up). Contacts
// bounce, so an active edge counts only when the line has been quiet (no
// edge at all) for the debounce time before it, by the kernel's event
// timestamps: the edges of a press's and a release's bounce train are
// ignored whatever the thread's scheduling. The base then debounces accepted
// presses on the daemon's clock as for every backend.
#pragma once

#include <atomic>
#include <memory>
#include <string>
#include <thread>

#include "common/clock.h"
#include "config/config.h"
#include "drivers/button.h"
#include "drivers/gpio/gpio_line.h"

namespace aggscan::gpio {

class GpioButton final : public Button {
 public:
  /// `clock` must outlive the button.
  GpioButton(Clock& clock, const ButtonConfig& config);
  ~GpioButton() override;

  std::string Describe() const override;
  /// Edges seen since Start(), bounce included (tests, diagnostics).
  int edges_seen() const { return edges_.load(); }

 protected:
  Status DoStart() override;
  void DoStop() override;

 private:
  void Run();

  const GpioLineConfig config_;
  const TimeNs debounce_;
  std::unique_ptr<GpioLine> line_;
  std::atomic<bool> stop_{false};
  std::atomic<int> edges_{0};
  std::thread thread_;
};

}  // namespace aggscan::gpio
