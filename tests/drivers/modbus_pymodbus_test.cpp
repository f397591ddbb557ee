// Interoperability: the Modbus backend (libmodbus) against an independent
// Modbus implementation, python3-pymodbus, acting as a turntable with the
// generic register map (tests/drivers/pymodbus_turntable.py, started here as a
// subprocess on a free loopback port). Exits 77 (skipped) when no python3 with
// pymodbus is installed; never passes without having talked to it.
#include <fcntl.h>
#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <netinet/in.h>
#include <signal.h>
#include <spawn.h>
#include <sys/socket.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <string>
#include <thread>
#include <vector>

#include "config/turntable_profile.h"
#include "tests/drivers/modbus_test_server.h"
#include "drivers/modbus/modbus_turntable.h"

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

TEST(ModbusPymodbus, HomesMovesAndReadsAnglesBack) {
  const int port = FreePort();
  const std::string log = ::testing::TempDir() + "/pymodbus_turntable.log";
  PyServer server(port, log);
  ASSERT_TRUE(server.started()) << g_python;

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
  Result<TurntableProfile> profile = FindTurntableProfile(c.modbus.profile, "");
  ASSERT_TRUE(profile.ok()) << profile.error().ToString();
  modbus::ModbusTurntable t(modbus::Transport::kTcp, c, std::move(*profile));

  // Python and pymodbus take a moment to start listening.
  Status open = MakeError(ErrorClass::kInternal, "not tried");
  const auto deadline = Clock::now() + std::chrono::seconds(20);
  while (Clock::now() < deadline && !server.exited()) {
    open = t.Open();
    if (open.ok()) break;
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
  }
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
                 "SKIP: no python3 with pymodbus (Debian: apt-get install python3-pymodbus)\n");
    return 77;
  }
  return RUN_ALL_TESTS();
}
