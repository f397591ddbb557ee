#include "daemon/state_machine.h"

namespace aggscan::capture {

const char* PhaseName(Phase p) {
  switch (p) {
    case Phase::kIdle:
      return "idle";
    case Phase::kArmed:
      return "armed";
    case Phase::kHoming:
      return "homing";
    case Phase::kRotating:
      return "rotating";
    case Phase::kSettling:
      return "settling";
    case Phase::kWaitingDue:
      return "waiting";
    case Phase::kCapturing:
      return "capturing";
    case Phase::kStoring:
      return "storing";
    case Phase::kFinishing:
      return "finishing";
    case Phase::kAwaitingPose:
      return "awaiting_pose";
    case Phase::kFaulted:
      return "faulted";
  }
  return "?";
}

namespace {
template <class... Ts>
struct Overloaded : Ts... {
  using Ts::operator()...;
};
template <class... Ts>
Overloaded(Ts...) -> Overloaded<Ts...>;

StepResult Reject(const State& s, const Event& e, std::string why = {}) {
  StepResult r;
  r.next = s;
  r.accepted = false;
  r.reason = why.empty() ? std::string(EventName(e)) + " is not allowed while " + PhaseName(s.phase)
                         : std::move(why);
  return r;
}

StepResult Go(State next, std::vector<Effect> effects) {
  StepResult r;
  r.next = std::move(next);
  r.effects = std::move(effects);
  return r;
}

// Side in progress for interruption bookkeeping: 0 when none is (armed, or
// awaiting the next pose: the finished sides are complete).
int SideInProgress(const State& s) {
  switch (s.phase) {
    case Phase::kHoming:
    case Phase::kRotating:
    case Phase::kSettling:
    case Phase::kWaitingDue:
    case Phase::kCapturing:
    case Phase::kStoring:
    case Phase::kFinishing:
      return s.side;
    default:
      return 0;
  }
}

State Faulted(const State& s, ErrorClass cls, const std::string& msg) {
  State n = s;
  n.phase = Phase::kFaulted;
  n.fault_class = cls;
  n.fault_message = msg;
  return n;
}

}  // namespace

const char* EventName(const Event& e) {
  static const char* const kNames[] = {
      "arm",          "button",      "home_done",   "move_done",     "settle_done",
      "view_due",     "frame_ready", "view_stored", "side_finished", "device_fault",
      "store_failed", "abort",       "reset"};
  return kNames[e.index()];
}

const char* EffectName(const Effect& e) {
  static const char* const kNames[] = {
      "create_sample", "home",           "move_to",          "start_settle",
      "begin_side",    "wait_until_due", "trigger_capture",  "store_view",
      "finish_side",   "stop_motion",    "mark_interrupted", "mark_aborted",
      "record_fault",  "clear_fault"};
  return kNames[e.index()];
}

StepResult Step(const State& s, const Event& e) {
  return std::visit(
      Overloaded{
          [&](const Arm& a) -> StepResult {
            if (s.phase != Phase::kIdle) {
              return Reject(s, e,
                            std::string("cannot arm a sample while ") + PhaseName(s.phase) +
                                (s.phase == Phase::kFaulted ? ": reset the fault first"
                                                            : ": abort it first"));
            }
            if (a.plan.sides < 1 || a.plan.views_per_side < 1 || a.first_side < 1 ||
                a.first_side > a.plan.sides) {
              return Reject(s, e, "invalid capture plan");
            }
            State n;
            n.phase = Phase::kArmed;
            n.sample_id = a.sample_id;
            n.plan = a.plan;
            n.side = a.first_side;
            n.view = 0;
            return Go(n, {CreateSample{a.sample_id}});
          },
          [&](const ButtonPressed&) -> StepResult {
            if (s.phase != Phase::kArmed && s.phase != Phase::kAwaitingPose) {
              return Reject(s, e, std::string("button ignored while ") + PhaseName(s.phase));
            }
            State n = s;
            n.phase = Phase::kHoming;
            n.view = 0;
            return Go(n, {Home{}});
          },
          [&](const HomeDone&) -> StepResult {
            if (s.phase != Phase::kHoming) return Reject(s, e);
            State n = s;
            n.phase = Phase::kSettling;  // view 0 is at the home position
            n.view = 0;
            return Go(n, {BeginSide{s.side}, StartSettle{}});
          },
          [&](const MoveDone&) -> StepResult {
            if (s.phase != Phase::kRotating) return Reject(s, e);
            State n = s;
            n.phase = Phase::kSettling;
            return Go(n, {StartSettle{}});
          },
          [&](const SettleDone&) -> StepResult {
            if (s.phase != Phase::kSettling) return Reject(s, e);
            State n = s;
            n.phase = Phase::kWaitingDue;
            return Go(n, {WaitUntilDue{s.side, s.view}});
          },
          [&](const ViewDue&) -> StepResult {
            if (s.phase != Phase::kWaitingDue) return Reject(s, e);
            State n = s;
            n.phase = Phase::kCapturing;
            return Go(n, {TriggerCapture{s.side, s.view, s.view * s.plan.step_deg}});
          },
          [&](const FrameReady&) -> StepResult {
            if (s.phase != Phase::kCapturing) return Reject(s, e);
            State n = s;
            n.phase = Phase::kStoring;
            return Go(n, {StoreView{s.side, s.view}});
          },
          [&](const ViewStored&) -> StepResult {
            if (s.phase != Phase::kStoring) return Reject(s, e);
            State n = s;
            if (s.view + 1 < s.plan.views_per_side) {
              n.view = s.view + 1;
              n.phase = Phase::kRotating;
              return Go(n, {MoveTo{n.view * s.plan.step_deg, n.side, n.view}});
            }
            n.phase = Phase::kFinishing;
            return Go(n, {FinishSide{s.side, s.side >= s.plan.sides}});
          },
          [&](const SideFinished&) -> StepResult {
            if (s.phase != Phase::kFinishing) return Reject(s, e);
            if (s.side < s.plan.sides) {
              State n = s;
              n.phase = Phase::kAwaitingPose;
              n.side = s.side + 1;
              n.view = 0;
              return Go(n, {});
            }
            return Go(State{}, {});
          },
          [&](const DeviceFault& f) -> StepResult {
            if (!s.Active())
              return Reject(
                  s, e, std::string("device fault while ") + PhaseName(s.phase) + ": " + f.message);
            return Go(
                Faulted(s, f.cls, f.message),
                {StopMotion{}, MarkInterrupted{SideInProgress(s)}, RecordFault{f.cls, f.message}});
          },
          [&](const StoreFailed& f) -> StepResult {
            if (!s.Active()) return Reject(s, e);
            return Go(
                Faulted(s, f.cls, f.message),
                {StopMotion{}, MarkInterrupted{SideInProgress(s)}, RecordFault{f.cls, f.message}});
          },
          [&](const Abort&) -> StepResult {
            if (s.phase == Phase::kIdle)
              return Reject(s, e, "nothing to abort: no sample is armed");
            if (s.phase == Phase::kFaulted) return Go(State{}, {ClearFault{}});
            return Go(State{}, {StopMotion{}, MarkAborted{SideInProgress(s)}});
          },
          [&](const Reset&) -> StepResult {
            if (s.phase == Phase::kIdle) return Go(s, {});
            if (s.phase != Phase::kFaulted) {
              return Reject(s, e,
                            std::string("reset clears a fault; the rig is ") + PhaseName(s.phase) +
                                ": use abort to stop the capture");
            }
            return Go(State{}, {ClearFault{}});
          },
      },
      e);
}

}  // namespace aggscan::capture
