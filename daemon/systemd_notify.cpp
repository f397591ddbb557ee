#include "daemon/systemd_notify.h"

#include <systemd/sd-daemon.h>

#include "common/log.h"

namespace aggscan {

void SystemdNotifier::Ready(const std::string& status) {
  sd_notifyf(0, "READY=1\nSTATUS=%s", status.c_str());
}

void SystemdNotifier::Status(const std::string& status) {
  sd_notifyf(0, "STATUS=%s", status.c_str());
}

void SystemdNotifier::Stopping() { sd_notify(0, "STOPPING=1\nSTATUS=stopping"); }

void SystemdNotifier::StartWatchdog() {
  uint64_t usec = 0;
  if (sd_watchdog_enabled(0, &usec) <= 0 || usec == 0) return;
  interval_us_ = usec / 2;
  AGG_LOGI("systemd", "watchdog enabled: pinging every %llu ms",
           static_cast<unsigned long long>(interval_us_ / 1000));
  Ping();
}

void SystemdNotifier::Ping() {
  sd_notify(0, "WATCHDOG=1");
  // Real time, not the (possibly scaled) capture clock.
  loop_.AddRealTimer(MonotonicNs() + static_cast<TimeNs>(interval_us_) * 1000, [this] { Ping(); });
}

}  // namespace aggscan
