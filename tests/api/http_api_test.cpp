#include "daemon/http_api.h"

#include <gtest/gtest.h>
#include <httplib.h>
#include <netinet/in.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <atomic>
#include <cctype>
#include <chrono>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <memory>
#include <set>
#include <span>
#include <string>
#include <thread>
#include <vector>

#include "drivers/sim/jpeg.h"
#include "tests/api/fake_control.h"
#include "tests/util/loopback.h"

namespace aggscan {
namespace {

using nlohmann::json;
using testing::FakeControl;

class HttpApiTest : public ::testing::Test {
 protected:
  void SetUp() override {
    api_ = std::make_unique<HttpApi>(fake_, "127.0.0.1", 0);
    const Status st = api_->Start();
    ASSERT_TRUE(st.ok()) << st.error().ToString();
    ASSERT_GT(api_->port(), 0);
    client_ = std::make_unique<httplib::Client>("127.0.0.1", api_->port());
    client_->set_read_timeout(5, 0);
  }
  void TearDown() override {
    client_.reset();
    api_->Stop();
  }

  static json Body(const httplib::Result& r) { return json::parse(r->body, nullptr, false); }
  static std::string ErrorClassOf(const httplib::Result& r) {
    const json b = Body(r);
    if (!b.is_object() || !b.contains("error")) return "<no error object: " + r->body + ">";
    EXPECT_TRUE(b["error"]["message"].is_string());
    return b["error"]["class"].get<std::string>();
  }

  // True once `answer` holds a whole response with a Content-Length body.
  static bool ResponseComplete(const std::string& answer) {
    const size_t end = answer.find("\r\n\r\n");
    if (end == std::string::npos) return false;
    const size_t cl = answer.find("Content-Length: ");
    if (cl == std::string::npos || cl > end) return false;
    return answer.size() >= end + 4 + std::stoul(answer.substr(cl + 16));
  }

  // Sends raw bytes and returns everything the server answers until it closes
  // the connection or goes quiet.
  std::string Raw(const std::string& request) {
    const int fd = ::socket(AF_INET, SOCK_STREAM, 0);
    sockaddr_in addr{};
    addr.sin_family = AF_INET;
    addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    addr.sin_port = htons(static_cast<uint16_t>(api_->port()));
    EXPECT_EQ(::connect(fd, reinterpret_cast<sockaddr*>(&addr), sizeof addr), 0);
    size_t sent = 0;
    while (sent < request.size()) {
      const ssize_t n = ::send(fd, request.data() + sent, request.size() - sent, MSG_NOSIGNAL);
      if (n <= 0) break;  // the server may close early on a refused body
      sent += static_cast<size_t>(n);
    }
    std::string answer;
    char buf[4096];
    while (!ResponseComplete(answer)) {
      pollfd p{fd, POLLIN, 0};
      if (::poll(&p, 1, 3000) <= 0) break;
      const ssize_t n = ::recv(fd, buf, sizeof buf, 0);
      if (n <= 0) break;
      answer.append(buf, static_cast<size_t>(n));
    }
    ::close(fd);
    return answer;
  }

  FakeControl fake_;
  std::unique_ptr<HttpApi> api_;
  std::unique_ptr<httplib::Client> client_;
};

TEST_F(HttpApiTest, StatusReturnsControlJson) {
  auto r = client_->Get("/api/v1/status");
  ASSERT_TRUE(r);
  EXPECT_EQ(r->status, 200);
  EXPECT_EQ(r->get_header_value("Content-Type"), "application/json");
  EXPECT_EQ(Body(r), fake_.status);
}

TEST_F(HttpApiTest, ArmPassesIdToControl) {
  auto r = client_->Post("/api/v1/samples", R"({"id": "rock-12"})", "application/json");
  ASSERT_TRUE(r);
  EXPECT_EQ(r->status, 200);
  EXPECT_EQ(Body(r)["sample_id"], "rock-12");
  EXPECT_EQ(fake_.Calls(), std::vector<std::string>{"arm:rock-12"});
}

TEST_F(HttpApiTest, ArmIgnoresExtraFieldsAndContentType) {
  auto r = client_->Post("/api/v1/samples", R"({"id": "RR3_rock.40", "note": 1})", "text/plain");
  ASSERT_TRUE(r);
  EXPECT_EQ(r->status, 200);
  EXPECT_EQ(fake_.Calls(), std::vector<std::string>{"arm:RR3_rock.40"});
}

TEST_F(HttpApiTest, ListAndShowSamples) {
  auto list = client_->Get("/api/v1/samples");
  ASSERT_TRUE(list);
  EXPECT_EQ(list->status, 200);
  EXPECT_EQ(Body(list), fake_.samples);
  auto one = client_->Get("/api/v1/samples/rock-11");
  ASSERT_TRUE(one);
  EXPECT_EQ(one->status, 200);
  EXPECT_EQ(Body(one)["id"], "rock-11");
  EXPECT_EQ(fake_.Calls(), (std::vector<std::string>{"list", "get:rock-11"}));
}

// Reports: made by the control for a rock or a batch (with a shipped
// specification by name), served as a download and their file removed; one
// at a time (503 with Retry-After), an unknown rock is a 404.
TEST_F(HttpApiTest, ReportsAreServedAsDownloads) {
  auto r = client_->Get("/api/v1/samples/rock-11/report.pdf");
  ASSERT_TRUE(r);
  EXPECT_EQ(r->status, 200) << r->body;
  EXPECT_EQ(r->get_header_value("Content-Type"), "application/pdf");
  EXPECT_EQ(r->body.rfind("%PDF", 0), 0u);
  EXPECT_NE(r->get_header_value("Content-Disposition").find("rock-11-report.pdf"),
            std::string::npos);
  r = client_->Get("/api/v1/batches/week-49/report.html?spec=fp14-class1");
  ASSERT_TRUE(r);
  EXPECT_EQ(r->status, 200) << r->body;
  EXPECT_EQ(r->get_header_value("Content-Type").rfind("text/html", 0), 0u);
  ASSERT_EQ(fake_.reports.size(), 2u);
  EXPECT_EQ(fake_.reports[0].kind, "rock");
  EXPECT_EQ(fake_.reports[1].kind, "batch");
  EXPECT_EQ(fake_.reports[1].name, "week-49");
  EXPECT_EQ(fake_.reports[1].spec, "fp14-class1");
  fake_.report_fail = MakeError(ErrorClass::kConflict, "another report is being made");
  r = client_->Get("/api/v1/samples/rock-11/report.html");
  ASSERT_TRUE(r);
  EXPECT_EQ(r->status, 503);
  EXPECT_EQ(r->get_header_value("Retry-After"), "5");
  fake_.report_fail = MakeError(ErrorClass::kNotFound, "no sample rock-99");
  r = client_->Get("/api/v1/samples/rock-99/report.pdf");
  ASSERT_TRUE(r);
  EXPECT_EQ(r->status, 404);
  r = client_->Post("/api/v1/samples/rock-11/report.pdf", "", "application/json");
  ASSERT_TRUE(r);
  EXPECT_EQ(r->status, 405);
  // The made files are gone once served.
  ASSERT_EQ(fake_.reports_made.size(), 2u);
  for (const std::string& p : fake_.reports_made) {
    EXPECT_FALSE(std::filesystem::exists(p)) << p;
    EXPECT_FALSE(std::filesystem::exists(p.substr(0, p.rfind('/')))) << p;
  }
}

TEST_F(HttpApiTest, ResultsAndMeshFiles) {
  const std::string dir = ::testing::TempDir();
  const std::string morph = dir + "/api_morphology.json", ply = dir + "/api_mesh.ply";
  {
    std::ofstream(morph) << R"({"sample_id": "rock-11", "morphology_3d": {"volume_mm3": 1234.5}})";
  }
  { std::ofstream(ply, std::ios::binary) << std::string("ply\0\x01\x02binary", 15); }
  fake_.result_files["rock-11/morphology.json"] = morph;
  fake_.result_files["rock-11/mesh.ply"] = ply;
  auto r = client_->Get("/api/v1/samples/rock-11/results");
  ASSERT_TRUE(r);
  EXPECT_EQ(r->status, 200);
  EXPECT_EQ(r->get_header_value("Content-Type"), "application/json");
  EXPECT_EQ(Body(r)["morphology_3d"]["volume_mm3"], 1234.5);
  auto m = client_->Get("/api/v1/samples/rock-11/mesh.ply");
  ASSERT_TRUE(m);
  EXPECT_EQ(m->status, 200);
  EXPECT_EQ(m->body, std::string("ply\0\x01\x02binary", 15));
  EXPECT_EQ(m->get_header_value("Content-Type"), "application/octet-stream");
  EXPECT_NE(m->get_header_value("Content-Disposition").find("rock-11_mesh.ply"), std::string::npos);
  // Not finished yet: 404 with the reason; unknown files and bad ids.
  auto stl = client_->Get("/api/v1/samples/rock-11/mesh.stl");
  ASSERT_TRUE(stl);
  EXPECT_EQ(stl->status, 404);
  EXPECT_NE(Body(stl)["error"]["message"].get<std::string>().find("no results yet"),
            std::string::npos);
  auto other = client_->Get("/api/v1/samples/rock-11/sample.json");
  ASSERT_TRUE(other);
  EXPECT_EQ(other->status, 400);  // not a result: "rock-11/sample.json" is no sample id
  auto bad = client_->Get("/api/v1/samples/..%2Fetc/results");
  ASSERT_TRUE(bad);
  EXPECT_EQ(bad->status, 400);
  auto post = client_->Post("/api/v1/samples/rock-11/results", "", "text/plain");
  ASSERT_TRUE(post);
  EXPECT_EQ(post->status, 405);
  EXPECT_EQ(fake_.Calls(),
            (std::vector<std::string>{"result:rock-11/morphology.json", "result:rock-11/mesh.ply",
                                      "result:rock-11/mesh.stl"}));
}

TEST_F(HttpApiTest, ButtonAbortReset) {
  for (const char* path : {"/api/v1/button", "/api/v1/abort", "/api/v1/reset"}) {
    auto r = client_->Post(path);
    ASSERT_TRUE(r) << path;
    EXPECT_EQ(r->status, 200) << path;
    EXPECT_TRUE(Body(r).is_object()) << path;
  }
  EXPECT_EQ(fake_.Calls(), (std::vector<std::string>{"press:api", "abort", "reset"}));
}

TEST_F(HttpApiTest, RetryIsAPostOnTheSample) {
  auto r = client_->Post("/api/v1/samples/rock-9/retry", "{}", "application/json");
  ASSERT_TRUE(r);
  EXPECT_EQ(r->status, 200) << r->body;
  EXPECT_EQ(json::parse(r->body)["requeued"], 1);
  auto g = client_->Get("/api/v1/samples/rock-9/retry");
  ASSERT_TRUE(g);
  EXPECT_EQ(g->status, 405);
  EXPECT_EQ(g->get_header_value("Allow"), "POST");
  auto bad = client_->Post("/api/v1/samples/.x/retry", "{}", "application/json");
  ASSERT_TRUE(bad);
  EXPECT_EQ(bad->status, 400);
  fake_.fail = MakeError(ErrorClass::kNotFound, "sample rock-9 has no failed job to retry");
  auto none = client_->Post("/api/v1/samples/rock-9/retry", "{}", "application/json");
  ASSERT_TRUE(none);
  EXPECT_EQ(none->status, 404);
  EXPECT_EQ(fake_.Calls(), (std::vector<std::string>{"retry:rock-9", "retry:rock-9"}));
}

TEST_F(HttpApiTest, MetricsIsPrometheusText) {
  auto r = client_->Get("/metrics");
  ASSERT_TRUE(r);
  EXPECT_EQ(r->status, 200);
  EXPECT_EQ(r->get_header_value("Content-Type").rfind("text/plain; version=0.0.4", 0), 0u);
  EXPECT_NE(r->body.find("aggscan_up 1"), std::string::npos);
}

TEST_F(HttpApiTest, HeadAndOptions) {
  auto head = client_->Head("/api/v1/status");
  ASSERT_TRUE(head);
  EXPECT_EQ(head->status, 200);
  EXPECT_TRUE(head->body.empty());
  auto opt = client_->Options("/api/v1/samples");
  ASSERT_TRUE(opt);
  EXPECT_EQ(opt->status, 204);
  EXPECT_EQ(opt->get_header_value("Allow"), "GET, HEAD, POST, OPTIONS");
}

TEST_F(HttpApiTest, ErrorClassesMapToHttpStatus) {
  const std::vector<std::pair<ErrorClass, int>> cases = {
      {ErrorClass::kInvalidArgument, 400},
      {ErrorClass::kNotFound, 404},
      {ErrorClass::kConflict, 409},
      {ErrorClass::kInvalidState, 409},
      {ErrorClass::kDeviceMissing, 503},
      {ErrorClass::kDisconnected, 503},
      {ErrorClass::kTimeout, 503},
      {ErrorClass::kStalled, 503},
      {ErrorClass::kDeviceFault, 503},
      {ErrorClass::kDiskFull, 507},
      {ErrorClass::kIo, 500},
      {ErrorClass::kCorrupt, 500},
      {ErrorClass::kInvalidConfig, 500},
      {ErrorClass::kInternal, 500},
  };
  for (const auto& [cls, status] : cases) {
    EXPECT_EQ(HttpStatusFor(cls), status) << ErrorClassName(cls);
    fake_.fail =
        MakeError(cls, std::string("failure of class ") + ErrorClassName(cls), "errno text");
    auto r = client_->Post("/api/v1/abort");
    ASSERT_TRUE(r);
    EXPECT_EQ(r->status, status) << ErrorClassName(cls);
    EXPECT_EQ(ErrorClassOf(r), ErrorClassName(cls));
    const json b = Body(r);
    EXPECT_EQ(b["error"]["message"], std::string("failure of class ") + ErrorClassName(cls));
    EXPECT_EQ(b["error"]["detail"], "errno text");
  }
  fake_.fail = MakeError(ErrorClass::kNotFound, "no sample rock-99");
  auto r = client_->Get("/api/v1/samples/rock-99");
  ASSERT_TRUE(r);
  EXPECT_EQ(r->status, 404);
  EXPECT_EQ(ErrorClassOf(r), "not_found");
}

TEST_F(HttpApiTest, NonUtf8ErrorMessageStillValidJson) {
  fake_.fail = MakeError(ErrorClass::kIo, "bad bytes \xff\xfe here");
  auto r = client_->Post("/api/v1/reset");
  ASSERT_TRUE(r);
  EXPECT_EQ(r->status, 500);
  EXPECT_EQ(ErrorClassOf(r), "io");
}

TEST_F(HttpApiTest, BadArmBodiesAre400) {
  const std::vector<std::string> bodies = {
      "",
      "{",
      "not json",
      "[1,2]",
      "\"rock-1\"",
      "42",
      "null",
      "{}",
      R"({"id": 7})",
      R"({"id": null})",
      R"({"id": ["a"]})",
      R"({"ID": "rock-1"})",
      std::string(20000, '['),
      "{\"id\": \"rock\xff\"}",
  };
  for (const auto& body : bodies) {
    auto r = client_->Post("/api/v1/samples", body, "application/json");
    ASSERT_TRUE(r) << body.substr(0, 40);
    EXPECT_EQ(r->status, 400) << body.substr(0, 40);
    EXPECT_EQ(ErrorClassOf(r), "invalid_argument") << body.substr(0, 40);
  }
  EXPECT_EQ(fake_.CallCount(), 0u);
}

TEST_F(HttpApiTest, InvalidIdsInBodyNeverReachControl) {
  const std::vector<std::string> ids = {"",
                                        "..",
                                        "../etc",
                                        "../../etc/passwd",
                                        "a/b",
                                        "/abs",
                                        "a b",
                                        "a\nb",
                                        "a\tb",
                                        ".hidden",
                                        "-rf",
                                        "%2e%2e%2f",
                                        std::string(65, 'x'),
                                        std::string("a\0b", 3),
                                        "rock\x7f",
                                        "r\xc3\xa9"};
  for (const auto& id : ids) {
    auto r = client_->Post("/api/v1/samples",
                           json{{"id", id}}.dump(-1, ' ', false, json::error_handler_t::replace),
                           "application/json");
    ASSERT_TRUE(r);
    EXPECT_EQ(r->status, 400) << id;
    EXPECT_EQ(ErrorClassOf(r), "invalid_argument") << id;
  }
  // The longest valid id is accepted.
  auto ok = client_->Post("/api/v1/samples", json{{"id", std::string(64, 'x')}}.dump(),
                          "application/json");
  ASSERT_TRUE(ok);
  EXPECT_EQ(ok->status, 200);
  EXPECT_EQ(fake_.Calls(), std::vector<std::string>{"arm:" + std::string(64, 'x')});
}

TEST_F(HttpApiTest, TraversalInPathRefusedRawAndPercentEncoded) {
  const std::vector<std::string> paths = {
      "/api/v1/samples/../../etc/passwd",
      "/api/v1/samples/..",
      "/api/v1/samples/%2e%2e",
      "/api/v1/samples/%2e%2e%2f%2e%2e%2fetc%2fpasswd",
      "/api/v1/samples/%2E%2E%2F",
      "/api/v1/samples/..%2f..%2fetc",
      "/api/v1/samples/rock%2f..%2f..",
      "/api/v1/samples/%252e%252e%252f",
      "/api/v1/samples/a%20b",
      "/api/v1/samples/a%00b",
      "/api/v1/samples/a%0ab",
      "/api/v1/samples/.hidden",
      "/api/v1/samples/",
      "/api/v1/samples/" + std::string(65, 'x'),
  };
  for (const auto& path : paths) {
    auto r = client_->Get(path);
    ASSERT_TRUE(r) << path;
    EXPECT_EQ(r->status, 400) << path;
    EXPECT_EQ(ErrorClassOf(r), "invalid_argument") << path;
  }
  // Same through a raw socket, where no client library can normalise anything.
  const std::string raw =
      Raw("GET /api/v1/samples/%2e%2e%2f%2e%2e%2fetc HTTP/1.1\r\nHost: localhost\r\nConnection: "
          "close\r\n\r\n");
  EXPECT_EQ(raw.rfind("HTTP/1.1 400", 0), 0u) << raw;
  EXPECT_EQ(fake_.CallCount(), 0u);
}

TEST_F(HttpApiTest, BodyLimit) {
  // Exactly the limit is fine (the id is parsed, the padding ignored).
  std::string exact = R"({"id": "rock-1", "pad": ")";
  exact += std::string(HttpApi::kMaxBodyBytes - exact.size() - 2, 'x') + "\"}";
  ASSERT_EQ(exact.size(), HttpApi::kMaxBodyBytes);
  auto r1 = client_->Post("/api/v1/samples", exact, "application/json");
  ASSERT_TRUE(r1);
  EXPECT_EQ(r1->status, 200);

  const std::string big(HttpApi::kMaxBodyBytes + 1, ' ');
  for (const char* path : {"/api/v1/samples", "/api/v1/button", "/no/such/route"}) {
    httplib::Client c("127.0.0.1", api_->port());
    auto r = c.Post(path, big, "application/json");
    ASSERT_TRUE(r) << path;
    EXPECT_EQ(r->status, 413) << path;
    EXPECT_EQ(ErrorClassOf(r), "invalid_argument") << path;
  }
  // 1 MiB, far over the limit.
  httplib::Client c("127.0.0.1", api_->port());
  auto huge = c.Post("/api/v1/samples", std::string(1 << 20, 'x'), "application/json");
  ASSERT_TRUE(huge);
  EXPECT_EQ(huge->status, 413);
  EXPECT_EQ(fake_.Calls(), std::vector<std::string>{"arm:rock-1"});

  // The server is still healthy.
  auto after = client_->Get("/api/v1/status");
  ASSERT_TRUE(after);
  EXPECT_EQ(after->status, 200);
}

TEST_F(HttpApiTest, ChunkedBodyOverLimitIs413) {
  std::string req =
      "POST /api/v1/samples HTTP/1.1\r\nHost: localhost\r\nTransfer-Encoding: "
      "chunked\r\nConnection: "
      "close\r\n\r\n";
  const std::string chunk(16 * 1024, 'x');
  char size_line[32];
  std::snprintf(size_line, sizeof size_line, "%zx\r\n", chunk.size());
  for (int i = 0; i < 8; ++i) req += size_line + chunk + "\r\n";
  req += "0\r\n\r\n";
  const std::string answer = Raw(req);
  EXPECT_EQ(answer.rfind("HTTP/1.1 413", 0), 0u) << answer.substr(0, 200);
  EXPECT_NE(answer.find("\"invalid_argument\""), std::string::npos);
  EXPECT_EQ(fake_.CallCount(), 0u);
}

TEST_F(HttpApiTest, ChunkedSmallBodyAccepted) {
  const std::string body = R"({"id":"rock-7"})";
  char size_line[32];
  std::snprintf(size_line, sizeof size_line, "%zx\r\n", body.size());
  const std::string answer =
      Raw("POST /api/v1/samples HTTP/1.1\r\nHost: localhost\r\nTransfer-Encoding: chunked\r\n"
          "Connection: close\r\n\r\n" +
          std::string(size_line) + body + "\r\n0\r\n\r\n");
  EXPECT_EQ(answer.rfind("HTTP/1.1 200", 0), 0u) << answer.substr(0, 200);
  EXPECT_EQ(fake_.Calls(), std::vector<std::string>{"arm:rock-7"});
}

TEST_F(HttpApiTest, PostWithoutContentLengthDoesNotHang) {
  const auto t0 = std::chrono::steady_clock::now();
  const std::string answer =
      Raw("POST /api/v1/button HTTP/1.1\r\nHost: localhost\r\nConnection: close\r\n\r\n");
  EXPECT_EQ(answer.rfind("HTTP/1.1 200", 0), 0u) << answer.substr(0, 200);
  EXPECT_LT(std::chrono::steady_clock::now() - t0, std::chrono::seconds(2));
}

TEST_F(HttpApiTest, UnknownRouteIs404Json) {
  for (const char* path :
       {"/", "/api", "/api/v1", "/api/v1/statu", "/api/v2/status", "/api/v1/status/x"}) {
    auto r = client_->Get(path);
    ASSERT_TRUE(r) << path;
    EXPECT_EQ(r->status, 404) << path;
    EXPECT_EQ(ErrorClassOf(r), "not_found") << path;
  }
  auto post = client_->Post("/api/v1/nope", "{}", "application/json");
  ASSERT_TRUE(post);
  EXPECT_EQ(post->status, 404);
  EXPECT_EQ(ErrorClassOf(post), "not_found");
  // A very long path neither crashes the router nor reaches the control.
  auto lng = client_->Get("/" + std::string(8000, 'a'));
  ASSERT_TRUE(lng);
  EXPECT_GE(lng->status, 400);
  EXPECT_EQ(fake_.CallCount(), 0u);
}

TEST_F(HttpApiTest, WrongMethodIs405WithAllow) {
  struct Case {
    std::string method, path, allow;
  };
  const std::vector<Case> cases = {
      {"DELETE", "/api/v1/status", "GET, HEAD"}, {"POST", "/api/v1/status", "GET, HEAD"},
      {"GET", "/api/v1/button", "POST"},         {"PUT", "/api/v1/samples", "GET, HEAD, POST"},
      {"GET", "/api/v1/abort", "POST"},          {"PATCH", "/api/v1/reset", "POST"},
      {"POST", "/metrics", "GET, HEAD"},         {"DELETE", "/api/v1/samples/rock-1", "GET, HEAD"},
      {"POST", "/api/v1/events", "GET"},
  };
  for (const auto& c : cases) {
    httplib::Result r = c.method == "GET"     ? client_->Get(c.path)
                        : c.method == "POST"  ? client_->Post(c.path, "{}", "application/json")
                        : c.method == "PUT"   ? client_->Put(c.path, "{}", "application/json")
                        : c.method == "PATCH" ? client_->Patch(c.path, "{}", "application/json")
                                              : client_->Delete(c.path);
    ASSERT_TRUE(r) << c.method << " " << c.path;
    EXPECT_EQ(r->status, 405) << c.method << " " << c.path;
    EXPECT_EQ(r->get_header_value("Allow"), c.allow) << c.method << " " << c.path;
    EXPECT_EQ(ErrorClassOf(r), "invalid_argument");
  }
  EXPECT_EQ(fake_.CallCount(), 0u);
}

// The OpenAPI document is served, is OpenAPI 3, and agrees with the router:
// every path it lists is routed, with exactly its methods (HEAD beside GET
// but on the event stream), and an unlisted one is a 404.
TEST_F(HttpApiTest, OpenApiDocumentListsWhatIsRouted) {
  auto r = client_->Get("/api/v1/openapi.json");
  ASSERT_TRUE(r);
  EXPECT_EQ(r->status, 200);
  const json doc = Body(r);
  ASSERT_TRUE(doc.is_object()) << r->body.substr(0, 200);
  EXPECT_EQ(doc["openapi"].get<std::string>().rfind("3.", 0), 0u);
  ASSERT_TRUE(doc["paths"].is_object());
  EXPECT_GE(doc["paths"].size(), 19u);
  for (const auto& [path, item] : doc["paths"].items()) {
    std::string concrete = path;
    for (const auto& [param, value] : {std::pair<std::string, std::string>{"{id}", "rock-1"},
                                       {"{side}", "1"},
                                       {"{view}", "0"}}) {
      if (const size_t at = concrete.find(param); at != std::string::npos)
        concrete.replace(at, param.size(), value);
    }
    std::set<std::string> documented;
    for (const auto& [method, op] : item.items()) {
      if (method == "parameters") continue;
      std::string upper = method;
      for (char& c : upper) c = static_cast<char>(std::toupper(static_cast<unsigned char>(c)));
      documented.insert(upper);
      if (upper == "GET" && path != "/api/v1/events" && path != "/api/v1/preview")
        documented.insert("HEAD");
    }
    // OPTIONS answers with the router's Allow list for a routed path.
    auto o = client_->Options(concrete);
    ASSERT_TRUE(o) << path;
    EXPECT_EQ(o->status, 204) << path << ": " << o->body;
    std::set<std::string> allowed;
    std::string allow = o->get_header_value("Allow");
    for (size_t pos = 0; pos < allow.size();) {
      size_t end = allow.find(", ", pos);
      if (end == std::string::npos) end = allow.size();
      allowed.insert(allow.substr(pos, end - pos));
      pos = end + 2;
    }
    allowed.erase("OPTIONS");
    EXPECT_EQ(allowed, documented) << path;
  }
  auto none = client_->Get("/api/v1/not-documented");
  ASSERT_TRUE(none);
  EXPECT_EQ(none->status, 404);
}

// Without an event hub (a daemon that publishes none) the stream is a 404.
TEST_F(HttpApiTest, EventsWithoutAHubIs404) {
  auto r = client_->Get("/api/v1/events");
  ASSERT_TRUE(r);
  EXPECT_EQ(r->status, 404);
  EXPECT_EQ(ErrorClassOf(r), "not_found");
}

// Opens GET /api/v1/events on a raw socket; returns the fd (-1 on failure).
int OpenEventStream(int port) {
  const int fd = test::ConnectLoopback(port);
  if (fd < 0) return -1;
  const std::string req = "GET /api/v1/events HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n";
  if (::send(fd, req.data(), req.size(), MSG_NOSIGNAL) != static_cast<ssize_t>(req.size())) {
    ::close(fd);
    return -1;
  }
  return fd;
}

// Reads from `fd` until `want` shows up, the peer closes or `ms` pass.
std::string ReadUntil(int fd, const std::string& want, int ms) {
  std::string got;
  char buf[4096];
  const auto end = std::chrono::steady_clock::now() + std::chrono::milliseconds(ms);
  while (got.find(want) == std::string::npos && std::chrono::steady_clock::now() < end) {
    pollfd p{fd, POLLIN, 0};
    if (::poll(&p, 1, 50) <= 0) continue;
    const ssize_t n = ::recv(fd, buf, sizeof buf, 0);
    if (n <= 0) break;
    got.append(buf, static_cast<size_t>(n));
  }
  return got;
}

// Streams take published events as they come (suspended in between, so an
// idle stream costs no CPU); at most kMaxEventStreams are open, the next is
// refused with 503 while the ordinary API still answers; Stop ends them all
// at once.
TEST(HttpApiEvents, StreamsTakeEventsAreBoundedAndEndWithTheServer) {
  FakeControl fake;
  EventHub hub;
  HttpApiOptions o;
  o.events = &hub;
  HttpApi api(fake, "127.0.0.1", 0, o);
  ASSERT_TRUE(api.Start().ok());
  std::vector<int> fds;
  for (size_t i = 0; i < HttpApi::kMaxEventStreams; ++i) {
    const int fd = OpenEventStream(api.port());
    ASSERT_GE(fd, 0);
    const std::string head = ReadUntil(fd, ": aggscand events\n\n", 5000);
    ASSERT_NE(head.find("HTTP/1.1 200"), std::string::npos) << head;
    ASSERT_NE(head.find("text/event-stream"), std::string::npos) << head;
    fds.push_back(fd);
  }
  const int extra = OpenEventStream(api.port());
  const std::string refused = ReadUntil(extra, "too many event streams", 5000);
  EXPECT_NE(refused.find("HTTP/1.1 503"), std::string::npos) << refused;
  ::close(extra);
  httplib::Client c("127.0.0.1", api.port());
  auto status = c.Get("/api/v1/status");
  ASSERT_TRUE(status);
  EXPECT_EQ(status->status, 200);

  const uint64_t seq = hub.Publish("view", {{"number", 7}});
  const std::string id = "id: " + hub.IdOf(seq) + "\nevent: view\ndata: {\"number\":7";
  for (int fd : fds) {
    const std::string got = ReadUntil(fd, "\n\n", 5000);
    EXPECT_NE(got.find(id), std::string::npos) << got;
  }
  const auto t0 = std::chrono::steady_clock::now();
  api.Stop();
  EXPECT_LT(std::chrono::steady_clock::now() - t0, std::chrono::seconds(5));
  for (int fd : fds) {
    // The stream's end: the peer closes (recv 0) after the last chunk.
    char buf[256];
    ssize_t n = 1;
    for (int i = 0; i < 100 && n > 0; ++i) {
      pollfd p{fd, POLLIN, 0};
      if (::poll(&p, 1, 100) <= 0) continue;
      n = ::recv(fd, buf, sizeof buf, 0);
    }
    EXPECT_LE(n, 0);
    ::close(fd);
  }
  // Publishing after the server stopped reaches nobody and harms nothing.
  hub.Publish("view", {{"number", 8}});
}

TEST_F(HttpApiTest, GarbageRequestsGetJsonErrors) {
  // A request line libmicrohttpd cannot parse gets no answer: it closes the
  // connection (an invalid Content-Length gets its own HTML 400/413). What it
  // can parse is refused by the API with the JSON error shape.
  const std::string bad_line = Raw("GARBAGE\r\n\r\n");
  EXPECT_TRUE(bad_line.empty() || bad_line.rfind("HTTP/1.1 400", 0) == 0) << bad_line;
  const std::string bad_method = Raw("BREW /api/v1/status HTTP/1.1\r\nHost: localhost\r\n\r\n");
  EXPECT_EQ(bad_method.rfind("HTTP/1.1 400", 0), 0u) << bad_method;
  EXPECT_NE(bad_method.find("\"error\""), std::string::npos) << bad_method;
  const std::string bad_len =
      Raw("POST /api/v1/samples HTTP/1.1\r\nHost: localhost\r\nContent-Length: "
          "99999999999999999999\r\nConnection: close\r\n\r\n");
  EXPECT_TRUE(bad_len.rfind("HTTP/1.1 400", 0) == 0 || bad_len.rfind("HTTP/1.1 413", 0) == 0)
      << bad_len;
  const std::string neg_len =
      Raw("POST /api/v1/samples HTTP/1.1\r\nHost: localhost\r\nContent-Length: -5\r\nConnection: "
          "close\r\n\r\n");
  EXPECT_EQ(neg_len.rfind("HTTP/1.1 400", 0), 0u) << neg_len;
  auto r = client_->Get("/api/v1/status");
  ASSERT_TRUE(r);
  EXPECT_EQ(r->status, 200);
}

TEST_F(HttpApiTest, ThrowingControlIs500Json) {
  fake_.throw_all = true;
  for (const char* path :
       {"/api/v1/status", "/api/v1/samples", "/metrics", "/api/v1/samples/rock-1"}) {
    auto r = client_->Get(path);
    ASSERT_TRUE(r) << path;
    EXPECT_EQ(r->status, 500) << path;
    EXPECT_EQ(ErrorClassOf(r), "internal") << path;
  }
  auto arm = client_->Post("/api/v1/samples", R"({"id":"rock-1"})", "application/json");
  ASSERT_TRUE(arm);
  EXPECT_EQ(arm->status, 500);
  fake_.throw_all = false;
  auto r = client_->Get("/api/v1/status");
  ASSERT_TRUE(r);
  EXPECT_EQ(r->status, 200);
}

TEST_F(HttpApiTest, ConcurrentRequestsAllAnswered) {
  constexpr int kThreads = 8;
  constexpr int kRequests = 50;
  std::atomic<int> answered{0};
  std::vector<std::thread> threads;
  for (int t = 0; t < kThreads; ++t) {
    threads.emplace_back([&, t] {
      httplib::Client c("127.0.0.1", api_->port());
      c.set_keep_alive(t % 2 == 0);  // half reuse a connection, half reconnect every time
      for (int i = 0; i < kRequests; ++i) {
        httplib::Result r = (i % 3 == 0)   ? c.Post("/api/v1/button")
                            : (i % 3 == 1) ? c.Get("/api/v1/status")
                                           : c.Get("/api/v1/samples/rock-" + std::to_string(t));
        if (r && r->status == 200 && json::parse(r->body, nullptr, false).is_object()) ++answered;
      }
    });
  }
  for (auto& th : threads) th.join();
  EXPECT_EQ(answered.load(), kThreads * kRequests);
  EXPECT_EQ(fake_.CallCount(), static_cast<size_t>(kThreads * kRequests));
}

TEST_F(HttpApiTest, SecondServerOnSamePortFailsClearly) {
  HttpApi second(fake_, "127.0.0.1", api_->port());
  const Status st = second.Start();
  ASSERT_FALSE(st.ok());
  EXPECT_EQ(st.error().cls, ErrorClass::kConflict);
  const std::string expected =
      "cannot listen on 127.0.0.1:" + std::to_string(api_->port()) +
      ": address already in use — is another aggscand running? set daemon.listen_port";
  EXPECT_EQ(st.error().message, expected);
  EXPECT_EQ(second.port(), 0);
  second.Stop();  // harmless when never started
  // The first server is unaffected.
  auto r = client_->Get("/api/v1/status");
  ASSERT_TRUE(r);
  EXPECT_EQ(r->status, 200);
}

TEST(HttpApiLifecycle, BadAddressAndPort) {
  FakeControl fake;
  HttpApi bad_addr(fake, "203.0.113.7", 0);  // TEST-NET-3: not an address of this host
  const Status st = bad_addr.Start();
  ASSERT_FALSE(st.ok());
  EXPECT_EQ(st.error().message.rfind("cannot listen on 203.0.113.7:0: ", 0), 0u)
      << st.error().message;
  HttpApi bad_port(fake, "127.0.0.1", 70000);
  const Status st2 = bad_port.Start();
  ASSERT_FALSE(st2.ok());
  EXPECT_EQ(st2.error().cls, ErrorClass::kInvalidConfig);
}

TEST(HttpApiLifecycle, StartStopRepeatedly) {
  FakeControl fake;
  for (int i = 0; i < 20; ++i) {
    HttpApi api(fake, "127.0.0.1", 0);
    ASSERT_TRUE(api.Start().ok());
    if (i % 2 == 0) {
      httplib::Client c("127.0.0.1", api.port());
      auto r = c.Get("/api/v1/status");
      ASSERT_TRUE(r);
      EXPECT_EQ(r->status, 200);
    }
    api.Stop();
    api.Stop();  // idempotent
  }
  // Restart on the same object.
  HttpApi api(fake, "127.0.0.1", 0);
  ASSERT_TRUE(api.Start().ok());
  EXPECT_FALSE(api.Start().ok());  // already started
  api.Stop();
  ASSERT_TRUE(api.Start().ok());
  httplib::Client c("127.0.0.1", api.port());
  auto r = c.Get("/api/v1/status");
  ASSERT_TRUE(r);
  EXPECT_EQ(r->status, 200);
}

// The health endpoint: 200 only when the daemon says every device is ok, else
// 503 with the same report, so monitors need only the code.
TEST_F(HttpApiTest, HealthIs200WhenOkAnd503WithTheReportWhenNot) {
  auto r = client_->Get("/api/v1/health");
  ASSERT_TRUE(r);
  EXPECT_EQ(r->status, 200);
  EXPECT_EQ(Body(r)["status"], "ok");
  fake_.health = {{"status", "unhealthy"},
                  {"devices",
                   {{"turntable",
                     {{"state", "timeout"},
                      {"healthy", false},
                      {"message", "turntable: no answer from Modbus unit 1 — check wiring"}}}}}};
  r = client_->Get("/api/v1/health");
  ASSERT_TRUE(r);
  EXPECT_EQ(r->status, 503);
  EXPECT_EQ(Body(r)["devices"]["turntable"]["state"], "timeout");
  r = client_->Post("/api/v1/health", "{}", "application/json");
  ASSERT_TRUE(r);
  EXPECT_EQ(r->status, 405);
}

// A JPEG of `w` x `h` (a left-to-right grey ramp), as the camera writes them.
std::string RampJpeg(int w, int h) {
  std::vector<uint8_t> rgb(static_cast<size_t>(w) * h * 3);
  for (int y = 0; y < h; ++y)
    for (int x = 0; x < w; ++x)
      for (int c = 0; c < 3; ++c) rgb[(static_cast<size_t>(y) * w + x) * 3 + c] = x * 255 / w;
  auto jpeg = sim::EncodeJpeg(rgb.data(), w, h, 90);
  EXPECT_TRUE(jpeg.ok());
  return std::string(jpeg->begin(), jpeg->end());
}

std::pair<int, int> JpegSize(const std::string& bytes) {
  auto img = sim::DecodeJpeg(
      std::span(reinterpret_cast<const unsigned char*>(bytes.data()), bytes.size()));
  if (!img) return {0, 0};
  return {img->width, img->height};
}

// A stored view, its thumbnail (DCT-scaled to 1/8: 252x189 from 2016x1512)
// and its mask; paths that are not a view's are 404 with the shape to use,
// and a stored file that is not a JPEG is an error naming it, not a crash.
TEST_F(HttpApiTest, ViewsThumbnailsAndMasks) {
  const std::string dir = ::testing::TempDir();
  const std::string image = dir + "/api_view_007.jpg", mask = dir + "/api_view_007.png",
                    broken = dir + "/api_view_008.jpg";
  const std::string jpeg = RampJpeg(2016, 1512);
  { std::ofstream(image, std::ios::binary) << jpeg; }
  { std::ofstream(mask, std::ios::binary) << std::string("\x89PNG\r\n\x1a\n-mask-", 14); }
  { std::ofstream(broken, std::ios::binary) << "not a jpeg"; }
  fake_.view_files["rock-11/2/7/image"] = image;
  fake_.view_files["rock-11/2/7/mask"] = mask;
  fake_.view_files["rock-11/2/8/image"] = broken;
  EXPECT_EQ(ViewUrl("rock-11", 2, 7), "/api/v1/samples/rock-11/sides/2/views/7");

  auto full = client_->Get("/api/v1/samples/rock-11/sides/2/views/7");
  ASSERT_TRUE(full);
  EXPECT_EQ(full->status, 200);
  EXPECT_EQ(full->get_header_value("Content-Type"), "image/jpeg");
  EXPECT_EQ(full->body, jpeg);
  auto thumb = client_->Get("/api/v1/samples/rock-11/sides/2/views/7/thumbnail");
  ASSERT_TRUE(thumb);
  EXPECT_EQ(thumb->status, 200);
  EXPECT_EQ(thumb->get_header_value("Content-Type"), "image/jpeg");
  EXPECT_EQ(JpegSize(thumb->body), std::make_pair(252, 189));
  EXPECT_LT(thumb->body.size(), jpeg.size() / 10);
  auto again = client_->Get("/api/v1/samples/rock-11/sides/2/views/7/thumbnail");
  ASSERT_TRUE(again);
  EXPECT_EQ(again->body, thumb->body);  // from the cache
  auto m = client_->Get("/api/v1/samples/rock-11/sides/2/views/7/mask");
  ASSERT_TRUE(m);
  EXPECT_EQ(m->status, 200);
  EXPECT_EQ(m->get_header_value("Content-Type"), "image/png");
  EXPECT_EQ(m->body.size(), 14u);

  auto missing = client_->Get("/api/v1/samples/rock-11/sides/1/views/7/mask");
  ASSERT_TRUE(missing);
  EXPECT_EQ(missing->status, 404);
  EXPECT_EQ(ErrorClassOf(missing), "not_found");
  auto bad = client_->Get("/api/v1/samples/rock-11/sides/2/views/8/thumbnail");
  ASSERT_TRUE(bad);
  EXPECT_EQ(bad->status, 500);
  EXPECT_NE(Body(bad)["error"]["message"].get<std::string>().find("api_view_008.jpg"),
            std::string::npos)
      << bad->body;
  for (const char* path :
       {"/api/v1/samples/rock-11/sides/two/views/7",
        "/api/v1/samples/rock-11/sides/2/views/7/outline",
        "/api/v1/samples/rock-11/sides/2/views/1000", "/api/v1/samples/rock-11/sides/2/views/-1",
        "/api/v1/samples/rock-11/sides/2/views/7/thumbnail/x",
        "/api/v1/samples/rock-11/sides/2/views", "/api/v1/samples/rock-11/sides/2/views/7/"}) {
    auto r = client_->Get(path);
    ASSERT_TRUE(r) << path;
    EXPECT_EQ(r->status, 404) << path;
    EXPECT_NE(r->body.find("sides/{side}/views/{view}"), std::string::npos) << path << r->body;
  }
  auto bad_id = client_->Get("/api/v1/samples/..%2Fetc/sides/2/views/7");
  ASSERT_TRUE(bad_id);
  EXPECT_EQ(bad_id->status, 400);
  auto post = client_->Post("/api/v1/samples/rock-11/sides/2/views/7", "", "text/plain");
  ASSERT_TRUE(post);
  EXPECT_EQ(post->status, 405);
}

// Reads `n` bytes from `fd` (fewer if the peer closes or `ms` pass).
std::string ReadBytes(int fd, size_t n, int ms) {
  std::string got;
  char buf[4096];
  const auto end = std::chrono::steady_clock::now() + std::chrono::milliseconds(ms);
  while (got.size() < n && std::chrono::steady_clock::now() < end) {
    pollfd p{fd, POLLIN, 0};
    if (::poll(&p, 1, 50) <= 0) continue;
    const ssize_t r = ::recv(fd, buf, std::min(sizeof buf, n - got.size()), 0);
    if (r <= 0) break;
    got.append(buf, static_cast<size_t>(r));
  }
  return got;
}

int OpenPreviewStream(int port) {
  const int fd = test::ConnectLoopback(port);
  if (fd < 0) return -1;
  const std::string req = "GET /api/v1/preview HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n";
  if (::send(fd, req.data(), req.size(), MSG_NOSIGNAL) != static_cast<ssize_t>(req.size())) {
    ::close(fd);
    return -1;
  }
  return fd;
}

// Waits until `hub` counts `n` viewers.
bool ViewersReach(const PreviewHub& hub, int n) {
  for (int i = 0; i < 500 && hub.viewers() != n; ++i)
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  return hub.viewers() == n;
}

// The live view: the first viewer asks for stills (on_demand), each frame
// submitted reaches every viewer as one multipart part scaled to the
// configured size, a slow viewer gets the newest frame rather than a queue,
// kMaxPreviewStreams are open at most, and a viewer that leaves is counted out.
TEST(HttpApiPreview, FramesReachEveryViewerAsMjpegParts) {
  FakeControl fake;
  PreviewHub hub(640, 70);
  std::atomic<int> demanded{0};
  hub.SetOnDemand([&] { ++demanded; });
  HttpApiOptions o;
  o.preview = &hub;
  HttpApi api(fake, "127.0.0.1", 0, o);
  ASSERT_TRUE(api.Start().ok());

  std::vector<int> fds;
  for (size_t i = 0; i < HttpApi::kMaxPreviewStreams; ++i) {
    const int fd = OpenPreviewStream(api.port());
    ASSERT_GE(fd, 0);
    fds.push_back(fd);
  }
  ASSERT_TRUE(ViewersReach(hub, static_cast<int>(HttpApi::kMaxPreviewStreams)));
  EXPECT_EQ(demanded.load(), 1);
  const int extra = OpenPreviewStream(api.port());
  const std::string refused = ReadUntil(extra, "too many live views", 5000);
  EXPECT_NE(refused.find("HTTP/1.1 503"), std::string::npos) << refused;
  ::close(extra);

  auto frame = std::make_shared<Frame>();
  const std::string jpeg = RampJpeg(2016, 1512);
  frame->data.assign(jpeg.begin(), jpeg.end());
  frame->width = 2016;
  frame->height = 1512;
  hub.Submit(frame, "preview");
  for (int fd : fds) {
    std::string got = ReadUntil(fd, "\r\n\r\n", 5000);
    ASSERT_NE(got.find("HTTP/1.1 200"), std::string::npos) << got;
    EXPECT_NE(got.find("multipart/x-mixed-replace; boundary=aggscanframe"), std::string::npos)
        << got;
    // The part's head: "--aggscanframe" ... "Content-Length: N" and a blank line.
    for (int i = 0; i < 100; ++i) {
      const size_t at = got.find("Content-Length: ");
      if (at != std::string::npos && got.find("\r\n\r\n", at) != std::string::npos) break;
      got += ReadBytes(fd, 1, 50);
    }
    const size_t part = got.find("--aggscanframe\r\nContent-Type: image/jpeg\r\nContent-Length: ");
    ASSERT_NE(part, std::string::npos) << got;
    const size_t len_at =
        part + std::strlen("--aggscanframe\r\nContent-Type: image/jpeg\r\nContent-Length: ");
    const size_t len = std::stoul(got.substr(len_at));
    const size_t body_at = got.find("\r\n\r\n", len_at) + 4;
    got += ReadBytes(fd, body_at + len - std::min(got.size(), body_at + len), 5000);
    ASSERT_GE(got.size(), body_at + len);
    EXPECT_EQ(JpegSize(got.substr(body_at, len)), std::make_pair(504, 378));
  }
  EXPECT_EQ(hub.frames_published(), 1u);
  const PreviewFrame latest = hub.Latest();
  EXPECT_EQ(latest.source, "preview");
  EXPECT_EQ(latest.width, 504);

  // A frame that is not a JPEG is counted, not published.
  auto junk = std::make_shared<Frame>();
  junk->data = {1, 2, 3};
  hub.Submit(junk, "preview");
  for (int i = 0; i < 200 && hub.frames_failed() == 0; ++i)
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  EXPECT_EQ(hub.frames_failed(), 1u);
  EXPECT_EQ(hub.frames_published(), 1u);

  for (size_t i = 0; i < 3; ++i) ::close(fds[i]);
  // libmicrohttpd notices a closed viewer when a write to it fails.
  const int left = static_cast<int>(HttpApi::kMaxPreviewStreams) - 3;
  for (int i = 0; i < 50 && hub.viewers() != left; ++i) {
    hub.Submit(frame, "view");
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
  }
  EXPECT_EQ(hub.viewers(), left);
  EXPECT_EQ(hub.Latest().source, "view");
  api.Stop();
  EXPECT_EQ(hub.viewers(), 0);
  for (size_t i = 3; i < fds.size(); ++i) ::close(fds[i]);
}

TEST_F(HttpApiTest, PreviewWithoutAHubIs404) {
  auto r = client_->Get("/api/v1/preview");
  ASSERT_TRUE(r);
  EXPECT_EQ(r->status, 404);
  EXPECT_NE(r->body.find("preview_interval"), std::string::npos) << r->body;
}

}  // namespace
}  // namespace aggscan
