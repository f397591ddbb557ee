// The console's static files as the API serves them (ApiRouter::ServeConsole)
// and the arm form's description fields.
#include <gtest/gtest.h>
#include <httplib.h>

#include <filesystem>
#include <fstream>
#include <memory>
#include <string>

#include "common/fsutil.h"
#include "daemon/access.h"
#include "daemon/http_api.h"
#include "tests/api/fake_control.h"
#include "tests/util/temp_dir.h"

namespace aggscan {
namespace {

using nlohmann::json;
using testing::FakeControl;

void Write(const std::string& path, const std::string& text) {
  std::filesystem::create_directories(std::filesystem::path(path).parent_path());
  std::ofstream(path) << text;
}

class ConsoleFiles : public ::testing::Test {
 protected:
  void SetUp() override {
    root_ = dir_.path() + "/web";
    Write(root_ + "/index.html", "<!doctype html><title>console</title>");
    Write(root_ + "/ui/console.js", "'use strict';");
    Write(root_ + "/ui/vendor/three.min.js", "var THREE = {};");
    Write(root_ + "/ui/notes.txt", "no type served");
    Write(root_ + "/ui/.hidden.js", "secret");
    Write(dir_.path() + "/outside.js", "outside the web root");
  }
  void Start(AccessControl* access = nullptr) {
    HttpApiOptions o;
    o.web_root = root_;
    o.access = access;
    api_ = std::make_unique<HttpApi>(fake_, "127.0.0.1", 0, o);
    ASSERT_TRUE(api_->Start().ok());
    client_ = std::make_unique<httplib::Client>("127.0.0.1", api_->port());
    client_->set_read_timeout(5, 0);
  }
  void TearDown() override {
    if (api_) api_->Stop();
  }

  test::TempDir dir_;
  std::string root_;
  FakeControl fake_;
  std::unique_ptr<HttpApi> api_;
  std::unique_ptr<httplib::Client> client_;
};

TEST_F(ConsoleFiles, PageAndScriptsWithTypesPolicyAndRevalidation) {
  Start();
  auto page = client_->Get("/");
  ASSERT_TRUE(page);
  EXPECT_EQ(page->status, 200);
  EXPECT_EQ(page->body, "<!doctype html><title>console</title>");
  EXPECT_EQ(page->get_header_value("Content-Type"), "text/html; charset=utf-8");
  // Only the rig's own scripts, and no other site may frame the START button.
  const std::string csp = page->get_header_value("Content-Security-Policy");
  EXPECT_NE(csp.find("script-src 'self'"), std::string::npos) << csp;
  EXPECT_NE(csp.find("frame-ancestors 'none'"), std::string::npos) << csp;
  EXPECT_EQ(page->get_header_value("X-Frame-Options"), "DENY");

  auto js = client_->Get("/ui/vendor/three.min.js");
  ASSERT_TRUE(js);
  EXPECT_EQ(js->status, 200);
  EXPECT_EQ(js->get_header_value("Content-Type"), "text/javascript; charset=utf-8");
  EXPECT_EQ(js->get_header_value("X-Content-Type-Options"), "nosniff");
  const std::string etag = js->get_header_value("ETag");
  ASSERT_FALSE(etag.empty());
  EXPECT_EQ(js->get_header_value("Cache-Control"), "no-cache");
  auto again = client_->Get("/ui/vendor/three.min.js", {{"If-None-Match", etag}});
  ASSERT_TRUE(again);
  EXPECT_EQ(again->status, 304);
  EXPECT_TRUE(again->body.empty());
  // A changed file is a new ETag: the tablet gets the update.
  Write(root_ + "/ui/vendor/three.min.js", "var THREE = {REVISION: '112'};");
  auto changed = client_->Get("/ui/vendor/three.min.js", {{"If-None-Match", etag}});
  ASSERT_TRUE(changed);
  EXPECT_EQ(changed->status, 200);
  EXPECT_EQ(changed->body, "var THREE = {REVISION: '112'};");
  EXPECT_TRUE(fake_.Calls().empty());
}

TEST_F(ConsoleFiles, NothingOutsideTheRootNorHiddenNorUntyped) {
  Start();
  for (const char* path :
       {"/ui/../outside.js", "/ui/%2e%2e/outside.js", "/ui/.hidden.js", "/ui/notes.txt",
        "/ui/missing.js", "/ui/", "/ui//console.js", "/ui/a/b/c.js", "/ui/vendor/../../outside.js",
        "/outside.js", "/ui/console.js%00.png"}) {
    auto r = client_->Get(path);
    ASSERT_TRUE(r) << path;
    EXPECT_EQ(r->status, 404) << path;
    EXPECT_EQ(r->body.find("outside the web root"), std::string::npos) << path;
    EXPECT_EQ(r->body.find("secret"), std::string::npos) << path;
  }
  auto post = client_->Post("/ui/console.js", "{}", "application/json");
  ASSERT_TRUE(post);
  EXPECT_EQ(post->status, 405);
}

TEST_F(ConsoleFiles, NoRootIsA404ThatSaysWhy) {
  root_.clear();
  Start();
  auto r = client_->Get("/");
  ASSERT_TRUE(r);
  EXPECT_EQ(r->status, 404);
  EXPECT_NE(r->body.find("share/aggscan/web"), std::string::npos) << r->body;
}

TEST_F(ConsoleFiles, ServedWithoutCredentialsWhileTheApiAsksForThem) {
  const std::string accounts = dir_.path() + "/accounts";
  Result<std::string> hash = HashPassword("operator pass");
  ASSERT_TRUE(hash) << hash.error().ToString();
  ASSERT_TRUE(WriteFileAtomic(accounts, "ana:operator:" + *hash + "\n", false, 0600).ok());
  Result<std::unique_ptr<AccessControl>> access = AccessControl::Open(accounts);
  ASSERT_TRUE(access) << access.error().ToString();
  Start(access->get());
  auto page = client_->Get("/");
  ASSERT_TRUE(page);
  EXPECT_EQ(page->status, 200);
  auto js = client_->Get("/ui/console.js");
  ASSERT_TRUE(js);
  EXPECT_EQ(js->status, 200);
  auto status = client_->Get("/api/v1/status");
  ASSERT_TRUE(status);
  EXPECT_EQ(status->status, 401);
}

// The arm form: operator, lot and notes reach the control trimmed; wrong
// types, control characters and overlong text are refused with the field named.
TEST_F(ConsoleFiles, ArmDescriptionIsPassedOnAndChecked) {
  Start();
  auto r = client_->Post("/api/v1/samples",
                         json{{"id", "rock-7"},
                              {"operator", "  M. Rossi "},
                              {"lot", "lot-7"},
                              {"notes", "wet\nchipped"}}
                             .dump(),
                         "application/json");
  ASSERT_TRUE(r);
  EXPECT_EQ(r->status, 200) << r->body;
  {
    const ArmRequest a = fake_.LastArm();
    EXPECT_EQ(a.id, "rock-7");
    EXPECT_EQ(a.meta.value("operator", ""), "M. Rossi");
    EXPECT_EQ(a.meta.value("lot", ""), "lot-7");
    EXPECT_EQ(a.meta.value("notes", ""), "wet\nchipped");
    EXPECT_FALSE(a.meta.contains("id"));
  }
  r = client_->Post(
      "/api/v1/samples",
      json{{"id", "rock-9"},
           {"material", {{"name", "basalt"}, {"specific_gravity", 2.9}, {"basis", "oven-dry"}}}}
          .dump(),
      "application/json");
  ASSERT_TRUE(r);
  EXPECT_EQ(r->status, 200) << r->body;
  EXPECT_EQ(fake_.LastArm().meta["material"],
            (json{{"name", "basalt"}, {"specific_gravity", 2.9}, {"basis", "oven-dry"}}));
  const struct {
    json body;
    std::string says;
  } bad[] = {
      {{{"id", "rock-8"}, {"operator", 7}}, "\"operator\" must be a string"},
      {{{"id", "rock-8"}, {"lot", "a\nb"}}, "\"lot\" contains a control character"},
      {{{"id", "rock-8"}, {"notes", std::string("bell\x07")}}, "\"notes\" contains a control"},
      {{{"id", "rock-8"}, {"notes", std::string(2001, 'n')}}, "\"notes\" is 2001 bytes long"},
      {{{"id", "rock-8"}, {"operator", std::string(81, 'o')}}, "at most 80"},
      {{{"id", "rock-8"}, {"material", {{"specific_gravity", 2.65}}}}, "needs its basis"},
      {{{"id", "rock-8"}, {"material", {{"specific_gravity", 2650}, {"basis", "bulk-ssd"}}}},
       "kg/m3"},
      {{{"id", "rock-8"}, {"material", {{"basis", "wet"}}}}, "\"material.basis\" must be"},
  };
  for (const auto& b : bad) {
    auto e = client_->Post("/api/v1/samples", b.body.dump(), "application/json");
    ASSERT_TRUE(e);
    EXPECT_EQ(e->status, 400) << b.body.dump();
    const json err = json::parse(e->body, nullptr, false);
    ASSERT_TRUE(err.is_object()) << e->body;
    EXPECT_NE(err["error"]["message"].get<std::string>().find(b.says), std::string::npos)
        << e->body;
  }
  EXPECT_EQ(fake_.CallCount(), 2u);
}

}  // namespace
}  // namespace aggscan
