// The capture state machine: pure. Step(state, event) -> (next state, effects).
// No clock, thread, device or file inside: the capture service executes the
// effects and turns device answers, timers and requests into events.
//
//                 Arm                Button                 HomeDone
//   ┌──────┐ ─────────▶ ┌───────┐ ─────────▶ ┌────────┐ ─────────────────┐
//   │ Idle │            │ Armed │            │ Homing │                  │
//   └──────┘ ◀──┐       └───────┘            └────────┘                  ▼
//      ▲  ▲     │ Abort (from any state but Idle)                  ┌──────────┐
//      │  │     └────────────────────────────────────────────      │ Settling │◀─┐
//      │  │                                                        └──────────┘  │
//      │  │ Reset            SettleDone ┌────────────┐ ViewDue ┌───────────┐     │ MoveDone
//      │  │               ┌───────────▶ │ WaitingDue │ ──────▶ │ Capturing │     │
//      │ ┌┴────────┐      │             └────────────┘         └───────────┘     │
//      │ │ Faulted │      │                               FrameReady │           │
//      │ └─────────┘      │                                          ▼           │
//      │  ▲ DeviceFault / │            ViewStored, more views  ┌─────────┐  ┌──────────┐
//      │  │ StoreFailed   └── (Settling)                       │ Storing │─▶│ Rotating │
//      │  │ (any active state,                                 └─────────┘  └──────────┘
//      │  │  Finishing included)                   ViewStored, last view │
//      │  │                                                        ┌───────────┐
//      │  │                                                        │ Finishing │
//      │  │                                                        └───────────┘
//      │  │                                        SideFinished ┌───────┴──────┐
//      │  │                                         more sides │     last side │
//      │  │                                                    ▼               │
//      │  │  Button (operator flipped the rock) ┌──────────────┐               │
//      │  └──────────────── Homing ◀─────────── │ AwaitingPose │               │
//      │                                        └──────────────┘               │
//      └───────────────────────────────────────────────────────────────────────┘
//                      sample done (its record and sample job are stored)
//
// Finishing waits for the store's answer to FinishSide (manifest, record,
// side job and, on the last side, the sample's "captured" state and its
// sample job): SideFinished leaves it, a StoreFailed faults the capture, so a
// manifest that could not be written is a named fault, never a sample marked
// captured without it.
//
// Per view i of a side: Rotating (to i*step; view 0 needs no move after
// homing) → Settling → WaitingDue (view i is due at t0 + i*interval, t0 set
// when the side begins: the schedule never drifts, an overrun is recorded and
// the shot taken at once) → Capturing → Storing. Illegal events are rejected
// (the caller logs them with the current state) and change nothing.
#pragma once

#include <string>
#include <variant>
#include <vector>

#include "common/error.h"

namespace aggscan::capture {

enum class Phase {
  kIdle,
  kArmed,
  kHoming,
  kRotating,
  kSettling,
  kWaitingDue,
  kCapturing,
  kStoring,
  kFinishing,
  kAwaitingPose,
  kFaulted,
};
const char* PhaseName(Phase p);

struct Plan {
  int sides = 2;
  int views_per_side = 30;
  double step_deg = 30.0;
};

struct State {
  Phase phase = Phase::kIdle;
  std::string sample_id;
  Plan plan;
  int side = 0;  // 1-based while a sample is active
  int view = 0;  // 0-based within the side
  // Set in kFaulted: what went wrong, in operator terms.
  ErrorClass fault_class = ErrorClass::kInternal;
  std::string fault_message;
  /// True while a sample is armed or being captured.
  bool Active() const { return phase != Phase::kIdle && phase != Phase::kFaulted; }
};

// ---- Events -------------------------------------------------------------
struct Arm {
  std::string sample_id;
  Plan plan;
  int first_side = 1;
};
struct ButtonPressed {};
struct HomeDone {};
struct MoveDone {};
struct SettleDone {};
struct ViewDue {};
struct FrameReady {};
struct ViewStored {};
struct SideFinished {};  // FinishSide's files and jobs are stored
struct DeviceFault {
  ErrorClass cls;
  std::string message;
};
struct StoreFailed {
  ErrorClass cls;
  std::string message;
};
struct Abort {};
struct Reset {};
using Event = std::variant<Arm, ButtonPressed, HomeDone, MoveDone, SettleDone, ViewDue, FrameReady,
                           ViewStored, SideFinished, DeviceFault, StoreFailed, Abort, Reset>;
const char* EventName(const Event& e);

// ---- Effects ------------------------------------------------------------
struct CreateSample {
  std::string sample_id;
};
struct Home {};
struct MoveTo {
  double angle_deg;
  int side = 0, view = 0;  // the view it is for (a hand-turned table's prompt names it)
};
struct StartSettle {};
struct BeginSide {
  int side;
};  // side dir ready; t0 = end of the first settle
struct WaitUntilDue {
  int side;
  int view;
};
struct TriggerCapture {
  int side;
  int view;
  double commanded_deg;
};
struct StoreView {
  int side;
  int view;
};
// Manifest, record, side job; last_side: also the sample "captured" and its
// sample job. Answered by SideFinished or StoreFailed.
struct FinishSide {
  int side;
  bool last_side = false;
};
struct StopMotion {};
struct MarkInterrupted {
  int side;
};  // side (0 = none in progress) and sample interrupted
struct MarkAborted {
  int side;
};
struct RecordFault {
  ErrorClass cls;
  std::string message;
};
struct ClearFault {};
using Effect = std::variant<CreateSample, Home, MoveTo, StartSettle, BeginSide, WaitUntilDue,
                            TriggerCapture, StoreView, FinishSide, StopMotion, MarkInterrupted,
                            MarkAborted, RecordFault, ClearFault>;
const char* EffectName(const Effect& e);

struct StepResult {
  State next;
  std::vector<Effect> effects;
  bool accepted = true;  // false: illegal in this state, nothing changed
  std::string reason;    // why it was rejected, for the log / API answer
};

/// The transition function. Pure and total: every (state, event) pair has an answer.
StepResult Step(const State& s, const Event& e);

}  // namespace aggscan::capture
