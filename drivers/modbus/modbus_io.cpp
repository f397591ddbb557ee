#include "drivers/modbus/modbus_io.h"

#include <modbus.h>

#include <cerrno>
#include <chrono>

#include "drivers/modbus/link_hygiene.h"

namespace aggscan::modbus {
namespace {

LinkSettings FromTurntable(const Config& c, const char* section) {
  const ModbusTurntableConfig& m = c.turntable.modbus;
  LinkSettings s;
  s.tcp = true;  // validated: only a modbus-tcp turntable's link is shared
  s.host = m.host;
  s.port = m.port;
  s.unit_id = m.unit_id;
  s.response_timeout = m.response_timeout;
  s.section = std::string(section) + " (link = \"turntable\": [turntable.modbus])";
  return s;
}

}  // namespace

std::string LinkSettings::Describe() const {
  if (tcp) return "unit " + std::to_string(unit_id) + " at " + host + ":" + std::to_string(port);
  return "unit " + std::to_string(unit_id) + " on " + device + " at " + std::to_string(baud) +
         " 8" + parity + "1";
}

bool LinkSettings::SameLink(const LinkSettings& o) const {
  return tcp == o.tcp && (tcp ? host == o.host && port == o.port : device == o.device) &&
         unit_id == o.unit_id;
}

LinkSettings ButtonLinkSettings(const Config& c) {
  const ModbusButtonConfig& b = c.button.modbus;
  if (b.link == "turntable") return FromTurntable(c, "[button.modbus]");
  LinkSettings s;
  s.tcp = b.link == "tcp";
  s.host = b.host;
  s.port = b.port;
  s.device = b.device;
  s.baud = b.baud;
  s.parity = b.parity == "even" ? 'E' : b.parity == "odd" ? 'O' : 'N';
  s.unit_id = b.unit_id;
  s.response_timeout = b.response_timeout;
  s.section = "[button.modbus]";
  return s;
}

LinkSettings LightLinkSettings(const Config& c) {
  if (c.light.modbus.link == "button") return ButtonLinkSettings(c);
  return FromTurntable(c, "[light.modbus]");
}

BitLink::BitLink(LinkSettings settings) : s_(std::move(settings)) {}

BitLink::~BitLink() {
  if (ctx_) {
    modbus_close(ctx_);
    modbus_free(ctx_);
  }
}

Status BitLink::Connect() {
  std::lock_guard<std::mutex> l(mu_);
  return ConnectLocked();
}

Status BitLink::ConnectLocked() {
  if (connected_) return OkStatus();
  if (!ctx_) {
    ctx_ = s_.tcp ? modbus_new_tcp_pi(s_.host.c_str(), std::to_string(s_.port).c_str())
                  : modbus_new_rtu(s_.device.c_str(), s_.baud, s_.parity, 8, 1);
    if (!ctx_) {
      return MakeError(ErrorClass::kInvalidConfig,
                       "cannot set up Modbus " + s_.Describe() + "; check " + s_.section,
                       modbus_strerror(errno));
    }
    modbus_set_slave(ctx_, s_.unit_id);
    modbus_set_response_timeout(ctx_, static_cast<uint32_t>(s_.response_timeout / kNsPerSec),
                                static_cast<uint32_t>((s_.response_timeout % kNsPerSec) / 1000));
  }
  if (modbus_connect(ctx_) != 0) {
    const int err = errno;
    return MakeError(err == ETIMEDOUT ? ErrorClass::kTimeout : ErrorClass::kDeviceMissing,
                     "cannot reach Modbus " + s_.Describe() + "; check that the controller is on" +
                         (s_.tcp ? " the network" : " the serial line") + " and " + s_.section,
                     modbus_strerror(err));
  }
  connected_ = true;
  return OkStatus();
}

Error BitLink::Classify(int err, const std::string& what) {
  const std::string detail = what + ": " + modbus_strerror(err);
  if (err > MODBUS_ENOBASE && err < MODBUS_ENOBASE + 0x20) {
    return MakeError(ErrorClass::kDeviceFault,
                     "Modbus " + s_.Describe() + " refused " + what + " (" + modbus_strerror(err) +
                         "); check the address in " + s_.section,
                     detail);
  }
  // Anything else may have left the connection out of step: reopen next time
  // (a TCP answer still on its way dies with the connection; on a serial line
  // it is waited out first, since the port's buffer would keep it).
  if (!s_.tcp) WaitOutLateAnswer(ctx_, s_.response_timeout, RtuQuietGap(s_.baud));
  modbus_close(ctx_);
  connected_ = false;
  if (err == ETIMEDOUT) {
    return MakeError(
        ErrorClass::kTimeout,
        "no answer from Modbus " + s_.Describe() + "; check the controller and " + s_.section,
        detail);
  }
  return MakeError(ErrorClass::kDisconnected,
                   "lost the link to Modbus " + s_.Describe() + "; check the cable and " +
                       s_.section + " (it is reopened on the next request)",
                   detail);
}

Result<bool> BitLink::ReadBit(bool discrete, int address) {
  std::lock_guard<std::mutex> l(mu_);
  if (Status s = ConnectLocked(); !s) return s.error();
  DropStaleInput(ctx_);  // nothing waiting now can answer the request below
  uint8_t bit = 0;
  const int rc = discrete ? modbus_read_input_bits(ctx_, address, 1, &bit)
                          : modbus_read_bits(ctx_, address, 1, &bit);
  if (rc != 1) {
    return Classify(errno, std::string(discrete ? "reading discrete input " : "reading coil ") +
                               std::to_string(address));
  }
  return bit != 0;
}

Status BitLink::WriteCoil(int address, bool on) {
  std::lock_guard<std::mutex> l(mu_);
  if (Status s = ConnectLocked(); !s) return s;
  DropStaleInput(ctx_);
  if (modbus_write_bit(ctx_, address, on ? 1 : 0) != 1) {
    return Classify(errno, "writing coil " + std::to_string(address));
  }
  return OkStatus();
}

ModbusButton::ModbusButton(Clock& clock, const ButtonConfig& config, std::shared_ptr<BitLink> link)
    : Button(clock, config.debounce), config_(config.modbus), link_(std::move(link)) {}

ModbusButton::~ModbusButton() { Stop(); }

std::string ModbusButton::Describe() const {
  return "Modbus button, " + std::string(config_.input == "coil" ? "coil " : "discrete input ") +
         std::to_string(config_.address) + " of " + link_->settings().Describe();
}

Status ModbusButton::DoStart() {
  // The first read is the open check, and the level a press must rise from.
  Result<bool> first = link_->ReadBit(config_.input == "discrete", config_.address);
  if (!first) return first.error();
  {
    std::lock_guard<std::mutex> l(mu_);
    stop_ = false;
  }
  polls_ = 0;
  thread_ = std::thread([this, last = *first] { Run(last); });
  return OkStatus();
}

void ModbusButton::DoStop() {
  {
    std::lock_guard<std::mutex> l(mu_);
    stop_ = true;
  }
  cv_.notify_all();
  if (thread_.joinable()) thread_.join();
}

void ModbusButton::Run(bool last) {
  constexpr int kFailuresForFault = 3;  // a lone lost reply on a noisy line is no fault
  int failures = 0;
  std::unique_lock<std::mutex> l(mu_);
  while (
      !cv_.wait_for(l, std::chrono::nanoseconds(config_.poll_interval), [this] { return stop_; })) {
    l.unlock();
    Result<bool> bit = link_->ReadBit(config_.input == "discrete", config_.address);
    if (bit) {
      failures = 0;
      if (*bit && !last) DeliverPress("modbus");
      last = *bit;
    } else if (++failures >= kFailuresForFault) {
      ReportFault(bit.error());
      ++polls_;
      return;
    }
    ++polls_;
    l.lock();
  }
}

std::string ModbusLight::Describe() const {
  return "Modbus light, coil " + std::to_string(config_.coil) + " of " +
         link_->settings().Describe();
}

}  // namespace aggscan::modbus
