// One GPIO line through libgpiod v1 (Debian 12's libgpiod 1.6): the chip
// looked up by name, path, number or label, the line by offset or name, and
// the request, with every failure classified and naming the config section.
#pragma once

#include <memory>
#include <string>

#include "common/error.h"
#include "config/config.h"

struct gpiod_chip;
struct gpiod_line;

namespace aggscan::gpio {

enum class LineUse { kBothEdges, kOutput };

/// A requested line; releases the line and closes the chip on destruction.
class GpioLine {
 public:
  /// Opens `config.chip`, finds `config.line` and requests it for `use` as
  /// `consumer`. `section` ("[button.gpio]") is named in error messages.
  /// Bias applies to inputs; active_low is left to the caller (edges and
  /// levels here are raw).
  static Result<std::unique_ptr<GpioLine>> Open(const GpioLineConfig& config, LineUse use,
                                                const std::string& consumer,
                                                const std::string& section);
  ~GpioLine();
  GpioLine(const GpioLine&) = delete;
  GpioLine& operator=(const GpioLine&) = delete;

  gpiod_line* line() const { return line_; }
  /// "line 3 ('start') of gpiochip1 [gpio-sim.0-node0]".
  const std::string& name() const { return name_; }

 private:
  GpioLine() = default;
  gpiod_chip* chip_ = nullptr;
  gpiod_line* line_ = nullptr;
  bool requested_ = false;
  std::string name_;
};

}  // namespace aggscan::gpio
