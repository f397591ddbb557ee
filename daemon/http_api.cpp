#include "daemon/http_api.h"

#include <arpa/inet.h>
#include <fcntl.h>
#include <microhttpd.h>
#include <netdb.h>
#include <netinet/in.h>
#include <poll.h>
#include <sys/socket.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <cctype>
#include <cerrno>
#include <condition_variable>
#include <cstdarg>
#include <cstring>
#include <deque>
#include <exception>
#include <mutex>
#include <nlohmann/json.hpp>
#include <thread>
#include <unordered_set>
#include <variant>

#include "common/fsutil.h"
#include "common/log.h"
#include "store/layout.h"
#include "store/sample_meta.h"

namespace aggscan {

namespace {

using json = nlohmann::json;
using SteadyClock = std::chrono::steady_clock;

constexpr const char* kCat = "api";
constexpr const char* kJsonType = "application/json";
constexpr const char* kMetricsType = "text/plain; version=0.0.4; charset=utf-8";
constexpr const char* kSamplesPrefix = "/api/v1/samples/";
constexpr const char* kBatchesPrefix = "/api/v1/batches/";
// Threads that run routed requests (each may wait up to kRequestBudget on the
// capture loop); the polling thread hands them complete requests only, so a
// slow client never occupies one.
constexpr size_t kHandlerThreads = 4;
// View thumbnails: 252x189 from the 2016x1512 default still (JPEG DCT scaling
// gives 1/8); the budget holds several samples' worth.
constexpr int kThumbnailSide = 320;
constexpr int kThumbnailQuality = 80;
constexpr size_t kThumbnailCacheBytes = size_t{4} * 1024 * 1024;
// Per-connection memory of libmicrohttpd (read buffer and parsed head): above
// ApiLimits' header and URI limits, so those are answered with our JSON
// errors; a head larger than the pool gets libmicrohttpd's own 431 or 414.
constexpr size_t kConnectionMemory = size_t{64} * 1024;
// Separates the frames of the live view's multipart answer.
constexpr const char* kFrameBoundary = "aggscanframe";
// A body over the limit is still read (and dropped) up to this size, so that
// the client is in a state to read the 413; a larger one is cut off.
constexpr size_t kDrainLimitBytes = 1 << 20;
// How often the watchdog looks for connections past their receive or send limit.
constexpr auto kWatchdogPeriod = std::chrono::milliseconds(200);

// Never throws on invalid UTF-8 (a daemon message or an echoed id may hold any bytes).
std::string Dump(const json& j) {
  return j.dump(-1, ' ', false, json::error_handler_t::replace) + "\n";
}

ApiResponse JsonResponse(int status, const json& body) {
  ApiResponse r;
  r.status = status;
  r.content_type = kJsonType;
  r.body = Dump(body);
  return r;
}

ApiResponse ErrorFrom(const Error& e) {
  return ErrorResponse(HttpStatusFor(e.cls), e.cls, e.message, e.detail);
}

std::string Lower(std::string_view s) {
  std::string out(s);
  for (char& c : out) c = static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
  return out;
}

bool IEquals(std::string_view a, std::string_view b) {
  if (a.size() != b.size()) return false;
  for (size_t i = 0; i < a.size(); ++i) {
    if (std::tolower(static_cast<unsigned char>(a[i])) !=
        std::tolower(static_cast<unsigned char>(b[i])))
      return false;
  }
  return true;
}

int HexDigit(char c) {
  if (c >= '0' && c <= '9') return c - '0';
  if (c >= 'a' && c <= 'f') return c - 'a' + 10;
  if (c >= 'A' && c <= 'F') return c - 'A' + 10;
  return -1;
}

// Percent-decodes a path once ("%252e" becomes "%2e"); '+' stays '+' in a path,
// and a '%' not followed by two hex digits is kept as it is.
std::string PercentDecode(std::string_view s) {
  std::string out;
  out.reserve(s.size());
  for (size_t i = 0; i < s.size(); ++i) {
    if (s[i] == '%' && i + 2 < s.size()) {
      const int hi = HexDigit(s[i + 1]);
      const int lo = HexDigit(s[i + 2]);
      if (hi >= 0 && lo >= 0) {
        out += static_cast<char>(hi * 16 + lo);
        i += 2;
        continue;
      }
    }
    out += s[i];
  }
  return out;
}

// Splits "host[:port]" ("[v6]:port" for IPv6). False when it is not of that form.
bool SplitHostPort(std::string_view s, std::string* host, int* port, bool* port_given) {
  *port = 0;
  *port_given = false;
  std::string_view rest;
  if (!s.empty() && s[0] == '[') {
    const size_t close = s.find(']');
    if (close == std::string_view::npos) return false;
    *host = std::string(s.substr(0, close + 1));
    rest = s.substr(close + 1);
  } else {
    const size_t colon = s.find(':');
    *host = std::string(s.substr(0, colon));
    rest = colon == std::string_view::npos ? std::string_view{} : s.substr(colon);
  }
  if (host->empty() || host->size() > 255) return false;
  for (unsigned char c : *host) {
    if (!(std::isalnum(c) || c == '.' || c == '-' || c == '_' || c == ':' || c == '[' || c == ']'))
      return false;
  }
  if (rest.empty()) return true;
  if (rest[0] != ':' || rest.size() < 2 || rest.size() > 6) return false;
  int p = 0;
  for (char c : rest.substr(1)) {
    if (c < '0' || c > '9') return false;
    p = p * 10 + (c - '0');
  }
  if (p < 1 || p > 65535) return false;
  *port = p;
  *port_given = true;
  return true;
}

bool IsSafeMethod(const std::string& m) { return m == "GET" || m == "HEAD" || m == "OPTIONS"; }

bool IsKnownMethod(const std::string& m) {
  return IsSafeMethod(m) || m == "POST" || m == "PUT" || m == "PATCH" || m == "DELETE";
}

// Paths and ids echoed into logs and messages: printable ASCII only, capped.
std::string Printable(std::string_view s, size_t max_len = 200) {
  std::string out;
  for (unsigned char c : s.substr(0, max_len)) {
    if (c >= 0x20 && c < 0x7f) {
      out += static_cast<char>(c);
    } else {
      char buf[8];
      std::snprintf(buf, sizeof buf, "\\x%02x", c);
      out += buf;
    }
  }
  if (s.size() > max_len) out += "...";
  return out;
}

enum class Endpoint {
  kNone,
  kStatus,
  kHealth,
  kSamples,
  kSample,
  kSampleFile,
  kSampleRetry,
  kSampleMeta,
  kBatches,
  kBatch,
  kReport,
  kButton,
  kCalibration,
  kAbort,
  kReset,
  kMetrics,
  kEvents,
  kOpenApi,
  kView,
  kPreview,
  kSession,
  kConsole,
  kImageArchive
};

// Methods each endpoint accepts (HEAD is answered wherever GET is).
const char* AllowedMethods(Endpoint ep) {
  switch (ep) {
    case Endpoint::kStatus:
    case Endpoint::kHealth:
    case Endpoint::kSample:
    case Endpoint::kSampleFile:
    case Endpoint::kMetrics:
    case Endpoint::kOpenApi:
    case Endpoint::kView:
    case Endpoint::kConsole:
    case Endpoint::kImageArchive:
      return "GET, HEAD";
    case Endpoint::kEvents:
    case Endpoint::kPreview:
      return "GET";
    case Endpoint::kSession:
      return "GET, HEAD, POST, DELETE";
    case Endpoint::kSamples:
      return "GET, HEAD, POST";
    case Endpoint::kSampleMeta:
      return "PATCH";
    case Endpoint::kBatches:
    case Endpoint::kReport:
      return "GET, HEAD";
    case Endpoint::kBatch:
      return "GET, HEAD, PUT, DELETE";
    case Endpoint::kSampleRetry:
    case Endpoint::kButton:
    case Endpoint::kCalibration:
    case Endpoint::kAbort:
    case Endpoint::kReset:
      return "POST";
    case Endpoint::kNone:
      break;
  }
  return "";
}

bool MethodAllowed(Endpoint ep, const std::string& method) {
  const std::string allowed = AllowedMethods(ep);
  size_t pos = 0;
  while (pos < allowed.size()) {
    size_t end = allowed.find(", ", pos);
    if (end == std::string::npos) end = allowed.size();
    if (allowed.compare(pos, end - pos, method) == 0) return true;
    pos = end + 2;
  }
  return false;
}

// `path` is already percent-decoded (once); `id` gets whatever follows
// the samples prefix up to the next '/', unvalidated, and `file` what follows
// that ("results" or a mesh file name).
Endpoint Match(const std::string& path, std::string* id, std::string* file) {
  if (path == "/api/v1/status") return Endpoint::kStatus;
  if (path == "/api/v1/health") return Endpoint::kHealth;
  if (path == "/api/v1/samples") return Endpoint::kSamples;
  if (path == "/api/v1/batches") return Endpoint::kBatches;
  if (path.rfind(kBatchesPrefix, 0) == 0) {
    *id = path.substr(std::strlen(kBatchesPrefix));
    const size_t slash = id->find('/');
    if (slash != std::string::npos) {
      const std::string rest = id->substr(slash + 1);
      if (rest == "report.pdf" || rest == "report.html") {
        *file = "batch/" + rest;
        id->resize(slash);
        return Endpoint::kReport;
      }
    }
    return Endpoint::kBatch;
  }
  if (path == "/api/v1/button") return Endpoint::kButton;
  if (path == "/api/v1/calibration") return Endpoint::kCalibration;
  if (path == "/api/v1/abort") return Endpoint::kAbort;
  if (path == "/api/v1/reset") return Endpoint::kReset;
  if (path == "/metrics") return Endpoint::kMetrics;
  if (path == "/api/v1/events") return Endpoint::kEvents;
  if (path == "/api/v1/openapi.json") return Endpoint::kOpenApi;
  if (path == "/api/v1/preview") return Endpoint::kPreview;
  if (path == "/api/v1/session") return Endpoint::kSession;
  if (path == "/" || path == "/index.html") {
    *file = "index.html";
    return Endpoint::kConsole;
  }
  if (path.rfind("/ui/", 0) == 0) {
    *file = path.substr(1);
    return Endpoint::kConsole;
  }
  if (path.rfind(kSamplesPrefix, 0) == 0) {
    *id = path.substr(std::strlen(kSamplesPrefix));
    const size_t slash = id->find('/');
    if (slash == std::string::npos) return Endpoint::kSample;
    *file = id->substr(slash + 1);
    id->resize(slash);
    if (*file == "results") {
      *file = layout::kMorphology;
      return Endpoint::kSampleFile;
    }
    if (*file == layout::kMeshPly || *file == layout::kMeshObj || *file == layout::kMeshStl)
      return Endpoint::kSampleFile;
    if (*file == "retry") return Endpoint::kSampleRetry;
    if (*file == "meta") return Endpoint::kSampleMeta;
    if (*file == "report.pdf" || *file == "report.html") {
      *file = "rock/" + *file;
      return Endpoint::kReport;
    }
    if (*file == "images.zip") return Endpoint::kImageArchive;
    if (file->rfind("sides/", 0) == 0) return Endpoint::kView;  // checked by ServeView
    // Anything else is not a sub-resource: the whole rest is the (invalid) id.
    *id = path.substr(std::strlen(kSamplesPrefix));
    file->clear();
    return Endpoint::kSample;
  }
  return Endpoint::kNone;
}

std::string InvalidIdMessage(const std::string& id) {
  return "invalid sample id \"" + Printable(id, 80) +
         "\": use 1-64 characters from A-Z a-z 0-9 . _ -, not starting with '.' or '-'";
}

ApiResponse Reply(const Result<json>& r) {
  if (!r.ok()) return ErrorFrom(r.error());
  return JsonResponse(200, r.value().is_null() ? json::object() : r.value());
}

}  // namespace

int HttpStatusFor(ErrorClass cls) {
  switch (cls) {
    case ErrorClass::kInvalidArgument:
      return 400;
    case ErrorClass::kNotFound:
      return 404;
    case ErrorClass::kConflict:
    case ErrorClass::kInvalidState:
    case ErrorClass::kCancelled:
      return 409;
    case ErrorClass::kDeviceMissing:
    case ErrorClass::kDisconnected:
    case ErrorClass::kTimeout:
    case ErrorClass::kStalled:
    case ErrorClass::kDeviceFault:
      return 503;
    case ErrorClass::kDiskFull:
      return 507;
    case ErrorClass::kInvalidConfig:
    case ErrorClass::kIo:
    case ErrorClass::kCorrupt:
    case ErrorClass::kInternal:
      return 500;
  }
  return 500;
}

const std::string* ApiRequest::Header(std::string_view name) const {
  for (const auto& [k, v] : headers) {
    if (IEquals(k, name)) return &v;
  }
  return nullptr;
}

ApiResponse ErrorResponse(int status, ErrorClass cls, const std::string& message,
                          const std::string& detail) {
  json err = {{"class", ErrorClassName(cls)}, {"message", message}};
  if (!detail.empty()) err["detail"] = detail;
  return JsonResponse(status, json{{"error", std::move(err)}});
}

// ------------------------------------------------------------ HostPolicy --

HostPolicy::HostPolicy(const std::vector<std::string>& names,
                       const std::vector<std::string>& origins, int port)
    : port_(port) {
  for (const std::string& n : names) {
    std::string host;
    int p = 0;
    bool given = false;
    if (SplitHostPort(Lower(n), &host, &p, &given)) names_.emplace_back(host, p);
  }
  for (const std::string& o : origins) origins_.push_back(Lower(o));
}

HostPolicy HostPolicy::ForListen(const std::string& listen_address,
                                 const std::vector<std::string>& extra_names,
                                 const std::vector<std::string>& origins, int port) {
  std::vector<std::string> names = {"localhost", "127.0.0.1", "[::1]"};
  if (!listen_address.empty()) {
    const bool v6 = listen_address.find(':') != std::string::npos && listen_address[0] != '[';
    names.push_back(v6 ? "[" + listen_address + "]" : listen_address);
  }
  names.insert(names.end(), extra_names.begin(), extra_names.end());
  return HostPolicy(names, origins, port);
}

bool HostPolicy::Allowed(std::string_view name, int port, bool port_given) const {
  for (const auto& [n, p] : names_) {
    if (n != name) continue;
    // No port in a Host header means the scheme's default, 80 here.
    if (!port_given) return p == 0 || p == 80;
    if (p == 0 ? port == port_ : port == p) return true;
  }
  return false;
}

bool HostPolicy::HostAllowed(std::string_view host) const {
  std::string name;
  int port = 0;
  bool given = false;
  if (!SplitHostPort(Lower(host), &name, &port, &given)) return false;
  return Allowed(name, port, given);
}

bool HostPolicy::OriginAllowed(std::string_view origin) const {
  const std::string o = Lower(origin);
  if (std::find(origins_.begin(), origins_.end(), o) != origins_.end()) return true;
  int default_port = 0;
  std::string_view rest = o;
  if (rest.starts_with("http://")) {
    default_port = 80;
    rest.remove_prefix(7);
  } else if (rest.starts_with("https://")) {
    default_port = 443;
    rest.remove_prefix(8);
  } else {
    return false;  // "null", file://, anything else
  }
  std::string name;
  int port = 0;
  bool given = false;
  if (!SplitHostPort(rest, &name, &port, &given)) return false;
  // An origin always has a port (the scheme's default when not written).
  return Allowed(name, given ? port : default_port, true);
}

// ------------------------------------------------------------- ApiRouter --

ApiRouter::ApiRouter(DaemonControl& control, HostPolicy policy)
    : control_(control),
      policy_(std::move(policy)),
      thumbnails_(kThumbnailSide, kThumbnailQuality, kThumbnailCacheBytes) {}

std::optional<ApiResponse> ApiRouter::CheckHead(const ApiRequest& head) {
  if (!IsKnownMethod(head.method)) {
    ApiResponse r = ErrorResponse(400, ErrorClass::kInvalidArgument,
                                  "unsupported method " + Printable(head.method, 16) +
                                      ": the API answers GET, HEAD, POST and OPTIONS");
    r.close = true;
    return r;
  }
  if (head.target.size() > ApiLimits::kMaxUriBytes) {
    ApiResponse r = ErrorResponse(414, ErrorClass::kInvalidArgument,
                                  "request URI too long: " + std::to_string(head.target.size()) +
                                      " bytes, at most " + std::to_string(ApiLimits::kMaxUriBytes));
    r.close = true;
    return r;
  }
  size_t bytes = 0;
  for (const auto& [k, v] : head.headers) bytes += k.size() + v.size();
  if (head.headers.size() > ApiLimits::kMaxHeaderCount || bytes > ApiLimits::kMaxHeaderBytes) {
    ApiResponse r =
        ErrorResponse(431, ErrorClass::kInvalidArgument,
                      "request header fields too large: " + std::to_string(head.headers.size()) +
                          " fields of " + std::to_string(bytes) + " bytes; at most " +
                          std::to_string(ApiLimits::kMaxHeaderCount) + " fields of " +
                          std::to_string(ApiLimits::kMaxHeaderBytes) + " bytes together");
    r.close = true;
    return r;
  }
  if (const std::string* len = head.Header("Content-Length")) {
    const bool digits = !len->empty() && len->find_first_not_of("0123456789") == std::string::npos;
    if (!digits) {
      ApiResponse r = ErrorResponse(400, ErrorClass::kInvalidArgument,
                                    "could not read the request body (bad Content-Length)");
      r.close = true;
      return r;
    }
    if (len->size() > 18 || std::stoull(*len) > ApiLimits::kMaxBodyBytes) {
      ApiResponse r = ErrorResponse(
          413, ErrorClass::kInvalidArgument,
          "request body too large: at most " + std::to_string(ApiLimits::kMaxBodyBytes) + " bytes");
      r.close = true;
      return r;
    }
  }
  return std::nullopt;
}

ApiResponse ApiRouter::Handle(const ApiRequest& req) {
  try {
    return HandleUnsafe(req);
  } catch (const std::exception& e) {
    AGG_LOGE(kCat, "%s %s: unhandled exception: %s", Printable(req.method, 16).c_str(),
             Printable(req.target).c_str(), e.what());
    return ErrorResponse(500, ErrorClass::kInternal, "internal error in the HTTP API; report it",
                         e.what());
  } catch (...) {
    AGG_LOGE(kCat, "%s %s: unhandled non-standard exception", Printable(req.method, 16).c_str(),
             Printable(req.target).c_str());
    return ErrorResponse(500, ErrorClass::kInternal, "internal error in the HTTP API; report it");
  }
}

ApiResponse ApiRouter::HandleUnsafe(const ApiRequest& req) {
  if (std::optional<ApiResponse> refused = CheckHead(req)) return *refused;
  if (req.body.size() > ApiLimits::kMaxBodyBytes) {
    ApiResponse r = ErrorResponse(
        413, ErrorClass::kInvalidArgument,
        "request body too large: at most " + std::to_string(ApiLimits::kMaxBodyBytes) + " bytes");
    r.close = true;
    return r;
  }
  // DNS rebinding: a page of another site whose name now resolves to this rig
  // reaches it with that name as Host.
  const std::string* host = req.Header("Host");
  if (host == nullptr) {
    return ErrorResponse(400, ErrorClass::kInvalidArgument,
                         "missing Host header (HTTP/1.1 requires one)");
  }
  if (!policy_.HostAllowed(*host)) {
    return ErrorResponse(
        421, ErrorClass::kInvalidArgument,
        "Host \"" + Printable(*host, 80) +
            "\" is not a name of this rig's API (a defence against DNS rebinding): add it to "
            "daemon.allowed_hosts");
  }
  // A browser names the page that sent a request; the CLI and curl send none.
  if (!IsSafeMethod(req.method)) {
    if (const std::string* origin = req.Header("Origin");
        origin != nullptr && !policy_.OriginAllowed(*origin)) {
      return ErrorResponse(
          403, ErrorClass::kInvalidArgument,
          "Origin \"" + Printable(*origin, 80) +
              "\" may not change the rig's state: add it to daemon.allowed_origins");
    }
  }

  const std::string raw_path = req.target.substr(0, req.target.find('?'));
  const std::string path = PercentDecode(raw_path);
  std::string id, file;
  const Endpoint ep = Match(path, &id, &file);
  // Credentials, when the rig requires them: for everything but logging in
  // (an unknown path too: a stranger learns nothing of what is routed).
  std::optional<Principal> who;
  const bool open_to_all =
      (ep == Endpoint::kSession && req.method == "POST") || ep == Endpoint::kConsole;
  if (access_ != nullptr && !open_to_all) {
    auto checked = access_->Check(req.Header("Authorization"), req.Header("Cookie"), req.peer);
    if (const auto* refusal = std::get_if<AccessControl::Refusal>(&checked)) {
      ApiResponse r =
          ErrorResponse(refusal->status, ErrorClass::kInvalidArgument, refusal->message);
      if (refusal->status == 401)
        r.headers.emplace_back("WWW-Authenticate", "Bearer realm=\"aggscand\"");
      if (refusal->retry_after_s > 0)
        r.headers.emplace_back("Retry-After", std::to_string(refusal->retry_after_s));
      return r;
    }
    who = std::get<Principal>(checked);
    if (!IsSafeMethod(req.method)) {
      // A cookie is sent by the browser whatever page asks; the Authorization
      // header only by our own console's script.
      if (who->via == "cookie") {
        return ErrorResponse(403, ErrorClass::kInvalidArgument,
                             "a request that changes the rig's state must carry its credentials "
                             "in the Authorization header, not only the session cookie");
      }
      if (who->role != Role::kOperator && ep != Endpoint::kSession) {
        return ErrorResponse(403, ErrorClass::kInvalidArgument,
                             "account " + who->user +
                                 " is a viewer and may only look: capturing needs an operator "
                                 "account");
      }
    }
  }
  if (ep == Endpoint::kNone) {
    return ErrorResponse(
        404, ErrorClass::kNotFound,
        "no such endpoint: " + req.method + " " + Printable(path) + " (see /api/v1/status)");
  }
  if (req.method == "OPTIONS") {
    ApiResponse r;
    r.status = 204;
    r.headers.emplace_back("Allow", std::string(AllowedMethods(ep)) + ", OPTIONS");
    return r;
  }
  if (!MethodAllowed(ep, req.method)) {
    ApiResponse r = ErrorResponse(405, ErrorClass::kInvalidArgument,
                                  "method " + req.method + " not allowed on " + Printable(path) +
                                      "; allowed: " + AllowedMethods(ep));
    r.headers.emplace_back("Allow", AllowedMethods(ep));
    return r;
  }

  const bool get = req.method == "GET" || req.method == "HEAD";
  switch (ep) {
    case Endpoint::kStatus:
      return JsonResponse(200, control_.GetStatus());
    case Endpoint::kHealth: {
      // 200 only when every device is healthy, else 503 with the same body:
      // a monitor or `curl -f` needs only the code, an operator reads the
      // body (which device, what to check, when the next retry is).
      const json h = control_.GetHealth();
      const bool ok = h.is_object() && h.value("status", "") == "ok";
      return JsonResponse(ok ? 200 : 503, h);
    }
    case Endpoint::kSamples:
      if (get) return Reply(control_.ListSamples());
      return ArmFromBody(req.body, req.ctx);
    case Endpoint::kSample:
      if (!layout::IsValidSampleId(id))
        return ErrorResponse(400, ErrorClass::kInvalidArgument, InvalidIdMessage(id));
      return Reply(control_.GetSample(id));
    case Endpoint::kSampleFile:
      if (!layout::IsValidSampleId(id))
        return ErrorResponse(400, ErrorClass::kInvalidArgument, InvalidIdMessage(id));
      return ServeResultFile(id, file);
    case Endpoint::kView:
      if (!layout::IsValidSampleId(id))
        return ErrorResponse(400, ErrorClass::kInvalidArgument, InvalidIdMessage(id));
      return ServeView(id, file);
    case Endpoint::kImageArchive:
      if (!layout::IsValidSampleId(id))
        return ErrorResponse(400, ErrorClass::kInvalidArgument, InvalidIdMessage(id));
      return ServeImageArchive(id);
    case Endpoint::kSampleRetry:
      if (!layout::IsValidSampleId(id))
        return ErrorResponse(400, ErrorClass::kInvalidArgument, InvalidIdMessage(id));
      return Reply(control_.Retry(id));
    case Endpoint::kSampleMeta: {
      if (!layout::IsValidSampleId(id))
        return ErrorResponse(400, ErrorClass::kInvalidArgument, InvalidIdMessage(id));
      const json doc = json::parse(req.body, nullptr, /*allow_exceptions=*/false);
      if (doc.is_discarded() || !doc.is_object()) {
        return ErrorResponse(400, ErrorClass::kInvalidArgument,
                             "request body is not a JSON object: expected the fields to change, "
                             "e.g. {\"lot\": \"L-12\", \"material\": {\"specific_gravity\": "
                             "2.65, \"basis\": \"bulk-ssd\"}} (null removes a field)");
      }
      return Reply(control_.EditMeta(id, doc, who ? who->user : "api", req.ctx));
    }
    case Endpoint::kBatches:
      return Reply(control_.ListBatches());
    case Endpoint::kReport:
      return ServeReport(req, id, file);
    case Endpoint::kBatch: {
      if (!layout::IsValidSampleId(id)) {
        return ErrorResponse(400, ErrorClass::kInvalidArgument,
                             "invalid batch name \"" + Printable(id, 80) +
                                 "\": use 1-64 characters from A-Z a-z 0-9 . _ -, not starting "
                                 "with '.' or '-'");
      }
      if (get) return Reply(control_.GetBatch(id));
      if (req.method == "DELETE") return Reply(control_.DeleteBatch(id));
      const json doc = json::parse(req.body, nullptr, /*allow_exceptions=*/false);
      if (doc.is_discarded()) {
        return ErrorResponse(400, ErrorClass::kInvalidArgument,
                             "request body is not valid JSON: expected {\"lot\", \"from\", "
                             "\"to\", \"samples\", \"notes\"}");
      }
      return Reply(control_.PutBatch(id, doc));
    }
    case Endpoint::kCalibration:
      return Reply(control_.ArmCalibration(req.ctx));
    case Endpoint::kButton:
      return Reply(control_.Press(who ? "api:" + who->user : "api", req.ctx));
    case Endpoint::kSession:
      return HandleSession(req, who);
    case Endpoint::kConsole:
      return ServeConsoleFile(req, file);
    case Endpoint::kAbort:
      return Reply(control_.Abort(req.ctx));
    case Endpoint::kReset:
      return Reply(control_.Reset(req.ctx));
    case Endpoint::kMetrics: {
      ApiResponse r;
      r.status = 200;
      r.content_type = kMetricsType;
      r.body = control_.Metrics();
      return r;
    }
    case Endpoint::kOpenApi: {
      ApiResponse r;
      r.status = 200;
      r.content_type = kJsonType;
      r.body = OpenApiDocument();
      return r;
    }
    case Endpoint::kEvents: {
      // Admitted here (Host, method); the transport streams it.
      ApiResponse r;
      r.status = 200;
      r.stream = ApiResponse::Stream::kEvents;
      return r;
    }
    case Endpoint::kPreview: {
      ApiResponse r;
      r.status = 200;
      r.stream = ApiResponse::Stream::kPreview;
      return r;
    }
    case Endpoint::kNone:
      break;
  }
  return ErrorResponse(500, ErrorClass::kInternal, "unrouted endpoint; report it");
}

ApiResponse ApiRouter::ServeReport(const ApiRequest& req, const std::string& name,
                                   const std::string& what) {
  if (!layout::IsValidSampleId(name))
    return ErrorResponse(400, ErrorClass::kInvalidArgument, InvalidIdMessage(name));
  ReportRequest r;
  const size_t slash = what.find('/');
  r.kind = what.substr(0, slash);
  r.format = what.substr(what.rfind('.') + 1);
  r.name = name;
  // ?spec=NAME (the transport appends the decoded query to the target).
  if (const size_t q = req.target.find('?'); q != std::string::npos) {
    std::string query = req.target.substr(q + 1);
    for (size_t b = 0; b <= query.size();) {
      size_t e = query.find('&', b);
      if (e == std::string::npos) e = query.size();
      const std::string kv = query.substr(b, e - b);
      if (kv.rfind("spec=", 0) == 0) r.spec = kv.substr(5);
      b = e + 1;
    }
  }
  Result<std::string> path = control_.MakeReport(r);
  if (!path) {
    // Two at once is a moment's wait, not a fault.
    if (path.error().cls == ErrorClass::kConflict) {
      ApiResponse busy = ErrorResponse(503, ErrorClass::kConflict, path.error().message);
      busy.headers.emplace_back("Retry-After", "5");
      return busy;
    }
    return ErrorFrom(path.error());
  }
  Result<std::string> body = ReadFile(*path);
  ::unlink(path->c_str());
  ::rmdir(path->substr(0, path->rfind('/')).c_str());
  if (!body) return ErrorFrom(body.error());
  ApiResponse resp;
  resp.status = 200;
  resp.content_type = r.format == "pdf" ? "application/pdf" : "text/html; charset=utf-8";
  resp.body = std::move(*body);
  resp.headers.emplace_back("Content-Disposition",
                            "attachment; filename=\"" + name + "-report." + r.format + "\"");
  resp.headers.emplace_back("Cache-Control", "no-store");
  return resp;
}

ApiResponse ApiRouter::ServeImageArchive(const std::string& id) {
  Result<std::vector<ArchiveMember>> members = control_.ImageArchive(id);
  if (!members) return ErrorFrom(members.error());
  Result<std::unique_ptr<ZipStream>> zip = ZipStream::Open(std::move(*members));
  if (!zip) return ErrorFrom(zip.error());
  ApiResponse r;
  r.status = 200;
  r.content_type = "application/zip";
  r.headers.emplace_back("Content-Disposition", "attachment; filename=\"" + id + "_images.zip\"");
  r.headers.emplace_back("Cache-Control", "no-store");
  r.source = std::shared_ptr<BodySource>(std::move(*zip));
  return r;
}

ApiResponse ApiRouter::ServeResultFile(const std::string& id, const std::string& name) {
  Result<std::string> path = control_.ResultFile(id, name);
  if (!path) return ErrorFrom(path.error());
  Result<std::string> bytes = ReadFile(*path);
  if (!bytes) return ErrorFrom(bytes.error());
  const bool is_json = name.size() > 5 && name.compare(name.size() - 5, 5, ".json") == 0;
  ApiResponse r;
  r.status = 200;
  if (!is_json)
    r.headers.emplace_back("Content-Disposition",
                           "attachment; filename=\"" + id + "_" + name + "\"");
  r.content_type = is_json                  ? kJsonType
                   : name.ends_with(".obj") ? "text/plain; charset=utf-8"
                   : name.ends_with(".stl") ? "model/stl"
                                            : "application/octet-stream";
  r.body = std::move(*bytes);
  return r;
}

namespace {

// The console's files: names of letters, digits, '-', '_', '.' at most two
// folders deep, never starting with '.', so nothing outside the web root
// (and no hidden file) can be named.
bool IsConsoleFileName(const std::string& name) {
  if (name.empty() || name.size() > 128) return false;
  int slashes = 0;
  char prev = '/';
  for (char c : name) {
    if (c == '/') {
      if (++slashes > 2 || prev == '/') return false;
    } else if (c == '.') {
      if (prev == '/') return false;
    } else if (!std::isalnum(static_cast<unsigned char>(c)) && c != '-' && c != '_') {
      return false;
    }
    prev = c;
  }
  return prev != '/';
}

const char* ConsoleContentType(const std::string& name) {
  if (name.ends_with(".html")) return "text/html; charset=utf-8";
  if (name.ends_with(".js")) return "text/javascript; charset=utf-8";
  if (name.ends_with(".css")) return "text/css; charset=utf-8";
  if (name.ends_with(".svg")) return "image/svg+xml";
  if (name.ends_with(".png")) return "image/png";
  if (name.ends_with(".wav")) return "audio/wav";
  if (name.ends_with(".json")) return "application/json";
  return nullptr;
}

}  // namespace

ApiResponse ApiRouter::ServeConsoleFile(const ApiRequest& req, const std::string& file) {
  if (web_root_.empty()) {
    return ErrorResponse(404, ErrorClass::kNotFound,
                         "this aggscand serves no console: its files were not found (install "
                         "share/aggscan/web beside the binaries, or set daemon.web_root)");
  }
  const char* type = IsConsoleFileName(file) ? ConsoleContentType(file) : nullptr;
  const std::string path = web_root_ + "/" + file;
  struct stat st {};
  if (type == nullptr || ::stat(path.c_str(), &st) != 0 || !S_ISREG(st.st_mode)) {
    return ErrorResponse(404, ErrorClass::kNotFound,
                         "no such console file: " + Printable(file, 80) + " (the console is at /)");
  }
  // Revalidated on every load (an update of the rig takes effect at once),
  // answered 304 while unchanged: a tablet on a weak link loads the
  // libraries once.
  const std::string etag = "\"" + std::to_string(st.st_mtim.tv_sec) + "-" +
                           std::to_string(st.st_mtim.tv_nsec) + "-" + std::to_string(st.st_size) +
                           "\"";
  ApiResponse r;
  r.headers.emplace_back("ETag", etag);
  r.headers.emplace_back("Cache-Control", "no-cache");
  if (const std::string* inm = req.Header("If-None-Match"); inm != nullptr && *inm == etag) {
    r.status = 304;
    return r;
  }
  Result<std::string> bytes = ReadFile(path);
  if (!bytes) return ErrorFrom(bytes.error());
  r.status = 200;
  r.content_type = type;
  if (file == "index.html") {
    // The page runs only our own scripts and talks only to this rig; no other
    // site may frame it (clickjacking of the START button).
    r.headers.emplace_back("Content-Security-Policy",
                           "default-src 'self'; script-src 'self'; style-src 'self' "
                           "'unsafe-inline'; img-src 'self' blob: data:; connect-src 'self'; "
                           "media-src 'self' data:; object-src 'none'; base-uri 'none'; "
                           "frame-ancestors 'none'");
    r.headers.emplace_back("X-Frame-Options", "DENY");
  }
  r.headers.emplace_back("X-Content-Type-Options", "nosniff");
  r.body = std::move(*bytes);
  return r;
}

namespace {

// A side or view number of a view's path: 1-3 digits, nothing else.
std::optional<int> SmallNumber(std::string_view s) {
  if (s.empty() || s.size() > 3) return std::nullopt;
  int n = 0;
  for (char c : s) {
    if (c < '0' || c > '9') return std::nullopt;
    n = n * 10 + (c - '0');
  }
  return n;
}

}  // namespace

ApiResponse ApiRouter::ServeView(const std::string& id, const std::string& sub) {
  // sub: "sides/{side}/views/{view}" with an optional "/thumbnail" or "/mask".
  static const std::string kShape =
      "a view is /api/v1/samples/{id}/sides/{side}/views/{view} (side from 1, view from 0), "
      "optionally followed by /thumbnail or /mask";
  std::vector<std::string_view> parts;
  for (size_t pos = 0;;) {
    const size_t slash = sub.find('/', pos);
    parts.emplace_back(std::string_view(sub).substr(pos, slash - pos));
    if (slash == std::string::npos) break;
    pos = slash + 1;
  }
  const std::optional<int> side = parts.size() >= 4 ? SmallNumber(parts[1]) : std::nullopt;
  const std::optional<int> view = parts.size() >= 4 ? SmallNumber(parts[3]) : std::nullopt;
  const std::string_view what = parts.size() == 5 ? parts[4] : std::string_view();
  if (parts.size() < 4 || parts.size() > 5 || parts[0] != "sides" || parts[2] != "views" || !side ||
      !view || (parts.size() == 5 && what != "thumbnail" && what != "mask")) {
    return ErrorResponse(
        404, ErrorClass::kNotFound,
        "no such resource \"" + Printable(sub, 80) + "\" of sample " + id + ": " + kShape);
  }
  const ViewFileKind kind = what == "mask" ? ViewFileKind::kMask : ViewFileKind::kImage;
  Result<std::string> path = control_.ViewFile(id, *side, *view, kind);
  if (!path) return ErrorFrom(path.error());
  ApiResponse r;
  r.status = 200;
  // A resumed side may shoot a view again under the same name: browsers must
  // not keep an old copy (thumbnails stay cached here, keyed by the file's
  // size and modification time).
  r.headers.emplace_back("Cache-Control", "no-cache");
  if (what == "thumbnail") {
    Result<ScaledJpeg> thumb = thumbnails_.Get(*path);
    if (!thumb) return ErrorFrom(thumb.error());
    r.content_type = "image/jpeg";
    r.body = std::move(thumb->jpeg);
    return r;
  }
  Result<std::string> bytes = ReadFile(*path);
  if (!bytes) return ErrorFrom(bytes.error());
  r.content_type = kind == ViewFileKind::kMask ? "image/png" : "image/jpeg";
  r.body = std::move(*bytes);
  return r;
}

ApiResponse ApiRouter::HandleSession(const ApiRequest& req, const std::optional<Principal>& who) {
  if (access_ == nullptr) {
    if (req.method == "GET" || req.method == "HEAD")
      return JsonResponse(200, json{{"user", nullptr}, {"role", "operator"}, {"auth", "none"}});
    return ErrorResponse(404, ErrorClass::kNotFound,
                         "this rig's API needs no login: it listens on a loopback address without "
                         "daemon.credentials_file");
  }
  const std::string cookie_attrs =
      std::string("; Path=/; HttpOnly; SameSite=Strict") + (tls_ ? "; Secure" : "");
  if (req.method == "GET" || req.method == "HEAD") {
    return JsonResponse(
        200, json{{"user", who->user}, {"role", RoleName(who->role)}, {"auth", who->via}});
  }
  if (req.method == "DELETE") {
    access_->Logout(AccessControl::SessionToken(req.Header("Authorization"), req.Header("Cookie")));
    ApiResponse r = JsonResponse(200, json{{"user", who->user}, {"logged_out", true}});
    r.headers.emplace_back(
        "Set-Cookie", std::string(AccessControl::kCookie) + "=" + cookie_attrs + "; Max-Age=0");
    return r;
  }
  static const std::string kExpected =
      R"(expected a JSON object {"user": "...", "password": "..."})";
  const json doc = json::parse(req.body, nullptr, /*allow_exceptions=*/false);
  if (!doc.is_object() || !doc.contains("user") || !doc["user"].is_string() ||
      !doc.contains("password") || !doc["password"].is_string()) {
    return ErrorResponse(400, ErrorClass::kInvalidArgument, "cannot log in: " + kExpected);
  }
  auto login =
      access_->Login(doc["user"].get<std::string>(), doc["password"].get<std::string>(), req.peer);
  if (const auto* refusal = std::get_if<AccessControl::Refusal>(&login)) {
    ApiResponse r = ErrorResponse(refusal->status, ErrorClass::kInvalidArgument, refusal->message);
    if (refusal->retry_after_s > 0)
      r.headers.emplace_back("Retry-After", std::to_string(refusal->retry_after_s));
    return r;
  }
  const auto& session = std::get<AccessControl::Session>(login);
  const auto lifetime =
      std::chrono::duration_cast<std::chrono::seconds>(AccessControl::kSessionLifetime).count();
  ApiResponse r = JsonResponse(200, json{{"user", session.who.user},
                                         {"role", RoleName(session.who.role)},
                                         {"token", session.token},
                                         {"expires_in_s", lifetime}});
  r.headers.emplace_back("Set-Cookie", std::string(AccessControl::kCookie) + "=" + session.token +
                                           cookie_attrs + "; Max-Age=" + std::to_string(lifetime));
  r.headers.emplace_back("Cache-Control", "no-store");
  return r;
}

ApiResponse ApiRouter::ArmFromBody(const std::string& body, const CallContext& ctx) {
  static const std::string kExpected =
      R"(expected a JSON object {"id": "<sample id>"} (optional "operator", "lot", "notes", "material": {"name", "specific_gravity", "basis"}))";
  const json doc = json::parse(body, nullptr, /*allow_exceptions=*/false);
  if (doc.is_discarded()) {
    return ErrorResponse(400, ErrorClass::kInvalidArgument,
                         "request body is not valid JSON: " + kExpected);
  }
  if (!doc.is_object()) {
    return ErrorResponse(400, ErrorClass::kInvalidArgument,
                         "request body is not a JSON object: " + kExpected);
  }
  const auto it = doc.find("id");
  if (it == doc.end() || !it->is_string()) {
    return ErrorResponse(400, ErrorClass::kInvalidArgument,
                         "missing or non-string \"id\": " + kExpected);
  }
  ArmRequest req;
  req.id = it->get<std::string>();
  if (!layout::IsValidSampleId(req.id))
    return ErrorResponse(400, ErrorClass::kInvalidArgument, InvalidIdMessage(req.id));
  // Other fields are let through as before (a newer console's, say); the
  // description's own are checked.
  json described = json::object();
  for (const char* k : {"operator", "lot", "notes", "material"}) {
    if (doc.contains(k)) described[k] = doc[k];
  }
  Result<json> meta = sample_meta::CheckPatch(described, /*allow_removal=*/false);
  if (!meta) return ErrorResponse(400, ErrorClass::kInvalidArgument, meta.error().message);
  req.meta = std::move(*meta);
  return Reply(control_.Arm(req, ctx));
}

// -------------------------------------------------------------- transport --

namespace {

std::string HostPort(const std::string& host, int port) {
  const bool v6 = host.find(':') != std::string::npos;
  return (v6 ? "[" + host + "]" : host) + ":" + std::to_string(port);
}

std::string LowerFirst(std::string s) {
  if (!s.empty()) s[0] = static_cast<char>(std::tolower(static_cast<unsigned char>(s[0])));
  return s;
}

// Our own listen socket: SO_REUSEADDR (a restart finds the port free at once)
// but never SO_REUSEPORT (a second aggscand must fail, not share the port),
// our backlog, and the errno of a failed bind for the operator.
Result<int> OpenListenSocket(const std::string& address, int port) {
  const std::string where = "cannot listen on " + HostPort(address, port);
  addrinfo hints{};
  hints.ai_family = AF_UNSPEC;
  hints.ai_socktype = SOCK_STREAM;
  hints.ai_flags = AI_PASSIVE;
  addrinfo* list = nullptr;
  const std::string service = std::to_string(port);
  const int rc =
      getaddrinfo(address.empty() ? nullptr : address.c_str(), service.c_str(), &hints, &list);
  if (rc != 0) {
    return MakeError(ErrorClass::kInvalidConfig,
                     where + ": address does not resolve — check daemon.listen_address",
                     gai_strerror(rc));
  }
  int err = EADDRNOTAVAIL;
  int fd = -1;
  for (addrinfo* ai = list; ai != nullptr && fd < 0; ai = ai->ai_next) {
    const int s =
        ::socket(ai->ai_family, ai->ai_socktype | SOCK_CLOEXEC | SOCK_NONBLOCK, ai->ai_protocol);
    if (s < 0) {
      err = errno;
      continue;
    }
    const int yes = 1;
    ::setsockopt(s, SOL_SOCKET, SO_REUSEADDR, &yes, sizeof yes);
    if (::bind(s, ai->ai_addr, ai->ai_addrlen) != 0 || ::listen(s, HttpApi::kListenBacklog) != 0) {
      err = errno;
      ::close(s);
      continue;
    }
    fd = s;
  }
  freeaddrinfo(list);
  if (fd >= 0) return fd;
  const std::string why = std::strerror(err);
  if (err == EADDRINUSE) {
    return MakeError(
        ErrorClass::kConflict,
        where + ": " + LowerFirst(why) + " — is another aggscand running? set daemon.listen_port",
        why);
  }
  return MakeError(
      ErrorClass::kInvalidConfig,
      where + ": " + LowerFirst(why) + " — check daemon.listen_address and daemon.listen_port",
      why);
}

// The client's address as text, for the access log and the lockout.
std::string PeerAddress(MHD_Connection* connection) {
  const MHD_ConnectionInfo* info =
      MHD_get_connection_info(connection, MHD_CONNECTION_INFO_CLIENT_ADDRESS);
  if (info == nullptr || info->client_addr == nullptr) return "";
  char buf[INET6_ADDRSTRLEN] = {0};
  const sockaddr* sa = info->client_addr;
  if (sa->sa_family == AF_INET) {
    ::inet_ntop(AF_INET, &reinterpret_cast<const sockaddr_in*>(sa)->sin_addr, buf, sizeof buf);
  } else if (sa->sa_family == AF_INET6) {
    const auto* in6 = reinterpret_cast<const sockaddr_in6*>(sa);
    ::inet_ntop(AF_INET6, &in6->sin6_addr, buf, sizeof buf);
  }
  return buf;
}

// libmicrohttpd would percent-decode the path itself, and a decoded "%00"
// would cut it short; the router decodes it once, on the bytes as sent.
size_t KeepEscaped(void*, MHD_Connection*, char* s) { return std::strlen(s); }

void LogMhd(void*, const char* fmt, va_list ap) {
  char buf[512];
  std::vsnprintf(buf, sizeof buf, fmt, ap);
  size_t n = std::strlen(buf);
  while (n > 0 && (buf[n - 1] == '\n' || buf[n - 1] == '\r')) buf[--n] = '\0';
  AGG_LOGD(kCat, "libmicrohttpd: %s", buf);
}

}  // namespace

struct HttpApi::Server {
  // One TCP connection, from accept to close (libmicrohttpd's socket context).
  struct Conn {
    // kStreaming: an event stream, open for as long as its client wants.
    enum Phase { kReceiving, kProcessing, kSending, kStreaming };
    int fd = -1;
    Phase phase = kReceiving;
    SteadyClock::time_point since;
    bool cut = false;  // the watchdog has shut it down
  };
  // One request on a connection (libmicrohttpd's request context).
  struct Exchange {
    MHD_Connection* connection = nullptr;
    Conn* conn = nullptr;
    ApiRequest req;
    bool queued = false;
    bool refused = false;                // answered before its body was read
    std::optional<ApiResponse> refusal;  // a 413 to send once the body is drained
    size_t drained = 0;                  // body bytes read and dropped
    std::optional<ApiResponse> answer;   // set by a handler thread, sent after resume
  };

  // One open GET /api/v1/events or /api/v1/preview. Its content reader runs
  // on libmicrohttpd's thread; with nothing to send it suspends the
  // connection, and a publish or a new frame (or the watchdog, for the
  // keep-alive, or Stop) resumes it. `mu` is held
  // from the reader's look at the hub to its suspend, and by whoever
  // resumes, so no event is missed between the two.
  struct Stream {
    Server* server = nullptr;
    MHD_Connection* connection = nullptr;
    ApiResponse::Stream kind = ApiResponse::Stream::kEvents;
    std::mutex mu;
    uint64_t after = 0;        // last event (or preview frame) seq written to buf
    std::string reset_reason;  // a "reset" event to send first
    std::string buf;           // formatted, not yet all taken by libmicrohttpd
    size_t off = 0;
    bool suspended = false;
    bool closing = false;  // the server stops: end the stream
    bool closed = false;   // libmicrohttpd freed the response
    SteadyClock::time_point last_write;
  };

  Server(DaemonControl& control, HostPolicy policy, EventHub* hub, PreviewHub* live)
      : router(control, std::move(policy)), events(hub), preview(live) {}

  ApiRouter router;
  EventHub* events;
  PreviewHub* preview;
  MHD_Daemon* daemon = nullptr;
  std::unordered_set<std::shared_ptr<Stream>> streams;  // under mu
  size_t downloads = 0;                                 // open archive downloads, under mu

  std::mutex mu;
  std::condition_variable work_cv;
  std::condition_variable watchdog_cv;
  std::deque<Exchange*> work;       // complete requests, their connections suspended
  std::unordered_set<Conn*> conns;  // every open connection
  bool stopping = false;
  std::vector<std::thread> handlers;
  std::thread watchdog;

  static MHD_Result Queue(MHD_Connection* c, const ApiResponse& r) {
    MHD_Response* resp = MHD_create_response_from_buffer(
        r.body.size(), const_cast<char*>(r.body.data()), MHD_RESPMEM_MUST_COPY);
    if (resp == nullptr) return MHD_NO;
    if (!r.content_type.empty())
      MHD_add_response_header(resp, MHD_HTTP_HEADER_CONTENT_TYPE, r.content_type.c_str());
    for (const auto& [k, v] : r.headers) MHD_add_response_header(resp, k.c_str(), v.c_str());
    if (r.close) MHD_add_response_header(resp, MHD_HTTP_HEADER_CONNECTION, "close");
    const MHD_Result ret = MHD_queue_response(c, static_cast<unsigned>(r.status), resp);
    MHD_destroy_response(resp);
    return ret;
  }

  // Answers an admitted GET /api/v1/events or /api/v1/preview with its
  // stream, or with 404 (nothing to stream) or 503 (too many open).
  MHD_Result OpenStream(MHD_Connection* connection, Exchange* ex) {
    const bool live = ex->answer->stream == ApiResponse::Stream::kPreview;
    if ((live ? static_cast<void*>(preview) : static_cast<void*>(events)) == nullptr) {
      SetPhase(ex->conn, Conn::kSending);
      return Queue(connection,
                   ErrorResponse(404, ErrorClass::kNotFound,
                                 live ? "this daemon has no live view (daemon.preview_interval "
                                        "is 0): set it, e.g. \"250ms\", and restart aggscand"
                                      : "this daemon publishes no live events"));
    }
    auto stream = std::make_shared<Stream>();
    stream->server = this;
    stream->connection = connection;
    stream->kind = ex->answer->stream;
    stream->last_write = SteadyClock::now();
    if (!live) {
      // The reconnect delay for EventSource, then a comment so the client
      // sees the stream open at once.
      stream->buf = "retry: 2000\n: aggscand events\n\n";
      stream->after = events->last_seq();
      if (const std::string* last = ex->req.Header("Last-Event-ID"); last != nullptr) {
        if (std::optional<uint64_t> seq = events->SeqAfter(*last)) {
          stream->after = *seq;
        } else {
          stream->reset_reason =
              "Last-Event-ID \"" + Printable(*last, 80) +
              "\" is not one of this run's events (aggscand restarted, or the id is not ours): "
              "reload the state (GET /api/v1/status), then follow the events";
        }
      }
    }
    const size_t limit = live ? HttpApi::kMaxPreviewStreams : HttpApi::kMaxEventStreams;
    {
      std::lock_guard<std::mutex> lock(mu);
      size_t open = 0;
      for (const auto& other : streams) open += other->kind == stream->kind;
      if (ex->conn != nullptr) {
        ex->conn->phase = open >= limit ? Conn::kSending : Conn::kStreaming;
        ex->conn->since = SteadyClock::now();
      }
      if (open >= limit) {
        const std::string what = live ? "live views" : "event streams";
        return Queue(connection,
                     ErrorResponse(503, ErrorClass::kConflict,
                                   "too many " + what + " open (" + std::to_string(limit) +
                                       "): close a console or dashboard, then retry"));
      }
      streams.insert(stream);
    }
    if (live) preview->AddViewer();
    auto* holder = new std::shared_ptr<Stream>(stream);
    // A live-view frame is some tens of KB: larger blocks, fewer calls.
    MHD_Response* resp = MHD_create_response_from_callback(
        MHD_SIZE_UNKNOWN, live ? 64 * 1024 : 4096, &StreamRead, holder, &StreamFree);
    if (resp == nullptr) {
      StreamFree(holder);
      return MHD_NO;
    }
    const std::string type =
        live ? std::string("multipart/x-mixed-replace; boundary=") + kFrameBoundary
             : "text/event-stream";
    MHD_add_response_header(resp, MHD_HTTP_HEADER_CONTENT_TYPE, type.c_str());
    MHD_add_response_header(resp, MHD_HTTP_HEADER_CACHE_CONTROL, "no-store");
    const MHD_Result ret = MHD_queue_response(connection, MHD_HTTP_OK, resp);
    MHD_destroy_response(resp);
    return ret;
  }

  // Answers with a body made while the client reads it (a sample's images
  // archive). Tens of MB to a tablet on a weak network can take longer than
  // kSendLimit, so it is exempt like an event stream; a client that stops
  // reading is closed by libmicrohttpd's idle timeout, and at most
  // kMaxDownloads run at once (each reads the disk while a capture may run).
  MHD_Result OpenSource(MHD_Connection* connection, Exchange* ex) {
    {
      std::lock_guard<std::mutex> lock(mu);
      if (downloads >= HttpApi::kMaxDownloads) {
        if (ex->conn != nullptr) {
          ex->conn->phase = Conn::kSending;
          ex->conn->since = SteadyClock::now();
        }
        return Queue(connection, ErrorResponse(503, ErrorClass::kConflict,
                                               "too many archive downloads at once (" +
                                                   std::to_string(HttpApi::kMaxDownloads) +
                                                   "): wait for one to finish, then retry"));
      }
      ++downloads;
      if (ex->conn != nullptr) {
        ex->conn->phase = Conn::kStreaming;
        ex->conn->since = SteadyClock::now();
      }
    }
    auto* holder = new SourceHolder{this, ex->answer->source};
    MHD_Response* resp = MHD_create_response_from_callback(MHD_SIZE_UNKNOWN, size_t{64} * 1024,
                                                           &SourceRead, holder, &SourceFree);
    if (resp == nullptr) {
      SourceFree(holder);
      return MHD_NO;
    }
    const ApiResponse& r = *ex->answer;
    if (!r.content_type.empty())
      MHD_add_response_header(resp, MHD_HTTP_HEADER_CONTENT_TYPE, r.content_type.c_str());
    for (const auto& [k, v] : r.headers) MHD_add_response_header(resp, k.c_str(), v.c_str());
    const MHD_Result ret = MHD_queue_response(connection, static_cast<unsigned>(r.status), resp);
    MHD_destroy_response(resp);
    return ret;
  }

  struct SourceHolder {
    Server* server;
    std::shared_ptr<BodySource> source;
  };

  static ssize_t SourceRead(void* cls, uint64_t, char* out, size_t max) {
    auto* h = static_cast<SourceHolder*>(cls);
    const ssize_t n = h->source->Read(out, max);
    if (n > 0) return n;
    if (n == 0) return MHD_CONTENT_READER_END_OF_STREAM;
    // The status line is out: the only way to tell the client is to cut the
    // answer short (chunked encoding without its last chunk).
    AGG_LOGW(kCat, "an archive download was cut short: %s", h->source->error().c_str());
    return MHD_CONTENT_READER_END_WITH_ERROR;
  }

  static void SourceFree(void* cls) {
    auto* h = static_cast<SourceHolder*>(cls);
    {
      std::lock_guard<std::mutex> lock(h->server->mu);
      --h->server->downloads;
    }
    delete h;
  }

  // Preview: the newest frame when it is newer than the last one sent (a
  // slow client skips frames); nothing to send: suspend, no keep-alive (MJPEG
  // has no comment), the connection's TCP keep-alive is enough.
  static void FillPreview(Stream& s) {
    const PreviewFrame f = s.server->preview->Latest();
    if (f.seq <= s.after || !f.jpeg) return;
    s.after = f.seq;
    s.buf = std::string("--") + kFrameBoundary +
            "\r\nContent-Type: image/jpeg\r\nContent-Length: " + std::to_string(f.jpeg->size()) +
            "\r\n\r\n";
    s.buf += *f.jpeg;
    s.buf += "\r\n";
  }

  static ssize_t StreamRead(void* cls, uint64_t, char* out, size_t max) {
    Stream& s = **static_cast<std::shared_ptr<Stream>*>(cls);
    std::lock_guard<std::mutex> lock(s.mu);
    if (s.closing) return MHD_CONTENT_READER_END_OF_STREAM;
    if (s.off >= s.buf.size() && s.kind == ApiResponse::Stream::kPreview) {
      s.buf.clear();
      s.off = 0;
      FillPreview(s);
      if (s.buf.empty()) {
        s.suspended = true;
        MHD_suspend_connection(s.connection);
        return 0;
      }
    } else if (s.off >= s.buf.size()) {
      s.buf.clear();
      s.off = 0;
      bool gap = false;
      const std::vector<LiveEvent> fresh = s.server->events->Since(s.after, &gap);
      if (gap && s.reset_reason.empty())
        s.reset_reason =
            "events were missed (more than the daemon keeps): reload the state (GET "
            "/api/v1/status), then follow the events";
      if (!s.reset_reason.empty()) {
        s.buf += FormatSse("", "reset", json{{"reason", s.reset_reason}}.dump());
        s.reset_reason.clear();
      }
      for (const LiveEvent& e : fresh) {
        s.buf += FormatSse(s.server->events->IdOf(e.seq), e.type, e.data);
        s.after = e.seq;
      }
      if (s.buf.empty() && SteadyClock::now() - s.last_write >= HttpApi::kEventKeepAlive)
        s.buf = ": keep-alive\n\n";
      if (s.buf.empty()) {
        s.suspended = true;
        MHD_suspend_connection(s.connection);
        return 0;
      }
    }
    const size_t n = std::min(max, s.buf.size() - s.off);
    s.buf.copy(out, n, s.off);  // raw bytes of the answer: no terminator
    s.off += n;
    s.last_write = SteadyClock::now();
    return static_cast<ssize_t>(n);
  }

  static void StreamFree(void* cls) {
    auto* holder = static_cast<std::shared_ptr<Stream>*>(cls);
    std::shared_ptr<Stream> s = *holder;
    delete holder;
    {
      std::lock_guard<std::mutex> lock(s->mu);
      s->closed = true;
    }
    if (s->kind == ApiResponse::Stream::kPreview) s->server->preview->RemoveViewer();
    std::lock_guard<std::mutex> lock(s->server->mu);
    s->server->streams.erase(s);
  }

  // Resumes every suspended stream (to send what was published, or a
  // keep-alive); `closing`: to end them. Takes mu: never call with it held.
  void WakeStreams(bool closing) {
    std::vector<std::shared_ptr<Stream>> open;
    {
      std::lock_guard<std::mutex> lock(mu);
      open.assign(streams.begin(), streams.end());
    }
    for (const auto& s : open) {
      std::lock_guard<std::mutex> lock(s->mu);
      if (s->closed) continue;
      if (closing) s->closing = true;
      if (s->suspended) {
        s->suspended = false;
        MHD_resume_connection(s->connection);
      }
    }
  }

  static MHD_Result CollectHeader(void* cls, MHD_ValueKind, const char* key, const char* value) {
    auto* ex = static_cast<Exchange*>(cls);
    ex->req.headers.emplace_back(key, value ? value : "");
    // One over the limit is enough to refuse; the rest need not be copied.
    return ex->req.headers.size() > ApiLimits::kMaxHeaderCount ? MHD_NO : MHD_YES;
  }
  static MHD_Result CollectArgument(void* cls, MHD_ValueKind, const char* key, const char* value) {
    auto* target = static_cast<std::string*>(cls);
    *target += target->find('?') == std::string::npos ? '?' : '&';
    *target += key;
    if (value != nullptr) *target += std::string("=") + value;
    return target->size() > ApiLimits::kMaxUriBytes ? MHD_NO : MHD_YES;
  }

  void SetPhase(Conn* c, Conn::Phase phase) {
    if (c == nullptr) return;
    std::lock_guard<std::mutex> lock(mu);
    c->phase = phase;
    c->since = SteadyClock::now();
  }

  static MHD_Result OnRequest(void* cls, MHD_Connection* connection, const char* url,
                              const char* method, const char*, const char* upload,
                              size_t* upload_size, void** req_cls) {
    auto* self = static_cast<Server*>(cls);
    auto* ex = static_cast<Exchange*>(*req_cls);
    if (ex == nullptr) {
      // The head is complete: check it before reading any body.
      ex = new Exchange;
      *req_cls = ex;
      ex->connection = connection;
      const MHD_ConnectionInfo* info =
          MHD_get_connection_info(connection, MHD_CONNECTION_INFO_SOCKET_CONTEXT);
      ex->conn = info != nullptr ? static_cast<Conn*>(info->socket_context) : nullptr;
      ex->req.method = method;
      ex->req.target = url;
      ex->req.peer = PeerAddress(connection);
      MHD_get_connection_values(connection, MHD_GET_ARGUMENT_KIND, &CollectArgument,
                                &ex->req.target);
      MHD_get_connection_values(connection, MHD_HEADER_KIND, &CollectHeader, ex);
      if (std::optional<ApiResponse> refused = ApiRouter::CheckHead(ex->req)) {
        // A body a little too large is read and dropped before the 413, so a
        // client that sends it whole before reading gets the answer, not a reset.
        const std::string* len = ex->req.Header("Content-Length");
        if (refused->status == 413 && len != nullptr && len->size() < 10 &&
            std::stoull(*len) <= kDrainLimitBytes) {
          ex->refusal = std::move(refused);
          return MHD_YES;
        }
        ex->refused = true;
        self->SetPhase(ex->conn, Conn::kSending);
        return Queue(connection, *refused);
      }
      return MHD_YES;
    }
    if (ex->answer) {
      if (ex->answer->stream != ApiResponse::Stream::kNone) return self->OpenStream(connection, ex);
      if (ex->answer->source) return self->OpenSource(connection, ex);
      self->SetPhase(ex->conn, Conn::kSending);
      return Queue(connection, *ex->answer);
    }
    if (ex->refused) {
      *upload_size = 0;  // the answer is out; the rest of the body is not wanted
      return MHD_YES;
    }
    if (*upload_size > 0 && !ex->refusal &&
        ex->req.body.size() + *upload_size > ApiLimits::kMaxBodyBytes) {
      // A chunked body (no Content-Length to refuse it by) that grew past the limit.
      ex->refusal = ErrorResponse(
          413, ErrorClass::kInvalidArgument,
          "request body too large: at most " + std::to_string(ApiLimits::kMaxBodyBytes) + " bytes");
      ex->refusal->close = true;
      ex->drained = ex->req.body.size();
      ex->req.body.clear();
    }
    if (ex->refusal) {
      const bool body_done = *upload_size == 0;
      ex->drained += *upload_size;
      *upload_size = 0;
      if (!body_done && ex->drained <= kDrainLimitBytes) return MHD_YES;
      ex->refused = true;
      self->SetPhase(ex->conn, Conn::kSending);
      return Queue(connection, *ex->refusal);
    }
    if (*upload_size > 0) {
      ex->req.body.append(upload, *upload_size);
      *upload_size = 0;
      return MHD_YES;
    }
    if (ex->queued) return MHD_YES;
    // The whole request is in: its time budget starts now.
    ex->queued = true;
    ex->req.ctx.deadline = SteadyClock::now() + kRequestBudget;
    const int fd = ex->conn != nullptr ? ex->conn->fd : -1;
    // The connection stays suspended (its fd open) until the handler thread
    // is done with the request, so the loop may look at the fd meanwhile.
    ex->req.ctx.client_gone = [fd] {
      if (fd < 0) return false;
      pollfd p{fd, POLLRDHUP, 0};
      return ::poll(&p, 1, 0) > 0 && (p.revents & (POLLRDHUP | POLLHUP | POLLERR)) != 0;
    };
    {
      std::lock_guard<std::mutex> lock(self->mu);
      if (!self->stopping) {
        if (ex->conn != nullptr) {
          ex->conn->phase = Conn::kProcessing;
          ex->conn->since = SteadyClock::now();
        }
        MHD_suspend_connection(connection);
        self->work.push_back(ex);
        self->work_cv.notify_one();
        return MHD_YES;
      }
    }
    ApiResponse r =
        ErrorResponse(503, ErrorClass::kInternal, "aggscand is stopping: the request was not run");
    r.close = true;
    return Queue(connection, r);
  }

  static void OnCompleted(void* cls, MHD_Connection* connection, void** req_cls,
                          MHD_RequestTerminationCode) {
    auto* self = static_cast<Server*>(cls);
    auto* ex = static_cast<Exchange*>(*req_cls);
    *req_cls = nullptr;
    Conn* conn = ex != nullptr ? ex->conn : nullptr;
    if (conn == nullptr) {
      const MHD_ConnectionInfo* info =
          MHD_get_connection_info(connection, MHD_CONNECTION_INFO_SOCKET_CONTEXT);
      conn = info != nullptr ? static_cast<Conn*>(info->socket_context) : nullptr;
    }
    delete ex;
    self->SetPhase(conn, Conn::kReceiving);  // the next request on a keep-alive connection
  }

  static void OnConnection(void* cls, MHD_Connection* connection, void** socket_context,
                           MHD_ConnectionNotificationCode code) {
    auto* self = static_cast<Server*>(cls);
    if (code == MHD_CONNECTION_NOTIFY_STARTED) {
      auto* c = new Conn;
      const MHD_ConnectionInfo* info =
          MHD_get_connection_info(connection, MHD_CONNECTION_INFO_CONNECTION_FD);
      c->fd = info != nullptr ? info->connect_fd : -1;
      c->since = SteadyClock::now();
      std::lock_guard<std::mutex> lock(self->mu);
      self->conns.insert(c);
      *socket_context = c;
      return;
    }
    auto* c = static_cast<Conn*>(*socket_context);
    if (c == nullptr) return;
    // libmicrohttpd closes the fd after this: the watchdog must not touch it then.
    std::lock_guard<std::mutex> lock(self->mu);
    self->conns.erase(c);
    delete c;
    *socket_context = nullptr;
  }

  void HandlerThread() {
    for (;;) {
      Exchange* ex = nullptr;
      bool stop = false;
      {
        std::unique_lock<std::mutex> lock(mu);
        work_cv.wait(lock, [this] { return stopping || !work.empty(); });
        if (work.empty()) return;
        ex = work.front();
        work.pop_front();
        stop = stopping;
      }
      ApiResponse r;
      if (stop) {
        r = ErrorResponse(503, ErrorClass::kInternal,
                          "aggscand is stopping: the request was not run");
        r.close = true;
      } else if (SteadyClock::now() >= ex->req.ctx.deadline) {
        r = ErrorResponse(
            503, ErrorClass::kTimeout,
            "the API was too busy to start this request in time: it was dropped and will not run "
            "later; try again");
      } else {
        r = router.Handle(ex->req);
      }
      ex->answer = std::move(r);
      MHD_resume_connection(ex->connection);
    }
  }

  // Cuts connections whose request has not arrived, or whose answer has not
  // been taken, in time: libmicrohttpd's own timeout is reset by every byte.
  void WatchdogThread() {
    std::unique_lock<std::mutex> lock(mu);
    auto keepalive_due = SteadyClock::now() + HttpApi::kEventKeepAlive;
    while (!stopping) {
      watchdog_cv.wait_for(lock, kWatchdogPeriod);
      if (SteadyClock::now() >= keepalive_due && !stopping) {
        // Idle event streams send their keep-alive.
        keepalive_due = SteadyClock::now() + HttpApi::kEventKeepAlive;
        lock.unlock();
        WakeStreams(false);
        lock.lock();
      }
      const auto now = SteadyClock::now();
      for (Conn* c : conns) {
        if (c->cut || c->fd < 0) continue;
        const bool late = (c->phase == Conn::kReceiving && now - c->since > kReceiveLimit) ||
                          (c->phase == Conn::kSending && now - c->since > kSendLimit);
        if (!late) continue;
        // libmicrohttpd sees the end of the stream and closes the connection itself.
        ::shutdown(c->fd, SHUT_RDWR);
        c->cut = true;
        AGG_LOGD(kCat, "closed a connection whose %s took longer than %lld s",
                 c->phase == Conn::kReceiving ? "request" : "answer",
                 static_cast<long long>(c->phase == Conn::kReceiving ? kReceiveLimit.count()
                                                                     : kSendLimit.count()));
      }
    }
  }
};

HttpApi::HttpApi(DaemonControl& control, std::string address, int port, HttpApiOptions options)
    : control_(control),
      address_(std::move(address)),
      requested_port_(port),
      options_(std::move(options)) {}

HttpApi::~HttpApi() { Stop(); }

Status HttpApi::Start() {
  if (server_) return MakeError(ErrorClass::kInvalidState, "HTTP API already started");
  if (requested_port_ < 0 || requested_port_ > 65535) {
    return MakeError(ErrorClass::kInvalidConfig, "invalid daemon.listen_port " +
                                                     std::to_string(requested_port_) +
                                                     ": use 1-65535, or 0 for any free port");
  }
  Result<int> fd = OpenListenSocket(address_, requested_port_);
  if (!fd) return fd.error();
  sockaddr_storage addr{};
  socklen_t len = sizeof addr;
  int port = requested_port_;
  if (::getsockname(*fd, reinterpret_cast<sockaddr*>(&addr), &len) == 0) {
    port = addr.ss_family == AF_INET6 ? ntohs(reinterpret_cast<sockaddr_in6*>(&addr)->sin6_port)
                                      : ntohs(reinterpret_cast<sockaddr_in*>(&addr)->sin_port);
  }
  auto server = std::make_unique<Server>(
      control_,
      HostPolicy::ForListen(address_, options_.allowed_hosts, options_.allowed_origins, port),
      options_.events, options_.preview);
  Server* s = server.get();
  const bool tls = !options_.tls_certificate_pem.empty() || !options_.tls_key_pem.empty();
  if (tls && MHD_is_feature_supported(MHD_FEATURE_TLS) != MHD_YES) {
    ::close(*fd);
    return MakeError(ErrorClass::kInvalidConfig,
                     "this libmicrohttpd has no TLS: serve plain HTTP on a loopback address "
                     "behind a reverse proxy that terminates TLS (see the README)");
  }
  s->router.RequireCredentials(options_.access, tls);
  s->router.ServeConsole(options_.web_root);
  // The key and certificate are read by libmicrohttpd at start (GnuTLS).
  MHD_OptionItem tls_options[] = {
      {MHD_OPTION_HTTPS_MEM_KEY, 0, const_cast<char*>(options_.tls_key_pem.c_str())},
      {MHD_OPTION_HTTPS_MEM_CERT, 0, const_cast<char*>(options_.tls_certificate_pem.c_str())},
      {MHD_OPTION_END, 0, nullptr}};
  MHD_OptionItem no_options[] = {{MHD_OPTION_END, 0, nullptr}};
  s->daemon = MHD_start_daemon(
      MHD_USE_INTERNAL_POLLING_THREAD | MHD_USE_EPOLL | MHD_ALLOW_SUSPEND_RESUME |
          MHD_USE_ERROR_LOG | (tls ? MHD_USE_TLS : 0),
      0, nullptr, nullptr, &Server::OnRequest, s,
      // First, or libmicrohttpd prints what it says about the earlier options itself.
      MHD_OPTION_EXTERNAL_LOGGER, &LogMhd, nullptr,            //
      MHD_OPTION_LISTEN_SOCKET, static_cast<MHD_socket>(*fd),  //
      MHD_OPTION_CONNECTION_LIMIT, kMaxConnections,            //
      MHD_OPTION_CONNECTION_MEMORY_LIMIT, kConnectionMemory,   //
      MHD_OPTION_CONNECTION_TIMEOUT, kIdleTimeoutSec,          //
      MHD_OPTION_NOTIFY_COMPLETED, &Server::OnCompleted, s,    //
      MHD_OPTION_NOTIFY_CONNECTION, &Server::OnConnection, s,  //
      MHD_OPTION_UNESCAPE_CALLBACK, &KeepEscaped, nullptr,     //
      MHD_OPTION_ARRAY, tls ? tls_options : no_options,        //
      MHD_OPTION_END);
  if (s->daemon == nullptr) {
    ::close(*fd);
    if (tls) {
      return MakeError(ErrorClass::kInvalidConfig,
                       "cannot start the HTTPS server on " + HostPort(address_, port) +
                           ": the TLS certificate or key was refused (check that "
                           "daemon.tls_certificate and daemon.tls_key are PEM files of one pair)");
    }
    return MakeError(ErrorClass::kInternal, "cannot start the HTTP server on " +
                                                HostPort(address_, port) +
                                                " (libmicrohttpd refused its options); report it");
  }
  for (size_t i = 0; i < kHandlerThreads; ++i)
    s->handlers.emplace_back([s] { s->HandlerThread(); });
  s->watchdog = std::thread([s] { s->WatchdogThread(); });
  if (s->events != nullptr) s->events->SetListener([s] { s->WakeStreams(false); });
  if (s->preview != nullptr) s->preview->SetListener([s] { s->WakeStreams(false); });
  server_ = std::move(server);
  bound_port_ = port;
  AGG_LOGI(kCat, "HTTP API listening on %s://%s%s", tls ? "https" : "http",
           HostPort(address_, bound_port_).c_str(),
           options_.access != nullptr ? " (credentials required)" : "");
  return OkStatus();
}

void HttpApi::Stop() {
  if (!server_) return;
  Server& s = *server_;
  {
    std::lock_guard<std::mutex> lock(s.mu);
    s.stopping = true;
  }
  s.work_cv.notify_all();
  s.watchdog_cv.notify_all();
  // Event streams end (their readers see `closing` once resumed).
  if (s.events != nullptr) s.events->SetListener({});
  if (s.preview != nullptr) s.preview->SetListener({});
  s.WakeStreams(true);
  // Handler threads answer what is queued with 503 and finish the calls in
  // flight (each bounded by kRequestBudget, and at once when the loop has
  // stopped), resuming every suspended connection.
  for (std::thread& t : s.handlers) t.join();
  s.watchdog.join();
  // Closes the listen socket and every connection, whatever their clients do.
  const MHD_socket listen_fd = MHD_quiesce_daemon(s.daemon);
  MHD_stop_daemon(s.daemon);
  if (listen_fd != MHD_INVALID_SOCKET) ::close(listen_fd);
  server_.reset();
  bound_port_ = 0;
}

}  // namespace aggscan
