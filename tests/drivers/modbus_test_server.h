// A Modbus turntable controller for the tests: a libmodbus server in the test
// process, on 127.0.0.1 (TCP, a free port) or on a pseudo-terminal pair (RTU:
// the backend opens device()), with a trapezoidal motion model on the real
// monotonic clock, alarms and fault injection.
//
// Its register layouts are written here from the maps themselves, not from
// the backend's profile code, so a profile or word-order mistake in the
// backend shows up as a wrong angle:
//   kGeneric    aggscan's reference map (config/turntables/generic.toml),
//               with the int32 word order selectable;
//   kLeadshine  the Leadshine iEM-RS PR-mode registers the
//               leadshine-iem-rs profile describes (PR0 block at 0x6200,
//               trigger 0x6002, status 0x1003, feedback position 0x1014,
//               alarm 0x2203, control word 0x1801).
#pragma once

#include <atomic>
#include <cstdint>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <thread>
#include <vector>

#include "config/config.h"
#include "drivers/turntable.h"

struct _modbus;

namespace aggscan::testing {

enum class ServerMap { kGeneric, kLeadshine };

struct ModbusServerOptions {
  ServerMap map = ServerMap::kGeneric;
  bool low_word_first = false;   // kGeneric: int32 values low word first
  int unit_id = 1;               // answers only requests to this unit
  double steps_per_rev = 32000;  // kGeneric: steps per platter turn (speed registers are deg/s)
  double motor_steps_per_rev = 10000;  // kLeadshine: pulses per motor turn (speed is motor rpm)
  double home_seconds = 0.3;           // homing run duration (position ramps to 0)
  int tcp_port = 0;                    // TCP: listen here (0 = a free port the kernel picks)
};

class ModbusTestServer {
 public:
  static std::unique_ptr<ModbusTestServer> StartTcp(const ModbusServerOptions& options);
  static std::unique_ptr<ModbusTestServer> StartRtu(const ModbusServerOptions& options);
  ~ModbusTestServer();
  ModbusTestServer(const ModbusTestServer&) = delete;
  ModbusTestServer& operator=(const ModbusTestServer&) = delete;

  int port() const { return port_; }                     // TCP
  const std::string& device() const { return device_; }  // RTU: the pty the backend opens

  // Fault injection.
  void SetSilent(bool silent);                         // requests are read and never answered
  void SetStallAtSteps(std::optional<int64_t> steps);  // motion stops there, still "moving"
  void RaiseAlarm(int code);                           // stops motion, alarm bit and code set
  void RejectRegister(int address);                    // requests touching it get exception 2
  void DropClient();                                   // TCP: closes the connection
  // The next request with Modbus function code `function` (0: any request) is
  // executed when it arrives but answered `seconds` later, on the connection
  // it came by (a controller or gateway that answers after the client's
  // response_timeout). The server handles nothing else meanwhile: a retry
  // waits behind the late answer, as on a single-threaded controller.
  void AnswerNextLate(double seconds, int function = 0);
  // The next request with function code `function` (0: any) is read and
  // dropped: neither carried out nor answered (lost on the line).
  void IgnoreNext(int function = 0);
  // TCP: answers carry another transaction id than their request's.
  void SetWrongTransactionId(bool on);
  // Moves come to rest this many steps past their target, in position (a
  // drive's following error inside its in-position window).
  void SetRestErrorSteps(int64_t steps);
  // Bits (addresses 0..63): discrete inputs the test sets (a button), coils
  // the backend writes (a lamp) or the test sets (a button on a coil).
  void SetDiscreteInput(int address, bool on);
  void SetCoil(int address, bool on);

  // Observations.
  int64_t position_steps();
  bool homed();
  int requests();                       // requests received (answered or not)
  std::vector<int64_t> move_targets();  // targets of accepted move commands, in order
  // Values written to the command register (kGeneric: 1 move, 2 home, 3 stop,
  // 4 reset; kLeadshine: the trigger values), in order, each write counted.
  std::vector<int> commands();
  std::vector<int64_t> rest_positions();  // where each of those moves came to rest, in order
  int64_t min_steps_since_last_move();    // lowest position since the last move command
  int64_t max_steps_since_last_move();
  uint16_t reg(int address);  // a holding register as the backend left it
  bool coil(int address);     // a coil as the backend left it
  int coil_writes();          // write-coil requests answered

 private:
  explicit ModbusTestServer(const ModbusServerOptions& options);
  void Loop();
  void Handle(const uint8_t* req, int len);
  void UpdateRegisters(int64_t now);  // model -> status registers
  void ApplyCommands(int64_t now);    // command registers -> model
  void Advance(int64_t now);
  void StartMotion(int64_t now, double target, double v, double a);

  ModbusServerOptions opt_;
  _modbus* ctx_ = nullptr;
  struct Mapping;
  std::unique_ptr<Mapping> map_;
  int listen_fd_ = -1;
  int client_fd_ = -1;
  int pty_master_ = -1;
  int pty_slave_keep_ = -1;
  int port_ = 0;
  std::string device_;
  std::atomic<bool> stop_{false};
  std::thread thread_;

  std::mutex mu_;
  bool silent_ = false;
  bool drop_ = false;
  std::optional<int64_t> stall_at_;
  std::vector<int> rejected_;
  int requests_ = 0;
  int coil_writes_ = 0;
  std::vector<int64_t> targets_;
  std::vector<int64_t> rests_;
  int64_t rest_error_ = 0;
  double late_seconds_ = 0;  // AnswerNextLate: armed when > 0
  int late_function_ = 0;
  bool wrong_tid_ = false;
  std::optional<int> ignore_function_;
  std::vector<int> commands_;
  // Motion model (steps, seconds on CLOCK_MONOTONIC).
  double pos_ = 0, start_pos_ = 0, goal_ = 0, v_ = 1, a_ = 1;
  int64_t t0_ = 0;
  bool moving_ = false, homing_ = false, homed_ = false, in_position_ = false, alarm_ = false;
  bool stalled_ = false;
  int alarm_code_ = 0;
  double min_pos_ = 0, max_pos_ = 0;
};

/// A turntable config that talks to `server` with the generic profile from
/// the source tree: 360 deg/s, 1440 deg/s^2 (fast, so the contract suite runs
/// in seconds of real time), 200 x 16 x 10 = 32000 steps per turn.
TurntableConfig ModbusConfigFor(const ModbusTestServer& server, bool tcp);

/// Polls `t` every 20 ms on the real clock until in_position, an error, or 10 s.
Result<TurntableStatus> WaitInPosition(Turntable& t);

}  // namespace aggscan::testing
