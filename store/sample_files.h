// The two per-side capture files of a sample (store/layout.h), as typed
// records that every writer and reader goes through:
//
//   ViewSidecar   side<N>/view_NNN.json   one view: angles, timestamps, camera settings
//   SideManifest  side<N>/manifest.json   written last: the side's complete views
//
// Each carries "schema" (kSampleFilesSchema). A file without it was written
// before these files carried a version and reads as version 1, which has the
// same fields; a newer version is refused. FromJson checks the type of every
// field present and names the file and the field when a required one is
// missing or a field has the wrong type. Keys a struct does not know (a newer
// or an older writer's) are kept in `extra` and written back by ToJson, so a
// FromJson -> ToJson round trip loses nothing.
//
// Which fields are optional follows what the writers set: the daemon
// (daemon/capture_service.cpp) writes every sidecar field below except
// `missing_controls` (only when a camera lacks a control); sidecars written by
// hand or by tests often carry no more than view and the angles, so only
// `view` is required there. A reader that needs a field (the calibration and
// the empty-turntable photos need measured_angle_deg) checks it and says so.
#pragma once

#include <cstdint>
#include <nlohmann/json.hpp>
#include <optional>
#include <string>
#include <vector>

#include "common/error.h"
#include "common/json_io.h"

namespace aggscan {

/// The schema version this release writes (1: the same fields, no "schema").
inline constexpr int kSampleFilesSchema = 2;

// --- side<N>/view_NNN.json -------------------------------------------------

struct ViewSidecar {
  int view = 0;                      // required: 0-based index within the side
  std::optional<int> side;           // 1-based
  std::optional<std::string> image;  // the photo, a file name in the side directory
  std::optional<std::string> sample_id;
  // Turntable angles (degrees): the one asked for and the one the encoder read.
  std::optional<double> commanded_angle_deg, measured_angle_deg;
  // Daemon monotonic clock (ns): when the view was due, triggered, exposed.
  std::optional<int64_t> due_monotonic_ns, trigger_monotonic_ns, capture_monotonic_ns;
  std::optional<std::string> capture_utc;   // "2026-12-06T16:18:51.005Z"
  std::optional<double> schedule_error_ms;  // exposure start - due time (may be negative)
  std::optional<bool> schedule_overrun;     // more than the tolerance late
  // Settings in effect for the frame, as read back from the camera.
  std::optional<double> exposure_us, gain, wb_red, wb_blue;
  std::optional<std::string> camera_id, camera_backend;
  std::optional<int> width, height;        // of the photo as the camera delivered it
  std::optional<uint64_t> frame_sequence;  // the driver's frame counter
  std::optional<double> time_scale;        // the sim clock's speed-up (1 on a real rig)
  // Locked settings the camera has no control for; empty (and not written)
  // when every setting was applied.
  std::vector<std::string> missing_controls;
  nlohmann::json extra = nlohmann::json::object();

  nlohmann::json ToJson() const;
  static Result<ViewSidecar> FromJson(const nlohmann::json& j, const jsonio::Source& src);
};

// --- side<N>/manifest.json -------------------------------------------------

struct SideManifest {
  struct Entry {
    int view = 0;       // required, >= 0, unique within the manifest
    std::string image;  // required: a plain file name in the side directory
    // The view's sidecar, a plain file name in the side directory. The store
    // always writes it; a manifest without it (hand-made, tests) reads as
    // nullopt, and a reader that needs one says so (or falls back to
    // layout::ViewSidecarName(view)).
    std::optional<std::string> sidecar;
    std::optional<int64_t> bytes;  // the image's size when the manifest was written
    nlohmann::json extra = nlohmann::json::object();

    nlohmann::json ToJson() const;
    static Result<Entry> FromJson(const nlohmann::json& j, const jsonio::Source& src);
  };

  int side = 1;                              // required, >= 1
  std::optional<std::string> sample_id;      // the store always writes it
  std::optional<std::string> completed_utc;  // the store always writes it
  std::vector<Entry> views;                  // required (may be empty); capture order
  nlohmann::json extra = nlohmann::json::object();

  nlohmann::json ToJson() const;
  static Result<SideManifest> FromJson(const nlohmann::json& j, const jsonio::Source& src);
};

/// What names the files in errors (jsonio::Source::what).
inline constexpr const char* kViewSidecarWhat = "view sidecar";
inline constexpr const char* kSideManifestWhat = "side manifest";

/// Reads side_dir/view_NNN.json: kNotFound when absent, kCorrupt naming the
/// file (and the field) when it does not parse or its "view" is not `view`.
Result<ViewSidecar> ReadViewSidecar(const std::string& side_dir, int view);
/// The same for a sidecar named by its path (a manifest entry's sidecar),
/// without the check of the view index.
Result<ViewSidecar> ReadViewSidecarFile(const std::string& path);
/// Reads side_dir/manifest.json: kNotFound when absent (the side is not
/// complete), kCorrupt naming the file and the field when it does not parse.
Result<SideManifest> ReadSideManifest(const std::string& side_dir);

}  // namespace aggscan
