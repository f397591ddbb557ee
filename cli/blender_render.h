// A second renderer for validation: the views of a simulated capture redrawn
// by Blender's Cycles path tracer (Debian's `blender`, CPU, headless, driven
// by scripts/blender/render_capture.py), so that accuracy is measured on
// photos the sim rig did not make: real soft and hard shadows,
// interreflection, other discs, floors, lights and stones, and object markers
// drawn as a person draws them with coloured pencils.
//
// How: the sim capture runs as usual (the real capture service, the sim
// turntable's errors, the flip, every sidecar and manifest) with its truth;
// then every view's photo is rendered again by Blender from that view's true
// rock and platter pose, and replaces the sim's photo (JPEG at the config's
// quality; the side manifests' byte counts follow). The renderer's own
// silhouette of the rock (Cycles' object index pass) replaces the truth mask,
// and truth.json records the renderer, the look and the seconds per frame.
// The sim's lens distortion must be off in such a capture: Blender draws a
// pinhole camera.
#pragma once

#include <cstdint>
#include <nlohmann/json.hpp>
#include <ostream>
#include <string>
#include <vector>

#include "common/error.h"

namespace aggscan {

/// What the rig stands on and in: the variety a quarry brings.
struct BlenderLook {
  std::string surface = "light-grey";  // white | light-grey | wood | rubber-mat | gravel
  std::string light = "softbox";       // softbox | two-lights | overcast | low-sun
  std::string stone = "granite";       // granite | dolomite | basalt | wet
  uint64_t seed = 1;                   // texture offsets, light placement, pencil strokes

  std::string Name() const { return surface + "/" + light + "/" + stone; }
  nlohmann::json ToJson() const;
};

const std::vector<std::string>& BlenderSurfaces();
const std::vector<std::string>& BlenderLights();
const std::vector<std::string>& BlenderStones();

/// "surface=wood,light=low-sun,stone=dolomite" (any subset; the rest default).
/// kInvalidArgument naming the unknown key or value and the known ones.
Result<BlenderLook> ParseBlenderLook(const std::string& spec);

/// The i-th look of a batch: surfaces and lights cycled (5 and 4 values), so
/// 20 rocks see every pairing; stones laid out so that the first 10 have every
/// stone, basalt on the rubber mat and dolomite on wood among them.
BlenderLook BatchLook(int i, uint64_t seed);

struct BlenderOptions {
  std::string blender = "blender";  // the program (PATH lookup)
  std::string script;               // render_capture.py; empty: BlenderScriptPath()
  int samples = 16;                 // Cycles samples per pixel
  int threads = 0;                  // render threads (0: all cores)
  double frame_timeout_s = 600;     // per frame; the whole run gets frames x this + 120 s
  // Also render side 1's views with the rock taken away (the disc at those
  // angles, same lights and exposure) as the sample's empty-turntable photos
  // (SAMPLE/empty/, store/empty_turntable.h): the worker's masks take them as
  // their background, and `aggscan masks train --backgrounds` composites the
  // rig's own rocks onto them.
  bool empty_plates = false;
  // Take the path tracer's noise out and a camera's in (scripts/blender/
  // denoise.py): at a few samples per pixel a soft shadow's penumbra is far
  // noisier than any camera's photo of it.
  bool denoise = true;
};

/// The render script: $AGGSCAN_BLENDER_SCRIPT, else the installed copy next
/// to the executable (../share/aggscan/blender/), else the source tree's.
std::string BlenderScriptPath();

/// True when `blender` can be run (for tests that skip without it).
bool BlenderAvailable(const BlenderOptions& o = {});

struct BlenderRenderReport {
  std::string renderer;  // "blender 3.4.1 cycles cpu"
  int frames = 0;
  double mean_frame_s = 0, max_frame_s = 0;
  double wall_s = 0;  // the whole Blender run (start-up, scene build, exposure probe, frames)
  // The renderer's silhouettes against the sim's for the same poses: a check
  // that camera, poses and mesh were carried over exactly (rock scenes only).
  double silhouette_iou_min = 0, silhouette_iou_mean = 0;
  nlohmann::json ToJson() const;
};

/// Re-renders every view of the simulated sample in `sample_dir` (written by
/// `aggscan sim capture` with truth) with Blender in `look`, in place. The
/// Blender scene and its log go to `sample_dir`/blender/. Errors name what is
/// wrong: no truth, lens distortion on, Blender missing or failing (with the
/// tail of its log), a frame missing.
Result<BlenderRenderReport> RerenderWithBlender(const std::string& sample_dir,
                                                const BlenderLook& look, const BlenderOptions& opts,
                                                std::ostream& log);

}  // namespace aggscan
