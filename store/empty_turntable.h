// Photos of the empty turntable: the disc, its labels, the floor and the
// lights of the place, shot by the rig with nothing on the disc at the
// angles it shoots rocks at. The masks take them as their background, pixel
// by pixel (pipeline/masks/mask.h): what differs from the empty disc at the same
// angle is the rock or its shadow, whatever the disc and floor look like.
//
// A set is one captured side of an empty turntable, installed for the rig:
//
//   <state_dir>/empty-turntable/<set id>/view_NNN.jpg   the photos, as captured
//   <state_dir>/empty-turntable/<set id>/manifest.json  written last (format below)
//   <state_dir>/empty-turntable/current.json            {"set": "<set id>"}: the set in use
//
// Installed sets are never changed or removed; a new one becomes current.
// When a sample is armed, the current set is linked into it (hard links, or
// copies where the filesystem has none) as SAMPLE/empty/, so that the sample
// keeps the photos it was shot against whatever is installed later.
//
// manifest.json: {"format": "aggscan-empty-turntable-1", "set": ID,
//   "source": where the photos came from, "captured_utc": ..., "width": W,
//   "height": H, "views": [{"image": "view_000.jpg", "angle_deg": 0.0}, ...]}
#pragma once

#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "common/error.h"

namespace aggscan {

struct EmptyTurntableView {
  std::string image;       // file name in the set's directory
  double angle_deg = 0.0;  // the turntable's measured angle when it was shot
};

struct EmptyTurntableSet {
  std::string id;             // directory name under <state_dir>/empty-turntable
  std::string source;         // e.g. the sample directory and side it was installed from
  std::string captured_utc;   // when its side was captured
  int width = 0, height = 0;  // photo size, pixels
  std::vector<EmptyTurntableView> views;

  nlohmann::json ToJson() const;
  /// kCorrupt naming `what` and the field that is wrong.
  static Result<EmptyTurntableSet> FromJson(const nlohmann::json& j, const std::string& what);

  /// The view shot nearest to `angle_deg` (angles taken modulo 360) and its
  /// distance in degrees; nullptr when the set has no view.
  const EmptyTurntableView* Nearest(double angle_deg, double* distance_deg) const;
};

std::string EmptyTurntableRoot(const std::string& state_dir);

/// The set in a directory (its manifest.json): kNotFound when there is none,
/// kCorrupt when it does not parse or names a photo that is not there.
Result<EmptyTurntableSet> LoadEmptyTurntableSet(const std::string& dir);

/// The rig's current set, or kNotFound when none is installed.
Result<EmptyTurntableSet> CurrentEmptyTurntableSet(const std::string& state_dir);

/// Installs side `side` of a captured sample (every view's photo and its
/// sidecar's measured angle; `width` x `height`: the photos' size, which the
/// caller has checked) as a new set and makes it current. Errors name what is
/// missing: kNotFound (no such side or no manifest: the side is not
/// complete), kInvalidArgument (a view without a measured angle).
Result<EmptyTurntableSet> InstallEmptyTurntableSet(const std::string& state_dir,
                                                   const std::string& sample_dir, int side,
                                                   int width, int height);

/// Writes a set into `dir` (created): `photos` are the JPEG files to copy in,
/// one per view of `set` in order; the manifest last. Used by the install and
/// by the validation renderer, which makes a sample's own SAMPLE/empty/.
Status WriteEmptyTurntableSet(const std::string& dir, const EmptyTurntableSet& set,
                              const std::vector<std::string>& photos);

/// Links the rig's current set into `sample_dir`/empty (hard links, copies
/// where that fails) unless the sample has one already. Returns what to
/// record in sample.json: {"set", "captured_utc", "views"} or, where there is
/// no usable set, {"set": null, "reason": ...}.
nlohmann::json LinkEmptyTurntableSet(const std::string& state_dir, const std::string& sample_dir);

}  // namespace aggscan
