#include "tests/drivers/modbus_test_server.h"

#include <arpa/inet.h>
#include <fcntl.h>
#include <modbus/modbus.h>
#include <netinet/in.h>
#include <poll.h>
#include <stdlib.h>
#include <sys/socket.h>
#include <termios.h>
#include <time.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <stdexcept>
#include <thread>

namespace aggscan::testing {
namespace {

int64_t NowNs() {
  timespec ts;
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return static_cast<int64_t>(ts.tv_sec) * 1'000'000'000 + ts.tv_nsec;
}

// Register layouts (0-based holding registers).
namespace generic {
constexpr int kTarget = 0, kCommand = 2, kStatus = 3, kActual = 4, kAlarm = 6, kSpeed = 7,
              kAccel = 8;
constexpr int kFirst = 0, kCount = 16;
}  // namespace generic
namespace leadshine {
constexpr int kMotionStatus = 0x1003;  // bit 2 running, bit 4 command completed, bit 6 homed
constexpr int kFeedbackPos = 0x1014;   // high, low
constexpr int kControlWord = 0x1801;   // 0x1111: reset current alarm
constexpr int kCurrentAlarm = 0x2203;
constexpr int kTrigger = 0x6002;  // Pr8.02: 0x10 PR0, 0x20 home, 0x40 quick stop
constexpr int kPr0 = 0x6200;      // mode, pos hi, pos lo, rpm, acc ms, dec ms, delay, trigger
constexpr int kFirst = 0x1000, kCount = 0x6210 - 0x1000;
}  // namespace leadshine

}  // namespace

constexpr int kBits = 64;  // coils and discrete inputs at 0..63

struct ModbusTestServer::Mapping {
  modbus_mapping_t* m = nullptr;
  ~Mapping() {
    if (m) modbus_mapping_free(m);
  }
  uint16_t& at(int address) { return m->tab_registers[address - m->start_registers]; }
};

ModbusTestServer::ModbusTestServer(const ModbusServerOptions& options)
    : opt_(options), map_(std::make_unique<Mapping>()) {
  const bool gen = opt_.map == ServerMap::kGeneric;
  map_->m = modbus_mapping_new_start_address(0, kBits, 0, kBits,
                                             gen ? generic::kFirst : leadshine::kFirst,
                                             gen ? generic::kCount : leadshine::kCount, 0, 0);
  if (!map_->m) throw std::runtime_error("modbus_mapping_new_start_address failed");
  UpdateRegisters(NowNs());
}

std::unique_ptr<ModbusTestServer> ModbusTestServer::StartTcp(const ModbusServerOptions& options) {
  std::unique_ptr<ModbusTestServer> s(new ModbusTestServer(options));
  s->ctx_ = modbus_new_tcp("127.0.0.1", options.tcp_port);  // port 0: the kernel picks a free one
  if (!s->ctx_) throw std::runtime_error("modbus_new_tcp failed");
  s->listen_fd_ = modbus_tcp_listen(s->ctx_, 1);
  if (s->listen_fd_ < 0) throw std::runtime_error("modbus_tcp_listen failed");
  sockaddr_in addr{};
  socklen_t len = sizeof(addr);
  getsockname(s->listen_fd_, reinterpret_cast<sockaddr*>(&addr), &len);
  s->port_ = ntohs(addr.sin_port);
  s->thread_ = std::thread([p = s.get()] { p->Loop(); });
  return s;
}

std::unique_ptr<ModbusTestServer> ModbusTestServer::StartRtu(const ModbusServerOptions& options) {
  std::unique_ptr<ModbusTestServer> s(new ModbusTestServer(options));
  s->pty_master_ = posix_openpt(O_RDWR | O_NOCTTY);
  if (s->pty_master_ < 0 || grantpt(s->pty_master_) != 0 || unlockpt(s->pty_master_) != 0) {
    throw std::runtime_error("cannot create a pseudo-terminal pair");
  }
  char name[128];
  if (ptsname_r(s->pty_master_, name, sizeof(name)) != 0) throw std::runtime_error("ptsname_r");
  s->device_ = name;
  // Keep the slave side open and raw: the master then never sees a hang-up
  // between the backend's opens, and nothing is echoed before the backend
  // sets its own line settings.
  s->pty_slave_keep_ = open(name, O_RDWR | O_NOCTTY);
  termios tio{};
  tcgetattr(s->pty_slave_keep_, &tio);
  cfmakeraw(&tio);
  tcsetattr(s->pty_slave_keep_, TCSANOW, &tio);
  s->ctx_ = modbus_new_rtu(name, 19200, 'N', 8, 1);
  if (!s->ctx_) throw std::runtime_error("modbus_new_rtu failed");
  modbus_set_slave(s->ctx_, options.unit_id);
  modbus_set_socket(s->ctx_, s->pty_master_);
  s->thread_ = std::thread([p = s.get()] { p->Loop(); });
  return s;
}

ModbusTestServer::~ModbusTestServer() {
  stop_ = true;
  if (thread_.joinable()) thread_.join();
  if (ctx_) {
    modbus_set_socket(ctx_, -1);  // the fds are closed below, once
    modbus_free(ctx_);
  }
  for (int fd : {client_fd_, listen_fd_, pty_slave_keep_, pty_master_}) {
    if (fd >= 0) close(fd);
  }
}

void ModbusTestServer::Loop() {
  uint8_t query[MODBUS_TCP_MAX_ADU_LENGTH];
  while (!stop_) {
    if (pty_master_ >= 0) {
      pollfd p{pty_master_, POLLIN, 0};
      if (poll(&p, 1, 20) <= 0 || !(p.revents & POLLIN)) continue;
      const int rc = modbus_receive(ctx_, query);
      if (rc > 0) {
        Handle(query, rc);
      } else if (rc < 0) {
        modbus_flush(ctx_);
      }
      continue;
    }
    {
      std::lock_guard<std::mutex> l(mu_);
      if (drop_ && client_fd_ >= 0) {
        close(client_fd_);
        client_fd_ = -1;
        modbus_set_socket(ctx_, -1);
      }
      drop_ = false;
    }
    pollfd fds[2] = {{listen_fd_, POLLIN, 0}, {client_fd_, POLLIN, 0}};
    if (poll(fds, client_fd_ >= 0 ? 2 : 1, 20) <= 0) continue;
    if (fds[0].revents & POLLIN) {
      if (client_fd_ >= 0) close(client_fd_);
      client_fd_ = modbus_tcp_accept(ctx_, &listen_fd_);
      continue;
    }
    if (client_fd_ >= 0 && (fds[1].revents & (POLLIN | POLLHUP | POLLERR))) {
      modbus_set_socket(ctx_, client_fd_);
      const int rc = modbus_receive(ctx_, query);
      if (rc > 0) {
        Handle(query, rc);
      } else if (rc < 0) {
        close(client_fd_);
        client_fd_ = -1;
        modbus_set_socket(ctx_, -1);
      }
    }
  }
}

void ModbusTestServer::Handle(const uint8_t* req, int len) {
  const int hl = modbus_get_header_length(ctx_);
  if (req[hl - 1] != opt_.unit_id) return;  // another unit's request: no answer
  std::unique_lock<std::mutex> l(mu_);
  ++requests_;
  if (silent_) return;
  const int function = req[hl];
  const int address = (req[hl + 1] << 8) | req[hl + 2];
  const bool single =
      function == MODBUS_FC_WRITE_SINGLE_REGISTER || function == MODBUS_FC_WRITE_SINGLE_COIL;
  const int count = single ? 1 : (req[hl + 3] << 8) | req[hl + 4];
  for (int r : rejected_) {
    if (r >= address && r < address + count) {
      modbus_reply_exception(ctx_, req, MODBUS_EXCEPTION_ILLEGAL_DATA_ADDRESS);
      return;
    }
  }
  const int64_t now = NowNs();
  Advance(now);
  UpdateRegisters(now);
  if (ignore_function_ && (*ignore_function_ == 0 || *ignore_function_ == function)) {
    ignore_function_.reset();
    return;
  }
  const bool late = late_seconds_ > 0 && (late_function_ == 0 || late_function_ == function);
  const bool wrong_tid = wrong_tid_ && pty_master_ < 0;
  if (!late && !wrong_tid) {
    if (modbus_reply(ctx_, req, len, map_->m) > 0 && function == MODBUS_FC_WRITE_SINGLE_COIL)
      ++coil_writes_;
    ApplyCommands(now);
    UpdateRegisters(now);
    return;
  }
  // Executed now, answered as injected: the answer is built into a socket
  // pair, held or altered, and then written to the link the request came by.
  const double delay = late ? late_seconds_ : 0.0;
  if (late) late_seconds_ = 0;
  int pair[2];
  if (socketpair(AF_UNIX, SOCK_STREAM, 0, pair) != 0) return;
  const int link = modbus_get_socket(ctx_);
  modbus_set_socket(ctx_, pair[0]);
  const int n = modbus_reply(ctx_, req, len, map_->m);
  modbus_set_socket(ctx_, link);
  uint8_t answer[MODBUS_TCP_MAX_ADU_LENGTH];
  const ssize_t got = n > 0 ? read(pair[1], answer, sizeof(answer)) : 0;
  close(pair[0]);
  close(pair[1]);
  ApplyCommands(now);
  UpdateRegisters(now);
  if (wrong_tid && got >= 2) answer[1] ^= 0x5A;  // MBAP bytes 0-1: the transaction id
  if (delay > 0) {
    l.unlock();  // observers and fault injection go on meanwhile
    std::this_thread::sleep_for(std::chrono::duration<double>(delay));
    l.lock();
  }
  if (got > 0) {
    // The client may have closed the connection meanwhile: no SIGPIPE.
    if (pty_master_ >= 0) {
      (void)!write(link, answer, static_cast<size_t>(got));
    } else {
      (void)send(link, answer, static_cast<size_t>(got), MSG_NOSIGNAL);
    }
  }
}

void ModbusTestServer::StartMotion(int64_t now, double target, double v, double a) {
  start_pos_ = pos_;
  goal_ = target;
  v_ = v;
  a_ = a;
  t0_ = now;
  moving_ = true;
  homing_ = false;
  in_position_ = false;
  stalled_ = false;
  min_pos_ = max_pos_ = pos_;
  targets_.push_back(static_cast<int64_t>(target));
}

void ModbusTestServer::Advance(int64_t now) {
  const double t = static_cast<double>(now - t0_) / 1e9;
  if (homing_) {
    const double f = t / opt_.home_seconds;
    if (f >= 1) {
      pos_ = 0;
      homing_ = moving_ = false;
      homed_ = in_position_ = true;
    } else {
      pos_ = start_pos_ * (1 - f);
    }
    return;
  }
  if (!moving_ || stalled_) return;
  // Trapezoidal (or triangular) profile from rest to rest.
  const double d = std::fabs(goal_ - start_pos_);
  const double sign = goal_ >= start_pos_ ? 1 : -1;
  double s = 0, total = 0;
  if (d >= v_ * v_ / a_) {
    const double ta = v_ / a_, da = 0.5 * v_ * v_ / a_;
    total = d / v_ + ta;
    if (t < ta)
      s = 0.5 * a_ * t * t;
    else if (t < total - ta)
      s = da + v_ * (t - ta);
    else if (t < total)
      s = d - 0.5 * a_ * (total - t) * (total - t);
    else
      s = d;
  } else {
    const double ta = std::sqrt(d / a_);
    total = 2 * ta;
    if (t < ta)
      s = 0.5 * a_ * t * t;
    else if (t < total)
      s = d - 0.5 * a_ * (total - t) * (total - t);
    else
      s = d;
  }
  const double next = start_pos_ + sign * s;
  if (stall_at_) {
    const double st = static_cast<double>(*stall_at_);
    if ((st - pos_) * (st - next) <= 0 && (st - start_pos_) * (goal_ - st) >= 0) {
      pos_ = st;
      stalled_ = true;  // still "moving": the motor turns, the platter does not
      min_pos_ = std::min(min_pos_, pos_);
      max_pos_ = std::max(max_pos_, pos_);
      return;
    }
  }
  pos_ = next;
  min_pos_ = std::min(min_pos_, pos_);
  max_pos_ = std::max(max_pos_, pos_);
  if (t >= total) {
    pos_ = goal_ + static_cast<double>(rest_error_);
    moving_ = false;
    in_position_ = true;
    rests_.push_back(std::lround(pos_));
  }
}

void ModbusTestServer::UpdateRegisters(int64_t now) {
  (void)now;
  const auto steps = static_cast<int32_t>(std::lround(pos_));
  const auto u = static_cast<uint32_t>(steps);
  const uint16_t hi = static_cast<uint16_t>(u >> 16), lo = static_cast<uint16_t>(u & 0xFFFF);
  if (opt_.map == ServerMap::kGeneric) {
    map_->at(generic::kStatus) =
        static_cast<uint16_t>(1 | (moving_ || homing_ ? 2 : 0) | (in_position_ ? 4 : 0) |
                              (homed_ ? 8 : 0) | (alarm_ ? 16 : 0));
    map_->at(generic::kActual) = opt_.low_word_first ? lo : hi;
    map_->at(generic::kActual + 1) = opt_.low_word_first ? hi : lo;
    map_->at(generic::kAlarm) = static_cast<uint16_t>(alarm_code_);
  } else {
    map_->at(leadshine::kMotionStatus) = static_cast<uint16_t>(
        (moving_ || homing_ ? 1 << 2 : 0) | (in_position_ ? 1 << 4 : 0) | (homed_ ? 1 << 6 : 0));
    map_->at(leadshine::kFeedbackPos) = hi;
    map_->at(leadshine::kFeedbackPos + 1) = lo;
    map_->at(leadshine::kCurrentAlarm) = static_cast<uint16_t>(alarm_code_);
  }
}

void ModbusTestServer::ApplyCommands(int64_t now) {
  auto home = [&] {
    start_pos_ = pos_;
    t0_ = now;
    homing_ = true;
    moving_ = homed_ = in_position_ = stalled_ = false;
  };
  auto stop = [&] { moving_ = homing_ = in_position_ = stalled_ = false; };
  auto reset = [&] {
    alarm_ = false;
    alarm_code_ = 0;
  };
  if (opt_.map == ServerMap::kGeneric) {
    const int cmd = map_->at(generic::kCommand);
    if (cmd == 0) return;
    commands_.push_back(cmd);
    map_->at(generic::kCommand) = 0;
    const uint16_t w0 = map_->at(generic::kTarget), w1 = map_->at(generic::kTarget + 1);
    const auto target =
        static_cast<int32_t>(opt_.low_word_first ? (static_cast<uint32_t>(w1) << 16) | w0
                                                 : (static_cast<uint32_t>(w0) << 16) | w1);
    const double per_deg = opt_.steps_per_rev / 360.0;
    const double v = map_->at(generic::kSpeed) * 0.1 * per_deg;
    const double a = map_->at(generic::kAccel) * 0.1 * per_deg;
    switch (cmd) {
      case 1:
        if (!alarm_ && v > 0 && a > 0) StartMotion(now, target, v, a);
        break;
      case 2:
        if (!alarm_) home();
        break;
      case 3:
        stop();
        break;
      case 4:
        reset();
        break;
      default:
        break;
    }
    return;
  }
  if (map_->at(leadshine::kControlWord) == 0x1111) {
    map_->at(leadshine::kControlWord) = 0;
    reset();
  }
  // Pr9.07 (the last register of the PR0 block) is mapped to Pr8.02.
  int trig = map_->at(leadshine::kTrigger);
  if (map_->at(leadshine::kPr0 + 7) != 0) {
    trig = map_->at(leadshine::kPr0 + 7);
    map_->at(leadshine::kPr0 + 7) = 0;
  }
  if (trig == 0) return;
  map_->at(leadshine::kTrigger) = 0;
  commands_.push_back(trig);
  if (trig == 0x10) {
    const int mode = map_->at(leadshine::kPr0);
    if ((mode & 0xF) != 1 || alarm_) return;  // only position moves are modelled
    const auto target =
        static_cast<int32_t>((static_cast<uint32_t>(map_->at(leadshine::kPr0 + 1)) << 16) |
                             map_->at(leadshine::kPr0 + 2));
    const double rpm = map_->at(leadshine::kPr0 + 3);
    const double acc_ms = map_->at(leadshine::kPr0 + 4);
    const double v = rpm * opt_.motor_steps_per_rev / 60.0;
    const double a =
        acc_ms > 0 ? (1000.0 * opt_.motor_steps_per_rev / 60.0) / (acc_ms / 1000.0) : 0;
    const double goal = (mode & 0x40) ? pos_ + target : target;
    if (v > 0 && a > 0) StartMotion(now, goal, v, a);
  } else if (trig == 0x20) {
    if (!alarm_) home();
  } else if (trig == 0x40) {
    stop();
  }
}

void ModbusTestServer::SetSilent(bool silent) {
  std::lock_guard<std::mutex> l(mu_);
  silent_ = silent;
}

void ModbusTestServer::SetStallAtSteps(std::optional<int64_t> steps) {
  std::lock_guard<std::mutex> l(mu_);
  stall_at_ = steps;
}

void ModbusTestServer::SetRestErrorSteps(int64_t steps) {
  std::lock_guard<std::mutex> l(mu_);
  rest_error_ = steps;
}

void ModbusTestServer::RaiseAlarm(int code) {
  std::lock_guard<std::mutex> l(mu_);
  Advance(NowNs());
  alarm_ = true;
  alarm_code_ = code;
  moving_ = homing_ = in_position_ = false;
  UpdateRegisters(NowNs());
}

void ModbusTestServer::AnswerNextLate(double seconds, int function) {
  std::lock_guard<std::mutex> l(mu_);
  late_seconds_ = seconds;
  late_function_ = function;
}

void ModbusTestServer::IgnoreNext(int function) {
  std::lock_guard<std::mutex> l(mu_);
  ignore_function_ = function;
}

void ModbusTestServer::SetWrongTransactionId(bool on) {
  std::lock_guard<std::mutex> l(mu_);
  wrong_tid_ = on;
}

std::vector<int> ModbusTestServer::commands() {
  std::lock_guard<std::mutex> l(mu_);
  return commands_;
}

void ModbusTestServer::RejectRegister(int address) {
  std::lock_guard<std::mutex> l(mu_);
  rejected_.push_back(address);
}

void ModbusTestServer::DropClient() {
  std::lock_guard<std::mutex> l(mu_);
  drop_ = true;
}

int64_t ModbusTestServer::position_steps() {
  std::lock_guard<std::mutex> l(mu_);
  Advance(NowNs());
  return std::lround(pos_);
}

bool ModbusTestServer::homed() {
  std::lock_guard<std::mutex> l(mu_);
  Advance(NowNs());
  return homed_;
}

int ModbusTestServer::requests() {
  std::lock_guard<std::mutex> l(mu_);
  return requests_;
}

std::vector<int64_t> ModbusTestServer::move_targets() {
  std::lock_guard<std::mutex> l(mu_);
  return targets_;
}

std::vector<int64_t> ModbusTestServer::rest_positions() {
  std::lock_guard<std::mutex> l(mu_);
  Advance(NowNs());
  return rests_;
}

int64_t ModbusTestServer::min_steps_since_last_move() {
  std::lock_guard<std::mutex> l(mu_);
  Advance(NowNs());
  return std::lround(min_pos_);
}

int64_t ModbusTestServer::max_steps_since_last_move() {
  std::lock_guard<std::mutex> l(mu_);
  Advance(NowNs());
  return std::lround(max_pos_);
}

uint16_t ModbusTestServer::reg(int address) {
  std::lock_guard<std::mutex> l(mu_);
  return map_->at(address);
}

TurntableConfig ModbusConfigFor(const ModbusTestServer& server, bool tcp) {
  TurntableConfig c;
  c.backend = tcp ? "modbus-tcp" : "modbus-rtu";
  c.max_speed_deg_s = 360.0;
  c.accel_deg_s2 = 1440.0;
  c.repeatability_deg = 0.01;  // the contract's tolerance: step quantisation (0.011 deg) only
  c.backlash_deg = 0.0;
  ModbusTurntableConfig& m = c.modbus;
  m.profile = std::string(AGGSCAN_SOURCE_DIR) + "/config/turntables/generic.toml";
  m.unit_id = 1;
  m.host = "127.0.0.1";
  m.port = server.port();
  m.device = server.device();
  m.baud = 19200;
  m.response_timeout = 200 * kNsPerMs;
  m.retries = 1;
  m.motor_steps_per_rev = 200;
  m.microsteps = 16;
  m.gear_ratio = 10.0;
  return c;
}

Result<TurntableStatus> WaitInPosition(Turntable& t) {
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(10);
  while (true) {
    Result<TurntableStatus> st = t.ReadStatus();
    if (!st || st->in_position || std::chrono::steady_clock::now() > deadline) return st;
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
}

void ModbusTestServer::SetDiscreteInput(int address, bool on) {
  std::lock_guard<std::mutex> l(mu_);
  map_->m->tab_input_bits[address] = on ? 1 : 0;
}

void ModbusTestServer::SetCoil(int address, bool on) {
  std::lock_guard<std::mutex> l(mu_);
  map_->m->tab_bits[address] = on ? 1 : 0;
}

bool ModbusTestServer::coil(int address) {
  std::lock_guard<std::mutex> l(mu_);
  return map_->m->tab_bits[address] != 0;
}

int ModbusTestServer::coil_writes() {
  std::lock_guard<std::mutex> l(mu_);
  return coil_writes_;
}

}  // namespace aggscan::testing
