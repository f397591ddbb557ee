// One injectable clock for the daemon, the sim rig and the tests.
//
// Time is a monotonic count of nanoseconds (TimeNs) on the clock's own time
// line. RealClock follows CLOCK_MONOTONIC. ScaledClock runs `scale` times faster
// than real time, so a 2-minute capture takes seconds. VirtualClock only moves
// when told (AdvanceTo), so an offline simulated capture takes no waiting at all
// and is fully deterministic.
#pragma once

#include <atomic>
#include <chrono>
#include <cstdint>
#include <mutex>
#include <string>

namespace aggscan {

using TimeNs = int64_t;  // nanoseconds on a clock's monotonic time line
constexpr TimeNs kNsPerMs = 1'000'000;
constexpr TimeNs kNsPerSec = 1'000'000'000;

class Clock {
 public:
  virtual ~Clock() = default;
  /// Monotonic time on this clock's time line.
  virtual TimeNs Now() const = 0;
  /// Wall-clock UTC time in ns since the Unix epoch that corresponds to Now().
  virtual int64_t UtcNs() const = 0;
  /// How many clock nanoseconds pass per real nanosecond (0 for virtual clocks).
  virtual double Scale() const = 0;
  /// True when time advances only through AdvanceTo().
  virtual bool IsVirtual() const { return false; }
  /// Virtual clocks: move time forward to t (never backwards). Others: no-op.
  virtual void AdvanceTo(TimeNs /*t*/) {}
  /// Real nanoseconds until clock time t is reached (>= 0). Virtual: 0.
  int64_t RealNsUntil(TimeNs t) const;
  /// Blocks the calling thread until clock time t (virtual clocks: advances).
  void SleepUntil(TimeNs t);
};

class RealClock final : public Clock {
 public:
  TimeNs Now() const override;
  int64_t UtcNs() const override;
  double Scale() const override { return 1.0; }
};

/// Runs `scale` times faster than real time, starting at the real monotonic
/// time of construction; UTC advances at the same scaled rate.
class ScaledClock final : public Clock {
 public:
  explicit ScaledClock(double scale);
  TimeNs Now() const override;
  int64_t UtcNs() const override;
  double Scale() const override { return scale_; }

 private:
  double scale_;
  TimeNs real_start_;
  int64_t utc_start_;
};

/// Moves only through AdvanceTo(). Starts at `start` with UTC `utc_start`.
class VirtualClock final : public Clock {
 public:
  explicit VirtualClock(TimeNs start = 0, int64_t utc_start_ns = 1'767'225'600LL * kNsPerSec);
  TimeNs Now() const override { return now_.load(); }
  int64_t UtcNs() const override { return utc_start_ + (now_.load() - start_); }
  double Scale() const override { return 0.0; }
  bool IsVirtual() const override { return true; }
  void AdvanceTo(TimeNs t) override;

 private:
  TimeNs start_;
  int64_t utc_start_;
  std::atomic<TimeNs> now_;
};

/// ISO 8601 UTC with milliseconds: "2026-11-22T04:14:48.123Z".
std::string FormatUtc(int64_t utc_ns);
/// FormatUtc of the real wall clock now (record timestamps).
std::string NowUtcString();
/// The wall clock now as "20261205T101500Z": sorts by time and holds no ':',
/// for names of files and folders.
std::string CompactUtcNow();
/// Raw CLOCK_MONOTONIC in ns (for measuring real durations).
TimeNs MonotonicNs();

}  // namespace aggscan
