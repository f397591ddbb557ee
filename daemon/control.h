// What the HTTP API (and through it the CLI) can ask of the running daemon.
// Implemented by the capture service, which posts each call to its event loop
// and waits for the answer: every method is safe to call from any thread.
// Errors carry an ErrorClass that the API maps to an HTTP status
// (kInvalidArgument 400, kNotFound 404, kConflict/kInvalidState 409, others 500/503).
#pragma once

#include <chrono>
#include <functional>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "common/error.h"
#include "daemon/report_maker.h"
#include "store/layout.h"

namespace aggscan {

/// The result files the API serves, as named in results/ (store/layout.h).
inline const std::vector<std::string>& ResultFileNames() {
  static const std::vector<std::string> names = {layout::kMorphology, layout::kMeshPly,
                                                 layout::kMeshObj, layout::kMeshStl};
  return names;
}

/// One file of a download made of several (DaemonControl::ImageArchive):
/// where it is and the name it has in the archive ("side1/view_000.jpg").
struct ArchiveMember {
  std::string path;
  std::string name;
};

/// Which file of a stored view DaemonControl::ViewFile names.
enum class ViewFileKind { kImage, kMask };

/// Where the API serves a stored view: GET .../views/{view} (the image),
/// .../thumbnail and .../mask.
inline std::string ViewUrl(const std::string& sample_id, int side, int view) {
  return "/api/v1/samples/" + sample_id + "/sides/" + std::to_string(side) + "/views/" +
         std::to_string(view);
}

/// What a state-changing call carries from its transport. A command that the
/// capture loop has not started by `deadline`, or whose client is gone, is
/// dropped (kTimeout / kConflict) and never runs afterwards: a press the
/// operator saw fail must not move the turntable later.
struct CallContext {
  using Clock = std::chrono::steady_clock;
  /// The latest moment the loop may start the command; max() = the service's own limit.
  Clock::time_point deadline = Clock::time_point::max();
  /// Optional; true once the requester has disconnected. Called on the loop
  /// thread just before the command would run, so it must be cheap and non-blocking.
  std::function<bool()> client_gone;

  /// A context whose deadline is `budget` from now.
  static CallContext Within(Clock::duration budget) {
    return CallContext{Clock::now() + budget, {}};
  }
};

/// What the operator fills in to arm a sample.
struct ArmRequest {
  std::string id;
  /// The sample's description as store/sample_meta.h checks it ("operator",
  /// "lot", "notes", "material"), already checked.
  nlohmann::json meta = nlohmann::json::object();
};

class DaemonControl {
 public:
  virtual ~DaemonControl() = default;
  /// {"state": "idle|armed|homing|...", "sample_id", "side", "view" (1-based, 0 = none),
  /// "views_per_side",
  ///  "sides", "fault": {"class","message"} | null, "status_line", "devices": {...},
  ///  "queue_depth", "failed_jobs": [{"sample_id", "side", "attempts", "error", "updated_utc"}...]
  ///  (newest first, at most 20), "failed_jobs_total", "uptime_s"}
  virtual nlohmann::json GetStatus() = 0;
  /// {"status": "ok|unhealthy", "state", "fault", "devices": {"camera"|"turntable"|"button":
  ///  {"backend", "id", "state": "ok|opening|<ErrorClassName>", "healthy", "message", "since_utc",
  ///   "last_ok_utc", "retries", "next_retry_utc", "next_retry_in_s"}}, "checked_utc"}
  virtual nlohmann::json GetHealth() = 0;
  /// Arms a new sample (or resumes an unfinished one with that id). The
  /// optional fields are the operator's description, kept in sample.json as
  /// "meta" (a resume keeps what was stored unless new text is given).
  virtual Result<nlohmann::json> Arm(const ArmRequest& request, const CallContext& ctx) = 0;
  Result<nlohmann::json> Arm(const std::string& sample_id, const CallContext& ctx) {
    return Arm(ArmRequest{sample_id, nlohmann::json::object()}, ctx);
  }
  /// Arms a capture of the calibration board lying on the disc (no rock):
  /// one side into state_dir/calibration-captures/calibration-<UTC>, which
  /// the worker solves into state_dir/calibration.json after START. The
  /// status's "calibration_capture" follows it. kInvalidConfig on a sim rig
  /// without sim.board_image.
  virtual Result<nlohmann::json> ArmCalibration(const CallContext& ctx) = 0;
  /// Same as pressing the physical start button. `source` e.g. "api".
  virtual Result<nlohmann::json> Press(const std::string& source, const CallContext& ctx) = 0;
  virtual Result<nlohmann::json> Abort(const CallContext& ctx) = 0;
  virtual Result<nlohmann::json> Reset(const CallContext& ctx) = 0;
  /// [{"id","state","created_utc","meta","sides","sides_done","views","result" (key figures, once
  ///  computed),"reconstruction": {"state": "queued|reconstructing|done|failed","error"}|null}...]
  virtual Result<nlohmann::json> ListSamples() = 0;
  /// The sample record plus per-side view lists and job states.
  virtual Result<nlohmann::json> GetSample(const std::string& sample_id) = 0;
  /// Puts the sample's failed jobs back in the worker's queue with their
  /// attempts reset (after the cause was fixed): {"sample_id", "requeued",
  /// "jobs"}. kNotFound when the sample does not exist or has no failed job.
  virtual Result<nlohmann::json> Retry(const std::string& sample_id) = 0;
  /// Edits a sample's description (operator, lot, notes, material) in its
  /// sample.json only, in any state; `doc` is the request as given, checked
  /// by store/sample_meta.h; `by` who asked. {"id", "meta", "changed"}.
  virtual Result<nlohmann::json> EditMeta(const std::string& sample_id, const nlohmann::json& doc,
                                          const std::string& by, const CallContext& ctx) = 0;
  /// Batches (store/batches.h): {"batches": [{"name", "lot", "from", "to",
  /// "samples", "notes", "members" (how many belong now)}...]}.
  virtual Result<nlohmann::json> ListBatches() = 0;
  /// One batch: its definition, "members" (ListSamples' entries of the
  /// samples that belong now, with their results) and "missing" (listed ids
  /// the store does not have). kNotFound naming the batches there are.
  virtual Result<nlohmann::json> GetBatch(const std::string& name) = 0;
  /// Creates or replaces a batch from {"lot", "from", "to", "samples",
  /// "notes"} (checked by BatchFromRequest); answers as GetBatch.
  virtual Result<nlohmann::json> PutBatch(const std::string& name, const nlohmann::json& doc) = 0;
  virtual Result<nlohmann::json> DeleteBatch(const std::string& name) = 0;
  /// Makes a rock's or a batch's QA report (daemon/report_maker.h) and
  /// returns its file, which the caller serves and then removes.
  virtual Result<std::string> MakeReport(const ReportRequest& request) = 0;
  /// Path of one of a sample's result files, written by the worker: name is
  /// "morphology.json", "mesh.ply", "mesh.obj" or "mesh.stl" (ResultFileNames()).
  /// kNotFound when the sample does not exist or has no such result yet.
  virtual Result<std::string> ResultFile(const std::string& sample_id, const std::string& name) = 0;
  /// Path of one stored view's file: its image (side<N>/view_NNN.jpg) or the
  /// worker's mask of it (results/masks/side<N>/view_NNN.png). `side` counts
  /// from 1, `view` from 0, as in the store. kNotFound when the sample, the
  /// view or (for a mask) the worker's result does not exist (yet).
  virtual Result<std::string> ViewFile(const std::string& sample_id, int side, int view,
                                       ViewFileKind kind) = 0;
  /// The files of a sample's images archive: sample.json and config.toml,
  /// every complete view of every side (image and sidecar) with the side's
  /// manifest, the calibration it was shot with and the worker's masks where
  /// they exist, each under its name in the sample directory. kNotFound when
  /// the sample does not exist or has no complete view yet.
  virtual Result<std::vector<ArchiveMember>> ImageArchive(const std::string& sample_id) = 0;
  /// Prometheus text exposition format.
  virtual std::string Metrics() = 0;
};

}  // namespace aggscan
