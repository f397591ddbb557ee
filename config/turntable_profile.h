// Register-map profiles of Modbus turntable controllers, as data
// (config/turntables/*.toml). A profile says where the target and the actual
// position live, how 32-bit values are split into registers, which register
// and value start a move, a homing run, a stop and an alarm reset, where each
// status flag is, and how speed and acceleration are scaled. The Modbus
// backend (drivers/modbus/) does nothing controller-specific beyond this.
//
// File format (hex integers such as 0x6002 are allowed; addresses are the
// 0-based protocol addresses of holding registers):
//
//   [profile]      name, model, source (free text); word_order = "high_first" |
//                  "low_first" (how an int32 is split over two registers);
//                  read_max_gap (status registers at most this far apart are
//                  read in one request; 0 = only adjacent ones)
//   [position]     target, actual: first register of each int32 (steps)
//   [speed]        addresses = [...], unit, scale (physical units per count)
//   [accel]        addresses = [...], unit, scale        (both optional)
//   [commands]     move, home, stop, reset_alarm = { address, value }
//   [status]       enabled, moving, in_position, homed, alarm =
//                  { address, bit [, active_low] }; moving, in_position are
//                  required, the others optional (see the struct below)
//   [alarm]        code = register of the alarm code (optional);
//                  [alarm.texts] "0x01" = "over current", ...
//   [[on_open]]    { address, value } written once after connecting
#pragma once

#include <map>
#include <string>
#include <vector>

#include "common/error.h"

namespace aggscan {

/// One register and the value written to it.
struct RegisterWrite {
  int address = -1;
  int value = 0;

  bool operator==(const RegisterWrite&) const = default;
};

/// One status bit. Absent when address < 0.
struct StatusFlag {
  int address = -1;
  int bit = 0;              // 0..15, bit 0 = least significant
  bool active_low = false;  // the condition holds when the bit is 0

  bool present() const { return address >= 0; }
  bool operator==(const StatusFlag&) const = default;
};

enum class WordOrder { kHighFirst, kLowFirst };

/// Physical unit of a speed register. Table degrees are at the platter;
/// motor rpm are before the gear (rpm = deg/s / 6 * gear_ratio).
enum class SpeedUnit { kTableDegPerS, kMotorRpm, kStepsPerS };
/// Physical unit of an acceleration register. ms_per_1000rpm is the time the
/// motor takes from 0 to 1000 rpm (a larger value is a gentler ramp).
enum class AccelUnit { kTableDegPerS2, kStepsPerS2, kMsPer1000Rpm };

struct ScaledRegisters {
  std::vector<int> addresses;  // each gets the same value (e.g. acceleration and deceleration)
  double scale = 1.0;          // physical units per register count (0.1 = tenths)

  bool present() const { return !addresses.empty(); }
  bool operator==(const ScaledRegisters&) const = default;
};

struct TurntableProfile {
  std::string file;    // where it was loaded from (messages)
  std::string name;    // short name, e.g. "generic"
  std::string model;   // controller product it describes
  std::string source;  // manual and section the map follows
  WordOrder word_order = WordOrder::kHighFirst;
  int read_max_gap = 0;

  int target_address = -1;  // int32 target position, steps (two registers)
  int actual_address = -1;  // int32 measured position, steps (two registers)

  ScaledRegisters speed;
  SpeedUnit speed_unit = SpeedUnit::kTableDegPerS;
  ScaledRegisters accel;
  AccelUnit accel_unit = AccelUnit::kTableDegPerS2;

  RegisterWrite move;         // starts the move to the target
  RegisterWrite home;         // starts homing (position 0 afterwards)
  RegisterWrite stop;         // stops motion
  RegisterWrite reset_alarm;  // clears an alarm (optional: address < 0)

  StatusFlag enabled;      // optional: absent = reported as enabled
  StatusFlag moving;       // required
  StatusFlag in_position;  // required: the commanded move or homing has completed
  StatusFlag homed;        // optional: absent = homed once a homing run completed since open
  StatusFlag alarm;        // optional: absent = alarm when the alarm code is not 0

  int alarm_code_address = -1;             // optional uint16 alarm code
  std::map<int, std::string> alarm_texts;  // alarm code -> operator text

  std::vector<RegisterWrite> on_open;  // fixed set-up writes after connecting

  bool operator==(const TurntableProfile&) const = default;
};

/// Parses a profile. Errors are kInvalidConfig, one line per problem:
/// "FILE: FIELD: what is wrong; what to do", every problem listed.
Result<TurntableProfile> ParseTurntableProfile(const std::string& toml, const std::string& file);
/// Reads and parses a profile file.
Result<TurntableProfile> LoadTurntableProfile(const std::string& path);
/// `profile` is a file path when it contains '/' or ends in ".toml", else a
/// name looked up as DIR/NAME.toml.
Result<TurntableProfile> FindTurntableProfile(const std::string& profile, const std::string& dir);

const char* WordOrderName(WordOrder w);

}  // namespace aggscan
