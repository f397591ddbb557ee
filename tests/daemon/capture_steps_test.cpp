// The steps of CaptureService::Execute, one effect at a time, on the sim rig:
// what each step stores, schedules or starts, and the events it queues for
// the state machine. CaptureServiceTestPeer runs a step on the service's loop
// and takes the events it queued, so the state machine never sees them.
#include <gtest/gtest.h>

#include <chrono>
#include <cstdlib>
#include <filesystem>
#include <future>
#include <memory>
#include <string>
#include <thread>
#include <vector>

#include "common/fsutil.h"
#include "config/config.h"
#include "daemon/capture_service.h"
#include "daemon/event_hub.h"
#include "daemon/event_loop.h"
#include "drivers/factory.h"
#include "store/layout.h"
#include "store/sample_store.h"
#include "tests/util/temp_dir.h"

namespace aggscan {

class CaptureServiceTestPeer {
 public:
  CaptureServiceTestPeer(CaptureService& s, EventLoop& loop) : s_(s), loop_(loop) {}

  /// Runs the step of `e` on the loop; returns the names of the events it
  /// queued (taken away: the state machine does not see them).
  std::vector<std::string> Run(const capture::Effect& e) {
    return OnLoop([&] {
      s_.Execute(e);
      std::vector<std::string> names;
      for (const capture::Event& ev : s_.pending_events_) names.push_back(capture::EventName(ev));
      s_.pending_events_.clear();
      return names;
    });
  }
  TimeNs side_t0() {
    return OnLoop([&] { return s_.side_t0_; });
  }
  TimeNs due() {
    return OnLoop([&] { return s_.pending_.due; });
  }
  TimeNs now() {
    return OnLoop([&] { return loop_.clock().Now(); });
  }
  bool motion_active() {
    return OnLoop([&] { return s_.motion_.active; });
  }
  double turntable_angle() {
    return OnLoop([&] {
      auto st = s_.dev_.turntable->ReadStatus();
      return st ? st->angle_deg : -1.0;
    });
  }
  LightPattern light_pattern() {
    return OnLoop([&] { return s_.LightPatternFor(); });
  }
  void set_events(EventHub* hub) {
    OnLoop([&] {
      s_.SetEventHub(hub);
      return 0;
    });
  }
  bool has_frame() {
    return OnLoop([&] { return static_cast<bool>(s_.pending_.frame); });
  }
  int faults(const std::string& cls) {
    return OnLoop([&] {
      auto it = s_.faults_by_class_.find(cls);
      return it == s_.faults_by_class_.end() ? 0 : it->second;
    });
  }

 private:
  template <typename F>
  auto OnLoop(F fn) -> decltype(fn()) {
    std::promise<decltype(fn())> done;
    loop_.Post([&] { done.set_value(fn()); });
    return done.get_future().get();
  }

  CaptureService& s_;
  EventLoop& loop_;
};

namespace {

using nlohmann::json;
using Names = std::vector<std::string>;

class CaptureSteps : public ::testing::Test {
 protected:
  virtual void Configure() {}
  void SetUp() override {
    config_.daemon.state_dir = dir_.path() + "/state";
    config_.camera.width = 320;
    config_.camera.height = 240;
    config_.capture.settle = 0;  // t0 is the end of the side's first settle: now
    config_.capture.interval = 2 * kNsPerSec;
    config_.material = {"granite", 2.65, "bulk-ssd"};
    Configure();  // a fixture's own settings over these
    store_ = std::make_unique<SampleStore>(config_.daemon.state_dir);
    ASSERT_TRUE(store_->Init().ok());
    loop_ = std::make_unique<EventLoop>(clock_);
    Result<RigDevices> rig = CreateRig(config_, clock_);
    ASSERT_TRUE(rig) << rig.error().ToString();
    service_ =
        std::make_unique<CaptureService>(*loop_, config_, "", std::move(*rig), *store_, nullptr);
    loop_->Post([this] { service_->Start(); });
    thread_ = std::thread([this] { loop_->Run(); });
    const auto until = std::chrono::steady_clock::now() + std::chrono::seconds(20);
    while (std::chrono::steady_clock::now() < until &&
           service_->GetHealth().value("status", "") != "ok") {
      std::this_thread::sleep_for(std::chrono::milliseconds(20));
    }
    ASSERT_EQ(service_->GetHealth().value("status", ""), "ok");
    Result<json> armed = service_->Arm("rock-1", CallContext::Within(std::chrono::seconds(5)));
    ASSERT_TRUE(armed) << armed.error().ToString();
    peer_ = std::make_unique<CaptureServiceTestPeer>(*service_, *loop_);
  }
  void TearDown() override {
    if (thread_.joinable()) {
      if (peer_) (void)peer_->Run(capture::StopMotion{});  // cancels the steps' timers
      loop_->Post([this] { service_->Shutdown(); });
      loop_->Quit(0);
      thread_.join();
    }
  }
  std::string SampleState(const std::string& id) {
    auto r = store_->LoadRecord(id);
    return r ? r->value("state", "") : "unreadable: " + r.error().ToString();
  }

  test::TempDir dir_;
  EventHub hub_;  // outlives the service that may publish to it
  Config config_;
  RealClock clock_;
  std::unique_ptr<SampleStore> store_;
  std::unique_ptr<EventLoop> loop_;
  std::unique_ptr<CaptureService> service_;
  std::unique_ptr<CaptureServiceTestPeer> peer_;
  std::thread thread_;
};

TEST_F(CaptureSteps, CreateSampleStoresTheRecordOrQueuesTheStoreFailure) {
  EXPECT_EQ(peer_->Run(capture::CreateSample{"rock-2"}), Names{});
  EXPECT_EQ(SampleState("rock-2"), "armed");
  EXPECT_TRUE(PathExists(store_->SampleDir("rock-2") + "/" + layout::kSampleRecord));
  // Again: the stored sample is resumed, nothing is overwritten.
  EXPECT_EQ(peer_->Run(capture::CreateSample{"rock-2"}), Names{});
  // A name that could leave the state directory is refused by the store.
  EXPECT_EQ(peer_->Run(capture::CreateSample{"../rock"}), Names{"store_failed"});
  EXPECT_FALSE(PathExists(dir_.path() + "/rock"));
}

TEST_F(CaptureSteps, BeginSideAndWaitUntilDueKeepTheSchedule) {
  const TimeNs before = peer_->now();
  EXPECT_EQ(peer_->Run(capture::BeginSide{1}), Names{});
  EXPECT_TRUE(PathExists(store_->SampleDir("rock-1") + "/" + layout::SideDirName(1)));
  const TimeNs t0 = peer_->side_t0();
  EXPECT_GE(t0, before);
  // View 0 is due at t0, already past: due at once.
  EXPECT_EQ(peer_->Run(capture::WaitUntilDue{1, 0}), Names{"view_due"});
  EXPECT_EQ(peer_->due(), t0);
  // View 3 at t0 + 3 intervals, not counted from now: the schedule never drifts.
  EXPECT_EQ(peer_->Run(capture::WaitUntilDue{1, 3}), Names{});
  EXPECT_EQ(peer_->due(), t0 + 3 * config_.capture.interval);
}

// Wait until the step's motion watch has seen the turntable arrive.
bool WaitMotionDone(CaptureServiceTestPeer& peer) {
  const auto until = std::chrono::steady_clock::now() + std::chrono::seconds(20);
  while (std::chrono::steady_clock::now() < until) {
    if (!peer.motion_active()) return true;
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  return false;
}

TEST_F(CaptureSteps, HomeThenMoveToStartTheTurntableAndWatchIt) {
  // Before homing the turntable refuses a move: the step queues the fault.
  EXPECT_EQ(peer_->Run(capture::MoveTo{90.0}), Names{"device_fault"});
  EXPECT_EQ(peer_->Run(capture::Home{}), Names{});
  EXPECT_TRUE(peer_->motion_active());
  ASSERT_TRUE(WaitMotionDone(*peer_));
  EXPECT_EQ(peer_->Run(capture::MoveTo{90.0}), Names{});
  EXPECT_TRUE(peer_->motion_active());
  const auto until = std::chrono::steady_clock::now() + std::chrono::seconds(20);
  double angle = -1;
  while (std::chrono::steady_clock::now() < until) {
    angle = peer_->turntable_angle();
    if (std::abs(angle - 90.0) < 0.5) break;
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
  }
  EXPECT_NEAR(angle, 90.0, 0.5);
  // StopMotion ends the watch and every timer of the capture.
  EXPECT_EQ(peer_->Run(capture::StopMotion{}), Names{});
  EXPECT_FALSE(peer_->motion_active());
}

TEST_F(CaptureSteps, MarkAbortedAndMarkInterruptedAreRecorded) {
  EXPECT_EQ(peer_->Run(capture::MarkInterrupted{0}), Names{});
  EXPECT_EQ(SampleState("rock-1"), "interrupted");
  EXPECT_EQ(peer_->Run(capture::MarkAborted{0}), Names{});
  EXPECT_EQ(SampleState("rock-1"), "aborted");
}

TEST_F(CaptureSteps, RecordFaultCountsItByClass) {
  EXPECT_EQ(peer_->faults("timeout"), 0);
  EXPECT_EQ(peer_->Run(capture::RecordFault{ErrorClass::kTimeout, "camera: no still"}), Names{});
  EXPECT_EQ(peer_->faults("timeout"), 1);
  EXPECT_EQ(peer_->Run(capture::ClearFault{}), Names{});
}

// A table turned by hand: the move is a prompt to the operator (the "turn"
// event, the light's fast blink until the hands-off moment), completes at
// once, and the view's sidecar carries no measured angle.
class ManualCaptureSteps : public CaptureSteps {
 protected:
  void Configure() override {
    config_.turntable.backend = "manual";
    // The prompt lasts about 3 s of the 10 s: long enough for a loaded machine.
    config_.capture.interval = 10 * kNsPerSec;
    config_.turntable.manual_hands_off = 7 * kNsPerSec;
  }

  // A new sample, homed, side 1 begun, the move to view 1 at `angle`: the
  // "turn" events published so far.
  std::vector<json> StartAndPromptView1(double angle) {
    peer_->set_events(&hub_);
    EXPECT_EQ(peer_->Run(capture::CreateSample{"rock-1"}), Names{});
    EXPECT_EQ(peer_->Run(capture::Home{}), Names{});
    EXPECT_TRUE(WaitMotionDone(*peer_));
    EXPECT_EQ(peer_->Run(capture::BeginSide{1}), Names{});
    EXPECT_EQ(peer_->Run(capture::MoveTo{angle, 1, 1}), Names{});
    EXPECT_TRUE(WaitMotionDone(*peer_)) << "nothing to wait for: nothing is driven";
    return TurnEvents();
  }

  std::vector<json> TurnEvents() {
    bool gap = false;
    std::vector<json> out;
    for (const LiveEvent& e : hub_.Since(0, &gap))
      if (e.type == "turn") out.push_back(json::parse(e.data));
    return out;
  }

  // Shoots and stores view 1 of side 1; its sidecar (null when it failed).
  json ShootAndStoreView1(double angle) {
    EXPECT_EQ(peer_->Run(capture::TriggerCapture{1, 1, angle}), Names{});
    const auto shot = std::chrono::steady_clock::now() + std::chrono::seconds(20);
    while (std::chrono::steady_clock::now() < shot && !peer_->has_frame()) {
      std::this_thread::sleep_for(std::chrono::milliseconds(20));
    }
    EXPECT_TRUE(peer_->has_frame());
    if (!peer_->has_frame()) return json();
    EXPECT_EQ(peer_->Run(capture::StoreView{1, 1}), Names{"view_stored"});
    auto car = ReadFile(store_->SampleDir("rock-1") + "/side1/view_001.json");
    EXPECT_TRUE(car) << car.error().ToString();
    return car ? json::parse(*car) : json();
  }
};

TEST_F(ManualCaptureSteps, TheMoveIsAPromptToTurnAndTheAngleIsLeftToTheLabels) {
  const std::vector<json> ev = StartAndPromptView1(30.0);
  ASSERT_EQ(ev.size(), 1u);
  const json& d = ev[0];
  EXPECT_EQ(d["side"], 1);
  EXPECT_EQ(d["move"], "table");
  EXPECT_EQ(d["number"], 2);
  EXPECT_DOUBLE_EQ(d["by_deg"].get<double>(), 30.0);
  // View 1 is due 10 s after t0, hands off 7 s before that.
  EXPECT_LE(d["hands_off_in_ms"].get<int64_t>(), 3000);
  EXPECT_GT(d["hands_off_in_ms"].get<int64_t>(), 1000);
  EXPECT_LE(d["due_in_ms"].get<int64_t>(), 10000);
  EXPECT_GT(d["due_in_ms"].get<int64_t>(), 8000);
  EXPECT_EQ(peer_->light_pattern(), LightPattern::kTurn);
  const auto until = std::chrono::steady_clock::now() + std::chrono::seconds(15);
  while (std::chrono::steady_clock::now() < until &&
         peer_->light_pattern() == LightPattern::kTurn) {
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  EXPECT_NE(peer_->light_pattern(), LightPattern::kTurn) << "hands off before the shot";
  // The same angle again is no turn.
  EXPECT_EQ(peer_->Run(capture::MoveTo{30.0, 1, 1}), Names{});
  EXPECT_EQ(TurnEvents().size(), 1u);
  // The view is shot and stored without a measured angle.
  const json c = ShootAndStoreView1(30.0);
  ASSERT_TRUE(c.is_object());
  EXPECT_FALSE(c.contains("measured_angle_deg")) << c.dump();
  EXPECT_EQ(c["turntable_backend"], "manual");
  EXPECT_DOUBLE_EQ(c["commanded_angle_deg"].get<double>(), 30.0);
}

// A camera walked round a still rock: the same prompt, to move the camera;
// the sidecar says how the view was taken.
class MovingCameraCaptureSteps : public ManualCaptureSteps {
 protected:
  void Configure() override {
    ManualCaptureSteps::Configure();
    config_.capture.mode = "moving_camera";
  }
};

TEST_F(MovingCameraCaptureSteps, TheMoveIsAPromptToCarryTheCameraOn) {
  const std::vector<json> ev = StartAndPromptView1(30.0);
  ASSERT_EQ(ev.size(), 1u);
  EXPECT_EQ(ev[0]["move"], "camera");
  EXPECT_EQ(peer_->light_pattern(), LightPattern::kTurn);
  const json c = ShootAndStoreView1(30.0);
  ASSERT_TRUE(c.is_object());
  EXPECT_EQ(c["capture_mode"], "moving_camera") << c.dump();
  EXPECT_FALSE(c.contains("measured_angle_deg")) << c.dump();
}

}  // namespace

// The sample's description: the config's material is a new sample's
// default; an edit through the service changes sample.json and the library's
// row, and the answers carry the mass from it; a batch by lot lists it.
TEST_F(CaptureSteps, DescriptionEditMassLibraryRowAndBatch) {
  EXPECT_EQ(peer_->Run(capture::CreateSample{"rock-1"}), Names{});
  auto rec = store_->LoadRecord("rock-1");
  ASSERT_TRUE(rec);
  EXPECT_EQ((*rec)["meta"]["material"], (json{{"name", "granite"},
                                              {"specific_gravity", 2.65},
                                              {"basis", "bulk-ssd"},
                                              {"source", "config"}}));
  // The worker's figures, as it writes them (a record of the earlier release).
  Result<std::string> text =
      ReadFile(std::string(AGGSCAN_SOURCE_DIR) + "/tests/core/data/morphology_v1.json");
  ASSERT_TRUE(text);
  json m = json::parse(*text);
  m["sample_id"] = "rock-1";
  ASSERT_TRUE(MakeDirsDurable(store_->SampleDir("rock-1") + "/results"));
  ASSERT_TRUE(WriteFileAtomic(layout::ResultsPath(store_->SampleDir("rock-1"), layout::kMorphology),
                              std::string_view(m.dump())));
  const auto ctx = [] { return CallContext::Within(std::chrono::seconds(5)); };
  Result<json> edited = service_->EditMeta(
      "rock-1", {{"lot", "L-7"}, {"material", {{"specific_gravity", 2.7}}}}, "qa", ctx());
  ASSERT_TRUE(edited) << edited.error().ToString();
  EXPECT_EQ(
      (*edited)["changed"],
      (json{{"lot", nullptr}, {"material.specific_gravity", 2.65}, {"material.source", "config"}}));
  // 155.7465 cm3 x 2.7.
  Result<json> got = service_->GetSample("rock-1");
  ASSERT_TRUE(got);
  EXPECT_NEAR((*got)["result"].value("mass_g", 0.0), 420.516, 1e-3) << got->dump();
  EXPECT_EQ((*got)["result"]["mass_basis"], "bulk-ssd");
  Result<std::string> csv = ReadFile(config_.daemon.state_dir + "/" + layout::kLibraryCsv);
  ASSERT_TRUE(csv);
  EXPECT_NE(csv->find("\nrock-1,"), std::string::npos) << *csv;
  EXPECT_NE(csv->find(",420.5,2.700,bulk-ssd,granite,,L-7,"), std::string::npos) << *csv;
  // A wrong edit is refused with what to do, and changes nothing.
  Result<json> bad =
      service_->EditMeta("rock-1", {{"material", {{"specific_gravity", 2700}}}}, "qa", ctx());
  ASSERT_FALSE(bad);
  EXPECT_NE(bad.error().message.find("kg/m3"), std::string::npos) << bad.error().message;
  // Without a specific gravity the answer says why there is no mass.
  ASSERT_TRUE(service_->EditMeta("rock-1", {{"material", nullptr}}, "qa", ctx()));
  got = service_->GetSample("rock-1");
  EXPECT_FALSE((*got)["result"].contains("mass_g"));
  EXPECT_NE((*got)["result"].value("mass_none", "").find("no specific gravity"), std::string::npos);
  // A batch by lot holds the sample, with its figures.
  Result<json> batch = service_->PutBatch("lot-7", {{"lot", "L-7"}});
  ASSERT_TRUE(batch) << batch.error().ToString();
  ASSERT_EQ((*batch)["members"].size(), 1u) << batch->dump();
  EXPECT_EQ((*batch)["members"][0]["id"], "rock-1");
  EXPECT_TRUE((*batch)["members"][0]["result"].contains("volume_mm3"));
  Result<json> batches = service_->ListBatches();
  ASSERT_TRUE(batches);
  EXPECT_EQ((*batches)["batches"][0]["members"], 1);
  EXPECT_EQ(service_->GetBatch("nope").error().cls, ErrorClass::kNotFound);
  // The rock's report, made by the aggscan program as the API serves it.
  ::setenv("AGGSCAN_CLI", (std::string(AGGSCAN_BINARY_DIR) + "/cli/aggscan").c_str(), 1);
  Result<std::string> pdf = service_->MakeReport({"rock", "rock-1", "pdf", ""});
  ASSERT_TRUE(pdf) << pdf.error().ToString();
  Result<std::string> head = ReadFile(*pdf);
  ASSERT_TRUE(head);
  EXPECT_EQ(head->rfind("%PDF", 0), 0u);
  std::filesystem::remove_all(std::filesystem::path(*pdf).parent_path());
  // A batch report needs every rock's mass: rock-1 has none now; said so.
  Result<std::string> no_mass = service_->MakeReport({"batch", "lot-7", "html", "fp14-class1"});
  ASSERT_FALSE(no_mass);
  EXPECT_EQ(no_mass.error().cls, ErrorClass::kInvalidState);
  EXPECT_NE(no_mass.error().message.find("no specific gravity for rock-1"), std::string::npos)
      << no_mass.error().message;
  // Over the network a specification is a shipped name, never a path.
  Result<std::string> path_spec = service_->MakeReport({"batch", "lot-7", "pdf", "../x.toml"});
  ASSERT_FALSE(path_spec);
  EXPECT_EQ(path_spec.error().cls, ErrorClass::kInvalidArgument);
  EXPECT_EQ(service_->MakeReport({"rock", "rock-9", "pdf", ""}).error().cls, ErrorClass::kNotFound);
  ASSERT_TRUE(service_->DeleteBatch("lot-7"));
  EXPECT_FALSE(service_->GetBatch("lot-7"));
}

}  // namespace aggscan
