// Simulated turntable: lazily evaluated motion segments on the clock's time
// line. See sim_turntable.h for the model.
#include "drivers/sim/sim_turntable.h"

#include <algorithm>
#include <cmath>
#include <deque>
#include <mutex>
#include <numbers>
#include <optional>
#include <random>

namespace aggscan::sim {
namespace {

constexpr size_t kHistory = 16;  // segments kept for PhysicalAngleAt(past t)

double Seconds(TimeNs ns) { return static_cast<double>(ns) * 1e-9; }

// One commanded motion, from t0 on. A hold is a motion that has ended.
struct Segment {
  enum class Kind { kHold, kHome, kMove };
  Kind kind = Kind::kHold;
  TimeNs t0 = 0;
  double p0 = 0.0;     // steady angle at t0
  double p1 = 0.0;     // angle at the end (target + error for moves)
  int dir = 0;         // +1 / -1 / 0 direction of travel
  double acc = 1.0;    // deg/s^2
  double vpk = 0.0;    // peak speed reached, deg/s
  double ta = 0.0;     // acceleration (= deceleration) time, s
  double tc = 0.0;     // constant-speed time, s
  double total = 0.0;  // duration, s
  bool stalls = false;
  double stall_pos = 0.0;
  double stall_s = 0.0;   // time of the stall from t0, s
  bool completes = true;  // in_position once ended (false after Stop)

  // Distance travelled after tau seconds on the trapezoid.
  double Travel(double tau) const {
    const double dist = std::fabs(p1 - p0);
    if (tau <= 0) return 0;
    if (tau >= total) return dist;
    if (tau < ta) return 0.5 * acc * tau * tau;
    if (tau < ta + tc) return 0.5 * acc * ta * ta + vpk * (tau - ta);
    const double rem = total - tau;
    return dist - 0.5 * acc * rem * rem;
  }

  bool Ended(TimeNs t) const {
    const double tau = Seconds(t - t0);
    switch (kind) {
      case Kind::kHold:
        return true;
      case Kind::kHome:
        return tau >= total;
      case Kind::kMove:
        return !stalls && tau >= total;
    }
    return true;
  }

  double Steady(TimeNs t) const {
    const double tau = Seconds(t - t0);
    switch (kind) {
      case Kind::kHold:
        return p0;
      case Kind::kHome:
        return tau >= total ? p1 : p0 + (p1 - p0) * std::max(0.0, tau) / total;
      case Kind::kMove:
        if (stalls && tau >= stall_s) return stall_pos;
        return p0 + dir * Travel(tau);
    }
    return p0;
  }
};

uint64_t SplitMix(uint64_t x) {
  x += 0x9E3779B97F4A7C15ULL;
  x = (x ^ (x >> 30)) * 0xBF58476D1CE4E5B9ULL;
  x = (x ^ (x >> 27)) * 0x94D049BB133111EBULL;
  return x ^ (x >> 31);
}

}  // namespace

struct SimTurntable::Model {
  Model(Clock& c, const TurntableConfig& cfg, uint64_t seed)
      : clock(c), config(cfg), rng(SplitMix(seed)) {
    segments.push_back(Segment{});
  }

  Clock& clock;
  const TurntableConfig config;
  mutable std::mutex mu;
  std::mt19937_64 rng;
  std::deque<Segment> segments;  // newest last
  TimeNs opened_at = 0;
  bool ever_opened = false;
  bool homed = false;
  bool unresponsive = false;  // timeout fault active
  int64_t moves = 0;          // StartMoveTo calls, for timeout_every_n_moves

  // Standard normal from the engine's raw bits (std::normal_distribution is
  // not the same across standard libraries; this is).
  double Gauss() {
    const double u1 = (static_cast<double>(rng() >> 11) + 1.0) * 0x1.0p-53;  // (0, 1]
    const double u2 = static_cast<double>(rng() >> 11) * 0x1.0p-53;
    return std::sqrt(-2.0 * std::log(u1)) * std::cos(2.0 * std::numbers::pi * u2);
  }

  const Segment& Current() const { return segments.back(); }
  void Push(Segment s) {
    segments.push_back(s);
    while (segments.size() > kHistory) segments.pop_front();
  }
  const Segment& At(TimeNs t) const {
    for (auto it = segments.rbegin(); it != segments.rend(); ++it)
      if (it->t0 <= t) return *it;
    return segments.front();
  }
  bool HomedAt(TimeNs t) {
    if (!homed && Current().kind == Segment::Kind::kHome && Current().Ended(t)) homed = true;
    return homed;
  }

  double Physical(TimeNs t) const {
    const Segment& s = At(t);
    double p = s.Steady(t);
    if (s.kind != Segment::Kind::kMove || s.stalls || s.dir == 0) return p;
    // The platter is coupled elastically to the motor: it leads by up to the
    // settle amplitude while decelerating, then rings down after the stop.
    const double tau = Seconds(t - s.t0);
    const double amp = config.settle_amplitude_deg;
    if (tau >= s.total) {
      const double dt = tau - s.total;
      const double tc = std::max(1e-9, Seconds(config.settle_time_constant));
      p += s.dir * amp * std::exp(-dt / tc) *
           std::cos(2.0 * std::numbers::pi * config.settle_frequency_hz * dt);
    } else if (s.ta > 0 && tau > s.total - s.ta) {
      p += s.dir * amp * (tau - (s.total - s.ta)) / s.ta;
    }
    return p;
  }

  std::optional<Error> Fault(TimeNs now) const {
    if (config.faults.disconnect_after && now >= opened_at + *config.faults.disconnect_after)
      return MakeError(ErrorClass::kDisconnected,
                       "sim turntable disconnected: check the cable / USB connection",
                       "simulated fault: disconnect_after");
    if (unresponsive)
      return MakeError(ErrorClass::kTimeout,
                       "sim turntable: no answer to status request (communication timeout)",
                       "simulated fault: timeout_every_n_moves");
    return std::nullopt;
  }
};

SimTurntable::SimTurntable(Clock& clock, const TurntableConfig& config, uint64_t seed)
    : m_(std::make_shared<Model>(clock, config, seed)) {}

SimTurntable::~SimTurntable() = default;

TurntableInfo SimTurntable::Info() const {
  return {"sim-turntable", "sim", "simulated turntable (trapezoidal motion)"};
}

double SimTurntable::PhysicalAngleAt(TimeNs t) const {
  std::lock_guard<std::mutex> l(m_->mu);
  return m_->Physical(t);
}

double SimTurntable::MeasuredAngleAt(TimeNs t) const {
  std::lock_guard<std::mutex> l(m_->mu);
  return m_->At(t).Steady(t);
}

double SimTurntable::MeasuredAngle() const { return MeasuredAngleAt(m_->clock.Now()); }

std::function<double(TimeNs)> SimTurntable::PhysicalAngleFunction() const {
  return [m = m_](TimeNs t) {
    std::lock_guard<std::mutex> l(m->mu);
    return m->Physical(t);
  };
}

Status SimTurntable::DoOpen() {
  std::lock_guard<std::mutex> l(m_->mu);
  const TimeNs now = m_->clock.Now();
  // Reopening after a disconnect is a fresh controller: homing is lost.
  if (m_->config.faults.disconnect_after &&
      now >= m_->opened_at + *m_->config.faults.disconnect_after && m_->ever_opened)
    m_->homed = false;
  m_->opened_at = now;
  m_->ever_opened = true;
  m_->unresponsive = false;
  return OkStatus();
}

Status SimTurntable::DoStartHome() {
  std::lock_guard<std::mutex> l(m_->mu);
  const TimeNs now = m_->clock.Now();
  if (m_->config.faults.disconnect_after &&
      now >= m_->opened_at + *m_->config.faults.disconnect_after)
    return *m_->Fault(now);
  m_->unresponsive = false;  // homing resets the controller
  Segment s;
  s.kind = Segment::Kind::kHome;
  s.t0 = now;
  s.p0 = m_->Current().Steady(now);
  s.p1 = 0.0;
  s.dir = 1;  // homing approaches in the positive direction
  s.total = std::max(1e-9, Seconds(m_->config.home_duration));
  m_->homed = false;
  m_->Push(s);
  return OkStatus();
}

Status SimTurntable::DoStartMoveTo(double angle_deg) {
  std::lock_guard<std::mutex> l(m_->mu);
  const TimeNs now = m_->clock.Now();
  if (auto f = m_->Fault(now)) return *f;
  if (!m_->HomedAt(now))
    return MakeError(ErrorClass::kInvalidState, "sim turntable is not homed: home first");
  const int n = m_->config.faults.timeout_every_n_moves;
  if (n > 0 && ++m_->moves % n == 0) {
    m_->unresponsive = true;  // the command is lost with the answer
    return *m_->Fault(now);
  }
  const double from = m_->Current().Steady(now);
  Segment s;
  s.kind = Segment::Kind::kMove;
  s.t0 = now;
  s.p0 = from;
  s.dir = angle_deg > from ? 1 : angle_deg < from ? -1 : 0;
  // Where the platter really ends: repeatability error, plus the backlash
  // when it approaches from above (homing approaches from below).
  const double err =
      m_->config.repeatability_deg * m_->Gauss() + (s.dir < 0 ? m_->config.backlash_deg : 0.0);
  s.p1 = angle_deg + err;
  s.dir = s.p1 > from ? 1 : s.p1 < from ? -1 : 0;
  const double dist = std::fabs(s.p1 - from);
  const double a = std::max(1e-9, m_->config.accel_deg_s2);
  const double v = std::max(1e-9, m_->config.max_speed_deg_s);
  s.acc = a;
  if (dist >= v * v / a) {
    s.ta = v / a;
    s.vpk = v;
    s.tc = (dist - v * v / a) / v;
  } else {
    s.ta = std::sqrt(dist / a);
    s.vpk = a * s.ta;
    s.tc = 0;
  }
  s.total = 2 * s.ta + s.tc;
  if (const auto& stall = m_->config.faults.stall_at_deg; stall && s.dir != 0) {
    const double ahead = (*stall - from) * s.dir;  // distance to the stall point along the move
    if (ahead > 0 && ahead <= dist) {
      s.stalls = true;
      s.stall_pos = *stall;
      double lo = 0, hi = s.total;  // invert the (monotonic) travel by bisection
      for (int i = 0; i < 60; ++i) {
        const double mid = 0.5 * (lo + hi);
        (s.Travel(mid) < ahead ? lo : hi) = mid;
      }
      s.stall_s = hi;
    }
  }
  m_->Push(s);
  return OkStatus();
}

Status SimTurntable::DoStop() {
  std::lock_guard<std::mutex> l(m_->mu);
  const TimeNs now = m_->clock.Now();
  if (auto f = m_->Fault(now)) return *f;
  if (m_->Current().Ended(now)) return OkStatus();  // nothing moving
  m_->HomedAt(now);
  Segment s;
  s.kind = Segment::Kind::kHold;
  s.t0 = now;
  s.p0 = s.p1 = m_->Current().Steady(now);
  s.completes = false;
  m_->Push(s);
  return OkStatus();
}

Result<TurntableStatus> SimTurntable::DoReadStatus() {
  std::lock_guard<std::mutex> l(m_->mu);
  const TimeNs now = m_->clock.Now();
  if (auto f = m_->Fault(now)) return *f;
  const Segment& s = m_->Current();
  TurntableStatus st;
  st.enabled = true;
  const bool ended = s.Ended(now);
  st.moving = !ended;
  st.in_position = ended && s.completes && !(s.kind == Segment::Kind::kHold && !m_->homed);
  st.homed = m_->HomedAt(now);
  st.angle_deg = s.Steady(now);
  return st;
}

void SimTurntable::DoClose() {}

}  // namespace aggscan::sim
