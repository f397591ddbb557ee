// CPU renderer of the sim world: what the rig camera would see.
//
// Method (one core, no GPU):
//  1. The rock is rasterized into a visibility buffer (triangle id + 1/z) in
//     undistorted pixel space, with integer edge functions, bounding-box
//     clipping to the rock's screen rectangle and back-face culling.
//  2. The rock is rasterized again from the key light (orthographic) into a
//     shadow map; its coverage, box-blurred, is the soft shadow on the disc
//     and table, its depth gives the rock's self-shadowing.
//  3. Every output pixel (distorted) is mapped through a radial lookup table
//     (computed once per resolution) to its undistorted ray: rock pixels take
//     the triangle from the visibility buffer and are shaded at the exact
//     ray/triangle intersection with the procedural texture; other pixels are
//     ray-cast against the disc (with its labels and ArUco markers), its rim and the table.
//     Shading the distorted pixels directly is the same as rendering an
//     undistorted image and remapping it, without the resampling blur.
//  4. Exposure (exposure_us * gain relative to the reference), white balance,
//     sRGB tone curve, Gaussian sensor noise (deterministic per seed).
#pragma once

#include <cstdint>
#include <memory>
#include <vector>

#include "drivers/sim/world.h"

namespace aggscan::sim {

/// Exposure settings a frame is taken with.
struct ExposureSettings {
  double exposure_us = 8000.0;
  double gain = 1.0;
  double wb_red = 1.0;
  double wb_blue = 1.0;
};

struct RenderOptions {
  ExposureSettings exposure;
  uint64_t noise_seed = 0;  // sensor noise stream; same seed -> same image
  bool want_mask = false;   // also produce the ground-truth rock mask
};

struct RenderedImage {
  int width = 0;
  int height = 0;
  std::vector<uint8_t> rgb;   // width*height*3, row-major, RGB8
  std::vector<uint8_t> mask;  // width*height, 255 = rock (markers included); empty unless asked
};

/// Renders frames of one world at one resolution; keeps its lookup tables and
/// scratch buffers between frames. Not thread-safe: one per thread. The world
/// must outlive it.
class Renderer {
 public:
  Renderer(const SimWorld& world, int width, int height);
  ~Renderer();
  Renderer(const Renderer&) = delete;
  Renderer& operator=(const Renderer&) = delete;

  /// Renders side (1-based) at the platter angle (degrees about +z).
  RenderedImage Render(int side, double platter_deg, const RenderOptions& options);
  /// Same, reusing `out`'s storage.
  void RenderInto(int side, double platter_deg, const RenderOptions& options, RenderedImage* out);

  /// Moves the camera (world -> camera; the world's own pose until called):
  /// a camera walked round a still rock. The next frame is drawn whole.
  void SetCamera(const Rigid& world_to_camera);
  const Rigid& camera() const { return w2c_; }

  const Intrinsics& intrinsics() const { return intr_; }
  int width() const { return intr_.width; }
  int height() const { return intr_.height; }

 private:
  struct Impl;
  void BuildBoardTexture(const SimBoard& board);
  void BuildArucoTexture(const SimArucoMarker& marker);

  const SimWorld& world_;
  Intrinsics intr_;
  Rigid w2c_;
  std::unique_ptr<Impl> impl_;
};

/// One-shot render at the world's configured resolution.
RenderedImage Render(const SimWorld& world, int side, double platter_deg,
                     const ExposureSettings& exposure, uint64_t noise_seed, bool want_mask = false);

}  // namespace aggscan::sim
