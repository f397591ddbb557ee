// libFuzzer target: one HTTP request through the API's router
// (daemon/http_api.h) as the transport hands it over, CheckHead on the head
// and then Handle, against the tests' fake DaemonControl (never blocks).
//
// The input is a request written as on the wire, "\n" or "\r\n" ending lines:
//   METHOD TARGET [VERSION] [!MODE]     target as sent: path, query, %-escapes
//   Name: value                         header fields, in order
//   *N Name: value                      that field N times (N <= 2000), so the
//                                       count and size limits are in reach
//   (empty line)
//   body                                "*N\n" first: the rest N times (N <= 40)
// MODE picks how the control answers: a digit or letter a-d is the
// ErrorClass (in declaration order) that every Result-returning call fails
// with, "t" every call throws, "u" health reports a device down.
//
// Checked for every input (abort() when violated): the status is 100..599;
// a refusal by CheckHead is what Handle answers too, closes the connection
// and reaches no control call; every answer except 204, /metrics and a mesh
// download is valid JSON, an error one {"error": {"class", "message"}} (an
// unhealthy /api/v1/health: the health document); no
// state-changing call (arm, press, abort, reset, retry) happens for a
// request refused by CheckHead or by the Host/Origin policy, nor for one
// whose Host does not name this rig.
#include <algorithm>
#include <cctype>
#include <cstdio>
#include <cstdlib>
#include <nlohmann/json.hpp>
#include <string>
#include <string_view>
#include <vector>

#include "daemon/http_api.h"
#include "tests/api/fake_control.h"
#include "tests/fuzz/fuzz_util.h"

namespace {

using aggscan::ApiRequest;
using aggscan::ApiResponse;
using nlohmann::json;

constexpr int kPort = 8080;
// The rig's names as the daemon would configure them: the defaults for a
// loopback listen address, one extra name without a port, one with its own.
const std::vector<std::string> kExtraNames = {"rig-7.lab", "scanner.local:9000"};
const std::vector<std::string> kOrigins = {"https://dash.lab"};
constexpr size_t kMaxRepeat = 2000;
constexpr size_t kMaxBodyRepeat = 40;

std::string Lower(std::string_view s) {
  std::string out(s);
  for (char& c : out) c = static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
  return out;
}

// Takes one line off `in` (without its "\n" or "\r\n"); false at the end.
bool NextLine(std::string_view* in, std::string_view* line) {
  if (in->empty()) return false;
  size_t end = in->find('\n');
  const size_t next = end == std::string_view::npos ? in->size() : end + 1;
  if (end == std::string_view::npos) end = in->size();
  *line = in->substr(0, end);
  if (!line->empty() && line->back() == '\r') line->remove_suffix(1);
  in->remove_prefix(next);
  return true;
}

// "*N rest": N (capped) and the rest; 1 and the whole line otherwise.
size_t Repeat(std::string_view* line, size_t cap) {
  if (line->empty() || line->front() != '*') return 1;
  size_t i = 1;
  size_t n = 0;
  while (i < line->size() && std::isdigit(static_cast<unsigned char>((*line)[i]))) {
    n = std::min(cap, n * 10 + static_cast<size_t>((*line)[i] - '0'));
    ++i;
  }
  if (i < line->size() && (*line)[i] == ' ') ++i;
  line->remove_prefix(i);
  return n;
}

struct Decoded {
  ApiRequest req;
  char mode = 0;
};

Decoded Decode(std::string_view in) {
  Decoded d;
  std::string_view line;
  if (!NextLine(&in, &line)) return d;
  // Request line: tokens separated by single spaces, as a client sends them.
  std::vector<std::string_view> tokens;
  while (!line.empty()) {
    const size_t sp = line.find(' ');
    tokens.push_back(line.substr(0, sp));
    if (sp == std::string_view::npos) break;
    line.remove_prefix(sp + 1);
  }
  if (!tokens.empty()) d.req.method = std::string(tokens[0]);
  if (tokens.size() > 1) d.req.target = std::string(tokens[1]);
  if (!tokens.empty() && tokens.back().size() == 2 && tokens.back()[0] == '!')
    d.mode = tokens.back()[1];
  while (NextLine(&in, &line) && !line.empty()) {
    const size_t n = Repeat(&line, kMaxRepeat);
    const size_t colon = line.find(':');
    std::string_view name = line.substr(0, colon);
    std::string_view value = colon == std::string_view::npos ? "" : line.substr(colon + 1);
    while (!value.empty() && (value.front() == ' ' || value.front() == '\t'))
      value.remove_prefix(1);
    for (size_t i = 0; i < n; ++i) d.req.headers.emplace_back(name, value);
  }
  size_t n = 1;
  if (!in.empty() && in.front() == '*') {
    std::string_view first;
    std::string_view rest = in;
    NextLine(&rest, &first);
    n = Repeat(&first, kMaxBodyRepeat);
    in = rest;
  }
  for (size_t i = 0; i < n; ++i) d.req.body.append(in);
  d.req.ctx = aggscan::CallContext::Within(aggscan::HttpApi::kRequestBudget);
  d.req.ctx.client_gone = [] { return false; };
  return d;
}

// The rig's host names, independent of HostPolicy's parsing: the name part of
// a Host ("[v6]" or up to the last ':').
bool NamesThisRig(const std::string& host) {
  const std::string h = Lower(host);
  std::string name = h;
  if (!h.empty() && h[0] == '[') {
    name = h.substr(0, h.find(']') + 1);
  } else if (const size_t colon = h.rfind(':'); colon != std::string::npos) {
    name = h.substr(0, colon);
  }
  std::vector<std::string> names = {"localhost", "127.0.0.1", "[::1]"};
  for (const std::string& n : kExtraNames) names.push_back(Lower(n.substr(0, n.find(':'))));
  return std::find(names.begin(), names.end(), name) != names.end();
}

bool IsStateChanging(const std::string& call) {
  for (const char* prefix : {"arm:", "press:", "abort", "reset", "retry:"}) {
    if (call.rfind(prefix, 0) == 0) return true;
  }
  return false;
}

// An invariant: libFuzzer reports the abort, the message says which one.
#define CHECK_INVARIANT(cond)                                      \
  do {                                                             \
    if (!(cond)) {                                                 \
      std::fprintf(stderr, "http_request: violated: %s\n", #cond); \
      std::abort();                                                \
    }                                                              \
  } while (0)

void CheckResponse(const ApiResponse& r) {
  CHECK_INVARIANT(r.status >= 100 && r.status <= 599);
  if (r.status == 204) return;
  if (r.content_type.rfind("text/plain; version=0.0.4", 0) == 0) return;  // /metrics
  const bool download = std::any_of(r.headers.begin(), r.headers.end(),
                                    [](const auto& h) { return h.first == "Content-Disposition"; });
  if (download) {
    CHECK_INVARIANT(r.status == 200);
    return;
  }
  CHECK_INVARIANT(r.content_type == "application/json");
  const json body = json::parse(r.body, nullptr, /*allow_exceptions=*/false);
  CHECK_INVARIANT(!body.is_discarded());
  // /api/v1/health answers 503 with the health document itself (a monitor
  // needs only the code, the operator reads which device is down).
  const bool unhealthy = r.status == 503 && body.is_object() && body.contains("status") &&
                         body["status"].is_string() && body["status"] != "ok" &&
                         !body.contains("error");
  if (r.status >= 400 && !unhealthy) {
    CHECK_INVARIANT(body.is_object() && body.contains("error") && body["error"].is_object());
    const json& err = body["error"];
    CHECK_INVARIANT(err.contains("class") && err["class"].is_string() && !err["class"].empty());
    CHECK_INVARIANT(err.contains("message") && err["message"].is_string() &&
                    !err["message"].empty());
  }
}

// Result files as the worker leaves them, for the download routes.
void PrepareResults(aggscan::testing::FakeControl& control) {
  static const std::string dir = [] {
    const std::string d = aggscan::fuzz::ScratchDir() + "/results";
    aggscan::fuzz::WriteFile(d + "/morphology.json", R"({"volume_mm3": 1234.5, "faces": 12})");
    aggscan::fuzz::WriteFile(
        d + "/mesh.ply", "ply\nformat ascii 1.0\nelement vertex 0\nelement face 0\nend_header\n");
    return d;
  }();
  control.result_files["rock-11/morphology.json"] = dir + "/morphology.json";
  control.result_files["rock-11/mesh.ply"] = dir + "/mesh.ply";
  control.result_files["rock-11/mesh.stl"] = dir + "/missing.stl";  // listed, then deleted
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  using namespace aggscan;
  const Decoded d = Decode(fuzz::AsView(data, size));
  const ApiRequest& req = d.req;

  testing::FakeControl control;
  PrepareResults(control);
  if (d.mode == 't') control.throw_all = true;
  if (d.mode == 'u') control.health["status"] = "unhealthy";
  const int cls = d.mode >= '0' && d.mode <= '9'   ? d.mode - '0'
                  : d.mode >= 'a' && d.mode <= 'd' ? d.mode - 'a' + 10
                                                   : -1;
  if (cls >= 0) control.fail = MakeError(static_cast<ErrorClass>(cls), "fuzzed failure", "detail");

  const HostPolicy policy = HostPolicy::ForListen("127.0.0.1", kExtraNames, kOrigins, kPort);
  ApiRouter router(control, policy);

  const std::optional<ApiResponse> refused = ApiRouter::CheckHead(req);
  if (refused) {
    CheckResponse(*refused);
    CHECK_INVARIANT(refused->status >= 400 && refused->close);
  }
  const ApiResponse r = router.Handle(req);
  CheckResponse(r);
  const std::vector<std::string> calls = control.Calls();
  if (refused) {
    CHECK_INVARIANT(r.status == refused->status);
    CHECK_INVARIANT(calls.empty());
  }

  // Refused by the Host/Origin policy: answered before any control call.
  const std::string* host = req.Header("Host");
  const std::string* origin = req.Header("Origin");
  const bool safe = req.method == "GET" || req.method == "HEAD" || req.method == "OPTIONS";
  if (host == nullptr || !policy.HostAllowed(*host) ||
      (!safe && origin != nullptr && !policy.OriginAllowed(*origin))) {
    CHECK_INVARIANT(r.status >= 400);
    CHECK_INVARIANT(calls.empty());
  }

  const bool changed = std::any_of(calls.begin(), calls.end(), IsStateChanging);
  if (changed) {
    CHECK_INVARIANT(host != nullptr && policy.HostAllowed(*host) && NamesThisRig(*host));
    CHECK_INVARIANT(origin == nullptr || policy.OriginAllowed(*origin));
    CHECK_INVARIANT(req.method == "POST");
    CHECK_INVARIANT(calls.size() == 1);
  }
  return 0;
}
