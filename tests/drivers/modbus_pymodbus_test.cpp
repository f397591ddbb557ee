// Interoperability: the Modbus backend (libmodbus) against an independent
// Modbus implementation, python3-pymodbus, acting as a turntable with the
// generic register map (tests/drivers/pymodbus_turntable.py, started here as a
// subprocess on a free loopback port). Exits 77 (skipped) when no python3 with
// pymodbus is installed; never passes without having talked to it.
#include <fcntl.h>
#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <modbus/modbus.h>
#include <netinet/in.h>
#include <signal.h>
#include <spawn.h>
#include <sys/socket.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <memory>
#include <string>
#include <thread>
#include <vector>

#include "config/turntable_profile.h"
#include "drivers/modbus/modbus_turntable.h"
#include "tests/drivers/modbus_test_server.h"

extern char** environ;

namespace aggscan {
namespace {

using Clock = std::chrono::steady_clock;

std::string g_python;  // an interpreter that imports pymodbus

// Runs argv; returns the exit status (-1 when it could not start).
int Run(const std::vector<std::string>& argv, bool quiet) {
  std::vector<char*> args;
  for (const auto& a : argv) args.push_back(const_cast<char*>(a.c_str()));
  args.push_back(nullptr);
  posix_spawn_file_actions_t fa;
  posix_spawn_file_actions_init(&fa);
  if (quiet) {
    posix_spawn_file_actions_addopen(&fa, 1, "/dev/null", O_WRONLY, 0);
    posix_spawn_file_actions_addopen(&fa, 2, "/dev/null", O_WRONLY, 0);
  }
  pid_t pid = 0;
  const int rc = posix_spawnp(&pid, args[0], &fa, nullptr, args.data(), environ);
  posix_spawn_file_actions_destroy(&fa);
  if (rc != 0) return -1;
  int status = 0;
  waitpid(pid, &status, 0);
  return WIFEXITED(status) ? WEXITSTATUS(status) : -1;
}

// The pymodbus controller process; killed and reaped when it goes.
class PyServer {
 public:
  PyServer(int port, const std::string& log) {
    const std::string script =
        std::string(AGGSCAN_SOURCE_DIR) + "/tests/drivers/pymodbus_turntable.py";
    std::vector<std::string> argv = {g_python,          script, "--port", std::to_string(port),
                                     "--steps-per-rev", "32000"};
    std::vector<char*> args;
    for (auto& a : argv) args.push_back(a.data());
    args.push_back(nullptr);
    posix_spawn_file_actions_t fa;
    posix_spawn_file_actions_init(&fa);
    posix_spawn_file_actions_addopen(&fa, 1, log.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0644);
    posix_spawn_file_actions_adddup2(&fa, 1, 2);
    if (posix_spawnp(&pid_, args[0], &fa, nullptr, args.data(), environ) != 0) pid_ = -1;
    posix_spawn_file_actions_destroy(&fa);
  }
  ~PyServer() {
    if (pid_ > 0) {
      kill(pid_, SIGTERM);
      int status = 0;
      waitpid(pid_, &status, 0);
    }
  }
  bool started() const { return pid_ > 0; }
  bool exited() {
    int status = 0;
    return pid_ > 0 && waitpid(pid_, &status, WNOHANG) == pid_ ? (pid_ = -1, true) : false;
  }

 private:
  pid_t pid_ = -1;
};

int FreePort() {
  int fd = socket(AF_INET, SOCK_STREAM, 0);
  sockaddr_in a{};
  a.sin_family = AF_INET;
  a.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  bind(fd, reinterpret_cast<sockaddr*>(&a), sizeof(a));
  socklen_t len = sizeof(a);
  getsockname(fd, reinterpret_cast<sockaddr*>(&a), &len);
  close(fd);
  return ntohs(a.sin_port);
}

TurntableConfig PyConfig(int port) {
  TurntableConfig c;
  c.backend = "modbus-tcp";
  c.max_speed_deg_s = 360.0;
  c.accel_deg_s2 = 1440.0;
  c.modbus.profile = std::string(AGGSCAN_SOURCE_DIR) + "/config/turntables/generic.toml";
  c.modbus.host = "127.0.0.1";
  c.modbus.port = port;
  c.modbus.motor_steps_per_rev = 200;
  c.modbus.microsteps = 16;
  c.modbus.gear_ratio = 10.0;  // 32000 steps per turn, as the server is told
  c.modbus.response_timeout = 500 * kNsPerMs;
  return c;
}

std::unique_ptr<modbus::ModbusTurntable> MakeTurntable(const TurntableConfig& c) {
  Result<TurntableProfile> profile = FindTurntableProfile(c.modbus.profile, "");
  EXPECT_TRUE(profile.ok()) << profile.error().ToString();
  if (!profile.ok()) return nullptr;
  return std::make_unique<modbus::ModbusTurntable>(modbus::Transport::kTcp, c, std::move(*profile));
}

// Python and pymodbus take a moment to start listening.
Status OpenWhenListening(PyServer& server, Turntable& t) {
  Status open = MakeError(ErrorClass::kInternal, "not tried");
  const auto deadline = Clock::now() + std::chrono::seconds(20);
  while (Clock::now() < deadline && !server.exited()) {
    open = t.Open();
    if (open.ok()) break;
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
  }
  return open;
}

TEST(ModbusPymodbus, HomesMovesAndReadsAnglesBack) {
  const int port = FreePort();
  const std::string log = ::testing::TempDir() + "/pymodbus_turntable.log";
  PyServer server(port, log);
  ASSERT_TRUE(server.started()) << g_python;
  auto tp = MakeTurntable(PyConfig(port));
  ASSERT_TRUE(tp);
  modbus::ModbusTurntable& t = *tp;
  Status open = OpenWhenListening(server, t);
  ASSERT_TRUE(open.ok()) << open.error().ToString() << "; server log: " << log;

  Result<TurntableStatus> st = t.ReadStatus();
  ASSERT_TRUE(st.ok()) << st.error().ToString();
  EXPECT_TRUE(st->enabled);
  EXPECT_FALSE(st->homed);
  EXPECT_EQ(t.StartMoveTo(10).error().cls, ErrorClass::kInvalidState);  // home first

  ASSERT_TRUE(t.StartHome().ok());
  st = testing::WaitInPosition(t);
  ASSERT_TRUE(st.ok()) << st.error().ToString();
  ASSERT_TRUE(st->in_position);
  EXPECT_TRUE(st->homed);
  EXPECT_NEAR(st->angle_deg, 0.0, 1e-9);

  const double step = 360.0 / 32000;
  for (double target : {30.0, 400.0, -45.0, 123.4}) {
    ASSERT_TRUE(t.StartMoveTo(target).ok());
    Result<TurntableStatus> moving = t.ReadStatus();
    ASSERT_TRUE(moving.ok());
    EXPECT_FALSE(moving->in_position) << target;
    st = testing::WaitInPosition(t);
    ASSERT_TRUE(st.ok()) << st.error().ToString();
    ASSERT_TRUE(st->in_position) << target;
    EXPECT_FALSE(st->moving);
    EXPECT_FALSE(st->alarm);
    EXPECT_NEAR(st->angle_deg, target, step) << target;
  }

  // Stop mid-move: the angle stays where it stopped, between the two targets.
  ASSERT_TRUE(t.StartMoveTo(300.0).ok());
  std::this_thread::sleep_for(std::chrono::milliseconds(200));
  ASSERT_TRUE(t.Stop().ok());
  Result<TurntableStatus> a = t.ReadStatus();
  std::this_thread::sleep_for(std::chrono::milliseconds(200));
  Result<TurntableStatus> b = t.ReadStatus();
  ASSERT_TRUE(a.ok() && b.ok());
  EXPECT_FALSE(b->moving);
  EXPECT_FALSE(b->in_position);
  EXPECT_GT(b->angle_deg, 123.4 + 10);
  EXPECT_LT(b->angle_deg, 300.0 - 10);
  EXPECT_EQ(a->angle_deg, b->angle_deg);
  t.Close();
}

// The test's own connection to the peer's control registers
// (pymodbus_turntable.py: 10 late command ms, 11 late status ms, 12 stops,
// 13 commands).
class PeerControl {
 public:
  explicit PeerControl(int port) : ctx_(modbus_new_tcp("127.0.0.1", port)) {
    modbus_set_slave(ctx_, 1);
    modbus_set_response_timeout(ctx_, 5, 0);  // it waits behind late answers
    connected_ = modbus_connect(ctx_) == 0;
  }
  ~PeerControl() {
    modbus_close(ctx_);
    modbus_free(ctx_);
  }
  bool connected() const { return connected_; }
  bool Set(int reg, int value) { return modbus_write_register(ctx_, reg, value) == 1; }
  int Get(int reg) {
    uint16_t v = 0;
    return modbus_read_registers(ctx_, reg, 1, &v) == 1 ? v : -1;
  }

 private:
  modbus_t* ctx_;
  bool connected_ = false;
};

// One answer after response_timeout (the desynchronised link): the
// backend re-opens the connection before the retry, so every later request
// still gets its own answer, and an unanswered stop is not sent again once
// the state shows the platter stopped.
TEST(ModbusPymodbus, LateAnswersKeepTheLinkInStepAndAStopIsSentOnce) {
  const int port = FreePort();
  const std::string log = ::testing::TempDir() + "/pymodbus_turntable_late.log";
  PyServer server(port, log);
  ASSERT_TRUE(server.started()) << g_python;
  TurntableConfig c = PyConfig(port);
  c.modbus.response_timeout = 300 * kNsPerMs;
  c.modbus.retries = 2;
  auto tp = MakeTurntable(c);
  ASSERT_TRUE(tp);
  modbus::ModbusTurntable& t = *tp;
  Status open = OpenWhenListening(server, t);
  ASSERT_TRUE(open.ok()) << open.error().ToString() << "; server log: " << log;
  PeerControl control(port);
  ASSERT_TRUE(control.connected());
  ASSERT_TRUE(t.StartHome().ok());
  Result<TurntableStatus> st = testing::WaitInPosition(t);
  ASSERT_TRUE(st.ok() && st->in_position) << (st.ok() ? "" : st.error().ToString());

  // A status read answered 450 ms late: one retry on a new connection.
  ASSERT_TRUE(control.Set(11, 450));
  int sent = t.requests_sent();
  st = t.ReadStatus();
  ASSERT_TRUE(st.ok()) << st.error().ToString();
  EXPECT_TRUE(st->homed);
  EXPECT_NEAR(st->angle_deg, 0.0, 1e-9);
  EXPECT_EQ(t.requests_sent() - sent, 2);

  // A stop answered 450 ms late, mid-move.
  const double step = 360.0 / 32000;
  ASSERT_TRUE(t.StartMoveTo(300.0).ok());
  std::this_thread::sleep_for(std::chrono::milliseconds(200));
  const int commands = control.Get(13);
  ASSERT_TRUE(control.Set(10, 450));
  Status stop = t.Stop();
  ASSERT_TRUE(stop.ok()) << stop.error().ToString();
  EXPECT_EQ(control.Get(12), 1);             // stops the peer received
  EXPECT_EQ(control.Get(13) - commands, 1);  // and nothing else was commanded
  st = t.ReadStatus();
  ASSERT_TRUE(st.ok()) << st.error().ToString();
  EXPECT_FALSE(st->moving);
  EXPECT_GT(st->angle_deg, 10.0);
  EXPECT_LT(st->angle_deg, 290.0);
  const double stopped_at = st->angle_deg;

  // In step: every read answered at the first try, with the peer's angle.
  sent = t.requests_sent();
  for (int i = 0; i < 20; ++i) {
    st = t.ReadStatus();
    ASSERT_TRUE(st.ok()) << i << ": " << st.error().ToString();
    EXPECT_EQ(st->angle_deg, stopped_at) << i;
  }
  EXPECT_EQ(t.requests_sent() - sent, 20);
  ASSERT_TRUE(t.StartMoveTo(123.4).ok());
  st = testing::WaitInPosition(t);
  ASSERT_TRUE(st.ok() && st->in_position) << (st.ok() ? "" : st.error().ToString());
  EXPECT_NEAR(st->angle_deg, 123.4, step);
  EXPECT_EQ(control.Get(12), 1);
  t.Close();
}

}  // namespace
}  // namespace aggscan

int main(int argc, char** argv) {
  ::testing::InitGoogleTest(&argc, argv);
  // AGGSCAN_PYTHON names the interpreter; else Debian's python3 (where
  // python3-pymodbus installs), then a python3 on PATH (may be another one).
  std::vector<std::string> candidates = {"/usr/bin/python3", "python3"};
  if (const char* env = std::getenv("AGGSCAN_PYTHON")) candidates = {env};
  for (const auto& py : candidates) {
    if (aggscan::Run({py, "-c", "import pymodbus.server, pymodbus.datastore"}, true) == 0) {
      aggscan::g_python = py;
      break;
    }
  }
  if (aggscan::g_python.empty()) {
    std::fprintf(stderr,
                 "SKIP: no python3 with pymodbus.server (Debian: apt-get install python3-pymodbus "
                 "python3-serial-asyncio)\n");
    return 77;
  }
  return RUN_ALL_TESTS();
}
