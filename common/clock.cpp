#include "common/clock.h"

#include <time.h>

#include <cstdio>
#include <thread>

namespace aggscan {

TimeNs MonotonicNs() {
  timespec ts{};
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return static_cast<TimeNs>(ts.tv_sec) * kNsPerSec + ts.tv_nsec;
}

static int64_t RealUtcNs() {
  timespec ts{};
  clock_gettime(CLOCK_REALTIME, &ts);
  return static_cast<int64_t>(ts.tv_sec) * kNsPerSec + ts.tv_nsec;
}

int64_t Clock::RealNsUntil(TimeNs t) const {
  const double s = Scale();
  if (s <= 0.0) return 0;
  const TimeNs d = t - Now();
  if (d <= 0) return 0;
  return static_cast<int64_t>(static_cast<double>(d) / s);
}

void Clock::SleepUntil(TimeNs t) {
  if (IsVirtual()) {
    AdvanceTo(t);
    return;
  }
  while (Now() < t) {
    std::this_thread::sleep_for(std::chrono::nanoseconds(RealNsUntil(t) + 1000));
  }
}

std::string NowUtcString() { return FormatUtc(RealUtcNs()); }

std::string CompactUtcNow() {
  const time_t t = time(nullptr);
  tm parts{};
  gmtime_r(&t, &parts);
  char buf[32];
  strftime(buf, sizeof buf, "%Y%m%dT%H%M%SZ", &parts);
  return buf;
}

TimeNs RealClock::Now() const { return MonotonicNs(); }
int64_t RealClock::UtcNs() const { return RealUtcNs(); }

ScaledClock::ScaledClock(double scale)
    : scale_(scale > 0 ? scale : 1.0), real_start_(MonotonicNs()), utc_start_(RealUtcNs()) {}

TimeNs ScaledClock::Now() const {
  return real_start_ +
         static_cast<TimeNs>(static_cast<double>(MonotonicNs() - real_start_) * scale_);
}

int64_t ScaledClock::UtcNs() const { return utc_start_ + (Now() - real_start_); }

VirtualClock::VirtualClock(TimeNs start, int64_t utc_start_ns)
    : start_(start), utc_start_(utc_start_ns), now_(start) {}

void VirtualClock::AdvanceTo(TimeNs t) {
  TimeNs cur = now_.load();
  while (t > cur && !now_.compare_exchange_weak(cur, t)) {
  }
}

std::string FormatUtc(int64_t utc_ns) {
  const time_t secs = static_cast<time_t>(utc_ns / kNsPerSec);
  const int ms = static_cast<int>((utc_ns % kNsPerSec) / kNsPerMs);
  tm tmv{};
  gmtime_r(&secs, &tmv);
  char buf[64];
  std::snprintf(buf, sizeof buf, "%04d-%02d-%02dT%02d:%02d:%02d.%03dZ", tmv.tm_year + 1900,
                tmv.tm_mon + 1, tmv.tm_mday, tmv.tm_hour, tmv.tm_min, tmv.tm_sec, ms);
  return buf;
}

}  // namespace aggscan
