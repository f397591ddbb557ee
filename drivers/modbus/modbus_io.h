// Start button and status light on Modbus bits (button backend "modbus",
// light backend "modbus"), through libmodbus.
//
//  - The button polls a discrete input (function 2) or a coil (function 1)
//    every poll_interval; a press is the bit's rising edge (a bit already set
//    at Start() is no press). Three failed polls in a row are a runtime fault
//    (Health(): kTimeout, kDisconnected or kDeviceFault, naming the link and
//    the address); the daemon then restarts it with its backoff.
//  - The light writes one coil (function 5) as the pattern changes level.
//  - The link: its own (tcp / rtu), or the turntable's TCP settings as a
//    second connection. A button and a light on the same link settings share
//    one connection (BitLink serialises their requests), which is what a
//    single RS-485 line needs.
#pragma once

#include <atomic>
#include <condition_variable>
#include <memory>
#include <mutex>
#include <string>
#include <thread>

#include "common/clock.h"
#include "config/config.h"
#include "drivers/button.h"
#include "drivers/status_light.h"

struct _modbus;  // NOLINT(bugprone-reserved-identifier): libmodbus's own tag for modbus_t

namespace aggscan::modbus {

/// Where a bit lives: TCP or RTU link settings, resolved from the config.
struct LinkSettings {
  bool tcp = true;
  std::string host;
  int port = 502;
  std::string device;
  int baud = 19200;
  char parity = 'N';
  int unit_id = 1;
  TimeNs response_timeout = 200 * kNsPerMs;
  std::string section;  // config section named in messages, "[button.modbus]"

  /// "unit 1 at 10.0.0.5:502" or "unit 1 on /dev/ttyUSB1 at 19200 8N1".
  std::string Describe() const;
  bool SameLink(const LinkSettings& o) const;
};
/// The button's link ([button.modbus], or [turntable.modbus] for link = "turntable").
LinkSettings ButtonLinkSettings(const Config& config);
/// The light's link ([turntable.modbus] or the button's).
LinkSettings LightLinkSettings(const Config& config);

/// One Modbus connection, opened on first use and reopened after a lost
/// link; one request at a time.
class BitLink {
 public:
  explicit BitLink(LinkSettings settings);
  ~BitLink();
  BitLink(const BitLink&) = delete;
  BitLink& operator=(const BitLink&) = delete;

  /// Connects now if not connected (the device's open check).
  Status Connect();
  /// Reads one discrete input (`discrete`) or coil.
  Result<bool> ReadBit(bool discrete, int address);
  Status WriteCoil(int address, bool on);
  const LinkSettings& settings() const { return s_; }

 private:
  Status ConnectLocked();
  Error Classify(int err, const std::string& what);

  const LinkSettings s_;
  std::mutex mu_;
  _modbus* ctx_ = nullptr;
  bool connected_ = false;
};

class ModbusButton final : public Button {
 public:
  /// `clock` must outlive the button.
  ModbusButton(Clock& clock, const ButtonConfig& config, std::shared_ptr<BitLink> link);
  ~ModbusButton() override;
  std::string Describe() const override;
  /// Completed polls since Start() (tests: a deterministic wait).
  int polls() const { return polls_.load(); }

 protected:
  Status DoStart() override;
  void DoStop() override;

 private:
  void Run(bool last);

  const ModbusButtonConfig config_;
  std::shared_ptr<BitLink> link_;
  std::mutex mu_;
  std::condition_variable cv_;
  bool stop_ = false;
  std::atomic<int> polls_{0};
  std::thread thread_;
};

class ModbusLight final : public StatusLight {
 public:
  ModbusLight(const ModbusLightConfig& config, std::shared_ptr<BitLink> link)
      : config_(config), link_(std::move(link)) {}
  ~ModbusLight() override { Close(); }
  std::string Describe() const override;

 protected:
  Status DoOpen() override { return link_->Connect(); }
  Status DoSet(bool on) override { return link_->WriteCoil(config_.coil, on); }
  void DoClose() override {}

 private:
  const ModbusLightConfig config_;
  std::shared_ptr<BitLink> link_;
};

}  // namespace aggscan::modbus
