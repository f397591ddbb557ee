// The on-disk layout of a sample, shared by the daemon, the worker and the CLI.
//
//   <state_dir>/samples/<id>/
//     sample.json              sample record (state, plan, sides); rewritten atomically
//     config.toml              effective config at arm time
//     calibration.json         copy of state_dir/calibration.json at arm time (write-once;
//                              absent when there was no valid one: see sample.json "calibration")
//     side<N>/                 N = 1..sides
//       view_NNN.jpg           the still, exactly as the camera delivered it
//       view_NNN.json          sidecar: angles, timestamps, exposure, schedule error
//       manifest.json          written last: the side is complete iff it exists
//     side<N>.interrupted-<k>/ an interrupted attempt, moved aside before a re-shoot
//     results/                 worker output, one record per stage (pipeline/core/records.h):
//       masks/side<N>/view_NNN.png   rock masks
//       side<N>_morph2d.json         masks and 2D figures of a side (SideResult)
//       morph2d.json                 2D figures over the sides (no calibration)
//       calibration_used.json        the rig calibration the sample was measured with
//       poses_side<N>.json           every view's pose (PosesRecord)
//       stitch.json                  each side's table frame -> object frame (StitchRecord)
//       surface.json, mesh.ply/.obj/.stl   the model, mm, object frame (SurfaceRecord)
//       morphology.json              the figures, quality and warnings (Morphology)
//       stages.json                  each stage's fingerprint (pipeline/core/stage_runner.h)
//     truth/                   sim ground truth (only when sim.write_truth)
//     empty/                   photos of the empty turntable, linked in at arm time from the
//                              rig's current set (store/empty_turntable.h): the masks' background
//   <state_dir>/calibration-captures/<id>/   a capture of the calibration board lying on the
//                              disc: one side, laid out like a sample; the worker solves the
//                              rig calibration from it (never masks or measures it as a rock)
//   <state_dir>/queue.db       SQLite queue of side and sample jobs
//   <state_dir>/library.csv    one row of figures per reconstructed sample
//
// Files appear only under their final names when complete (see fsutil.h).
#pragma once

#include <string>

namespace aggscan::layout {

inline std::string SamplesDir(const std::string& state_dir) { return state_dir + "/samples"; }
inline std::string SampleDir(const std::string& state_dir, const std::string& id) {
  return SamplesDir(state_dir) + "/" + id;
}
/// The collections a capture can belong to (a folder of the state directory).
inline constexpr const char* kSamplesCollection = "samples";
inline constexpr const char* kCalibrationCollection = "calibration-captures";
/// Calibration captures are named "calibration-<UTC>"; rocks may not be, so
/// an id names one capture whatever its collection.
inline constexpr const char* kCalibrationIdPrefix = "calibration-";
inline std::string CalibrationCaptureDir(const std::string& state_dir, const std::string& id) {
  return state_dir + "/" + kCalibrationCollection + "/" + id;
}
inline std::string SideDirName(int side) { return "side" + std::to_string(side); }
std::string ViewStem(int view);  // "view_007"
inline std::string ViewImageName(int view) { return ViewStem(view) + ".jpg"; }
inline std::string ViewSidecarName(int view) { return ViewStem(view) + ".json"; }
inline constexpr const char* kManifest = "manifest.json";
inline constexpr const char* kSampleRecord = "sample.json";
inline constexpr const char* kConfigCopy = "config.toml";
inline constexpr const char* kCalibrationCopy = "calibration.json";  // rig calibration at arm time
inline constexpr const char* kResultsDir = "results";
inline constexpr const char* kTruthDir = "truth";
inline constexpr const char* kEmptyDir = "empty";
inline std::string QueuePath(const std::string& state_dir) { return state_dir + "/queue.db"; }
inline constexpr const char* kLibraryCsv = "library.csv";  // in the state directory

// The files of results/ (see above).
inline constexpr const char* kMorphology = "morphology.json";
inline constexpr const char* kSurface = "surface.json";
inline constexpr const char* kStitch = "stitch.json";
inline constexpr const char* kCalibrationUsed = "calibration_used.json";
inline constexpr const char* kCalibrationResult = "calibration_result.json";  // of a board capture
inline constexpr const char* kSampleMorph2d = "morph2d.json";
inline constexpr const char* kStageLedger = "stages.json";
inline constexpr const char* kMeshPly = "mesh.ply";
inline constexpr const char* kMeshObj = "mesh.obj";
inline constexpr const char* kMeshStl = "mesh.stl";
inline std::string PosesName(int side) { return "poses_" + SideDirName(side) + ".json"; }
inline std::string SideResultName(int side) { return SideDirName(side) + "_morph2d.json"; }
inline std::string ViewMaskName(int side, int view) {
  return "masks/" + SideDirName(side) + "/" + ViewStem(view) + ".png";
}
/// sample_dir/results/name.
inline std::string ResultsPath(const std::string& sample_dir, const std::string& name) {
  return sample_dir + "/" + kResultsDir + "/" + name;
}
/// The state directory a sample directory lies in (STATE_DIR/samples/ID or
/// STATE_DIR/calibration-captures/ID), or "" when it is not laid out so.
std::string StateDirOfSample(const std::string& sample_dir);
/// The sample id of a sample directory: its name (a trailing slash allowed).
std::string SampleIdOfDir(const std::string& sample_dir);

/// Sample ids: 1..64 chars of [A-Za-z0-9._-], not starting with '.' or '-'.
/// Anything else could name a path outside the state directory.
bool IsValidSampleId(const std::string& id);

}  // namespace aggscan::layout
