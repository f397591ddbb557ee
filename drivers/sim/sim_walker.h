// The sim's operator walking the camera round a still rock (capture.mode =
// "moving_camera"): where the sim camera stands for each view.
//
// The rock lies on the disc, which does not turn. At each prompt (Step) the
// operator waits a reaction time and walks for a walk time (sim.hand_reaction_*
// and sim.hand_turn_* ranges), then holds the camera still at the next
// position until the following prompt. The positions of a side form a rough
// ring round the disc: the plan's angle as the azimuth (counted the way the
// platter would turn, so the views see the rock's sides in the same order),
// the elevation alternating over sim.walk_elevation_spread_deg about
// sim.camera_elevation_deg, and random offsets a person walking with a camera
// makes: azimuth +-6 deg, elevation +-3 deg, distance +-8 %, aim point
// +-12 mm across and +-8 mm up, roll +-4 deg. Later rounds of a plan that goes
// round more than once are offset by half a step. With sim.walk_shuffle the
// positions after the first are visited in a random order. Homing starts a
// new side: a new round, with new offsets. Deterministic for a seed.
// Thread-safe.
#pragma once

#include <cstdint>
#include <functional>
#include <memory>

#include "common/clock.h"
#include "config/config.h"
#include "drivers/sim/world.h"

namespace aggscan::sim {

class SimWalker {
 public:
  /// `clock` must outlive this object (CameraFunction does not need it).
  /// Until the first Home the camera stands at the first side's position 0.
  SimWalker(Clock& clock, const Config& config);
  ~SimWalker();
  SimWalker(const SimWalker&) = delete;
  SimWalker& operator=(const SimWalker&) = delete;

  /// A new side: a new round of positions; the camera is at its first at once.
  void Home();
  /// The prompt, now: walk to the side's next position.
  void Step();
  /// The camera's pose (world -> camera) at clock time t.
  Rigid CameraAt(TimeNs t) const;
  /// CameraAt as a function that stays valid after this object is destroyed.
  std::function<Rigid(TimeNs)> CameraFunction() const;
  /// The pose of plan position j of the current side (tests).
  Rigid PositionOfCurrentSide(int j) const;

 private:
  struct Model;
  Clock& clock_;
  std::shared_ptr<Model> m_;  // shared with CameraFunction
};

/// The camera pose looking from `centre` at `aim` (world frame, z up), turned
/// by `roll_deg` about its optical axis; OpenCV camera axes (x right, y down).
Rigid LookAt(const Vec3& centre, const Vec3& aim, double roll_deg);

}  // namespace aggscan::sim
