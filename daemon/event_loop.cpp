#include "daemon/event_loop.h"

#include <signal.h>
#include <sys/epoll.h>
#include <sys/eventfd.h>
#include <sys/signalfd.h>
#include <sys/timerfd.h>
#include <unistd.h>

#include <cerrno>
#include <climits>
#include <stdexcept>

namespace aggscan {

EventLoop::EventLoop(Clock& clock) : clock_(clock) {
  epfd_ = ::epoll_create1(EPOLL_CLOEXEC);
  eventfd_ = ::eventfd(0, EFD_CLOEXEC | EFD_NONBLOCK);
  timerfd_ = ::timerfd_create(CLOCK_MONOTONIC, TFD_CLOEXEC | TFD_NONBLOCK);
  if (epfd_ < 0 || eventfd_ < 0 || timerfd_ < 0)
    throw std::runtime_error("event loop: cannot create fds");
  for (int fd : {eventfd_, timerfd_}) {
    epoll_event ev{};
    ev.events = EPOLLIN;
    ev.data.fd = fd;
    ::epoll_ctl(epfd_, EPOLL_CTL_ADD, fd, &ev);
  }
}

EventLoop::~EventLoop() {
  for (int fd : {sigfd_, timerfd_, eventfd_, epfd_}) {
    if (fd >= 0) ::close(fd);
  }
}

void EventLoop::Wake() {
  const uint64_t one = 1;
  ssize_t n = ::write(eventfd_, &one, sizeof one);
  (void)n;
}

void EventLoop::Post(std::function<void()> fn) {
  {
    std::lock_guard<std::mutex> l(mu_);
    posted_.push_back(std::move(fn));
  }
  Wake();
}

void EventLoop::Hold() {
  std::lock_guard<std::mutex> l(mu_);
  ++holds_;
}

void EventLoop::Release() {
  {
    std::lock_guard<std::mutex> l(mu_);
    if (holds_ > 0) --holds_;
  }
  Wake();
}

EventLoop::TimerId EventLoop::AddTimer(TimeNs at, std::function<void()> fn) {
  const TimerId id = next_id_++;
  timers_[id] = Timer{at, false, std::move(fn)};
  return id;
}

EventLoop::TimerId EventLoop::AddRealTimer(TimeNs real_at, std::function<void()> fn) {
  const TimerId id = next_id_++;
  timers_[id] = Timer{real_at, true, std::move(fn)};
  return id;
}

void EventLoop::CancelTimer(TimerId id) { timers_.erase(id); }

void EventLoop::HandleSignals(const std::vector<int>& signals, std::function<void(int)> fn) {
  sigset_t set;
  sigemptyset(&set);
  for (int s : signals) sigaddset(&set, s);
  ::pthread_sigmask(SIG_BLOCK, &set, nullptr);
  sigfd_ = ::signalfd(-1, &set, SFD_CLOEXEC | SFD_NONBLOCK);
  epoll_event ev{};
  ev.events = EPOLLIN;
  ev.data.fd = sigfd_;
  ::epoll_ctl(epfd_, EPOLL_CTL_ADD, sigfd_, &ev);
  on_signal_ = std::move(fn);
}

void EventLoop::Quit(int code) {
  quit_ = true;
  exit_code_ = code;
  Wake();
}

// Runs every timer that is due now; true if any ran.
bool EventLoop::FireDueTimers() {
  bool any = false;
  for (;;) {
    const TimeNs now_clock = clock_.Now();
    const TimeNs now_real = MonotonicNs();
    auto due = timers_.end();
    for (auto it = timers_.begin(); it != timers_.end(); ++it) {
      const bool is_due = it->second.real ? it->second.at <= now_real : it->second.at <= now_clock;
      if (is_due && (due == timers_.end() || it->second.at < due->second.at)) due = it;
    }
    if (due == timers_.end()) return any;
    auto fn = std::move(due->second.fn);
    timers_.erase(due);
    fn();
    any = true;
    if (quit_) return any;
  }
}

void EventLoop::ArmTimerFd() {
  TimeNs real_deadline = LLONG_MAX;
  const TimeNs now_real = MonotonicNs();
  for (const auto& [id, t] : timers_) {
    // A virtual clock only moves by jumping (Run), never while we sleep here:
    // arming its timers (RealNsUntil is 0) would spin the loop for as long as
    // a Hold() lasts. Release() and Post() wake the loop instead.
    if (!t.real && clock_.IsVirtual()) continue;
    const TimeNs r = t.real ? t.at : now_real + clock_.RealNsUntil(t.at);
    if (r < real_deadline) real_deadline = r;
  }
  itimerspec its{};
  if (real_deadline != LLONG_MAX) {
    if (real_deadline <= now_real) real_deadline = now_real + 1;
    its.it_value.tv_sec = real_deadline / kNsPerSec;
    its.it_value.tv_nsec = real_deadline % kNsPerSec;
  }
  ::timerfd_settime(timerfd_, TFD_TIMER_ABSTIME, &its, nullptr);
}

int EventLoop::Run() {
  quit_ = false;
  stopped_ = false;
  while (!quit_) {
    std::vector<std::function<void()>> tasks;
    int holds;
    {
      std::lock_guard<std::mutex> l(mu_);
      tasks.swap(posted_);
      holds = holds_;
    }
    for (auto& t : tasks) {
      t();
      if (quit_) break;
    }
    if (quit_) break;
    const bool fired = FireDueTimers();
    if (quit_) break;
    if (!tasks.empty() || fired) continue;

    if (clock_.IsVirtual() && holds == 0) {
      // Nothing can happen until the next clock timer: jump to it.
      TimeNs next = LLONG_MAX;
      for (const auto& [id, t] : timers_) {
        if (!t.real && t.at < next) next = t.at;
      }
      bool posted_meanwhile;
      {
        std::lock_guard<std::mutex> l(mu_);
        posted_meanwhile = !posted_.empty() || holds_ > 0;
      }
      if (next != LLONG_MAX && !posted_meanwhile) {
        clock_.AdvanceTo(next);
        continue;
      }
    }
    ArmTimerFd();
    epoll_event evs[4];
    const int n = ::epoll_wait(epfd_, evs, 4, -1);
    if (n < 0 && errno != EINTR) break;
    for (int i = 0; i < n; ++i) {
      const int fd = evs[i].data.fd;
      uint64_t v;
      if (fd == eventfd_ || fd == timerfd_) {
        ssize_t r = ::read(fd, &v, sizeof v);
        (void)r;
      } else if (fd == sigfd_) {
        signalfd_siginfo si{};
        while (::read(sigfd_, &si, sizeof si) == static_cast<ssize_t>(sizeof si)) {
          if (on_signal_) on_signal_(static_cast<int>(si.ssi_signo));
        }
      }
    }
  }
  stopped_ = true;
  return exit_code_;
}

}  // namespace aggscan
