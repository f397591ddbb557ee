// Sim photos for the mask tests: a procedural rock's world rendered at the
// rig's 2016 x 1512 and passed through JPEG (quality 92), as the capture
// stores them, with the renderer's ground-truth mask.
#pragma once

#include <cstdint>
#include <memory>
#include <opencv2/core.hpp>

#include "common/error.h"
#include "drivers/sim/render.h"
#include "drivers/sim/world.h"

namespace aggscan::testing {

struct SimPhoto {
  cv::Mat bgr, truth;  // CV_8UC3 photo after JPEG; CV_8UC1 0/255 truth mask
};

class SimPhotos {
 public:
  /// The default config's world for procedural rock `seed`.
  static Result<SimPhotos> Create(uint64_t seed);
  /// Side `side` with the platter at `angle` deg; sensor noise seeded per side.
  SimPhoto Render(int side, double angle);

 private:
  uint64_t seed_ = 0;
  std::shared_ptr<sim::SimWorld> world_;
  std::unique_ptr<sim::Renderer> renderer_;
};

}  // namespace aggscan::testing
