#include "drivers/sim/sim_hand.h"

#include <algorithm>
#include <cmath>
#include <mutex>
#include <numbers>
#include <random>
#include <vector>

#include "drivers/sim/scramble.h"

namespace aggscan::sim {
namespace {

struct Motion {
  TimeNs start = 0, end = 0;
  double from = 0, to = 0;
};

}  // namespace

struct SimHand::Model {
  mutable std::mutex mu;
  std::mt19937_64 rng;
  std::vector<Motion> motions;  // in time order
  double start_deg = 0;
  double planned_deg = 0;  // where the hand means the table to be after its last turn
  int turns = 0, late = 0;

  double AngleAt(TimeNs t) const {
    std::lock_guard<std::mutex> l(mu);
    double a = start_deg;
    for (const Motion& m : motions) {
      if (t <= m.start) break;
      if (t >= m.end) {
        a = m.to;
        continue;
      }
      const double u = static_cast<double>(t - m.start) /
                       static_cast<double>(std::max<TimeNs>(1, m.end - m.start));
      return m.from + (m.to - m.from) * 0.5 * (1.0 - std::cos(std::numbers::pi * u));
    }
    return a;
  }
};

SimHand::SimHand(Clock& clock, const Config& config)
    : clock_(clock),
      cfg_(config.sim),
      interval_(config.capture.interval),
      half_exposure_(static_cast<TimeNs>(config.camera.exposure.exposure_us * 500.0)),
      m_(std::make_shared<Model>()) {
  m_->rng.seed(Scramble(config.sim.seed ^ 0x48414E44ULL));
  std::uniform_real_distribution<double> start(-15.0, 15.0);
  m_->start_deg = start(m_->rng);
  m_->planned_deg = m_->start_deg;
}

SimHand::~SimHand() = default;

void SimHand::Turn(double from_deg, double to_deg) {
  const TimeNs now = clock_.Now();
  std::lock_guard<std::mutex> l(m_->mu);
  auto uniform = [&](double lo, double hi) {
    return hi > lo ? std::uniform_real_distribution<double>(lo, hi)(m_->rng) : lo;
  };
  const double err = uniform(-cfg_.hand_angle_error_deg, cfg_.hand_angle_error_deg);
  const auto reaction = static_cast<TimeNs>(uniform(static_cast<double>(cfg_.hand_reaction_min),
                                                    static_cast<double>(cfg_.hand_reaction_max)));
  const auto duration = static_cast<TimeNs>(
      uniform(static_cast<double>(cfg_.hand_turn_min), static_cast<double>(cfg_.hand_turn_max)));
  ++m_->turns;
  Motion m;
  m.start = now + reaction;
  if (cfg_.hand_late_every > 0 && m_->turns % cfg_.hand_late_every == 0) {
    // Late: the prompt comes right after a shot, so the next one is due about
    // an interval from now; the turn's middle falls on its mid-exposure.
    m.start = now + interval_ + half_exposure_ - duration / 2;
    ++m_->late;
  }
  // A turn never starts before the previous one ended.
  if (!m_->motions.empty()) m.start = std::max(m.start, m_->motions.back().end);
  m.end = m.start + duration;
  m.from = m_->planned_deg;
  m.to = m_->planned_deg + (to_deg - from_deg) + err;
  m_->planned_deg = m.to;
  m_->motions.push_back(m);
}

double SimHand::AngleAt(TimeNs t) const { return m_->AngleAt(t); }

std::function<double(TimeNs)> SimHand::AngleFunction() const {
  std::shared_ptr<Model> m = m_;
  return [m](TimeNs t) { return m->AngleAt(t); };
}

int SimHand::turns() const {
  std::lock_guard<std::mutex> l(m_->mu);
  return m_->turns;
}

int SimHand::late_turns() const {
  std::lock_guard<std::mutex> l(m_->mu);
  return m_->late;
}

}  // namespace aggscan::sim
