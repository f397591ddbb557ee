// Simulated start button: no hardware to watch; presses come from software
// (the HTTP API, the CLI, tests) through InjectPress()/Press() and take the
// same debounced path as a hardware press.
#pragma once

#include <string>

#include "common/clock.h"
#include "config/config.h"
#include "drivers/button.h"

namespace aggscan::sim {

class SimButton final : public Button {
 public:
  /// `clock` must outlive the button.
  SimButton(Clock& clock, const ButtonConfig& config);

  /// One press from the simulated operator (source "sim").
  void Press() { InjectPress("sim"); }
  std::string Describe() const override {
    return "sim button (presses from the API, CLI or tests)";
  }

 protected:
  Status DoStart() override { return OkStatus(); }
  void DoStop() override {}
};

}  // namespace aggscan::sim
