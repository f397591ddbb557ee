#include "drivers/sim/sim_walker.h"

#include <algorithm>
#include <cmath>
#include <mutex>
#include <numbers>
#include <numeric>
#include <random>
#include <vector>

#include "drivers/sim/scramble.h"

namespace aggscan::sim {
namespace {

constexpr double kDeg = std::numbers::pi / 180.0;

struct Switch {
  TimeNs at = 0;
  Rigid pose;
};

}  // namespace

Rigid LookAt(const Vec3& centre, const Vec3& aim, double roll_deg) {
  const Vec3 zc = Normalized(aim - centre);
  Vec3 xc = Normalized(Cross(zc, Vec3{0, 0, 1}));
  if (Norm(xc) < 0.5) xc = {1, 0, 0};  // looking straight down
  Vec3 yc = Cross(zc, xc);
  const double c = std::cos(roll_deg * kDeg), s = std::sin(roll_deg * kDeg);
  const Vec3 xr = xc * c + yc * s, yr = yc * c - xc * s;
  Rigid r;
  r.R = {xr.x, xr.y, xr.z, yr.x, yr.y, yr.z, zc.x, zc.y, zc.z};
  r.t = -r.Rotate(centre);
  return r;
}

struct SimWalker::Model {
  mutable std::mutex mu;
  std::mt19937_64 rng;
  SimConfig sim;
  CaptureConfig capture;
  std::vector<Rigid> positions;  // the current side's plan positions
  std::vector<int> order;        // the order they are visited in
  int next = 0;                  // the next entry of order
  std::vector<Switch> switches;  // in time order

  double Uniform(double lo, double hi) {
    return hi > lo ? std::uniform_real_distribution<double>(lo, hi)(rng) : lo;
  }

  void NewSide() {
    const int n = std::max(1, capture.views_per_side);
    positions.clear();
    for (int j = 0; j < n; ++j) {
      const double plan = j * capture.step_deg;
      const int round = static_cast<int>(std::floor(plan / 360.0 + 1e-9));
      // The platter turning by +a shows the rock as a camera walked by -a.
      const double az = (-plan - 0.5 * capture.step_deg * round + Uniform(-6, 6)) * kDeg;
      const double el =
          (sim.camera_elevation_deg +
           ((j + round) % 2 == 0 ? -0.5 : 0.5) * sim.walk_elevation_spread_deg + Uniform(-3, 3)) *
          kDeg;
      const double dist = sim.camera_distance_mm * (1.0 + Uniform(-0.08, 0.08));
      const Vec3 aim{Uniform(-12, 12), Uniform(-12, 12), kAimHeightMm + Uniform(-8, 8)};
      // Azimuth 0 is the tripod's side of the rig (-y), as in SimWorld.
      const Vec3 dir{std::sin(az) * std::cos(el), -std::cos(az) * std::cos(el), std::sin(el)};
      positions.push_back(LookAt(aim + dir * dist, aim, Uniform(-4, 4)));
    }
    order.resize(n);
    std::iota(order.begin(), order.end(), 0);
    if (sim.walk_shuffle) std::shuffle(order.begin() + 1, order.end(), rng);
    next = 0;
  }

  Rigid At(TimeNs t) const {
    std::lock_guard<std::mutex> l(mu);
    Rigid r = switches.front().pose;
    for (const Switch& s : switches) {
      if (s.at > t) break;
      r = s.pose;
    }
    return r;
  }
};

SimWalker::SimWalker(Clock& clock, const Config& config)
    : clock_(clock), m_(std::make_shared<Model>()) {
  m_->rng.seed(Scramble(config.sim.seed ^ 0x57414C4BULL));
  m_->sim = config.sim;
  m_->capture = config.capture;
  m_->NewSide();
  m_->switches.push_back({0, m_->positions[0]});
}

SimWalker::~SimWalker() = default;

void SimWalker::Home() {
  const TimeNs now = clock_.Now();
  std::lock_guard<std::mutex> l(m_->mu);
  m_->NewSide();
  m_->switches.push_back({now, m_->positions[static_cast<size_t>(m_->order[0])]});
  m_->next = 1;
}

void SimWalker::Step() {
  const TimeNs now = clock_.Now();
  std::lock_guard<std::mutex> l(m_->mu);
  const SimConfig& c = m_->sim;
  const auto reaction = static_cast<TimeNs>(m_->Uniform(static_cast<double>(c.hand_reaction_min),
                                                        static_cast<double>(c.hand_reaction_max)));
  const auto walk = static_cast<TimeNs>(
      m_->Uniform(static_cast<double>(c.hand_turn_min), static_cast<double>(c.hand_turn_max)));
  const int k = m_->order[static_cast<size_t>(m_->next % static_cast<int>(m_->order.size()))];
  ++m_->next;
  const TimeNs at = std::max(now + reaction + walk, m_->switches.back().at);
  m_->switches.push_back({at, m_->positions[static_cast<size_t>(k)]});
}

Rigid SimWalker::CameraAt(TimeNs t) const { return m_->At(t); }

std::function<Rigid(TimeNs)> SimWalker::CameraFunction() const {
  std::shared_ptr<Model> m = m_;
  return [m](TimeNs t) { return m->At(t); };
}

Rigid SimWalker::PositionOfCurrentSide(int j) const {
  std::lock_guard<std::mutex> l(m_->mu);
  return m_->positions.at(static_cast<size_t>(j));
}

}  // namespace aggscan::sim
