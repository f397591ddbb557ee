// The Pololu Tic stepper controller's native USB protocol: the constants, the
// variable block's layout and the unit conversions, without any USB I/O (the
// backend in usb_tic_turntable.* and the test gadget both use it).
//
// Source of every fact here: the "Tic Stepper Motor Controller User's Guide"
// (Pololu document 0J71, https://www.pololu.com/docs/0J71), cited by section.
#pragma once

#include <cstddef>
#include <cstdint>
#include <optional>
#include <span>
#include <string>

#include "common/error.h"

namespace aggscan::tic {

// USB IDs: Pololu's vendor ID 0x1FFB and one product ID per model, as
// Pololu's own software matches them (pololu-tic-software,
// include/tic_protocol.h, TIC_VENDOR_ID / TIC_PRODUCT_ID_*).
inline constexpr uint16_t kVendorId = 0x1FFB;
struct Product {
  uint16_t id;
  const char* name;
};
inline constexpr Product kProducts[] = {
    {0x00B3, "Tic T825"}, {0x00B5, "Tic T834"}, {0x00BD, "Tic T500"},
    {0x00C3, "Tic N825"}, {0x00C9, "Tic T249"}, {0x00CB, "Tic 36v4"},
};
/// The model name for a product ID, or nullptr when it is not a Tic.
const char* ProductName(uint16_t product_id);
/// The Tic's native USB interface is interface 0 (pololu-tic-software opens
/// interface 0; the others are its CDC serial port). Commands themselves are
/// vendor control transfers on endpoint 0 (section 11).
inline constexpr int kNativeInterface = 0;

// Section 11: "All of the Tic's USB commands are implemented as vendor-defined
// control transfers on endpoint 0" -- quick / 7-bit write / 32-bit write
// (data[15:0] in wValue, data[31:16] in wIndex) are host-to-device vendor
// requests to the device, block reads device-to-host (wIndex = offset,
// wLength = 1..128).
inline constexpr uint8_t kRequestTypeOut = 0x40;
inline constexpr uint8_t kRequestTypeIn = 0xC0;
inline constexpr int kMaxBlockRead = 128;

// Section 8 "Command reference": command bytes (bRequest on USB).
enum Command : uint8_t {
  kCmdSetTargetPosition = 0xE0,  // 32-bit write, microsteps
  kCmdSetTargetVelocity = 0xE3,  // 32-bit write, microsteps / 10000 s
  kCmdHaltAndSetPosition =
      0xEC,                // 32-bit write: abrupt stop, position := value, clears "uncertain"
  kCmdHaltAndHold = 0x89,  // quick: abrupt stop, sets "position uncertain"
  kCmdGoHome = 0x97,       // 7-bit write: 0 = reverse, 1 = forward
  kCmdResetCommandTimeout = 0x8C,  // quick
  kCmdDeenergize = 0x86,           // quick
  kCmdEnergize = 0x85,             // quick
  kCmdExitSafeStart = 0x83,        // quick
  kCmdEnterSafeStart = 0x8F,       // quick
  kCmdReset = 0xB0,                // quick: forget the current state (as after power-up)
  kCmdClearDriverError = 0x8A,     // quick
  kCmdSetMaxSpeed = 0xE6,          // 32-bit write, microsteps / 10000 s
  kCmdSetStartingSpeed = 0xE5,     // 32-bit write, microsteps / 10000 s
  kCmdSetMaxAccel = 0xEA,          // 32-bit write, microsteps / 100 s^2
  kCmdSetMaxDecel = 0xE9,          // 32-bit write, microsteps / 100 s^2
  kCmdSetStepMode = 0x94,          // 7-bit write
  kCmdGetVariable = 0xA1,          // block read of the variables
};

// Section 7 "Variable reference": offsets in the variable block (little-endian).
inline constexpr int kVarOperationState = 0x00;   // u8
inline constexpr int kVarMiscFlags1 = 0x01;       // u8
inline constexpr int kVarErrorStatus = 0x02;      // u16: errors stopping the motor now
inline constexpr int kVarErrorsOccurred = 0x04;   // u32
inline constexpr int kVarPlanningMode = 0x09;     // u8: 0 off, 1 target position, 2 target velocity
inline constexpr int kVarTargetPosition = 0x0A;   // i32, microsteps
inline constexpr int kVarTargetVelocity = 0x0E;   // i32
inline constexpr int kVarStartingSpeed = 0x12;    // u32
inline constexpr int kVarMaxSpeed = 0x16;         // u32, microsteps / 10000 s
inline constexpr int kVarMaxDecel = 0x1A;         // u32, microsteps / 100 s^2
inline constexpr int kVarMaxAccel = 0x1E;         // u32, microsteps / 100 s^2
inline constexpr int kVarCurrentPosition = 0x22;  // i32, microsteps
inline constexpr int kVarCurrentVelocity = 0x26;  // i32, microsteps / 10000 s
/// The backend reads offsets 0x00 up to (not including) this in one request:
/// everything through the current velocity.
inline constexpr int kStatusBlockSize = 0x2A;

// Section 7, "Operation state" values (section 5.4 describes them).
enum OperationState : uint8_t {
  kStateReset = 0,
  kStateDeenergized = 2,
  kStateSoftError = 4,
  kStateWaitingForErrLine = 6,
  kStateStartingUp = 8,
  kStateNormal = 10,
};
// Section 7, "Misc flags 1" bits.
inline constexpr uint8_t kFlagEnergized = 1u << 0;
inline constexpr uint8_t kFlagPositionUncertain = 1u << 1;
inline constexpr uint8_t kFlagForwardLimitActive = 1u << 2;
inline constexpr uint8_t kFlagReverseLimitActive = 1u << 3;
inline constexpr uint8_t kFlagHomingActive = 1u << 4;
// Section 7, "Error status" bits (section 5.4 describes each error).
enum ErrorBit : int {
  kErrIntentionallyDeenergized = 0,
  kErrMotorDriver = 1,
  kErrLowVin = 2,
  kErrKillSwitch = 3,
  kErrRequiredInputInvalid = 4,
  kErrSerial = 5,
  kErrCommandTimeout = 6,
  kErrSafeStartViolation = 7,
  kErrErrLineHigh = 8,
};
inline constexpr int kPlanningTargetPosition = 1;

// Section 8, "Set step mode" data values: 0 = full step, 1 = 1/2, 2 = 1/4,
// 3 = 1/8, 4 = 1/16, 5 = 1/32 (all models), 7 = 1/64, 8 = 1/128, 9 = 1/256
// (Tic 36v4 only).
/// The step mode code for a microstep factor, or nullopt when no Tic has it.
std::optional<uint8_t> StepModeCode(int microsteps);

// Section 7/8 units: speeds in microsteps per 10000 s, accelerations in
// microsteps per 100 s^2; limits from the "Set max speed" and "Set max
// acceleration" commands (section 8).
inline constexpr double kSpeedUnitsPerStepPerS = 10000.0;
inline constexpr double kAccelUnitsPerStepPerS2 = 100.0;
inline constexpr uint32_t kMaxSpeedLimit = 500'000'000;
inline constexpr uint32_t kMinAccelLimit = 100;
inline constexpr uint32_t kMaxAccelLimit = 0x7FFFFFFF;

/// The Tic's speed value for a platter speed, or kInvalidConfig naming
/// turntable.max_speed_deg_s when it is outside what the Tic accepts.
Result<uint32_t> SpeedUnits(double deg_per_s, double steps_per_rev);
/// The Tic's acceleration value for a platter acceleration (same rules).
Result<uint32_t> AccelUnits(double deg_per_s2, double steps_per_rev);

/// The variables the backend uses, decoded from a block read from offset 0.
struct Variables {
  uint8_t operation_state = 0;
  uint8_t misc_flags = 0;
  uint16_t error_status = 0;
  uint32_t errors_occurred = 0;
  uint8_t planning_mode = 0;
  int32_t target_position = 0;
  uint32_t max_speed = 0;
  uint32_t max_decel = 0;
  uint32_t max_accel = 0;
  int32_t current_position = 0;
  int32_t current_velocity = 0;

  bool energized() const { return misc_flags & kFlagEnergized; }
  bool position_uncertain() const { return misc_flags & kFlagPositionUncertain; }
  bool homing_active() const { return misc_flags & kFlagHomingActive; }
  bool has_error(ErrorBit b) const { return (error_status >> b) & 1u; }
};
/// Decodes a variable block read from offset 0; kDeviceFault when it is
/// shorter than kStatusBlockSize or the operation state is not a known one.
Result<Variables> ParseVariables(std::span<const uint8_t> block);

/// "motor driver error, safe start violation" for an error status; "none" for 0.
std::string ErrorStatusText(uint16_t error_status);
/// "normal", "de-energized", ... for an operation state.
const char* OperationStateName(uint8_t state);

// Little-endian field access in a variable block (Section 11: multi-byte
// values in a block read are least-significant byte first).
inline uint32_t ReadU32(std::span<const uint8_t> b, size_t at) {
  return b[at] | (b[at + 1] << 8) | (b[at + 2] << 16) | (static_cast<uint32_t>(b[at + 3]) << 24);
}
inline void WriteU32(std::span<uint8_t> b, size_t at, uint32_t v) {
  for (int i = 0; i < 4; ++i) b[at + i] = static_cast<uint8_t>(v >> (8 * i));
}

}  // namespace aggscan::tic
