// Access control of the API (daemon/access.h) through the real HTTP server:
// accounts, roles, sessions, the cookie that only reads, the lockout after
// failed logins, TLS, and the CLI's side (`aggscan user`, credentials from
// the environment).
#include "daemon/access.h"

#include <gtest/gtest.h>
#include <httplib.h>
#include <stdlib.h>
#include <sys/stat.h>

#include <chrono>
#include <cstdio>
#include <fstream>
#include <memory>
#include <sstream>
#include <string>
#include <thread>

#include "cli/client.h"
#include "cli/user_command.h"
#include "common/fsutil.h"
#include "config/config.h"
#include "daemon/http_api.h"
#include "tests/api/fake_control.h"
#include "tests/util/temp_dir.h"

namespace aggscan {
namespace {

using nlohmann::json;
using testing::FakeControl;

// Adds an account with `aggscan user add`, the password on stdin.
int AddUser(const std::string& file, const std::string& name, const std::string& role,
            const std::string& password, std::string* err_text = nullptr) {
  std::istringstream in(password + "\n");
  std::ostringstream out, err;
  const int rc = RunUserCommand({"add", name, "--role", role, "--file", file}, in, out, err);
  if (err_text != nullptr) *err_text = err.str();
  return rc;
}

TEST(Accounts, FileFormatAndModeAreChecked) {
  test::TempDir dir;
  const std::string file = dir.path() + "/accounts";
  ASSERT_EQ(AddUser(file, "alice", "operator", "correct horse"), 0);
  ASSERT_EQ(AddUser(file, "qa", "viewer", "battery staple"), 0);
  std::string err;
  EXPECT_EQ(AddUser(file, "short", "viewer", "1234567", &err), 1);
  EXPECT_NE(err.find("at least 8"), std::string::npos) << err;
  EXPECT_EQ(AddUser(file, "bad name", "viewer", "12345678", &err), 2);
  EXPECT_EQ(AddUser(file, "bob", "admin", "12345678", &err), 2);

  struct stat st {};
  ASSERT_EQ(::stat(file.c_str(), &st), 0);
  EXPECT_EQ(st.st_mode & 0777, 0600u);
  Result<std::vector<Account>> accounts = LoadAccounts(file);
  ASSERT_TRUE(accounts) << accounts.error().ToString();
  ASSERT_EQ(accounts->size(), 2u);
  EXPECT_EQ((*accounts)[0].name, "alice");
  EXPECT_EQ((*accounts)[0].role, Role::kOperator);
  EXPECT_EQ((*accounts)[0].hash.rfind("$y$", 0), 0u);  // yescrypt
  EXPECT_TRUE(PasswordMatches("correct horse", (*accounts)[0].hash));
  EXPECT_FALSE(PasswordMatches("correct horse ", (*accounts)[0].hash));
  std::ostringstream out, e2;
  std::istringstream none;
  EXPECT_EQ(RunUserCommand({"list", "--file", file}, none, out, e2), 0);
  EXPECT_EQ(out.str(), "alice operator\nqa viewer\n");

  // Readable by others: refused, saying what to do.
  ASSERT_EQ(::chmod(file.c_str(), 0644), 0);
  Result<std::vector<Account>> open = LoadAccounts(file);
  ASSERT_FALSE(open);
  EXPECT_NE(open.error().message.find("chmod 600 " + file), std::string::npos)
      << open.error().message;
  ASSERT_EQ(::chmod(file.c_str(), 0600), 0);

  for (const auto& [text, says] : std::vector<std::pair<std::string, std::string>>{
           {"alice:operator\n", "expected name:role:hash"},
           {"alice:root:$y$x$y\n", "is not operator or viewer"},
           {"alice:viewer:hunter22\n", "is not a crypt(3) hash"},
           {"a b:viewer:$y$x$y\n", "is not 1-32 characters"},
           {"# c\n\nalice:viewer:$y$x$y\nalice:operator:$y$x$y\n", "line 4: account alice twice"},
       }) {
    Result<std::vector<Account>> parsed = ParseAccounts(text, "F");
    ASSERT_FALSE(parsed) << text;
    EXPECT_NE(parsed.error().message.find(says), std::string::npos) << parsed.error().message;
  }
  std::istringstream in2;
  std::ostringstream o3, e3;
  EXPECT_EQ(RunUserCommand({"remove", "qa", "--file", file}, in2, o3, e3), 0) << e3.str();
  EXPECT_EQ(LoadAccounts(file)->size(), 1u);
}

class AccessTest : public ::testing::Test {
 protected:
  void SetUp() override {
    file_ = dir_.path() + "/accounts";
    ASSERT_EQ(AddUser(file_, "alice", "operator", "correct horse"), 0);
    ASSERT_EQ(AddUser(file_, "qa", "viewer", "battery staple"), 0);
    Result<std::unique_ptr<AccessControl>> ac = AccessControl::Open(file_);
    ASSERT_TRUE(ac) << ac.error().ToString();
    access_ = std::move(*ac);
    HttpApiOptions o;
    o.access = access_.get();
    api_ = std::make_unique<HttpApi>(fake_, "127.0.0.1", 0, o);
    ASSERT_TRUE(api_->Start().ok());
    client_ = std::make_unique<httplib::Client>("127.0.0.1", api_->port());
    client_->set_read_timeout(10, 0);
  }
  void TearDown() override { api_->Stop(); }

  // Logs in; returns the token ("" on failure) and the Set-Cookie header.
  std::string Login(const std::string& user, const std::string& password, int* status = nullptr,
                    std::string* cookie = nullptr) {
    auto r = client_->Post("/api/v1/session", json{{"user", user}, {"password", password}}.dump(),
                           "application/json");
    if (status != nullptr) *status = r ? r->status : 0;
    if (!r || r->status != 200) return "";
    if (cookie != nullptr) *cookie = r->get_header_value("Set-Cookie");
    return json::parse(r->body)["token"].get<std::string>();
  }
  static httplib::Headers Bearer(const std::string& token) {
    return {{"Authorization", "Bearer " + token}};
  }

  test::TempDir dir_;
  std::string file_;
  std::unique_ptr<AccessControl> access_;
  FakeControl fake_;
  std::unique_ptr<HttpApi> api_;
  std::unique_ptr<httplib::Client> client_;
};

TEST_F(AccessTest, EveryRequestNeedsCredentialsAndViewersOnlyRead) {
  // Nothing without credentials, not even an unknown path; no CORS header.
  for (const char* path : {"/api/v1/status", "/api/v1/events", "/api/v1/preview", "/metrics",
                           "/api/v1/nothing", "/api/v1/samples/rock-11/sides/1/views/0"}) {
    auto r = client_->Get(path);
    ASSERT_TRUE(r) << path;
    EXPECT_EQ(r->status, 401) << path;
    EXPECT_EQ(r->get_header_value("WWW-Authenticate"), "Bearer realm=\"aggscand\"") << path;
    EXPECT_FALSE(r->has_header("Access-Control-Allow-Origin")) << path;
  }
  auto press = client_->Post("/api/v1/button", "{}", "application/json");
  ASSERT_TRUE(press);
  EXPECT_EQ(press->status, 401);
  EXPECT_TRUE(fake_.Calls().empty());

  // A viewer reads, may not press.
  std::string cookie;
  const std::string viewer = Login("qa", "battery staple", nullptr, &cookie);
  ASSERT_FALSE(viewer.empty());
  EXPECT_NE(cookie.find("aggscan_session=" + viewer), std::string::npos) << cookie;
  EXPECT_NE(cookie.find("HttpOnly"), std::string::npos);
  EXPECT_NE(cookie.find("SameSite=Strict"), std::string::npos);
  EXPECT_EQ(cookie.find("Secure"), std::string::npos);  // plain HTTP on loopback
  auto status = client_->Get("/api/v1/status", Bearer(viewer));
  ASSERT_TRUE(status);
  EXPECT_EQ(status->status, 200);
  auto me = client_->Get("/api/v1/session", Bearer(viewer));
  ASSERT_TRUE(me);
  EXPECT_EQ(json::parse(me->body), (json{{"user", "qa"}, {"role", "viewer"}, {"auth", "bearer"}}));
  auto refused = client_->Post("/api/v1/button", Bearer(viewer), "{}", "application/json");
  ASSERT_TRUE(refused);
  EXPECT_EQ(refused->status, 403);
  EXPECT_NE(refused->body.find("is a viewer"), std::string::npos) << refused->body;
  EXPECT_EQ(fake_.Calls(), std::vector<std::string>{"status"});

  // An operator presses; the press names who.
  const std::string op = Login("alice", "correct horse");
  ASSERT_FALSE(op.empty());
  auto pressed = client_->Post("/api/v1/button", Bearer(op), "{}", "application/json");
  ASSERT_TRUE(pressed);
  EXPECT_EQ(pressed->status, 200) << pressed->body;
  EXPECT_EQ(fake_.Calls().back(), "press:api:alice");

  // The cookie alone reads (an <img>, an EventSource), never changes state:
  // a form on another site would send it too.
  httplib::Headers with_cookie{{"Cookie", "theme=dark; aggscan_session=" + op}};
  auto read = client_->Get("/api/v1/status", with_cookie);
  ASSERT_TRUE(read);
  EXPECT_EQ(read->status, 200);
  auto forged = client_->Post("/api/v1/button", with_cookie, "{}", "application/json");
  ASSERT_TRUE(forged);
  EXPECT_EQ(forged->status, 403);
  EXPECT_NE(forged->body.find("Authorization header"), std::string::npos) << forged->body;

  // Basic credentials (curl -u, the CLI) work without a session.
  httplib::Client basic("127.0.0.1", api_->port());
  basic.set_basic_auth("alice", "correct horse");
  auto armed = basic.Post("/api/v1/samples", R"({"id":"rock-9"})", "application/json");
  ASSERT_TRUE(armed);
  EXPECT_EQ(armed->status, 200);
  EXPECT_EQ(fake_.Calls().back(), "arm:rock-9");

  // Logging out ends the session.
  auto out = client_->Delete("/api/v1/session", Bearer(op));
  ASSERT_TRUE(out);
  EXPECT_EQ(out->status, 200);
  EXPECT_NE(out->get_header_value("Set-Cookie").find("Max-Age=0"), std::string::npos);
  auto after = client_->Get("/api/v1/status", Bearer(op));
  ASSERT_TRUE(after);
  EXPECT_EQ(after->status, 401);
  EXPECT_NE(after->body.find("log in again"), std::string::npos);
}

TEST_F(AccessTest, FailedLoginsAreSlowedDownPerAddress) {
  int status = 0;
  for (int i = 0; i < AccessControl::kFreeFailures; ++i) {
    EXPECT_EQ(Login("alice", "wrong password " + std::to_string(i), &status), "");
    EXPECT_EQ(status, 401) << i;
  }
  // Locked: even the right password is not tried now.
  auto r = client_->Post("/api/v1/session",
                         json{{"user", "alice"}, {"password", "correct horse"}}.dump(),
                         "application/json");
  ASSERT_TRUE(r);
  EXPECT_EQ(r->status, 429);
  EXPECT_EQ(r->get_header_value("Retry-After"), "2");
  httplib::Client basic("127.0.0.1", api_->port());
  basic.set_basic_auth("alice", "correct horse");
  auto b = basic.Get("/api/v1/status");
  ASSERT_TRUE(b);
  EXPECT_EQ(b->status, 429);
  // After the lockout the right password works, and the count starts again.
  std::this_thread::sleep_for(std::chrono::milliseconds(2100));
  EXPECT_FALSE(Login("alice", "correct horse", &status).empty());
  EXPECT_EQ(status, 200);
  // An unknown name fails the same way as a wrong password.
  EXPECT_EQ(Login("mallory", "correct horse", &status), "");
  EXPECT_EQ(status, 401);
  // A stale session token (aggscand restarted) is refused but never locks
  // the tablet out.
  for (int i = 0; i < 3 * AccessControl::kFreeFailures; ++i) {
    auto stale = client_->Get("/api/v1/status", Bearer("0123456789abcdef"));
    ASSERT_TRUE(stale);
    EXPECT_EQ(stale->status, 401);
  }
  EXPECT_FALSE(Login("alice", "correct horse", &status).empty());
}

TEST_F(AccessTest, AccountsAddedWhileRunningNeedNoRestart) {
  int status = 0;
  EXPECT_EQ(Login("carol", "new password", &status), "");
  // A different size or time: reread at the next login.
  std::this_thread::sleep_for(std::chrono::milliseconds(20));
  ASSERT_EQ(AddUser(file_, "carol", "viewer", "new password"), 0);
  EXPECT_FALSE(Login("carol", "new password", &status).empty());
  EXPECT_EQ(access_->accounts(), 3u);
}

TEST(AccessConfig, NetworkAddressesNeedCredentialsAndTls) {
  auto problems = [](const std::string& daemon_toml) {
    std::vector<ConfigProblem> found;
    (void)LoadConfigString("[daemon]\n" + daemon_toml, "test.toml", &found);
    std::string all;
    for (const ConfigProblem& p : found) all += p.ToString() + "\n";
    return all;
  };
  EXPECT_EQ(problems("listen_address = \"127.0.0.1\"\n"), "");
  EXPECT_EQ(problems("listen_address = \"::1\"\n"), "");
  EXPECT_EQ(problems("listen_address = \"localhost\"\n"), "");
  const std::string open = problems("listen_address = \"0.0.0.0\"\n");
  EXPECT_NE(open.find("opens the API to the network"), std::string::npos) << open;
  EXPECT_NE(open.find("daemon.credentials_file"), std::string::npos) << open;
  const std::string clear =
      problems("listen_address = \"192.168.1.20\"\ncredentials_file = \"/etc/aggscan/a\"\n");
  EXPECT_NE(clear.find("daemon.tls_certificate"), std::string::npos) << clear;
  EXPECT_EQ(
      problems("listen_address = \"192.168.1.20\"\ncredentials_file = \"/etc/aggscan/a\"\n"
               "tls_certificate = \"/etc/aggscan/c.pem\"\ntls_key = \"/etc/aggscan/k.pem\"\n"),
      "");
  const std::string half = problems("tls_certificate = \"/c.pem\"\n");
  EXPECT_NE(half.find("daemon.tls_key"), std::string::npos) << half;
  EXPECT_TRUE(IsLoopbackAddress("127.3.2.1"));
  EXPECT_FALSE(IsLoopbackAddress("10.0.0.1"));
  EXPECT_FALSE(IsLoopbackAddress("::"));
}

// HTTPS with a certificate made by openssl; the client is OpenSSL, the
// server GnuTLS (libmicrohttpd): two implementations that must agree.
TEST(AccessTls, ServesHttpsWithTheConfiguredCertificate) {
  test::TempDir dir;
  const std::string cert = dir.path() + "/cert.pem", key = dir.path() + "/key.pem";
  const std::string cmd =
      "openssl req -x509 -newkey rsa:2048 -nodes -days 2 -subj /CN=localhost -addext "
      "subjectAltName=DNS:localhost,IP:127.0.0.1 -keyout " +
      key + " -out " + cert + " >/dev/null 2>&1";
  ASSERT_EQ(std::system(cmd.c_str()), 0) << "openssl (scripts/install-deps.sh) must be installed";
  const std::string accounts = dir.path() + "/accounts";
  ASSERT_EQ(AddUser(accounts, "alice", "operator", "correct horse"), 0);
  auto access = AccessControl::Open(accounts);
  ASSERT_TRUE(access);
  FakeControl fake;
  HttpApiOptions o;
  o.access = access->get();
  o.tls_certificate_pem = *ReadFile(cert);
  o.tls_key_pem = *ReadFile(key);
  HttpApi api(fake, "127.0.0.1", 0, o);
  ASSERT_TRUE(api.Start().ok());

  httplib::Client https("https://127.0.0.1:" + std::to_string(api.port()));
  https.set_ca_cert_path(cert.c_str());
  https.enable_server_certificate_verification(true);
  auto login =
      https.Post("/api/v1/session", json{{"user", "alice"}, {"password", "correct horse"}}.dump(),
                 "application/json");
  ASSERT_TRUE(login) << httplib::to_string(login.error());
  EXPECT_EQ(login->status, 200);
  EXPECT_NE(login->get_header_value("Set-Cookie").find("; Secure"), std::string::npos);
  // Plain HTTP to the TLS port gets no API answer.
  httplib::Client plain("127.0.0.1", api.port());
  plain.set_read_timeout(3, 0);
  auto r = plain.Get("/api/v1/status");
  EXPECT_TRUE(!r || r->status != 200);
  // A client that does not trust the certificate refuses the server.
  httplib::Client untrusting("https://127.0.0.1:" + std::to_string(api.port()));
  untrusting.set_ca_cert_path((dir.path() + "/none.pem").c_str());
  EXPECT_FALSE(untrusting.Get("/api/v1/status"));

  // The CLI: https:// with AGGSCAN_CA_CERT, credentials from the environment.
  ::setenv("AGGSCAN_CA_CERT", cert.c_str(), 1);
  std::ostringstream out, err;
  const std::string url = "https://127.0.0.1:" + std::to_string(api.port());
  ::setenv("AGGSCAN_USER", "alice", 1);
  ::setenv("AGGSCAN_PASSWORD", "wrong password", 1);
  EXPECT_EQ(RunClientCommand({"--url", url, "press"}, out, err), kClientExitDaemonError);
  EXPECT_NE(err.str().find("wrong account name or password"), std::string::npos) << err.str();
  ::setenv("AGGSCAN_PASSWORD", "correct horse", 1);
  EXPECT_EQ(RunClientCommand({"--url", url, "press"}, out, err), kClientExitOk) << err.str();
  EXPECT_EQ(fake.Calls().back(), "press:api:alice");
  ::unsetenv("AGGSCAN_USER");
  ::unsetenv("AGGSCAN_PASSWORD");
  ::unsetenv("AGGSCAN_CA_CERT");
  api.Stop();
}

}  // namespace
}  // namespace aggscan
