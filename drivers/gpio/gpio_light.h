// Status light on a GPIO output line (light backend "gpio"), through libgpiod v1.
#pragma once

#include <memory>
#include <string>

#include "config/config.h"
#include "drivers/gpio/gpio_line.h"
#include "drivers/status_light.h"

namespace aggscan::gpio {

class GpioLight final : public StatusLight {
 public:
  explicit GpioLight(const GpioLineConfig& config) : config_(config) {}
  ~GpioLight() override { Close(); }
  std::string Describe() const override {
    return "GPIO light, line " + config_.line + " of chip " + config_.chip;
  }

 protected:
  Status DoOpen() override;
  Status DoSet(bool on) override;
  void DoClose() override { line_.reset(); }

 private:
  const GpioLineConfig config_;
  std::unique_ptr<GpioLine> line_;
};

}  // namespace aggscan::gpio
