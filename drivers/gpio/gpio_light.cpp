#include "drivers/gpio/gpio_light.h"

#include <gpiod.h>

#include <cerrno>
#include <cstring>

namespace aggscan::gpio {

Status GpioLight::DoOpen() {
  Result<std::unique_ptr<GpioLine>> l =
      GpioLine::Open(config_, LineUse::kOutput, "aggscan-light", "[light.gpio]");
  if (!l) return l.error();
  line_ = std::move(*l);
  return OkStatus();
}

Status GpioLight::DoSet(bool on) {
  if (!line_) return MakeError(ErrorClass::kInvalidState, "GPIO light is not open");
  if (gpiod_line_set_value(line_->line(), on != config_.active_low ? 1 : 0) != 0) {
    return MakeError(ErrorClass::kDisconnected,
                     "cannot set GPIO " + line_->name() + "; check [light.gpio]",
                     std::strerror(errno));
  }
  return OkStatus();
}

}  // namespace aggscan::gpio
