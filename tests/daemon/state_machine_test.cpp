// Table-driven test of the capture state machine: every (phase, event) pair
// is either listed below with its next phase and effects, or must be rejected
// without changing anything.
#include "daemon/state_machine.h"

#include <gtest/gtest.h>

#include <map>
#include <string>
#include <tuple>

namespace aggscan::capture {
namespace {

constexpr Phase kAllPhases[] = {Phase::kIdle,         Phase::kArmed,    Phase::kHoming,
                                Phase::kRotating,     Phase::kSettling, Phase::kWaitingDue,
                                Phase::kCapturing,    Phase::kStoring,  Phase::kFinishing,
                                Phase::kAwaitingPose, Phase::kFaulted};

std::vector<Event> AllEvents() {
  return {Arm{"rock-1", Plan{2, 3, 30.0}, 1},
          ButtonPressed{},
          HomeDone{},
          MoveDone{},
          SettleDone{},
          ViewDue{},
          FrameReady{},
          ViewStored{},
          SideFinished{},
          DeviceFault{ErrorClass::kStalled, "stalled"},
          StoreFailed{ErrorClass::kDiskFull, "disk full"},
          Abort{},
          Reset{}};
}

// A mid-sample state in the given phase: side 1, view 1 of 3, 2 sides.
State InPhase(Phase p) {
  State s;
  s.phase = p;
  if (p != Phase::kIdle) {
    s.sample_id = "rock-1";
    s.plan = Plan{2, 3, 30.0};
    s.side = 1;
    s.view = 1;
  }
  if (p == Phase::kFinishing) s.view = 2;  // the last view of side 1 is stored
  if (p == Phase::kAwaitingPose) {
    s.side = 2;
    s.view = 0;
  }
  if (p == Phase::kFaulted) {
    s.fault_class = ErrorClass::kTimeout;
    s.fault_message = "timeout";
  }
  return s;
}

std::string Effects(const StepResult& r) {
  std::string out;
  for (const auto& e : r.effects) {
    if (!out.empty()) out += ",";
    out += EffectName(e);
  }
  return out;
}

struct Row {
  Phase from;
  std::string event;
  Phase to;
  std::string effects;
};

// Every accepted transition from the InPhase() states.
const Row kTable[] = {
    {Phase::kIdle, "arm", Phase::kArmed, "create_sample"},
    {Phase::kIdle, "reset", Phase::kIdle, ""},
    {Phase::kArmed, "button", Phase::kHoming, "home"},
    {Phase::kArmed, "device_fault", Phase::kFaulted, "stop_motion,mark_interrupted,record_fault"},
    {Phase::kArmed, "store_failed", Phase::kFaulted, "stop_motion,mark_interrupted,record_fault"},
    {Phase::kArmed, "abort", Phase::kIdle, "stop_motion,mark_aborted"},
    {Phase::kHoming, "home_done", Phase::kSettling, "begin_side,start_settle"},
    {Phase::kRotating, "move_done", Phase::kSettling, "start_settle"},
    {Phase::kSettling, "settle_done", Phase::kWaitingDue, "wait_until_due"},
    {Phase::kWaitingDue, "view_due", Phase::kCapturing, "trigger_capture"},
    {Phase::kCapturing, "frame_ready", Phase::kStoring, "store_view"},
    {Phase::kStoring, "view_stored", Phase::kRotating, "move_to"},
    {Phase::kFinishing, "side_finished", Phase::kAwaitingPose, ""},
    {Phase::kAwaitingPose, "button", Phase::kHoming, "home"},
    {Phase::kFaulted, "abort", Phase::kIdle, "clear_fault"},
    {Phase::kFaulted, "reset", Phase::kIdle, "clear_fault"},
};

TEST(StateMachine, EveryPhaseEventPair) {
  // Faults and aborts are accepted in every active phase.
  std::map<std::pair<Phase, std::string>, Row> table;
  for (const Row& r : kTable) table[{r.from, r.event}] = r;
  for (Phase p : {Phase::kHoming, Phase::kRotating, Phase::kSettling, Phase::kWaitingDue,
                  Phase::kCapturing, Phase::kStoring, Phase::kFinishing, Phase::kAwaitingPose}) {
    table[{p, "device_fault"}] = {p, "device_fault", Phase::kFaulted,
                                  "stop_motion,mark_interrupted,record_fault"};
    table[{p, "store_failed"}] = {p, "store_failed", Phase::kFaulted,
                                  "stop_motion,mark_interrupted,record_fault"};
    table[{p, "abort"}] = {p, "abort", Phase::kIdle, "stop_motion,mark_aborted"};
  }
  int accepted = 0, rejected = 0;
  for (Phase p : kAllPhases) {
    for (const Event& e : AllEvents()) {
      const State s = InPhase(p);
      const StepResult r = Step(s, e);
      const auto it = table.find({p, EventName(e)});
      SCOPED_TRACE(std::string(PhaseName(p)) + " x " + EventName(e));
      if (it == table.end()) {
        EXPECT_FALSE(r.accepted);
        EXPECT_FALSE(r.reason.empty());
        EXPECT_EQ(r.next.phase, s.phase);
        EXPECT_TRUE(r.effects.empty());
        ++rejected;
      } else {
        EXPECT_TRUE(r.accepted) << r.reason;
        EXPECT_EQ(PhaseName(r.next.phase), std::string(PhaseName(it->second.to)));
        EXPECT_EQ(Effects(r), it->second.effects);
        ++accepted;
      }
    }
  }
  EXPECT_EQ(accepted + rejected, 11 * 13);
  EXPECT_EQ(accepted, static_cast<int>(table.size()));
}

TEST(StateMachine, LastViewOfSideFinishesThenAwaitsNextPose) {
  State s = InPhase(Phase::kStoring);
  s.view = 2;  // last of 3
  StepResult r = Step(s, ViewStored{});
  ASSERT_TRUE(r.accepted);
  EXPECT_EQ(r.next.phase, Phase::kFinishing);
  EXPECT_EQ(Effects(r), "finish_side");
  EXPECT_EQ(std::get<FinishSide>(r.effects[0]).side, 1);
  EXPECT_FALSE(std::get<FinishSide>(r.effects[0]).last_side);
  // Only the store's answer moves on: the next pose is asked for once side 1 is stored.
  StepResult f = Step(r.next, SideFinished{});
  ASSERT_TRUE(f.accepted);
  EXPECT_EQ(f.next.phase, Phase::kAwaitingPose);
  EXPECT_EQ(f.next.side, 2);
  EXPECT_EQ(f.next.view, 0);
  EXPECT_TRUE(f.effects.empty());
}

TEST(StateMachine, LastViewOfLastSideFinishesSampleOnlyWhenStored) {
  State s = InPhase(Phase::kStoring);
  s.side = 2;
  s.view = 2;
  StepResult r = Step(s, ViewStored{});
  ASSERT_TRUE(r.accepted);
  EXPECT_EQ(r.next.phase, Phase::kFinishing);
  EXPECT_EQ(Effects(r), "finish_side");
  EXPECT_EQ(std::get<FinishSide>(r.effects[0]).side, 2);
  EXPECT_TRUE(std::get<FinishSide>(r.effects[0]).last_side);
  StepResult done = Step(r.next, SideFinished{});
  ASSERT_TRUE(done.accepted);
  EXPECT_EQ(done.next.phase, Phase::kIdle);
  EXPECT_TRUE(done.effects.empty());
}

TEST(StateMachine, StoreFailureWhileFinishingIsAFaultOfThatSide) {
  // Disk full on the last manifest: the capture faults (named), the side is
  // marked interrupted for re-arming, and the sample is never left "captured".
  State s = InPhase(Phase::kStoring);
  s.side = 2;
  s.view = 2;
  StepResult r = Step(Step(s, ViewStored{}).next,
                      StoreFailed{ErrorClass::kDiskFull, "cannot finish side 2: disk full"});
  ASSERT_TRUE(r.accepted);
  EXPECT_EQ(r.next.phase, Phase::kFaulted);
  EXPECT_EQ(r.next.fault_class, ErrorClass::kDiskFull);
  EXPECT_EQ(r.next.fault_message, "cannot finish side 2: disk full");
  EXPECT_EQ(r.next.sample_id, "rock-1");
  EXPECT_EQ(Effects(r), "stop_motion,mark_interrupted,record_fault");
  EXPECT_EQ(std::get<MarkInterrupted>(r.effects[1]).side, 2);
  // A late SideFinished after the fault changes nothing.
  EXPECT_FALSE(Step(r.next, SideFinished{}).accepted);
}

TEST(StateMachine, MoveTargetsAreViewTimesStep) {
  State s = InPhase(Phase::kStoring);
  s.view = 0;
  StepResult r = Step(s, ViewStored{});
  ASSERT_EQ(r.next.view, 1);
  EXPECT_DOUBLE_EQ(std::get<MoveTo>(r.effects[0]).angle_deg, 30.0);
  State w = InPhase(Phase::kWaitingDue);
  w.view = 2;
  StepResult c = Step(w, ViewDue{});
  EXPECT_DOUBLE_EQ(std::get<TriggerCapture>(c.effects[0]).commanded_deg, 60.0);
  EXPECT_EQ(std::get<TriggerCapture>(c.effects[0]).view, 2);
}

TEST(StateMachine, FaultRecordsReasonAndInterruptedSide) {
  StepResult r = Step(InPhase(Phase::kCapturing),
                      DeviceFault{ErrorClass::kStalled, "turntable stalled at 47 deg"});
  ASSERT_TRUE(r.accepted);
  EXPECT_EQ(r.next.fault_class, ErrorClass::kStalled);
  EXPECT_EQ(r.next.fault_message, "turntable stalled at 47 deg");
  EXPECT_EQ(std::get<MarkInterrupted>(r.effects[1]).side, 1);
  // Awaiting the next pose: no side is in progress, the finished ones stay complete.
  StepResult a =
      Step(InPhase(Phase::kAwaitingPose), DeviceFault{ErrorClass::kDisconnected, "gone"});
  EXPECT_EQ(std::get<MarkInterrupted>(a.effects[1]).side, 0);
}

TEST(StateMachine, ArmRejectsBadPlanAndBusyRig) {
  EXPECT_FALSE(Step(State{}, Arm{"x", Plan{0, 30, 30}, 1}).accepted);
  EXPECT_FALSE(Step(State{}, Arm{"x", Plan{2, 30, 30}, 3}).accepted);
  StepResult resume = Step(State{}, Arm{"x", Plan{2, 30, 30}, 2});
  ASSERT_TRUE(resume.accepted);
  EXPECT_EQ(resume.next.side, 2);
  StepResult busy = Step(InPhase(Phase::kCapturing), Arm{"y", Plan{}, 1});
  EXPECT_FALSE(busy.accepted);
  EXPECT_NE(busy.reason.find("abort it first"), std::string::npos);
  EXPECT_NE(Step(InPhase(Phase::kFaulted), Arm{"y", Plan{}, 1}).reason.find("reset"),
            std::string::npos);
}

TEST(StateMachine, FullSampleWalk) {
  // Drive a whole 2-side x 3-view sample with the events the service would post.
  State s;
  auto step = [&](const Event& e) {
    StepResult r = Step(s, e);
    EXPECT_TRUE(r.accepted) << EventName(e) << " in " << PhaseName(s.phase) << ": " << r.reason;
    s = r.next;
    return r;
  };
  step(Arm{"rock", Plan{2, 3, 120.0}, 1});
  int captures = 0, sides_finished = 0, last_sides = 0;
  for (int side = 1; side <= 2; ++side) {
    step(ButtonPressed{});
    step(HomeDone{});
    for (int v = 0; v < 3; ++v) {
      if (v > 0) step(MoveDone{});
      step(SettleDone{});
      StepResult c = step(ViewDue{});
      captures += std::holds_alternative<TriggerCapture>(c.effects[0]);
      step(FrameReady{});
      StepResult st = step(ViewStored{});
      for (const auto& eff : st.effects) {
        if (!std::holds_alternative<FinishSide>(eff)) continue;
        ++sides_finished;
        last_sides += std::get<FinishSide>(eff).last_side;
        step(SideFinished{});
      }
    }
  }
  EXPECT_EQ(captures, 6);
  EXPECT_EQ(sides_finished, 2);
  EXPECT_EQ(last_sides, 1);
  EXPECT_EQ(s.phase, Phase::kIdle);
}

}  // namespace
}  // namespace aggscan::capture
