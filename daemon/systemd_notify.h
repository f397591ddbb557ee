// systemd integration: READY/STATUS/STOPPING notifications and the watchdog,
// pinged from the event loop so a hung loop gets the service restarted.
// Without NOTIFY_SOCKET (run by hand, tests) every call is a no-op.
#pragma once

#include <string>

#include "daemon/event_loop.h"

namespace aggscan {

class SystemdNotifier {
 public:
  explicit SystemdNotifier(EventLoop& loop) : loop_(loop) {}
  void Ready(const std::string& status);
  void Status(const std::string& status);
  void Stopping();
  /// Starts pinging WATCHDOG=1 at half the interval systemd asked for
  /// (WATCHDOG_USEC); does nothing when the watchdog is off.
  void StartWatchdog();

 private:
  void Ping();
  EventLoop& loop_;
  uint64_t interval_us_ = 0;
};

}  // namespace aggscan
