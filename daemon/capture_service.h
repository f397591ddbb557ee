// The capture service: owns the capture state (on the event loop's thread),
// turns device answers, timers and requests into state-machine events, and
// executes the machine's effects against the devices, the sample store and
// the job queue. Implements DaemonControl for the HTTP API: those calls may
// come from any thread and are run on the loop.
#pragma once

#include <deque>
#include <functional>
#include <initializer_list>
#include <map>
#include <memory>
#include <optional>
#include <string>

#include "common/log.h"
#include "config/config.h"
#include "daemon/control.h"
#include "daemon/event_hub.h"
#include "daemon/event_loop.h"
#include "daemon/preview_hub.h"
#include "daemon/state_machine.h"
#include "drivers/factory.h"
#include "store/queue.h"
#include "store/sample_store.h"

namespace aggscan {

/// Health of one device, as shown by GET /api/v1/status and /api/v1/health.
struct DeviceHealth {
  bool healthy = false;
  std::string message;  // "ok", or what is wrong with the device, its link and what to check
  ErrorClass cls = ErrorClass::kDeviceMissing;  // meaningful when unhealthy
  bool tried = false;                           // an open was attempted (false: "not opened yet")
  int64_t since_utc_ns = 0;    // real wall time the current state (ok or this class) began
  int64_t last_ok_utc_ns = 0;  // real wall time it last opened or worked; 0 = never
  int retries = 0;             // failed open attempts since it was last ok
  TimeNs next_retry_real = 0;  // MonotonicNs() of the next open attempt; 0 = none scheduled
  uint64_t retry_timer = 0;    // EventLoop timer of that attempt; 0 = none
};

/// The state directory's filesystem, shown as the "storage" device of health.
struct StorageHealth {
  bool healthy = false;
  ErrorClass cls = ErrorClass::kIo;  // meaningful when unhealthy
  std::string message;
  int64_t free_bytes = -1;  // available to aggscand (statvfs f_bavail), -1 = unknown
  int64_t total_bytes = -1;
  int64_t free_inodes = -1;      // files that can still be created, -1 = unknown
  int64_t side_needs_bytes = 0;  // estimate for the next side, margin included
  int side_needs_files = 0;
};

class CaptureService final : public DaemonControl {
 public:
  CaptureService(EventLoop& loop, Config config, std::string effective_config_toml,
                 RigDevices devices, SampleStore& store, JobQueue* queue);
  ~CaptureService() override;

  /// Loop thread: opens the devices (retrying in the background with backoff
  /// when one is missing) and starts listening to the button.
  void Start();
  /// Loop thread: interrupts an active capture (recorded as interrupted) and
  /// closes the devices.
  void Shutdown();

  /// Called on the loop thread whenever the status line changes ("side 1 view 7/30").
  void SetStatusListener(std::function<void(const std::string&)> fn) { on_status_ = std::move(fn); }
  /// Called on the loop thread after every accepted transition.
  void SetTransitionListener(std::function<void(const capture::State&)> fn) {
    on_transition_ = std::move(fn);
  }
  /// Publishes the live events (state, view, worker, health, fault) there;
  /// set before Start(). Borrowed: must outlive the service.
  void SetEventHub(EventHub* hub) { events_ = hub; }
  /// Shoots the live view into `hub` while a screen watches it and no side
  /// runs, and hands it each view stored during a side; set before Start().
  /// Borrowed: must outlive the service.
  void SetPreviewHub(PreviewHub* hub);

  // DaemonControl (any thread).
  nlohmann::json GetStatus() override;
  nlohmann::json GetHealth() override;
  using DaemonControl::Arm;
  Result<nlohmann::json> Arm(const ArmRequest& request, const CallContext& ctx) override;
  Result<nlohmann::json> ArmCalibration(const CallContext& ctx) override;
  Result<nlohmann::json> Press(const std::string& source, const CallContext& ctx) override;
  Result<nlohmann::json> Abort(const CallContext& ctx) override;
  Result<nlohmann::json> Reset(const CallContext& ctx) override;
  Result<nlohmann::json> Retry(const std::string& sample_id) override;
  Result<nlohmann::json> EditMeta(const std::string& sample_id, const nlohmann::json& doc,
                                  const std::string& by, const CallContext& ctx) override;
  Result<nlohmann::json> ListBatches() override;
  Result<nlohmann::json> GetBatch(const std::string& name) override;
  Result<nlohmann::json> PutBatch(const std::string& name, const nlohmann::json& doc) override;
  Result<nlohmann::json> DeleteBatch(const std::string& name) override;
  Result<std::string> MakeReport(const ReportRequest& request) override;
  Result<nlohmann::json> ListSamples() override;
  Result<nlohmann::json> GetSample(const std::string& sample_id) override;
  Result<std::string> ResultFile(const std::string& sample_id, const std::string& name) override;
  Result<std::string> ViewFile(const std::string& sample_id, int side, int view,
                               ViewFileKind kind) override;
  Result<std::vector<ArchiveMember>> ImageArchive(const std::string& sample_id) override;
  std::string Metrics() override;

  // Loop-thread versions (used by the offline sim capture and by the above).
  Result<nlohmann::json> ArmOnLoop(const ArmRequest& request);
  /// The sample's key figures from its morphology.json, with the mass from
  /// `meta` (its record's description); null when none yet.
  nlohmann::json ResultSummary(const std::string& sample_id, const nlohmann::json& meta) const;
  Result<nlohmann::json> ArmOnLoop(const std::string& sample_id) {
    return ArmOnLoop(ArmRequest{sample_id, nlohmann::json::object()});
  }
  /// Arms a capture of the calibration board (one side, into
  /// state_dir/calibration-captures/calibration-<UTC>); the worker solves it.
  Result<nlohmann::json> ArmCalibrationOnLoop();
  /// The latest calibration capture: {"id", "state" (armed | capturing |
  /// queued | solving | done | failed | interrupted | aborted), "error",
  /// "result" (the worker's summary once solved)}; null when none was made
  /// since start-up.
  nlohmann::json CalibrationCaptureOnLoop() const;
  Result<nlohmann::json> PressOnLoop(const std::string& source);
  Result<nlohmann::json> AbortOnLoop();
  Result<nlohmann::json> ResetOnLoop();
  nlohmann::json StatusOnLoop() const;
  /// Each device's health (state, message, last ok, retries, next retry) and
  /// "status": "ok" when every device is healthy, else "unhealthy".
  nlohmann::json HealthOnLoop() const;
  /// The worker as it last reported itself in the queue: state, job, stage,
  /// progress, and whether it is healthy (heard from within
  /// worker.silent_after), with what to do when it is not. Null without a
  /// queue.
  nlohmann::json WorkerOnLoop() const;
  const capture::State& state() const { return state_; }
  std::string StatusLine() const;
  /// Loop thread (or before the loop runs): checks state_dir/calibration.json
  /// against the camera config and logs a change; the status API shows the
  /// result as "calibration" (null until the first check). Once called, every
  /// arm checks again (a calibration may be written while aggscand runs).
  void RefreshCalibration();

 private:
  // Tests run the steps of Execute() one at a time (tests/daemon/capture_steps_test.cpp).
  friend class CaptureServiceTestPeer;
  struct MotionWatch {
    bool active = false;
    bool homing = false;
    double target_deg = 0;
    TimeNs deadline = 0;
    double last_angle = 0;
    TimeNs last_progress = 0;
    int comm_errors = 0;
    std::optional<TurntableStatus> last_status;  // the latest status read, for the time-out message
  };
  // A hand-turned table (turntable.backend = "manual"): true from the prompt
  // to turn until the hands-off moment before the next view is due (the
  // light blinks "turn"); turn_epoch_ drops a stale hands-off timer.
  bool turn_prompt_ = false;
  uint64_t turn_epoch_ = 0;
  bool ManualTurntable() const;
  void PromptTurn(int side, int view, double from_deg, double to_deg);

  struct PendingView {
    int side = 0, view = 0;
    uint64_t request_id = 0;
    double commanded_deg = 0;
    std::optional<double> measured_deg;  // none: a hand-turned table (the worker measures it)
    TimeNs due = 0, trigger = 0;
    FramePtr frame;
  };

  /// Runs `fn` on the loop and waits for its answer until ctx.deadline (at most
  /// the service's own limit). If the loop has not started it by then, or
  /// ctx.client_gone() says nobody waits for it, it is dropped and never runs.
  template <typename F>
  auto OnLoop(F fn, const CallContext& ctx = {}) -> decltype(fn());
  void Dispatch(capture::Event e);
  void Execute(const capture::Effect& eff);
  // The steps of Execute(), one per effect. A step that fails queues a fault
  // event on pending_events_: it is handled once the transition's effects ran.
  /// Creates the sample's directory or resumes the stored one.
  void Run(const capture::CreateSample& e);
  /// Starts homing; PollMotion() watches it until home or capture.home_timeout.
  void Run(const capture::Home& e);
  /// Starts the move to the view's angle; PollMotion() watches for arrival, stall and time-out.
  void Run(const capture::MoveTo& e);
  /// SettleDone after capture.settle, so the platter is still when the view is shot.
  void Run(const capture::StartSettle& e);
  /// Creates the side's directory; its schedule starts (t0) at the end of the first settle.
  void Run(const capture::BeginSide& e);
  /// ViewDue at t0 + view * interval (at once when already late): the schedule never drifts.
  void Run(const capture::WaitUntilDue& e);
  /// Reads the angle, holds the loop and requests the still; faults after frame_timeout.
  void Run(const capture::TriggerCapture& e);
  /// Writes the still and its record, publishes the view and its schedule error; ViewStored.
  void Run(const capture::StoreView& e);
  /// Stores the side's manifest, queues its jobs (last side: the sample's too); SideFinished.
  void Run(const capture::FinishSide& e);
  /// Cancels the capture's timers and late callbacks, releases the loop and stops the turntable.
  void Run(const capture::StopMotion& e);
  /// Records the sample and the side in progress as interrupted.
  void Run(const capture::MarkInterrupted& e);
  /// Records the sample as aborted by the operator.
  void Run(const capture::MarkAborted& e);
  /// Counts and logs the fault; a lost device is marked unhealthy and reopened in the background.
  void Run(const capture::RecordFault& e);
  /// Forgets the store fault and reopens the devices that are not healthy (reset).
  void Run(const capture::ClearFault& e);
  void PollMotion(uint64_t epoch);
  void Fault(ErrorClass cls, const std::string& message);
  /// Opens every device that is not healthy (the healthy ones are left alone).
  void OpenDevices();
  /// One open attempt of one device ("camera", "turntable", "button"); on
  /// failure the next attempt is scheduled with exponential backoff.
  void TryOpen(const std::string& name);
  Status OpenDevice(const std::string& name);
  void MarkHealthy(const std::string& name);
  /// Records the failure; logs it once per device and error class.
  void MarkUnhealthy(const std::string& name, ErrorClass cls, const std::string& message);
  void ScheduleReopen(const std::string& name);
  /// Reads the turntable's status every daemon.health_probe_interval while no
  /// side runs; comm_retries consecutive failures make it unhealthy.
  void ProbeDevices();
  /// Logs and publishes the worker turning silent or coming back, and
  /// publishes its report when it changed: every 500 ms while events are
  /// published, else every few seconds.
  void WatchWorker();
  /// Publishes a "calibration" event when the latest calibration capture
  /// changes state; re-checks the rig calibration when it was solved.
  void WatchCalibration();
  /// The plan of the capture being armed: the config's, one side for the board.
  SamplePlan CurrentPlan() const;
  /// The store a capture id belongs to: calibration captures by their
  /// reserved prefix (layout::kCalibrationIdPrefix), rocks otherwise.
  const SampleStore& StoreOf(const std::string& id) const {
    return id.rfind(layout::kCalibrationIdPrefix, 0) == 0 ? cal_store_ : store_;
  }
  SampleStore& StoreOf(const std::string& id) {
    return id.rfind(layout::kCalibrationIdPrefix, 0) == 0 ? cal_store_ : store_;
  }
  void Publish(const std::string& type, nlohmann::json data);
  /// Starts the live view's tick unless it runs (a screen began watching).
  void StartPreview();
  /// Every daemon.preview_interval while a screen watches: one preview still
  /// when the camera is free and no side runs.
  void PreviewTick();
  void OnPreviewFrame(uint64_t generation, Result<FramePtr> frame);
  /// Requests the still of pending_ (TriggerCapture, or once a preview still
  /// the camera was busy with has arrived).
  Status ShootView();
  /// Turns a runtime fault recorded by the button or light thread into health.
  void ProbeButtonAndLight();
  /// The status light's pattern for the current state and device health.
  LightPattern LightPatternFor() const;
  /// True while a side is being shot (homing .. storing): devices are not
  /// reopened or probed then.
  bool SideRunning() const;
  /// Free space and files on the state directory's filesystem against what
  /// the next side needs (from the armed sample's stored views, else from the
  /// camera resolution), and the capture's storage fault if any.
  StorageHealth CheckStorage() const;
  /// kDiskFull naming free vs needed bytes when a side does not fit.
  Status CheckStorageForSide() const;
  /// Arming an existing sample: completes what is stored (manifests of sides
  /// whose views are all there, "captured") and queues the work the queue
  /// lacks. kConflict when that completed the whole sample.
  Status CompleteAndQueue(const std::string& sample_id);
  /// Whether a capture may be armed now: idle (kInvalidState naming the
  /// phase and what to do, `what` being "arm" or the like) and every device
  /// healthy.
  Status CheckCanArm(const std::string& what) const;
  /// kDeviceMissing/... naming the first unhealthy device of `names`, for refusing a capture.
  Status CheckDevicesHealthy(std::initializer_list<const char*> names) const;
  void NotifyStatus();
  uint64_t AddEpochTimer(TimeNs at, std::function<void()> fn);

  EventLoop& loop_;
  Config config_;
  std::string config_toml_;
  RigDevices dev_;
  SampleStore& store_;
  SampleStore cal_store_;  // state_dir/calibration-captures
  std::mutex batches_mu_;  // one writer of state_dir/batches at a time
  ReportMaker reports_;    // one report at a time
  JobQueue* queue_;
  bool calibration_capture_ = false;  // the armed (or last) capture is of the board
  std::string cal_last_id_;           // the latest calibration capture
  std::string cal_reported_;          // its state as last published

  capture::State state_;
  std::deque<capture::Event> pending_events_;
  bool dispatching_ = false;
  uint64_t epoch_ = 1;  // bumped on stop/fault/abort: stale timers and callbacks are ignored
  MotionWatch motion_;
  PendingView pending_;
  uint64_t next_request_id_ = 1;
  bool holding_ = false;
  TimeNs side_t0_ = 0;
  std::map<std::string, DeviceHealth> health_;
  std::optional<capture::StoreFailed> store_fault_;  // the store failure the capture is faulted on
  // CheckStorage()'s last scan: sample id -> (stored views, their bytes).
  mutable std::pair<std::string, std::pair<int, int64_t>> view_bytes_;
  RateLimitedLog device_log_{"devices"};
  int probe_failures_ = 0;  // consecutive failed turntable status reads of the idle probe  // keys
                            // "device/class": one line per class until recovery
  TimeNs started_real_ = 0;
  bool worker_healthy_ = true;  // WatchWorker()'s last finding
  EventHub* events_ = nullptr;
  PreviewHub* preview_ = nullptr;
  bool preview_ticking_ = false;
  bool preview_in_flight_ = false;   // the camera is busy with a preview still
  uint64_t preview_generation_ = 1;  // bumped when the camera is reopened: late stills are dropped
  bool shot_waits_for_preview_ =
      false;  // a view's trigger came while a preview still was in flight
  RateLimitedLog preview_log_{"preview"};
  uint64_t previews_shot_ = 0;
  uint64_t preview_failures_ = 0;
  uint64_t preview_delayed_views_ = 0;
  std::string published_state_;   // phase/sample/side of the last "state" event
  std::string published_worker_;  // what the last "worker" event said
  std::string last_status_;
  nlohmann::json calibration_;  // CheckRigCalibration() result; null = never checked
  nlohmann::json arm_meta_ = nlohmann::json::object();  // the armed sample's operator, lot, notes
  std::function<void(const std::string&)> on_status_;
  std::function<void(const capture::State&)> on_transition_;

  // Metrics.
  uint64_t views_captured_ = 0;
  uint64_t overruns_ = 0;
  uint64_t samples_completed_ = 0;
  uint64_t sides_completed_ = 0;
  double last_schedule_error_ms_ = 0;
  double max_schedule_error_ms_ = 0;
  std::map<std::string, uint64_t> faults_by_class_;
  std::map<std::string, uint64_t> rejected_events_;
};

}  // namespace aggscan
