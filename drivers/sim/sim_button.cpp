#include "drivers/sim/sim_button.h"

namespace aggscan::sim {

SimButton::SimButton(Clock& clock, const ButtonConfig& config) : Button(clock, config.debounce) {}

}  // namespace aggscan::sim
