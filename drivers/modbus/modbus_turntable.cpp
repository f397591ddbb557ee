#include "drivers/modbus/modbus_turntable.h"

#include <modbus/modbus.h>

#include <algorithm>
#include <cerrno>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <map>
#include <set>

#include "common/log.h"
#include "drivers/modbus/link_hygiene.h"
#include "drivers/turntable_legs.h"

namespace aggscan::modbus {
namespace {

constexpr const char* kLog = "turntable";

std::string Hex(int v) {
  char buf[16];
  std::snprintf(buf, sizeof(buf), "0x%04X", v);
  return buf;
}

const char* ExceptionName(int code) {
  switch (code) {
    case MODBUS_EXCEPTION_ILLEGAL_FUNCTION:
      return "illegal function";
    case MODBUS_EXCEPTION_ILLEGAL_DATA_ADDRESS:
      return "illegal data address";
    case MODBUS_EXCEPTION_ILLEGAL_DATA_VALUE:
      return "illegal data value";
    case MODBUS_EXCEPTION_SLAVE_OR_SERVER_FAILURE:
      return "server device failure";
    case MODBUS_EXCEPTION_ACKNOWLEDGE:
      return "acknowledge (still processing)";
    case MODBUS_EXCEPTION_SLAVE_OR_SERVER_BUSY:
      return "server device busy";
    case MODBUS_EXCEPTION_NEGATIVE_ACKNOWLEDGE:
      return "negative acknowledge";
    case MODBUS_EXCEPTION_MEMORY_PARITY:
      return "memory parity error";
    case MODBUS_EXCEPTION_GATEWAY_PATH:
      return "gateway path unavailable";
    case MODBUS_EXCEPTION_GATEWAY_TARGET:
      return "gateway target device failed to respond";
    default:
      return "unknown exception";
  }
}

bool IsException(int err) { return err > MODBUS_ENOBASE && err <= EMBXGTAR; }
// The request may be answered if sent again: no answer, a garbled answer, busy.
bool IsTransient(int err) {
  return err == ETIMEDOUT || err == EMBBADCRC || err == EMBBADDATA || err == EMBMDATA ||
         err == EMBBADSLAVE || err == EMBUNKEXC || err == EMBBADEXC || err == EMBXSBUSY ||
         err == EMBXACK || err == EAGAIN || err == EINTR;
}
// The link itself went away: a reconnect may help.
bool IsLinkLoss(int err) {
  return err == ECONNRESET || err == EPIPE || err == EBADF || err == EIO || err == ENXIO ||
         err == ENODEV || err == ENOTCONN || err == ECONNABORTED || err == ESHUTDOWN;
}

uint16_t Low(int64_t v) { return static_cast<uint16_t>(static_cast<uint32_t>(v) & 0xFFFFu); }
uint16_t High(int64_t v) { return static_cast<uint16_t>(static_cast<uint32_t>(v) >> 16); }

}  // namespace

void ModbusTurntable::CtxDeleter::operator()(_modbus* ctx) const {
  modbus_close(ctx);
  modbus_free(ctx);
}

ModbusTurntable::ModbusTurntable(Transport transport, const TurntableConfig& config,
                                 TurntableProfile profile)
    : transport_(transport), config_(config), profile_(std::move(profile)) {
  // Every status register, grouped into as few reads as the profile allows.
  std::set<int> regs;
  for (const StatusFlag* f : {&profile_.enabled, &profile_.moving, &profile_.in_position,
                              &profile_.homed, &profile_.alarm}) {
    if (f->present()) regs.insert(f->address);
  }
  regs.insert(profile_.actual_address);
  regs.insert(profile_.actual_address + 1);
  if (profile_.alarm_code_address >= 0) regs.insert(profile_.alarm_code_address);
  for (int r : regs) {
    if (!read_blocks_.empty()) {
      auto& [first, count] = read_blocks_.back();
      const int last = first + count - 1;
      if (r - last - 1 <= profile_.read_max_gap && r - first + 1 <= MODBUS_MAX_READ_REGISTERS) {
        count = r - first + 1;
        continue;
      }
    }
    read_blocks_.emplace_back(r, 1);
  }
}

ModbusTurntable::~ModbusTurntable() = default;

double ModbusTurntable::StepsPerDeg() const { return config_.modbus.steps_per_rev() / 360.0; }

bool ModbusTurntable::NearSteps(int64_t steps, int64_t goal) const {
  const double window = std::max(1.0, config_.modbus.in_position_window_deg * StepsPerDeg());
  return std::fabs(static_cast<double>(steps - goal)) <= window;
}

std::string ModbusTurntable::LinkDescription() const {
  const ModbusTurntableConfig& m = config_.modbus;
  if (transport_ == Transport::kTcp) {
    return "unit " + std::to_string(m.unit_id) + " at " + m.host + ":" + std::to_string(m.port);
  }
  const char parity = m.parity == "even" ? 'E' : m.parity == "odd" ? 'O' : 'N';
  return "unit " + std::to_string(m.unit_id) + " on " + m.device + " at " + std::to_string(m.baud) +
         " " + std::to_string(m.data_bits) + parity + std::to_string(m.stop_bits);
}

TurntableInfo ModbusTurntable::Info() const {
  TurntableInfo info;
  info.backend = transport_ == Transport::kTcp ? "modbus-tcp" : "modbus-rtu";
  const ModbusTurntableConfig& m = config_.modbus;
  info.id = transport_ == Transport::kTcp
                ? m.host + ":" + std::to_string(m.port) + "/" + std::to_string(m.unit_id)
                : m.device + "/" + std::to_string(m.unit_id);
  info.model = profile_.model.empty() ? profile_.name : profile_.model;
  return info;
}

int ModbusTurntable::requests_sent() const {
  std::lock_guard<std::mutex> l(mu_);
  return requests_;
}

Error ModbusTurntable::ClassifyFailure(int err, const std::string& what, int attempts) const {
  const std::string link = LinkDescription();
  const std::string detail = what + ": " + modbus_strerror(err) + " (" + std::to_string(attempts) +
                             (attempts == 1 ? " try" : " tries") + ", response_timeout " +
                             FormatDuration(config_.modbus.response_timeout) + ")";
  if (IsException(err)) {
    const int code = err - MODBUS_ENOBASE;
    return MakeError(ErrorClass::kDeviceFault,
                     "Modbus " + link + " refused " + what + " with exception " +
                         std::to_string(code) + " (" + ExceptionName(code) +
                         ") — check that turntable.modbus.profile \"" + profile_.name +
                         "\" matches the controller",
                     detail);
  }
  if (IsLinkLoss(err)) {
    return MakeError(ErrorClass::kDisconnected,
                     "lost the link to Modbus " + link + " — check the cable" +
                         (transport_ == Transport::kTcp ? " and the network" : " and the adapter") +
                         "; it is reopened on the next request",
                     detail);
  }
  if (err == ETIMEDOUT) {
    return MakeError(
        ErrorClass::kTimeout,
        "no answer from Modbus " + link +
            (transport_ == Transport::kTcp ? " — check the controller, the network and unit id"
                                           : " — check wiring and unit id"),
        detail);
  }
  // Garbled or mismatched answers that stayed so after every retry.
  return MakeError(ErrorClass::kTimeout,
                   "no valid answer from Modbus " + link + " (" + modbus_strerror(err) +
                       (transport_ == Transport::kTcp
                            ? ") — check that " + config_.modbus.host + ":" +
                                  std::to_string(config_.modbus.port) +
                                  " is the controller (or its gateway) speaking Modbus/TCP, "
                                  "that no other client drives it, and the unit id"
                            : std::string(") — check the line settings, termination and unit id")),
                   detail);
}

Status ModbusTurntable::Connect() {
  const ModbusTurntableConfig& m = config_.modbus;
  modbus_t* raw = nullptr;
  if (transport_ == Transport::kTcp) {
    // The protocol-independent variant: host names and IPv6 as well as IPv4.
    raw = modbus_new_tcp_pi(m.host.c_str(), std::to_string(m.port).c_str());
  } else {
    const char parity = m.parity == "even" ? 'E' : m.parity == "odd" ? 'O' : 'N';
    raw = modbus_new_rtu(m.device.c_str(), m.baud, parity, m.data_bits, m.stop_bits);
  }
  if (!raw) {
    return MakeError(ErrorClass::kInvalidConfig,
                     "cannot set up Modbus " + LinkDescription() + "; check turntable.modbus",
                     modbus_strerror(errno));
  }
  Ctx ctx(raw);
  modbus_set_slave(raw, m.unit_id);
  const TimeNs to = m.response_timeout;
  modbus_set_response_timeout(raw, static_cast<uint32_t>(to / kNsPerSec),
                              static_cast<uint32_t>((to % kNsPerSec) / 1000));
  if (modbus_connect(raw) != 0) {
    const int err = errno;
    const std::string detail = modbus_strerror(err);
    if (transport_ == Transport::kRtu) {
      if (err == ENOENT || err == ENODEV || err == ENXIO) {
        return MakeError(ErrorClass::kDeviceMissing,
                         "serial device " + m.device +
                             " not found — check that the USB/RS-485 adapter is plugged in and "
                             "turntable.modbus.device",
                         detail);
      }
      if (err == EACCES || err == EPERM) {
        return MakeError(ErrorClass::kDeviceMissing,
                         "no permission to open " + m.device +
                             " — add the service user to the dialout group (or fix the udev rule)",
                         detail);
      }
      return MakeError(ErrorClass::kDeviceMissing,
                       "cannot open serial device " + m.device + " at " + std::to_string(m.baud) +
                           " baud — check turntable.modbus line settings",
                       detail);
    }
    if (err == ETIMEDOUT) {
      return MakeError(ErrorClass::kTimeout,
                       "no answer from " + m.host + ":" + std::to_string(m.port) +
                           " — check the controller is powered and on the network",
                       detail);
    }
    return MakeError(ErrorClass::kDeviceMissing,
                     "cannot connect to the Modbus controller at " + m.host + ":" +
                         std::to_string(m.port) +
                         " — check it is powered and turntable.modbus.host and port",
                     detail);
  }
  if (transport_ == Transport::kRtu && m.rs485) {
    if (modbus_rtu_set_serial_mode(raw, MODBUS_RTU_RS485) != 0 && !rs485_warned_) {
      rs485_warned_ = true;  // once, not at every reconnect
      // USB adapters that switch direction by themselves do not take the ioctl.
      AGG_LOGW(kLog,
               "%s does not support RS-485 mode (%s); fine for adapters that switch "
               "direction themselves",
               m.device.c_str(), modbus_strerror(errno));
    }
  }
  ctx_ = std::move(ctx);
  connected_ = true;
  return OkStatus();
}

void ModbusTurntable::Resync(int err) {
  if (err == EMBXSBUSY || err == EMBXACK) return;  // answered: nothing is pending
  if (transport_ == Transport::kTcp || IsLinkLoss(err)) {
    // A late answer dies with the connection; the next try opens a new one.
    ctx_.reset();
    connected_ = false;
    return;
  }
  const int dropped = WaitOutLateAnswer(ctx_.get(), config_.modbus.response_timeout,
                                        RtuQuietGap(config_.modbus.baud));
  if (dropped > 0) AGG_LOGD(kLog, "dropped %d bytes of a late answer", dropped);
}

template <typename F>
Status ModbusTurntable::Transact(const std::string& what, F&& request,
                                 const std::function<Result<bool>()>& resend) {
  const int tries = 1 + config_.modbus.retries;
  int err = 0;
  int sent = 0;
  bool reconnected = false;
  for (int attempt = 1; attempt <= tries; ++attempt) {
    if (!connected_) {
      Status c = Connect();
      if (!c) {
        // The device went away during use: that is a disconnection.
        if (c.error().cls == ErrorClass::kDeviceMissing) {
          return MakeError(ErrorClass::kDisconnected, c.error().message, c.error().detail);
        }
        return c;
      }
    }
    if (const int stale = DropStaleInput(ctx_.get()); stale > 0) {
      AGG_LOGD(kLog, "%s: dropped %d bytes nobody asked for before sending", what.c_str(), stale);
    }
    ++requests_;
    ++sent;
    if (request(ctx_.get()) >= 0) {
      if (attempt > 1) AGG_LOGD(kLog, "%s: answered on try %d", what.c_str(), attempt);
      return OkStatus();
    }
    err = errno;
    // "Acknowledge": a command was taken and is being carried out.
    if (resend && err == EMBXACK) return OkStatus();
    if (IsException(err) && err != EMBXSBUSY && err != EMBXACK) break;
    const bool lost = IsLinkLoss(err);
    if (!lost && !IsTransient(err)) break;
    // Back in step before anything else is sent, also after the last try.
    Resync(err);
    // A command that may have been carried out is sent again only when the
    // controller's state shows it was not ("busy" refused it: no doubt).
    if (resend && err != EMBXSBUSY) {
      Result<bool> again = resend();
      if (!again) return again.error();
      if (!*again) {
        AGG_LOGI(kLog, "%s: %s, but the controller's state shows it was carried out", what.c_str(),
                 modbus_strerror(err));
        return OkStatus();
      }
      AGG_LOGI(kLog, "%s: %s and not carried out (try %d of %d)", what.c_str(),
               modbus_strerror(err), attempt, tries);
      continue;
    }
    if (lost) {
      if (reconnected) break;
      reconnected = true;  // one reopen per request; it does not count as a try
      --attempt;
      continue;
    }
    AGG_LOGD(kLog, "%s: %s (try %d of %d)", what.c_str(), modbus_strerror(err), attempt, tries);
  }
  return ClassifyFailure(err, what, sent);
}

Status ModbusTurntable::WriteRegisters(const std::vector<RegisterWrite>& writes,
                                       const std::string& what) {
  // Adjacent registers go out in one request (function 16), a lone one as
  // function 6.
  std::map<int, uint16_t> by_address;
  for (const auto& w : writes) by_address[w.address] = static_cast<uint16_t>(w.value);
  auto it = by_address.begin();
  while (it != by_address.end()) {
    const int first = it->first;
    std::vector<uint16_t> run;
    while (it != by_address.end() && it->first == first + static_cast<int>(run.size()) &&
           run.size() < MODBUS_MAX_WRITE_REGISTERS) {
      run.push_back(it->second);
      ++it;
    }
    const std::string label =
        "writing " + what + " (register " + Hex(first) +
        (run.size() > 1 ? ".." + Hex(first + static_cast<int>(run.size()) - 1) : std::string()) +
        ")";
    Status s =
        run.size() == 1
            ? Transact(label, [&](modbus_t* c) { return modbus_write_register(c, first, run[0]); })
            : Transact(label, [&](modbus_t* c) {
                return modbus_write_registers(c, first, static_cast<int>(run.size()), run.data());
              });
    if (!s) return s;
  }
  return OkStatus();
}

Status ModbusTurntable::WriteCommand(const RegisterWrite& command, const std::string& what,
                                     const std::function<bool(const Raw&)>& carried_out) {
  // A command is not idempotent (a move may be relative on some drives, a
  // second home restarts the search): when its answer is lost it is sent
  // again only if a fresh status read says it did not take effect.
  return Transact(
      "writing the " + what + " command (register " + Hex(command.address) + ")",
      [&](modbus_t* c) { return modbus_write_register(c, command.address, command.value); },
      [&]() -> Result<bool> {
        Result<Raw> raw = ReadRaw();
        if (!raw) return raw.error();
        return !carried_out(*raw);
      });
}

// Speed and acceleration registers from the motion limits, in the profile's
// units; an error when a value does not fit a register.
Status ModbusTurntable::MotionWrites(std::vector<RegisterWrite>* out) const {
  const double gear = config_.modbus.gear_ratio;
  auto put = [&](const ScaledRegisters& regs, double physical, const char* field) -> Status {
    const double counts = std::round(physical / regs.scale);
    if (!(counts >= 1 && counts <= 65535)) {
      return MakeError(ErrorClass::kInvalidConfig,
                       std::string("turntable.") + field + " gives " +
                           std::to_string(static_cast<long long>(counts)) +
                           " counts in the profile's register (1..65535 fit); change " + field +
                           " or the profile's scale");
    }
    for (int a : regs.addresses) out->push_back({a, static_cast<int>(counts)});
    return OkStatus();
  };
  if (profile_.speed.present()) {
    const double v = config_.max_speed_deg_s;
    double physical = v;
    switch (profile_.speed_unit) {
      case SpeedUnit::kTableDegPerS:
        physical = v;
        break;
      case SpeedUnit::kMotorRpm:
        physical = v / 6.0 * gear;
        break;
      case SpeedUnit::kStepsPerS:
        physical = v * StepsPerDeg();
        break;
    }
    Status s = put(profile_.speed, physical, "max_speed_deg_s");
    if (!s) return s;
  }
  if (profile_.accel.present()) {
    const double a = config_.accel_deg_s2;
    double physical = a;
    switch (profile_.accel_unit) {
      case AccelUnit::kTableDegPerS2:
        physical = a;
        break;
      case AccelUnit::kStepsPerS2:
        physical = a * StepsPerDeg();
        break;
      case AccelUnit::kMsPer1000Rpm:
        physical = 1000.0 / (a / 6.0 * gear) * 1000.0;
        break;
    }
    Status s = put(profile_.accel, physical, "accel_deg_s2");
    if (!s) return s;
  }
  return OkStatus();
}

Status ModbusTurntable::DoOpen() {
  std::lock_guard<std::mutex> l(mu_);
  phase_ = Phase::kNone;
  turn_offset_deg_ = 0.0;
  homed_since_open_ = false;
  std::vector<RegisterWrite> motion;
  Status s = MotionWrites(&motion);  // a limit that does not fit: refuse before talking
  if (!s) return s;
  s = Connect();
  if (!s) return s;
  if (!profile_.on_open.empty()) {
    s = WriteRegisters(profile_.on_open, "the profile's set-up values");
    if (!s) {
      ctx_.reset();
      connected_ = false;
      return s;
    }
  }
  if (!motion.empty()) s = WriteRegisters(motion, "speed and acceleration");
  if (s) {
    Result<Raw> r = ReadRaw();  // the unit must answer, or Open fails with the reason
    if (!r) s = r.error();
  }
  if (!s) {
    ctx_.reset();
    connected_ = false;
  }
  return s;
}

void ModbusTurntable::DoClose() {
  std::lock_guard<std::mutex> l(mu_);
  ctx_.reset();
  connected_ = false;
  phase_ = Phase::kNone;
}

Result<ModbusTurntable::Raw> ModbusTurntable::ReadRaw() {
  std::map<int, uint16_t> regs;
  for (const auto& block : read_blocks_) {
    // Plain locals, not structured bindings: clang before 16 cannot capture
    // those in a lambda, and the fuzz build uses Debian's clang 14.
    const int first = block.first;
    const int count = block.second;
    std::vector<uint16_t> buf(static_cast<size_t>(count));
    const std::string what = "reading status (register " + Hex(first) +
                             (count > 1 ? ".." + Hex(first + count - 1) : std::string()) + ")";
    Status s = Transact(what, [&](modbus_t* c) {
      const int n = modbus_read_registers(c, first, count, buf.data());
      if (n >= 0 && n != count) {
        errno = EMBBADDATA;
        return -1;
      }
      return n;
    });
    if (!s) return s.error();
    for (int i = 0; i < count; ++i) regs[first + i] = buf[static_cast<size_t>(i)];
  }
  auto flag = [&](const StatusFlag& f, bool absent) {
    if (!f.present()) return absent;
    const bool bit = (regs[f.address] >> f.bit) & 1u;
    return f.active_low ? !bit : bit;
  };
  Raw raw;
  const uint16_t w0 = regs[profile_.actual_address], w1 = regs[profile_.actual_address + 1];
  const uint32_t u = profile_.word_order == WordOrder::kHighFirst
                         ? (static_cast<uint32_t>(w0) << 16) | w1
                         : (static_cast<uint32_t>(w1) << 16) | w0;
  raw.steps = static_cast<int32_t>(u);
  raw.alarm_code = profile_.alarm_code_address >= 0 ? regs[profile_.alarm_code_address] : 0;
  raw.enabled = flag(profile_.enabled, true);
  raw.moving = flag(profile_.moving, false);
  raw.in_position = flag(profile_.in_position, false);
  raw.homed = flag(profile_.homed, homed_since_open_);
  raw.alarm = flag(profile_.alarm, raw.alarm_code != 0);
  return raw;
}

Status ModbusTurntable::StartLeg(int64_t target_steps) {
  std::vector<RegisterWrite> writes;
  Status s = MotionWrites(&writes);  // again each move: the controller may have been power-cycled
  if (!s) return s;
  const bool high_first = profile_.word_order == WordOrder::kHighFirst;
  writes.push_back({profile_.target_address, high_first ? High(target_steps) : Low(target_steps)});
  writes.push_back(
      {profile_.target_address + 1, high_first ? Low(target_steps) : High(target_steps)});
  s = WriteRegisters(writes, "the target position");
  if (!s) return s;
  s = WriteCommand(profile_.move, "move", [&](const Raw& r) {
    return r.moving || NearSteps(r.steps, target_steps);  // a short move may be over already
  });
  if (!s) return s;
  leg_steps_ = target_steps;
  return OkStatus();
}

Status ModbusTurntable::DoStartHome() {
  std::lock_guard<std::mutex> l(mu_);
  Result<Raw> raw = ReadRaw();
  if (!raw) return raw.error();
  if (raw->alarm && profile_.reset_alarm.address >= 0) {
    Status s =
        WriteCommand(profile_.reset_alarm, "reset alarm", [](const Raw& r) { return !r.alarm; });
    if (!s) return s;
  }
  Status s = WriteCommand(profile_.home, "home", [&](const Raw& r) {
    return r.moving || (NearSteps(r.steps, 0) && (!profile_.homed.present() || r.homed));
  });
  if (!s) return s;
  phase_ = Phase::kHoming;
  turn_offset_deg_ = 0.0;
  leg_steps_ = final_steps_ = 0;
  return OkStatus();
}

Status ModbusTurntable::DoStartMoveTo(double angle_deg) {
  std::lock_guard<std::mutex> l(mu_);
  Result<Raw> raw = ReadRaw();
  if (!raw) return raw.error();
  if (!raw->homed) {
    return MakeError(ErrorClass::kInvalidState, "turntable is not homed; home first");
  }
  if (raw->alarm) {
    auto it = profile_.alarm_texts.find(raw->alarm_code);
    return MakeError(ErrorClass::kDeviceFault,
                     "turntable controller is in alarm (code " + std::to_string(raw->alarm_code) +
                         (it != profile_.alarm_texts.end() ? ": " + it->second : std::string()) +
                         "); remove the cause, then home again (homing resets the alarm)");
  }
  const double spd = StepsPerDeg();
  const ControllerTarget target = PlanControllerTarget(angle_deg, turn_offset_deg_, raw->steps, spd,
                                                       config_.modbus.shortest_path);
  const MoveLegs legs = PlanBacklashLegs(raw->steps, target.steps,
                                         std::llround(config_.modbus.backlash_comp_deg * spd),
                                         ParseBacklashApproach(config_.modbus.backlash_approach));
  if (!legs.fit_int32()) {
    return MakeError(ErrorClass::kInvalidArgument,
                     "target " + std::to_string(angle_deg) +
                         " deg is beyond the controller's int32 "
                         "step range at " +
                         std::to_string(config_.modbus.steps_per_rev()) + " steps/rev");
  }
  Status s = StartLeg(legs.first);
  if (!s) return s;
  turn_offset_deg_ = target.turn_offset_deg;
  final_steps_ = legs.final;
  phase_ = legs.two_legs() ? Phase::kOvershoot : Phase::kFinal;
  return OkStatus();
}

Status ModbusTurntable::DoStop() {
  std::lock_guard<std::mutex> l(mu_);
  Status s = WriteCommand(profile_.stop, "stop", [](const Raw& r) { return !r.moving; });
  if (s) phase_ = Phase::kStopped;
  return s;
}

Status ModbusTurntable::ResetAlarm() {
  if (!is_open()) return MakeError(ErrorClass::kInvalidState, "turntable is not open");
  std::lock_guard<std::mutex> l(mu_);
  if (profile_.reset_alarm.address < 0) {
    return MakeError(ErrorClass::kInvalidState, "profile \"" + profile_.name +
                                                    "\" has no reset command; reset the controller "
                                                    "by hand (or power-cycle it)");
  }
  return WriteCommand(profile_.reset_alarm, "reset alarm", [](const Raw& r) { return !r.alarm; });
}

Result<TurntableStatus> ModbusTurntable::DoReadStatus() {
  std::lock_guard<std::mutex> l(mu_);
  Result<Raw> r = ReadRaw();
  if (!r) return r.error();
  const Raw& raw = *r;
  const double spd = StepsPerDeg();
  auto near = [&](int64_t goal) { return NearSteps(raw.steps, goal); };
  const bool settled = raw.in_position && !raw.moving && !raw.alarm;

  TurntableStatus st;
  st.enabled = raw.enabled;
  st.moving = raw.moving;
  st.alarm = raw.alarm;
  st.alarm_code = raw.alarm_code;
  if (raw.alarm) {
    auto it = profile_.alarm_texts.find(raw.alarm_code);
    st.alarm_text = it != profile_.alarm_texts.end()
                        ? it->second
                        : "alarm code " + std::to_string(raw.alarm_code) +
                              " (see the controller manual, profile \"" + profile_.name + "\")";
  }
  switch (phase_) {
    case Phase::kNone:
      st.in_position = settled;
      break;
    case Phase::kStopped:
      st.in_position = false;
      break;
    case Phase::kHoming:
      // Without a homed bit, a completed homing run is what makes it homed.
      st.in_position = settled && (!profile_.homed.present() || raw.homed) && near(0);
      if (st.in_position) homed_since_open_ = true;
      break;
    case Phase::kOvershoot:
      st.in_position = false;
      if (settled && near(leg_steps_)) {
        // First leg done: approach the target from the compensation side.
        Status s = StartLeg(final_steps_);
        if (!s) return s.error();
        phase_ = Phase::kFinal;
        st.moving = true;
      }
      break;
    case Phase::kFinal:
      st.in_position = settled && near(final_steps_);
      break;
  }
  st.homed = profile_.homed.present() ? raw.homed : homed_since_open_;
  st.angle_deg = static_cast<double>(raw.steps) / spd + turn_offset_deg_;
  return st;
}

}  // namespace aggscan::modbus
