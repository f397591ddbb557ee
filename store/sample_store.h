// The durable sample store: one directory per rock (layout in store/layout.h).
//
// Every file goes through WriteFileAtomic (temp name, fsync, rename, fsync dir).
// A view is complete when its sidecar exists (written after the image); a side
// is complete when its manifest exists (written after every view). Images are
// never overwritten: an interrupted side is moved aside, whole, before a
// re-shoot. At start-up Recover() deletes temporary leftovers, completes
// what a crash left one step short of complete (a side whose every planned
// view is stored gets its manifest; a sample whose every side has one is
// captured) and marks any other side that was being captured as interrupted.
#pragma once

#include <functional>
#include <nlohmann/json.hpp>
#include <span>
#include <string>
#include <vector>

#include "common/error.h"
#include "store/layout.h"

namespace aggscan {

struct SamplePlan {
  std::string profile = "paper";
  int sides = 2;
  int views_per_side = 30;
  double step_deg = 30.0;
  int64_t interval_ms = 2000;
};

/// What Recover() found and did.
struct RecoveryReport {
  int samples = 0;
  int temp_files_removed = 0;
  int sides_interrupted = 0;  // sides that were being captured and are now marked interrupted
  int sides_completed = 0;    // sides with every view stored whose manifest was written now
  std::vector<std::string> interrupted_samples;
  std::vector<std::string> completed_samples;  // every side had its manifest: now "captured"
};

/// What CompleteStored() found and did for one sample.
struct Completion {
  std::vector<int> sides_completed;   // manifests written now
  bool sample_captured = false;       // every side has a manifest (the sample is "captured")
  bool sample_completed_now = false;  // ... and was not marked so before
};

class SampleStore {
 public:
  /// `collection`: the folder of the state directory the captures go to,
  /// layout::kSamplesCollection (rocks) or layout::kCalibrationCollection.
  explicit SampleStore(std::string state_dir, std::string collection = layout::kSamplesCollection)
      : state_dir_(std::move(state_dir)), collection_(std::move(collection)) {}

  /// Creates <state_dir>/<collection> if needed.
  Status Init();
  /// Start-up recovery (see above). Safe to run on a clean store.
  Result<RecoveryReport> Recover();

  /// For arming `id`: a new id starts at side 1; an unfinished sample with the
  /// same plan resumes at its first side without a manifest. Errors:
  /// kInvalidArgument (bad id), kConflict (complete, or a different plan).
  Result<int> PrepareArm(const std::string& id, const SamplePlan& plan) const;
  /// Completes what is stored but not marked complete: a side without a
  /// manifest whose every planned view (image + sidecar) is stored gets its
  /// manifest (and "done" in the record); when every side has a manifest the
  /// sample becomes "captured". Nothing is moved or re-shot. Safe to repeat.
  Result<Completion> CompleteStored(const std::string& id);
  /// Creates the sample directory, record and config copy (or reopens an
  /// unfinished one) and marks it armed.
  /// `meta` ({"operator", "lot", "notes"}, each optional) is merged into the
  /// record's "meta": a resume keeps what it does not give again.
  Status CreateOrResume(const std::string& id, const SamplePlan& plan,
                        const std::string& config_toml,
                        const nlohmann::json& meta = nlohmann::json::object());
  /// Starts (or restarts) a side: an existing incomplete side directory is
  /// moved aside to side<N>.interrupted-<k>, then an empty one is created.
  Status BeginSide(const std::string& id, int side);
  /// Stores one view: image first, then its sidecar (the completion marker).
  /// Refuses to overwrite an existing view (kConflict).
  Status WriteView(const std::string& id, int side, int view, std::span<const unsigned char> image,
                   const nlohmann::json& sidecar);
  /// Writes the side manifest listing every view; the side is then complete.
  Status FinishSide(const std::string& id, int side);
  /// Sample-level state: armed | capturing | awaiting_pose | captured | interrupted | aborted.
  Status SetSampleState(const std::string& id, const std::string& state, int side_in_progress = 0,
                        const std::string& side_state = "");

  /// Edits the sample's description (store/sample_meta.h: `doc` is checked
  /// there, a null field removes it) in sample.json alone, in any state;
  /// "meta_history" gets {"utc", "by", "changed": {field: value before}}.
  /// Returns {"id", "meta", "changed"}; nothing is written when nothing changes.
  Result<nlohmann::json> EditMeta(const std::string& id, const nlohmann::json& doc,
                                  const std::string& by);

  Result<nlohmann::json> LoadRecord(const std::string& id) const;
  /// Summaries of every sample, sorted by creation time.
  Result<nlohmann::json> List() const;
  /// Record + the complete views of every side (+ interrupted attempts).
  Result<nlohmann::json> Describe(const std::string& id) const;

  /// Work the worker must have: (id, side) for every side with a manifest and
  /// (id, 0) for every captured sample. Start-up re-queues any of it that the
  /// queue lacks (e.g. an enqueue that failed or was lost with the queue file).
  /// `only`: just that sample's work.
  std::vector<std::pair<std::string, int>> CapturedWork(const std::string& only = "") const;

  /// The files that make a sample's images, as (path, name in the sample
  /// directory): sample.json, config.toml, calibration.json, each side's
  /// complete views (image, then sidecar) and manifest, and the worker's
  /// masks of them where they exist. Interrupted attempts are left out.
  /// kNotFound when there is no such sample.
  Result<std::vector<std::pair<std::string, std::string>>> ImageFiles(const std::string& id) const;

  /// Stored view images of `id` (every side and interrupted attempt): how
  /// many and their total bytes, for estimating what the next side needs.
  std::pair<int, int64_t> StoredViewBytes(const std::string& id) const;

  std::string SampleDir(const std::string& id) const;
  const std::string& state_dir() const { return state_dir_; }

 private:
  Status SaveRecord(const std::string& id, const nlohmann::json& rec);
  /// Load, edit, save atomically (one writer: the capture loop).
  Status UpdateRecord(const std::string& id, const std::function<void(nlohmann::json&)>& edit);
  /// Writes side<N>/manifest.json listing its complete views; returns the manifest.
  Result<nlohmann::json> WriteManifest(const std::string& id, int side);
  std::string CollectionDir() const { return state_dir_ + "/" + collection_; }
  std::string state_dir_;
  std::string collection_;
};

}  // namespace aggscan
