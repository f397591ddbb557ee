// The Modbus turntable backend against a libmodbus server in this process
// (tests/drivers/modbus_test_server.h): error classes and messages, bounded
// retries, exception replies, alarms, word order, the commercial profile,
// shortest path, backlash compensation, stall and link loss. The interface's
// general contract runs in turntable_contract_test.
#include "drivers/modbus/modbus_turntable.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <modbus/modbus.h>
#include <netinet/in.h>
#include <sys/socket.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <fstream>
#include <sstream>
#include <thread>

#include "common/fsutil.h"
#include "config/turntable_profile.h"
#include "tests/drivers/modbus_test_server.h"

namespace aggscan {
namespace {

using ::testing::HasSubstr;
using testing::ModbusServerOptions;
using testing::ModbusTestServer;
using testing::ServerMap;
using Clock = std::chrono::steady_clock;

const std::string kProfiles = std::string(AGGSCAN_SOURCE_DIR) + "/config/turntables/";

std::unique_ptr<modbus::ModbusTurntable> Make(const TurntableConfig& c) {
  Result<TurntableProfile> p = FindTurntableProfile(c.modbus.profile, c.modbus.profile_dir);
  EXPECT_TRUE(p.ok()) << p.error().ToString();
  return std::make_unique<modbus::ModbusTurntable>(
      c.backend == "modbus-tcp" ? modbus::Transport::kTcp : modbus::Transport::kRtu, c,
      std::move(*p));
}

void OpenHome(Turntable& t) {
  Status s = t.Open();
  ASSERT_TRUE(s.ok()) << s.error().ToString();
  ASSERT_TRUE(t.StartHome().ok());
  auto st = testing::WaitInPosition(t);
  ASSERT_TRUE(st.ok()) << st.error().ToString();
  ASSERT_TRUE(st->in_position && st->homed);
}

void MoveTo(Turntable& t, double deg, TurntableStatus* out) {
  Status s = t.StartMoveTo(deg);
  ASSERT_TRUE(s.ok()) << s.error().ToString();
  auto st = testing::WaitInPosition(t);
  ASSERT_TRUE(st.ok()) << st.error().ToString();
  ASSERT_TRUE(st->in_position) << "move to " << deg << " did not finish";
  *out = *st;
}

constexpr double kStepDeg = 360.0 / 32000;  // ModbusConfigFor: 200 x 16 x 10 steps per turn

TEST(ModbusTurntable, NoAnswerIsATimeoutNamingUnitPortAndLine) {
  auto server = ModbusTestServer::StartRtu({});
  TurntableConfig c = testing::ModbusConfigFor(*server, false);
  auto t = Make(c);
  ASSERT_TRUE(t->Open().ok());
  server->SetSilent(true);
  Result<TurntableStatus> st = t->ReadStatus();
  ASSERT_FALSE(st.ok());
  EXPECT_EQ(st.error().cls, ErrorClass::kTimeout);
  EXPECT_EQ(st.error().message, "no answer from Modbus unit 1 on " + server->device() +
                                    " at 19200 8N1 — check wiring and unit id");
  EXPECT_THAT(st.error().detail, HasSubstr("reading status"));
  // It answers again: the backend recovers without reopening.
  server->SetSilent(false);
  EXPECT_TRUE(t->ReadStatus().ok());
}

TEST(ModbusTurntable, TcpTimeoutNamesHostAndPort) {
  auto server = ModbusTestServer::StartTcp({});
  TurntableConfig c = testing::ModbusConfigFor(*server, true);
  auto t = Make(c);
  ASSERT_TRUE(t->Open().ok());
  server->SetSilent(true);
  Status s = t->StartHome();
  ASSERT_FALSE(s.ok());
  EXPECT_EQ(s.error().cls, ErrorClass::kTimeout);
  EXPECT_THAT(s.error().message, HasSubstr("no answer from Modbus unit 1 at 127.0.0.1:" +
                                           std::to_string(server->port())));
}

TEST(ModbusTurntable, RetriesAreBounded) {
  auto server = ModbusTestServer::StartRtu({});
  TurntableConfig c = testing::ModbusConfigFor(*server, false);
  c.modbus.retries = 3;
  c.modbus.response_timeout = 100 * kNsPerMs;
  auto t = Make(c);
  ASSERT_TRUE(t->Open().ok());
  server->SetSilent(true);
  const int before = server->requests();
  const int sent_before = t->requests_sent();
  const auto t0 = Clock::now();
  Result<TurntableStatus> st = t->ReadStatus();
  const double took = std::chrono::duration<double>(Clock::now() - t0).count();
  ASSERT_FALSE(st.ok());
  EXPECT_EQ(st.error().cls, ErrorClass::kTimeout);
  // One status block on the generic map: 1 try + 3 retries, then give up.
  EXPECT_EQ(server->requests() - before, 4);
  EXPECT_EQ(t->requests_sent() - sent_before, 4);
  EXPECT_THAT(st.error().detail, HasSubstr("4 tries"));
  EXPECT_GE(took, 0.35);
  EXPECT_LT(took, 2.0);
}

TEST(ModbusTurntable, WrongUnitIdGetsNoAnswer) {
  auto server = ModbusTestServer::StartRtu({});
  TurntableConfig c = testing::ModbusConfigFor(*server, false);
  c.modbus.unit_id = 7;
  c.modbus.retries = 0;
  auto t = Make(c);
  Status s = t->Open();
  ASSERT_FALSE(s.ok());
  EXPECT_EQ(s.error().cls, ErrorClass::kTimeout);
  EXPECT_THAT(s.error().message, HasSubstr("no answer from Modbus unit 7 on "));
  EXPECT_FALSE(t->is_open());
}

TEST(ModbusTurntable, ExceptionReplyIsNamedAndNotRetried) {
  auto server = ModbusTestServer::StartTcp({});
  TurntableConfig c = testing::ModbusConfigFor(*server, true);
  auto t = Make(c);
  ASSERT_TRUE(t->Open().ok());
  server->RejectRegister(2);  // the command register
  const int before = server->requests();
  Status s = t->StartHome();
  ASSERT_FALSE(s.ok());
  EXPECT_EQ(s.error().cls, ErrorClass::kDeviceFault);
  EXPECT_THAT(s.error().message, HasSubstr("refused writing the home command (register 0x0002)"));
  EXPECT_THAT(s.error().message, HasSubstr("exception 2 (illegal data address)"));
  EXPECT_THAT(s.error().message, HasSubstr("profile \"generic\""));
  EXPECT_EQ(server->requests() - before, 2);  // the status read, then one write: no retry
  EXPECT_THAT(s.error().detail, HasSubstr("(1 try,"));
}

TEST(ModbusTurntable, MissingDevicesAreClassified) {
  TurntableConfig c;
  c.backend = "modbus-rtu";
  c.modbus.profile = kProfiles + "generic.toml";
  c.modbus.device = "/dev/aggscan-no-such-tty";
  auto rtu = Make(c);
  Status s = rtu->Open();
  ASSERT_FALSE(s.ok());
  EXPECT_EQ(s.error().cls, ErrorClass::kDeviceMissing);
  EXPECT_THAT(s.error().message, HasSubstr("serial device /dev/aggscan-no-such-tty not found"));

  // A TCP port nobody listens on.
  int fd = socket(AF_INET, SOCK_STREAM, 0);
  sockaddr_in a{};
  a.sin_family = AF_INET;
  a.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  ASSERT_EQ(bind(fd, reinterpret_cast<sockaddr*>(&a), sizeof(a)), 0);
  socklen_t len = sizeof(a);
  getsockname(fd, reinterpret_cast<sockaddr*>(&a), &len);
  close(fd);
  c.backend = "modbus-tcp";
  c.modbus.host = "127.0.0.1";
  c.modbus.port = ntohs(a.sin_port);
  auto tcp = Make(c);
  s = tcp->Open();
  ASSERT_FALSE(s.ok());
  EXPECT_EQ(s.error().cls, ErrorClass::kDeviceMissing);
  EXPECT_THAT(s.error().message,
              HasSubstr("cannot connect to the Modbus controller at 127.0.0.1:"));
}

TEST(ModbusTurntable, LostConnectionIsReopenedOrReportedDisconnected) {
  auto server = ModbusTestServer::StartTcp({});
  TurntableConfig c = testing::ModbusConfigFor(*server, true);
  auto t = Make(c);
  OpenHome(*t);
  server->DropClient();
  std::this_thread::sleep_for(std::chrono::milliseconds(100));
  Result<TurntableStatus> st = t->ReadStatus();  // reconnects once and answers
  ASSERT_TRUE(st.ok()) << st.error().ToString();
  EXPECT_TRUE(st->homed);
  server.reset();  // the controller is gone
  st = t->ReadStatus();
  ASSERT_FALSE(st.ok());
  EXPECT_EQ(st.error().cls, ErrorClass::kDisconnected) << st.error().ToString();
}

// A USB-serial adapter pulled out: the pty pair goes away under the backend.
TEST(ModbusTurntable, UnpluggedSerialDeviceIsDisconnected) {
  auto server = ModbusTestServer::StartRtu({});
  const std::string device = server->device();
  auto t = Make(testing::ModbusConfigFor(*server, false));
  OpenHome(*t);
  server.reset();
  Result<TurntableStatus> st = t->ReadStatus();
  ASSERT_FALSE(st.ok());
  EXPECT_EQ(st.error().cls, ErrorClass::kDisconnected) << st.error().ToString();
  EXPECT_THAT(st.error().message, HasSubstr(device)) << st.error().ToString();
}

TEST(ModbusTurntable, AlarmIsReportedAndHomingResetsIt) {
  auto server = ModbusTestServer::StartRtu({});
  auto t = Make(testing::ModbusConfigFor(*server, false));
  OpenHome(*t);
  ASSERT_TRUE(t->StartMoveTo(300).ok());
  std::this_thread::sleep_for(std::chrono::milliseconds(200));
  server->RaiseAlarm(7);
  Result<TurntableStatus> st = t->ReadStatus();
  ASSERT_TRUE(st.ok()) << st.error().ToString();
  EXPECT_TRUE(st->alarm);
  EXPECT_EQ(st->alarm_code, 7);
  EXPECT_FALSE(st->in_position);
  EXPECT_FALSE(st->moving);
  EXPECT_THAT(st->alarm_text, HasSubstr("alarm code 7"));
  Status s = t->StartMoveTo(10);
  ASSERT_FALSE(s.ok());
  EXPECT_EQ(s.error().cls, ErrorClass::kDeviceFault);
  EXPECT_THAT(s.error().message, HasSubstr("in alarm (code 7)"));
  ASSERT_TRUE(t->StartHome().ok());
  st = testing::WaitInPosition(*t);
  ASSERT_TRUE(st.ok());
  EXPECT_FALSE(st->alarm);
  EXPECT_EQ(st->alarm_code, 0);
  EXPECT_TRUE(st->in_position && st->homed);
}

// A profile text with one line replaced (the shipped file stays the source).
std::string WriteVariant(const std::string& from, const std::string& what,
                         const std::string& with) {
  Result<std::string> text = ReadFile(kProfiles + from);
  EXPECT_TRUE(text.ok());
  std::string s = *text;
  const size_t at = s.find(what);
  EXPECT_NE(at, std::string::npos) << what;
  s.replace(at, what.size(), with);
  const std::string path = ::testing::TempDir() + "/variant_" + std::to_string(getpid()) + ".toml";
  std::ofstream(path) << s;
  return path;
}

TEST(ModbusTurntable, WordOrderIsTakenFromTheProfile) {
  ModbusServerOptions opt;
  opt.low_word_first = true;
  auto server = ModbusTestServer::StartTcp(opt);
  TurntableConfig c = testing::ModbusConfigFor(*server, true);
  c.modbus.profile =
      WriteVariant("generic.toml", "word_order = \"high_first\"", "word_order = \"low_first\"");
  auto t = Make(c);
  OpenHome(*t);
  TurntableStatus st;
  // 900 deg = 80000 steps (0x00013880) and -30 deg = -2667 steps (0xFFFFF595):
  // both words matter.
  MoveTo(*t, 900.0, &st);
  EXPECT_NEAR(st.angle_deg, 900.0, kStepDeg);
  EXPECT_EQ(server->position_steps(), 80000);
  MoveTo(*t, -30.0, &st);
  EXPECT_NEAR(st.angle_deg, -30.0, kStepDeg);
  EXPECT_EQ(server->position_steps(), -2667);

  // The shipped high_first profile against this low-word-first controller
  // reads a wrong angle: the test can tell the two orders apart.
  TurntableConfig wrong = testing::ModbusConfigFor(*server, true);
  auto w = Make(wrong);
  ASSERT_TRUE(w->Open().ok());
  Result<TurntableStatus> ws = w->ReadStatus();
  ASSERT_TRUE(ws.ok());
  EXPECT_GT(std::fabs(ws->angle_deg - -30.0), 1000.0) << ws->angle_deg;
}

TEST(ModbusTurntable, LeadshineProfileRoundTrip) {
  ModbusServerOptions opt;
  opt.map = ServerMap::kLeadshine;
  opt.motor_steps_per_rev = 10000;  // Pr0.00 pulses per revolution
  auto server = ModbusTestServer::StartRtu(opt);
  TurntableConfig c = testing::ModbusConfigFor(*server, false);
  c.modbus.profile = "leadshine-iem-rs";
  c.modbus.profile_dir = kProfiles;
  c.modbus.motor_steps_per_rev = 200;
  c.modbus.microsteps = 50;
  c.modbus.gear_ratio = 3.0;  // 30000 pulses per platter turn
  auto t = Make(c);
  OpenHome(*t);
  EXPECT_EQ(server->reg(0x6200), 0x0001);  // on_open: PR0 absolute position mode
  TurntableStatus st;
  for (double target : {30.0, 400.0, -45.0, 0.0}) {
    MoveTo(*t, target, &st);
    EXPECT_NEAR(st.angle_deg, target, 360.0 / 30000) << target;
    EXPECT_EQ(server->position_steps(), std::llround(target * 30000 / 360)) << target;
  }
  // 360 deg/s at the platter = 180 motor rpm; 1440 deg/s^2 = 720 rpm/s, so
  // 1000 rpm take 1389 ms (acceleration and deceleration alike).
  EXPECT_EQ(server->reg(0x6203), 180);
  EXPECT_EQ(server->reg(0x6204), 1389);
  EXPECT_EQ(server->reg(0x6205), 1389);
  // Stop, and the alarm code's text from the profile.
  ASSERT_TRUE(t->StartMoveTo(300.0).ok());
  std::this_thread::sleep_for(std::chrono::milliseconds(150));
  ASSERT_TRUE(t->Stop().ok());
  Result<TurntableStatus> r = t->ReadStatus();
  ASSERT_TRUE(r.ok());
  EXPECT_FALSE(r->moving);
  EXPECT_FALSE(r->in_position);
  EXPECT_GT(r->angle_deg, 1.0);
  EXPECT_LT(r->angle_deg, 299.0);
  server->RaiseAlarm(0x01);
  r = t->ReadStatus();
  ASSERT_TRUE(r.ok());
  EXPECT_TRUE(r->alarm);
  EXPECT_THAT(r->alarm_text, HasSubstr("over current"));
  ASSERT_TRUE(t->ResetAlarm().ok());
  r = t->ReadStatus();
  ASSERT_TRUE(r.ok());
  EXPECT_FALSE(r->alarm);
}

TEST(ModbusTurntable, ShortestPathKeepsCumulativeAngles) {
  auto server = ModbusTestServer::StartTcp({});
  TurntableConfig c = testing::ModbusConfigFor(*server, true);
  c.modbus.shortest_path = true;
  auto t = Make(c);
  OpenHome(*t);
  TurntableStatus st;
  MoveTo(*t, 350.0, &st);  // 10 deg backwards, not 350 forwards
  EXPECT_NEAR(st.angle_deg, 350.0, kStepDeg);
  EXPECT_EQ(server->position_steps(), std::llround(-10.0 / kStepDeg));
  MoveTo(*t, 720.0, &st);  // 10 deg forwards to the same place as 0
  EXPECT_NEAR(st.angle_deg, 720.0, kStepDeg);
  EXPECT_EQ(server->position_steps(), 0);
  MoveTo(*t, 750.0, &st);
  EXPECT_NEAR(st.angle_deg, 750.0, kStepDeg);
  EXPECT_EQ(server->position_steps(), std::llround(30.0 / kStepDeg));
}

TEST(ModbusTurntable, BacklashCompensationApproachesFromOneSide) {
  auto server = ModbusTestServer::StartRtu({});
  TurntableConfig c = testing::ModbusConfigFor(*server, false);
  c.modbus.backlash_comp_deg = 2.0;
  auto t = Make(c);
  OpenHome(*t);
  TurntableStatus st;
  MoveTo(*t, 90.0, &st);  // positive: straight there
  ASSERT_EQ(server->move_targets().size(), 1u);
  MoveTo(*t, 45.0, &st);  // negative: past 45 to 43, then up to 45
  EXPECT_NEAR(st.angle_deg, 45.0, kStepDeg);
  std::vector<int64_t> targets = server->move_targets();
  ASSERT_EQ(targets.size(), 3u);
  EXPECT_EQ(targets[1], std::llround(45.0 / kStepDeg) - std::llround(2.0 / kStepDeg));
  EXPECT_EQ(targets[2], std::llround(45.0 / kStepDeg));
  EXPECT_EQ(server->position_steps(), std::llround(45.0 / kStepDeg));

  // The other side: targets are approached going down.
  c.modbus.backlash_approach = "negative";
  auto n = Make(c);
  OpenHome(*n);
  MoveTo(*n, 30.0, &st);  // up: to 32, then down to 30
  EXPECT_NEAR(st.angle_deg, 30.0, kStepDeg);
  targets = server->move_targets();
  ASSERT_GE(targets.size(), 2u);
  EXPECT_EQ(targets[targets.size() - 2],
            std::llround(30.0 / kStepDeg) + std::llround(2.0 / kStepDeg));
  EXPECT_EQ(targets.back(), std::llround(30.0 / kStepDeg));
}

// What the capture service's stall detector sees: moving, angle not advancing.
TEST(ModbusTurntable, StallShowsAsMovingWithoutProgress) {
  auto server = ModbusTestServer::StartTcp({});
  auto t = Make(testing::ModbusConfigFor(*server, true));
  OpenHome(*t);
  server->SetStallAtSteps(std::llround(20.0 / kStepDeg));
  ASSERT_TRUE(t->StartMoveTo(90.0).ok());
  std::this_thread::sleep_for(std::chrono::milliseconds(600));  // the move alone takes 0.5 s
  Result<TurntableStatus> a = t->ReadStatus();
  std::this_thread::sleep_for(std::chrono::milliseconds(200));
  Result<TurntableStatus> b = t->ReadStatus();
  ASSERT_TRUE(a.ok() && b.ok());
  EXPECT_TRUE(a->moving && b->moving);
  EXPECT_FALSE(b->in_position);
  EXPECT_NEAR(a->angle_deg, 20.0, kStepDeg);
  EXPECT_EQ(a->angle_deg, b->angle_deg);
}

TEST(ModbusTurntable, MotionLimitThatDoesNotFitARegisterIsRefused) {
  auto server = ModbusTestServer::StartTcp({});
  TurntableConfig c = testing::ModbusConfigFor(*server, true);
  c.max_speed_deg_s = 7000.0;  // 70000 counts of 0.1 deg/s
  auto t = Make(c);
  Status s = t->Open();
  ASSERT_FALSE(s.ok());
  EXPECT_EQ(s.error().cls, ErrorClass::kInvalidConfig);
  EXPECT_THAT(s.error().message, HasSubstr("turntable.max_speed_deg_s gives 70000 counts"));
  EXPECT_EQ(server->requests(), 0);  // refused before talking
}

// A pty takes no TIOCSRS485: RS-485 mode is then a warning, not a failure
// (USB adapters that switch direction themselves behave the same).
TEST(ModbusTurntable, Rs485ModeIsOptionalWhereThePortLacksIt) {
  auto server = ModbusTestServer::StartRtu({});
  TurntableConfig c = testing::ModbusConfigFor(*server, false);
  c.modbus.rs485 = true;
  auto t = Make(c);
  ::testing::internal::CaptureStderr();
  OpenHome(*t);
  const std::string log = ::testing::internal::GetCapturedStderr();
  // The warning names the port and says why it is fine, once.
  const std::string warning = c.modbus.device + " does not support RS-485 mode";
  const size_t at = log.find(warning);
  ASSERT_NE(at, std::string::npos) << log;
  EXPECT_NE(log.find("adapters that switch direction themselves", at), std::string::npos) << log;
  EXPECT_EQ(log.find(warning, at + 1), std::string::npos) << log;
}

// Link hygiene: one answer that comes after response_timeout. The peer
// handles nothing meanwhile (the retry waits behind the late answer), so a
// master that sends the retry into the same stream reads each request's
// predecessor's answer from then on.
constexpr TimeNs kHygieneTimeout = 300 * kNsPerMs;
constexpr double kLateSeconds = 0.45;  // 1.5 x kHygieneTimeout

int Count(const std::vector<int>& commands, int value) {
  return static_cast<int>(std::count(commands.begin(), commands.end(), value));
}

// After the late answer: every request is answered at the first try (the
// backend's own count of requests sent rises by exactly one per read) and
// the angles read back are the peer's.
void ExpectInStep(ModbusTestServer& server, modbus::ModbusTurntable& t) {
  TurntableStatus st;
  MoveTo(t, 90.0, &st);
  EXPECT_NEAR(st.angle_deg, 90.0, kStepDeg);
  const int sent = t.requests_sent();
  const int received = server.requests();
  for (int i = 0; i < 20; ++i) {
    Result<TurntableStatus> r = t.ReadStatus();
    ASSERT_TRUE(r.ok()) << i << ": " << r.error().ToString();
    EXPECT_NEAR(r->angle_deg, 90.0, kStepDeg) << i;
    EXPECT_TRUE(r->in_position) << i;
  }
  EXPECT_EQ(t.requests_sent() - sent, 20);
  EXPECT_EQ(server.requests() - received, 20);
  EXPECT_EQ(server.position_steps(), 8000);
}

class ModbusLink : public ::testing::TestWithParam<bool> {  // true: TCP
 protected:
  void SetUp() override {
    server_ = GetParam() ? ModbusTestServer::StartTcp({}) : ModbusTestServer::StartRtu({});
    TurntableConfig c = testing::ModbusConfigFor(*server_, GetParam());
    c.modbus.response_timeout = kHygieneTimeout;
    c.modbus.retries = 2;
    t_ = Make(c);
    OpenHome(*t_);
  }
  std::unique_ptr<ModbusTestServer> server_;
  std::unique_ptr<modbus::ModbusTurntable> t_;
};

TEST_P(ModbusLink, LateAnswerToAReadDoesNotDesynchroniseTheLink) {
  server_->AnswerNextLate(kLateSeconds, MODBUS_FC_READ_HOLDING_REGISTERS);
  const int sent = t_->requests_sent();
  Result<TurntableStatus> st = t_->ReadStatus();
  ASSERT_TRUE(st.ok()) << st.error().ToString();
  EXPECT_TRUE(st->homed);
  EXPECT_NEAR(st->angle_deg, 0.0, kStepDeg);
  EXPECT_EQ(t_->requests_sent() - sent, 2);  // the late one and one retry
  ExpectInStep(*server_, *t_);
}

TEST_P(ModbusLink, UnansweredStopIsNotSentAgainWhenTheStateShowsItStopped) {
  ASSERT_TRUE(t_->StartMoveTo(300.0).ok());
  std::this_thread::sleep_for(std::chrono::milliseconds(150));
  server_->AnswerNextLate(kLateSeconds, MODBUS_FC_WRITE_SINGLE_REGISTER);
  Status s = t_->Stop();
  ASSERT_TRUE(s.ok()) << s.error().ToString();
  EXPECT_EQ(Count(server_->commands(), 3), 1);  // generic map: 3 = stop
  Result<TurntableStatus> st = t_->ReadStatus();
  ASSERT_TRUE(st.ok()) << st.error().ToString();
  EXPECT_FALSE(st->moving);
  EXPECT_GT(st->angle_deg, 1.0);
  EXPECT_LT(st->angle_deg, 299.0);
  ExpectInStep(*server_, *t_);
  EXPECT_EQ(Count(server_->commands(), 3), 1);
}

TEST_P(ModbusLink, UnansweredMoveAndHomeAreNotSentAgain) {
  server_->AnswerNextLate(kLateSeconds, MODBUS_FC_WRITE_SINGLE_REGISTER);
  Status s = t_->StartMoveTo(45.0);
  ASSERT_TRUE(s.ok()) << s.error().ToString();
  Result<TurntableStatus> st = testing::WaitInPosition(*t_);
  ASSERT_TRUE(st.ok()) << st.error().ToString();
  EXPECT_TRUE(st->in_position);
  EXPECT_NEAR(st->angle_deg, 45.0, kStepDeg);
  EXPECT_EQ(Count(server_->commands(), 1), 1);  // 1 = move
  EXPECT_EQ(server_->move_targets(), std::vector<int64_t>{4000});

  server_->AnswerNextLate(kLateSeconds, MODBUS_FC_WRITE_SINGLE_REGISTER);
  s = t_->StartHome();
  ASSERT_TRUE(s.ok()) << s.error().ToString();
  st = testing::WaitInPosition(*t_);
  ASSERT_TRUE(st.ok()) << st.error().ToString();
  EXPECT_TRUE(st->in_position && st->homed);
  EXPECT_EQ(Count(server_->commands(), 2), 2);  // 2 = home: OpenHome's and this one
  ExpectInStep(*server_, *t_);
}

// A command that never got through (lost on its way) is sent again, once the
// state shows it did not take effect.
TEST_P(ModbusLink, CommandThatDidNotTakeEffectIsSentAgain) {
  server_->IgnoreNext(MODBUS_FC_WRITE_SINGLE_REGISTER);
  Status s = t_->StartMoveTo(45.0);
  ASSERT_TRUE(s.ok()) << s.error().ToString();
  Result<TurntableStatus> st = testing::WaitInPosition(*t_);
  ASSERT_TRUE(st.ok()) << st.error().ToString();
  EXPECT_NEAR(st->angle_deg, 45.0, kStepDeg);
  EXPECT_EQ(Count(server_->commands(), 1), 1);
  EXPECT_EQ(server_->move_targets(), std::vector<int64_t>{4000});

  ASSERT_TRUE(t_->StartMoveTo(300.0).ok());
  std::this_thread::sleep_for(std::chrono::milliseconds(150));
  server_->IgnoreNext(MODBUS_FC_WRITE_SINGLE_REGISTER);
  s = t_->Stop();
  ASSERT_TRUE(s.ok()) << s.error().ToString();
  st = t_->ReadStatus();
  ASSERT_TRUE(st.ok()) << st.error().ToString();
  EXPECT_FALSE(st->moving);
  EXPECT_LT(st->angle_deg, 299.0);
  EXPECT_EQ(Count(server_->commands(), 3), 1);
}

INSTANTIATE_TEST_SUITE_P(TcpAndRtu, ModbusLink, ::testing::Bool(),
                         [](const ::testing::TestParamInfo<bool>& i) {
                           return std::string(i.param ? "Tcp" : "Rtu");
                         });

// libmodbus refuses an answer whose MBAP transaction id is not its
// request's; after every try the message fits a TCP link (no serial advice).
TEST(ModbusTurntable, TcpAnswerWithAnotherTransactionIdIsRefused) {
  auto server = ModbusTestServer::StartTcp({});
  TurntableConfig c = testing::ModbusConfigFor(*server, true);
  auto t = Make(c);
  ASSERT_TRUE(t->Open().ok());
  server->SetWrongTransactionId(true);
  Result<TurntableStatus> st = t->ReadStatus();
  ASSERT_FALSE(st.ok());
  EXPECT_EQ(st.error().cls, ErrorClass::kTimeout);
  EXPECT_THAT(st.error().message, HasSubstr("no valid answer from Modbus unit 1 at 127.0.0.1:" +
                                            std::to_string(server->port())));
  EXPECT_THAT(st.error().message, HasSubstr("speaking Modbus/TCP"));
  EXPECT_THAT(st.error().message, ::testing::Not(HasSubstr("termination")));
  EXPECT_THAT(st.error().message, ::testing::Not(HasSubstr("line settings")));
  EXPECT_THAT(st.error().detail, HasSubstr("2 tries"));
  server->SetWrongTransactionId(false);
  st = t->ReadStatus();
  EXPECT_TRUE(st.ok()) << st.error().ToString();
}

TEST(ModbusTurntable, InfoNamesBackendAndLink) {
  auto server = ModbusTestServer::StartRtu({});
  TurntableConfig c = testing::ModbusConfigFor(*server, false);
  c.modbus.parity = "even";
  c.modbus.baud = 38400;
  auto t = Make(c);
  EXPECT_EQ(t->Info().backend, "modbus-rtu");
  EXPECT_EQ(t->LinkDescription(), "unit 1 on " + server->device() + " at 38400 8E1");
}

}  // namespace
}  // namespace aggscan
