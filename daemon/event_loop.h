// One epoll loop that owns the daemon's state. Other threads (driver
// callbacks, HTTP handlers) only Post() closures to it. Timers are in the
// daemon clock's time (scaled for the sim) or in real monotonic time (the
// systemd watchdog); both are served by one timerfd. Signals arrive through a
// signalfd.
//
// Virtual clocks: when nothing is posted and no external operation is in
// flight (Hold()), the loop jumps the clock to the next timer instead of
// waiting, so an offline simulated capture runs as fast as the CPU allows and
// is deterministic.
#pragma once

#include <atomic>
#include <functional>
#include <map>
#include <mutex>
#include <vector>

#include "common/clock.h"

namespace aggscan {

class EventLoop {
 public:
  using TimerId = uint64_t;
  explicit EventLoop(Clock& clock);
  ~EventLoop();
  EventLoop(const EventLoop&) = delete;
  EventLoop& operator=(const EventLoop&) = delete;

  /// Thread-safe: runs fn on the loop thread.
  void Post(std::function<void()> fn);
  /// Loop thread: runs fn when the loop clock reaches `at`.
  TimerId AddTimer(TimeNs at, std::function<void()> fn);
  /// Loop thread: runs fn at real CLOCK_MONOTONIC time `real_at`.
  TimerId AddRealTimer(TimeNs real_at, std::function<void()> fn);
  void CancelTimer(TimerId id);
  /// Blocks these signals in the calling thread (call before starting other
  /// threads) and delivers them to fn on the loop.
  void HandleSignals(const std::vector<int>& signals, std::function<void(int)> fn);
  /// Marks an external operation in flight (e.g. a camera still): a virtual
  /// clock must not jump while one is. Thread-safe.
  void Hold();
  void Release();
  /// Runs until Quit(); returns the exit code given to Quit.
  int Run();
  /// Thread-safe.
  void Quit(int code = 0);
  /// True once Run() has returned: posted work will never run (any thread may ask).
  /// Before Run() starts, posted work waits for it.
  bool stopped() const { return stopped_.load(); }
  Clock& clock() { return clock_; }

 private:
  struct Timer {
    TimeNs at;
    bool real;
    std::function<void()> fn;
  };
  void Wake();
  void ArmTimerFd();
  bool FireDueTimers();
  Clock& clock_;
  int epfd_ = -1, eventfd_ = -1, timerfd_ = -1, sigfd_ = -1;
  std::mutex mu_;
  std::vector<std::function<void()>> posted_;
  int holds_ = 0;
  std::map<TimerId, Timer> timers_;
  TimerId next_id_ = 1;
  std::function<void(int)> on_signal_;
  std::atomic<bool> quit_{false};
  std::atomic<bool> stopped_{false};
  int exit_code_ = 0;
};

}  // namespace aggscan
