#include "drivers/gpio/gpio_line.h"

#include <gpiod.h>

#include <cerrno>
#include <cstring>

namespace aggscan::gpio {
namespace {

bool AllDigits(const std::string& s) {
  return !s.empty() && s.find_first_not_of("0123456789") == std::string::npos;
}

int BiasFlag(const std::string& bias) {
  if (bias == "pull-up") return GPIOD_LINE_REQUEST_FLAG_BIAS_PULL_UP;
  if (bias == "pull-down") return GPIOD_LINE_REQUEST_FLAG_BIAS_PULL_DOWN;
  if (bias == "disable") return GPIOD_LINE_REQUEST_FLAG_BIAS_DISABLE;
  return 0;  // as-is
}

}  // namespace

GpioLine::~GpioLine() {
  if (requested_) gpiod_line_release(line_);
  if (chip_) gpiod_chip_close(chip_);
}

Result<std::unique_ptr<GpioLine>> GpioLine::Open(const GpioLineConfig& config, LineUse use,
                                                 const std::string& consumer,
                                                 const std::string& section) {
  std::unique_ptr<GpioLine> g(new GpioLine());
  // gpiod_chip_open_lookup tries the argument as a path, a name, a label and
  // a number, in that order.
  g->chip_ = gpiod_chip_open_lookup(config.chip.c_str());
  if (!g->chip_) {
    const int err = errno;
    if (err == EACCES || err == EPERM) {
      return MakeError(ErrorClass::kDeviceMissing,
                       "GPIO chip '" + config.chip +
                           "' cannot be opened: permission denied; run "
                           "aggscand in a group that may use /dev/gpiochip* (gpio)",
                       std::strerror(err));
    }
    return MakeError(ErrorClass::kDeviceMissing,
                     "no GPIO chip '" + config.chip + "' (name, path, number or label); check " +
                         section + " chip (gpiodetect lists the chips)",
                     std::strerror(err));
  }
  const std::string chip_desc =
      std::string(gpiod_chip_name(g->chip_)) + " [" + gpiod_chip_label(g->chip_) + "]";
  const unsigned n = gpiod_chip_num_lines(g->chip_);
  if (AllDigits(config.line)) {
    const unsigned long offset = std::stoul(config.line);
    if (offset >= n) {
      return MakeError(ErrorClass::kDeviceMissing,
                       "GPIO chip " + chip_desc + " has " + std::to_string(n) + " lines; no line " +
                           config.line + "; check " + section + " line (gpioinfo lists them)");
    }
    g->line_ = gpiod_chip_get_line(g->chip_, static_cast<unsigned>(offset));
  } else {
    g->line_ = gpiod_chip_find_line(g->chip_, config.line.c_str());
    if (!g->line_) {
      return MakeError(ErrorClass::kDeviceMissing, "GPIO chip " + chip_desc + " has no line '" +
                                                       config.line + "'; check " + section +
                                                       " line (gpioinfo lists the names)");
    }
  }
  if (!g->line_) {
    return MakeError(ErrorClass::kIo,
                     "cannot read line " + config.line + " of GPIO chip " + chip_desc,
                     std::strerror(errno));
  }
  const char* line_name = gpiod_line_name(g->line_);
  g->name_ = "line " + std::to_string(gpiod_line_offset(g->line_)) +
             (line_name && *line_name ? std::string(" ('") + line_name + "')" : std::string()) +
             " of " + chip_desc;

  int rc = 0;
  if (use == LineUse::kBothEdges) {
    rc = gpiod_line_request_both_edges_events_flags(g->line_, consumer.c_str(),
                                                    BiasFlag(config.bias));
  } else {
    rc = gpiod_line_request_output(g->line_, consumer.c_str(), config.active_low ? 1 : 0);
  }
  if (rc != 0) {
    const int err = errno;
    if (err == EBUSY) {
      gpiod_line_update(g->line_);
      const char* user = gpiod_line_consumer(g->line_);
      return MakeError(ErrorClass::kConflict,
                       "GPIO " + g->name_ + " is busy (used by '" + (user ? user : "?") +
                           "'); stop that user or pick another line in " + section,
                       std::strerror(err));
    }
    if (err == EINVAL && BiasFlag(config.bias) != 0) {
      return MakeError(ErrorClass::kInvalidConfig,
                       "GPIO " + g->name_ + " does not take bias '" + config.bias + "'; set " +
                           section + " bias = \"as-is\" and fit a resistor",
                       std::strerror(err));
    }
    return MakeError(ErrorClass::kDeviceFault, "cannot request GPIO " + g->name_,
                     std::strerror(err));
  }
  g->requested_ = true;
  return g;
}

}  // namespace aggscan::gpio
