#include "drivers/gpio/gpio_button.h"

#include <gpiod.h>

#include <cerrno>
#include <cstring>

namespace aggscan::gpio {

GpioButton::GpioButton(Clock& clock, const ButtonConfig& config)
    : Button(clock, config.debounce), config_(config.gpio), debounce_(config.debounce) {}

GpioButton::~GpioButton() { Stop(); }

std::string GpioButton::Describe() const {
  return "GPIO button, line " + config_.line + " of chip " + config_.chip +
         (config_.active_low ? " (active low)" : " (active high)");
}

Status GpioButton::DoStart() {
  Result<std::unique_ptr<GpioLine>> l =
      GpioLine::Open(config_, LineUse::kBothEdges, "aggscan-button", "[button.gpio]");
  if (!l) return l.error();
  line_ = std::move(*l);
  stop_ = false;
  edges_ = 0;
  thread_ = std::thread([this] { Run(); });
  return OkStatus();
}

void GpioButton::DoStop() {
  stop_ = true;
  if (thread_.joinable()) thread_.join();
  line_.reset();
}

void GpioButton::Run() {
  const int active_type =
      config_.active_low ? GPIOD_LINE_EVENT_FALLING_EDGE : GPIOD_LINE_EVENT_RISING_EDGE;
  bool have_edge = false;
  TimeNs last_edge = 0;  // kernel timestamp of the previous edge, any direction
  const timespec wait = {0, 100L * 1000 * 1000};
  while (!stop_) {
    const int r = gpiod_line_event_wait(line_->line(), &wait);
    if (r == 0) continue;
    gpiod_line_event events[16];
    const int n = r < 0 ? -1 : gpiod_line_event_read_multiple(line_->line(), events, 16);
    if (n < 0) {
      const int err = errno;
      if (err == EINTR) continue;
      // ENODEV: the chip went away (an unbound gpio-sim, an unplugged USB GPIO adapter).
      ReportFault(MakeError(ErrorClass::kDisconnected,
                            "GPIO " + line_->name() +
                                " stopped delivering edges; check the chip "
                                "and [button.gpio]",
                            std::strerror(err)));
      return;
    }
    for (int i = 0; i < n; ++i) {
      ++edges_;
      const TimeNs t = static_cast<TimeNs>(events[i].ts.tv_sec) * kNsPerSec + events[i].ts.tv_nsec;
      const bool quiet_before = !have_edge || t - last_edge >= debounce_;
      have_edge = true;
      last_edge = t;
      if (events[i].event_type == active_type && quiet_before) DeliverPress("gpio");
    }
  }
}

}  // namespace aggscan::gpio
