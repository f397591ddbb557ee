#include "drivers/usb/tic_protocol.h"

#include <cmath>

namespace aggscan::tic {

const char* ProductName(uint16_t product_id) {
  for (const Product& p : kProducts)
    if (p.id == product_id) return p.name;
  return nullptr;
}

std::optional<uint8_t> StepModeCode(int microsteps) {
  switch (microsteps) {
    case 1:
      return 0;
    case 2:
      return 1;
    case 4:
      return 2;
    case 8:
      return 3;
    case 16:
      return 4;
    case 32:
      return 5;
    case 64:
      return 7;
    case 128:
      return 8;
    case 256:
      return 9;
    default:
      return std::nullopt;
  }
}

namespace {

// A platter rate (per degree) in the Tic's units, or kInvalidConfig naming
// the config key when it is outside [lo, hi].
Result<uint32_t> TicUnits(double per_deg, double steps_per_rev, double units_per_step, double lo,
                          double hi, const char* key, const char* range) {
  const double v = std::round(per_deg * steps_per_rev / 360.0 * units_per_step);
  if (!(v >= lo && v <= hi)) {
    return MakeError(ErrorClass::kInvalidConfig,
                     std::string("turntable.") + key + " " + std::to_string(per_deg) + " at " +
                         std::to_string(steps_per_rev) + " microsteps/rev is outside the Tic's " +
                         range + "; change " + key + " or the microstepping");
  }
  return static_cast<uint32_t>(v);
}

}  // namespace

Result<uint32_t> SpeedUnits(double deg_per_s, double steps_per_rev) {
  return TicUnits(deg_per_s, steps_per_rev, kSpeedUnitsPerStepPerS, 1, kMaxSpeedLimit,
                  "max_speed_deg_s", "speed range (up to 50000 microsteps/s)");
}

Result<uint32_t> AccelUnits(double deg_per_s2, double steps_per_rev) {
  return TicUnits(deg_per_s2, steps_per_rev, kAccelUnitsPerStepPerS2, kMinAccelLimit,
                  kMaxAccelLimit, "accel_deg_s2",
                  "acceleration range (1 to 21474836 microsteps/s^2)");
}

Result<Variables> ParseVariables(std::span<const uint8_t> b) {
  if (b.size() < static_cast<size_t>(kStatusBlockSize)) {
    return MakeError(ErrorClass::kDeviceFault, "the Tic answered the variable read with " +
                                                   std::to_string(b.size()) + " bytes, expected " +
                                                   std::to_string(kStatusBlockSize) +
                                                   " — is this a Tic with current firmware?");
  }
  Variables v;
  v.operation_state = b[kVarOperationState];
  switch (v.operation_state) {
    case kStateReset:
    case kStateDeenergized:
    case kStateSoftError:
    case kStateWaitingForErrLine:
    case kStateStartingUp:
    case kStateNormal:
      break;
    default:
      return MakeError(ErrorClass::kDeviceFault,
                       "the Tic reported operation state " + std::to_string(v.operation_state) +
                           ", which the Tic user's guide does not define — is this a Tic?");
  }
  v.misc_flags = b[kVarMiscFlags1];
  v.error_status = static_cast<uint16_t>(b[kVarErrorStatus] | (b[kVarErrorStatus + 1] << 8));
  v.errors_occurred = ReadU32(b, kVarErrorsOccurred);
  v.planning_mode = b[kVarPlanningMode];
  v.target_position = static_cast<int32_t>(ReadU32(b, kVarTargetPosition));
  v.max_speed = ReadU32(b, kVarMaxSpeed);
  v.max_decel = ReadU32(b, kVarMaxDecel);
  v.max_accel = ReadU32(b, kVarMaxAccel);
  v.current_position = static_cast<int32_t>(ReadU32(b, kVarCurrentPosition));
  v.current_velocity = static_cast<int32_t>(ReadU32(b, kVarCurrentVelocity));
  return v;
}

std::string ErrorStatusText(uint16_t error_status) {
  static const char* const kNames[] = {"intentionally de-energized",
                                       "motor driver error",
                                       "low VIN",
                                       "kill switch active",
                                       "required input invalid",
                                       "serial error",
                                       "command timeout",
                                       "safe start violation",
                                       "ERR line high"};
  std::string s;
  for (int bit = 0; bit < 16; ++bit) {
    if (!((error_status >> bit) & 1u)) continue;
    if (!s.empty()) s += ", ";
    s += bit < static_cast<int>(std::size(kNames)) ? kNames[bit]
                                                   : "error bit " + std::to_string(bit);
  }
  return s.empty() ? "none" : s;
}

const char* OperationStateName(uint8_t state) {
  switch (state) {
    case kStateReset:
      return "reset";
    case kStateDeenergized:
      return "de-energized";
    case kStateSoftError:
      return "soft error";
    case kStateWaitingForErrLine:
      return "waiting for ERR line";
    case kStateStartingUp:
      return "starting up";
    case kStateNormal:
      return "normal";
    default:
      return "unknown";
  }
}

}  // namespace aggscan::tic
