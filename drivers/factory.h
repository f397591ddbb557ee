// Explicit factory: picks each device backend from the config.
#pragma once

#include <memory>

#include "common/clock.h"
#include "common/error.h"
#include "config/config.h"
#include "drivers/button.h"
#include "drivers/camera.h"
#include "drivers/status_light.h"
#include "drivers/turntable.h"

namespace aggscan {

namespace sim {
class SimWorld;
}

struct RigDevices {
  std::shared_ptr<sim::SimWorld> world;  // set when any backend is "sim"
  /// The sim camera with sim.board_image set: the board lying on the disc
  /// instead of the rock, drawn for calibration captures.
  std::shared_ptr<sim::SimWorld> board_world;
  std::unique_ptr<Camera> camera;
  std::unique_ptr<Turntable> turntable;
  std::unique_ptr<Button> button;
  std::unique_ptr<StatusLight> light;  // null when [light] backend = "none"
};

/// Creates (does not open) the devices named by the config. Unknown backend
/// names are a kInvalidConfig error listing the known ones.
Result<RigDevices> CreateRig(const Config& config, Clock& clock);

/// The camera settings of [camera] (size, JPEG quality, locked exposure, gain
/// and white balance), as the daemon configures the camera at open.
CameraSettings CameraSettingsFor(const Config& config);

}  // namespace aggscan
