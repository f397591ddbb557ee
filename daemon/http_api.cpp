#include "daemon/http_api.h"

#include <httplib.h>
#include <netdb.h>
#include <sys/socket.h>
#include <unistd.h>

#include <cctype>
#include <cerrno>
#include <chrono>
#include <cstring>
#include <exception>
#include <functional>
#include <nlohmann/json.hpp>
#include <string_view>
#include <utility>

#include "common/fsutil.h"
#include "common/log.h"
#include "store/layout.h"

namespace aggscan {

namespace {

using json = nlohmann::json;

constexpr const char* kCat = "api";
// A client that streams a body past the limit is drained up to this many bytes
// (so the connection stays in sync for the 413), then cut off.
constexpr size_t kDrainLimitBytes = 1 << 20;
// Worker threads: the CLI and dashboards hold keep-alive connections, each of
// which occupies a worker until it closes or idles out.
constexpr size_t kWorkerThreads = 16;
// Short keep-alive so Stop() (daemon shutdown) never waits long on idle clients.
constexpr time_t kKeepAliveSec = 2;
constexpr const char* kJsonType = "application/json";
constexpr const char* kMetricsType = "text/plain; version=0.0.4; charset=utf-8";
constexpr const char* kSamplesPrefix = "/api/v1/samples/";
// Matches every path, including ones whose percent-decoding produced control
// characters ('.' would not match a decoded "%0a", leaving it unrouted).
constexpr const char* kAnyPath = "[\\s\\S]*";

// Never throws on invalid UTF-8 (a daemon message or an echoed id may hold any bytes).
std::string Dump(const json& j) {
  return j.dump(-1, ' ', false, json::error_handler_t::replace) + "\n";
}

void SetJson(httplib::Response& res, int status, const json& body) {
  res.status = status;
  res.set_content(Dump(body), kJsonType);
}

void SetError(httplib::Response& res, int status, ErrorClass cls, const std::string& message,
              const std::string& detail = {}) {
  json err = {{"class", ErrorClassName(cls)}, {"message", message}};
  if (!detail.empty()) err["detail"] = detail;
  SetJson(res, status, json{{"error", std::move(err)}});
}

void SetError(httplib::Response& res, const Error& e) {
  SetError(res, HttpStatusFor(e.cls), e.cls, e.message, e.detail);
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
  kButton,
  kAbort,
  kReset,
  kMetrics
};

// Methods each endpoint accepts (HEAD is answered wherever GET is).
const char* AllowedMethods(Endpoint ep) {
  switch (ep) {
    case Endpoint::kStatus:
    case Endpoint::kHealth:
    case Endpoint::kSample:
    case Endpoint::kSampleFile:
    case Endpoint::kMetrics:
      return "GET, HEAD";
    case Endpoint::kSamples:
      return "GET, HEAD, POST";
    case Endpoint::kSampleRetry:
    case Endpoint::kButton:
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

// `path` is already percent-decoded by cpp-httplib; `id` gets whatever follows
// the samples prefix up to the next '/', unvalidated, and `file` what follows
// that ("results" or a mesh file name).
Endpoint Match(const std::string& path, std::string* id, std::string* file) {
  if (path == "/api/v1/status") return Endpoint::kStatus;
  if (path == "/api/v1/health") return Endpoint::kHealth;
  if (path == "/api/v1/samples") return Endpoint::kSamples;
  if (path == "/api/v1/button") return Endpoint::kButton;
  if (path == "/api/v1/abort") return Endpoint::kAbort;
  if (path == "/api/v1/reset") return Endpoint::kReset;
  if (path == "/metrics") return Endpoint::kMetrics;
  if (path.rfind(kSamplesPrefix, 0) == 0) {
    *id = path.substr(std::strlen(kSamplesPrefix));
    const size_t slash = id->find('/');
    if (slash == std::string::npos) return Endpoint::kSample;
    *file = id->substr(slash + 1);
    id->resize(slash);
    if (*file == "results") {
      *file = "morphology.json";
      return Endpoint::kSampleFile;
    }
    if (*file == "mesh.ply" || *file == "mesh.obj" || *file == "mesh.stl") return Endpoint::kSampleFile;
    if (*file == "retry") return Endpoint::kSampleRetry;
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

enum class BodyRead { kOk, kTooLarge, kBroken };

bool IsChunked(const httplib::Request& req) {
  std::string te = req.get_header_value("Transfer-Encoding");
  for (char& c : te) c = static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
  return te.find("chunked") != std::string::npos;
}

// Reads the request body through the content reader, keeping at most
// kMaxBodyBytes. A request without Content-Length or chunked encoding has no
// body (cpp-httplib would otherwise wait for the peer to close).
BodyRead ReadBody(const httplib::Request& req, httplib::Response& res,
                  const httplib::ContentReader& reader, std::string* body) {
  const bool chunked = IsChunked(req);
  if (!req.has_header("Content-Length") && !chunked) return BodyRead::kOk;
  if (!chunked) {
    // cpp-httplib would saturate an unparsable or absurd length and then try to
    // skip that many bytes, holding a worker until its read timeout.
    const std::string len = req.get_header_value("Content-Length");
    const bool digits = !len.empty() && len.size() <= 18 &&
                        len.find_first_not_of("0123456789") == std::string::npos;
    if (!digits) return BodyRead::kBroken;
  }
  size_t total = 0;
  bool over = false;
  const bool ok = reader([&](const char* data, size_t n) {
    total += n;
    if (total > kDrainLimitBytes) return false;
    if (!over && body->size() + n > HttpApi::kMaxBodyBytes) {
      over = true;
      body->clear();
    }
    if (!over) body->append(data, n);
    return true;
  });
  // cpp-httplib sets 413 itself when Content-Length exceeds the payload limit.
  if (over || res.status == 413 || total > HttpApi::kMaxBodyBytes) return BodyRead::kTooLarge;
  return ok ? BodyRead::kOk : BodyRead::kBroken;
}

void Reply(httplib::Response& res, const Result<json>& r) {
  if (!r.ok()) {
    SetError(res, r.error());
    return;
  }
  SetJson(res, 200, r.value().is_null() ? json::object() : r.value());
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

// Routes one request to DaemonControl. Runs on cpp-httplib worker threads.
struct HttpApi::Impl {
  DaemonControl& control;

  // `reader` is null for methods that carry no body (GET, HEAD, OPTIONS).
  void Handle(const httplib::Request& req, httplib::Response& res,
              const httplib::ContentReader* reader) {
    try {
      HandleUnsafe(req, res, reader);
    } catch (const std::exception& e) {
      AGG_LOGE(kCat, "%s %s: unhandled exception: %s", req.method.c_str(),
               Printable(req.path).c_str(), e.what());
      res.headers.erase("Allow");
      SetError(res, 500, ErrorClass::kInternal, "internal error in the HTTP API; report it",
               e.what());
    } catch (...) {
      AGG_LOGE(kCat, "%s %s: unhandled non-standard exception", req.method.c_str(),
               Printable(req.path).c_str());
      SetError(res, 500, ErrorClass::kInternal, "internal error in the HTTP API; report it");
    }
  }

  void HandleUnsafe(const httplib::Request& req, httplib::Response& res,
                    const httplib::ContentReader* reader) {
    // Read (or drain) the body first, whatever the route: an unread body would
    // be parsed as the next request on a keep-alive connection.
    std::string body;
    if (reader != nullptr) {
      switch (ReadBody(req, res, *reader, &body)) {
        case BodyRead::kOk:
          break;
        case BodyRead::kTooLarge:
          res.set_header("Connection", "close");
          SetError(res, 413, ErrorClass::kInvalidArgument,
                   "request body too large: at most " + std::to_string(kMaxBodyBytes) + " bytes");
          return;
        case BodyRead::kBroken:
          res.set_header("Connection", "close");
          SetError(res, 400, ErrorClass::kInvalidArgument,
                   "could not read the request body (bad Content-Length or chunked encoding)");
          return;
      }
    }

    std::string id, file;
    const Endpoint ep = Match(req.path, &id, &file);
    if (ep == Endpoint::kNone) {
      SetError(
          res, 404, ErrorClass::kNotFound,
          "no such endpoint: " + req.method + " " + Printable(req.path) + " (see /api/v1/status)");
      return;
    }
    if (req.method == "OPTIONS") {
      res.status = 204;
      res.set_header("Allow", std::string(AllowedMethods(ep)) + ", OPTIONS");
      return;
    }
    if (!MethodAllowed(ep, req.method)) {
      res.set_header("Allow", AllowedMethods(ep));
      SetError(res, 405, ErrorClass::kInvalidArgument,
               "method " + req.method + " not allowed on " + Printable(req.path) +
                   "; allowed: " + AllowedMethods(ep));
      return;
    }

    const bool get = req.method == "GET" || req.method == "HEAD";
    switch (ep) {
      case Endpoint::kStatus:
        SetJson(res, 200, control.GetStatus());
        return;
      case Endpoint::kHealth: {
        // 200 only when every device is healthy, else 503 with the same body:
        // a monitor or `curl -f` needs only the code, an operator reads the
        // body (which device, what to check, when the next retry is).
        const json h = control.GetHealth();
        const bool ok = h.is_object() && h.value("status", "") == "ok";
        SetJson(res, ok ? 200 : 503, h);
        return;
      }
      case Endpoint::kSamples:
        if (get) {
          Reply(res, control.ListSamples());
        } else {
          ArmFromBody(body, res);
        }
        return;
      case Endpoint::kSample:
        if (!layout::IsValidSampleId(id)) {
          SetError(res, 400, ErrorClass::kInvalidArgument, InvalidIdMessage(id));
          return;
        }
        Reply(res, control.GetSample(id));
        return;
      case Endpoint::kSampleFile:
        if (!layout::IsValidSampleId(id)) {
          SetError(res, 400, ErrorClass::kInvalidArgument, InvalidIdMessage(id));
          return;
        }
        ServeResultFile(id, file, res);
        return;
      case Endpoint::kSampleRetry:
        if (!layout::IsValidSampleId(id)) {
          SetError(res, 400, ErrorClass::kInvalidArgument, InvalidIdMessage(id));
          return;
        }
        Reply(res, control.Retry(id));
        return;
      case Endpoint::kButton:
        Reply(res, control.Press("api"));
        return;
      case Endpoint::kAbort:
        Reply(res, control.Abort());
        return;
      case Endpoint::kReset:
        Reply(res, control.Reset());
        return;
      case Endpoint::kMetrics:
        res.status = 200;
        res.set_content(control.Metrics(), kMetricsType);
        return;
      case Endpoint::kNone:
        break;
    }
    SetError(res, 500, ErrorClass::kInternal, "unrouted endpoint; report it");
  }

  void ServeResultFile(const std::string& id, const std::string& name, httplib::Response& res) {
    Result<std::string> path = control.ResultFile(id, name);
    if (!path) {
      SetError(res, path.error());
      return;
    }
    Result<std::string> bytes = ReadFile(*path);
    if (!bytes) {
      SetError(res, bytes.error());
      return;
    }
    const bool is_json = name.size() > 5 && name.compare(name.size() - 5, 5, ".json") == 0;
    res.status = 200;
    if (!is_json) {
      res.set_header("Content-Disposition", "attachment; filename=\"" + id + "_" + name + "\"");
    }
    res.set_content(std::move(*bytes), is_json                       ? kJsonType
                                       : name.ends_with(".obj")      ? "text/plain; charset=utf-8"
                                       : name.ends_with(".stl")      ? "model/stl"
                                                                     : "application/octet-stream");
  }

  void ArmFromBody(const std::string& body, httplib::Response& res) {
    static const std::string kExpected = R"(expected a JSON object {"id": "<sample id>"})";
    const json doc = json::parse(body, nullptr, /*allow_exceptions=*/false);
    if (doc.is_discarded()) {
      SetError(res, 400, ErrorClass::kInvalidArgument,
               "request body is not valid JSON: " + kExpected);
      return;
    }
    if (!doc.is_object()) {
      SetError(res, 400, ErrorClass::kInvalidArgument,
               "request body is not a JSON object: " + kExpected);
      return;
    }
    const auto it = doc.find("id");
    if (it == doc.end() || !it->is_string()) {
      SetError(res, 400, ErrorClass::kInvalidArgument,
               "missing or non-string \"id\": " + kExpected);
      return;
    }
    const std::string id = it->get<std::string>();
    if (!layout::IsValidSampleId(id)) {
      SetError(res, 400, ErrorClass::kInvalidArgument, InvalidIdMessage(id));
      return;
    }
    Reply(res, control.Arm(id));
  }
};

namespace {

std::string HostPort(const std::string& host, int port) {
  const bool v6 = host.find(':') != std::string::npos;
  return (v6 ? "[" + host + "]" : host) + ":" + std::to_string(port);
}

// cpp-httplib reports a failed bind as a bare false. Repeat the bind on a
// scratch socket to learn why. Returns 0 if it now succeeds; sets *gai_text
// when the address does not resolve.
int ProbeBindErrno(const std::string& host, int port, std::string* gai_text) {
  addrinfo hints{};
  hints.ai_family = AF_UNSPEC;
  hints.ai_socktype = SOCK_STREAM;
  hints.ai_flags = AI_PASSIVE;
  addrinfo* list = nullptr;
  const std::string service = std::to_string(port);
  const int rc = getaddrinfo(host.empty() ? nullptr : host.c_str(), service.c_str(), &hints, &list);
  if (rc != 0) {
    *gai_text = gai_strerror(rc);
    return EINVAL;
  }
  int err = EADDRNOTAVAIL;
  for (addrinfo* ai = list; ai != nullptr; ai = ai->ai_next) {
    const int fd = ::socket(ai->ai_family, ai->ai_socktype | SOCK_CLOEXEC, ai->ai_protocol);
    if (fd < 0) {
      err = errno;
      continue;
    }
    const int yes = 1;
    ::setsockopt(fd, SOL_SOCKET, SO_REUSEADDR, &yes, sizeof yes);
    const bool bound = ::bind(fd, ai->ai_addr, ai->ai_addrlen) == 0;
    err = bound ? 0 : errno;
    ::close(fd);
    if (bound) break;
  }
  freeaddrinfo(list);
  return err;
}

std::string LowerFirst(std::string s) {
  if (!s.empty()) s[0] = static_cast<char>(std::tolower(static_cast<unsigned char>(s[0])));
  return s;
}

}  // namespace

HttpApi::HttpApi(DaemonControl& control, std::string address, int port)
    : control_(control), address_(std::move(address)), requested_port_(port) {}

HttpApi::~HttpApi() { Stop(); }

Status HttpApi::Start() {
  if (server_) return MakeError(ErrorClass::kInvalidState, "HTTP API already started");
  if (requested_port_ < 0 || requested_port_ > 65535) {
    return MakeError(ErrorClass::kInvalidConfig, "invalid daemon.listen_port " +
                                                     std::to_string(requested_port_) +
                                                     ": use 1-65535, or 0 for any free port");
  }
  impl_ = std::make_unique<Impl>(Impl{control_});
  server_ = std::make_unique<httplib::Server>();
  httplib::Server& svr = *server_;

  svr.new_task_queue = [] { return new httplib::ThreadPool(kWorkerThreads); };
  // SO_REUSEADDR only: cpp-httplib's default also sets SO_REUSEPORT, which would
  // let a second aggscand silently share the port instead of failing.
  svr.set_socket_options([](socket_t sock) {
    const int yes = 1;
    ::setsockopt(sock, SOL_SOCKET, SO_REUSEADDR, &yes, sizeof yes);
  });
  svr.set_keep_alive_timeout(kKeepAliveSec);
  // Headers and body go out in separate writes; with Nagle on, a keep-alive
  // client waits for its delayed ACK (40 ms) on every answer.
  svr.set_tcp_nodelay(true);
  svr.set_payload_max_length(kMaxBodyBytes);

  Impl* impl = impl_.get();
  const httplib::Server::Handler plain = [impl](const httplib::Request& req,
                                                httplib::Response& res) {
    impl->Handle(req, res, nullptr);
  };
  const httplib::Server::HandlerWithContentReader with_body =
      [impl](const httplib::Request& req, httplib::Response& res,
             const httplib::ContentReader& reader) { impl->Handle(req, res, &reader); };
  svr.Get(kAnyPath, plain);
  svr.Options(kAnyPath, plain);
  svr.Post(kAnyPath, with_body);
  svr.Put(kAnyPath, with_body);
  svr.Patch(kAnyPath, with_body);
  svr.Delete(kAnyPath, with_body);

  // Answers cpp-httplib produces itself (unparseable request, unknown method,
  // oversized URI) get the same JSON error shape; ours already have a body.
  const httplib::Server::HandlerWithResponse on_error = [](const httplib::Request&,
                                                           httplib::Response& res) {
    if (!res.body.empty()) return httplib::Server::HandlerResponse::Unhandled;
    ErrorClass cls = ErrorClass::kInvalidArgument;
    std::string message = "bad request";
    if (res.status == 404) {
      cls = ErrorClass::kNotFound;
      message = "no such endpoint";
    } else if (res.status == 413) {
      message = "request body too large: at most " + std::to_string(kMaxBodyBytes) + " bytes";
    } else if (res.status == 414) {
      message = "request URI too long";
    } else if (res.status >= 500) {
      cls = ErrorClass::kInternal;
      message = "internal error in the HTTP API; report it";
    }
    SetError(res, res.status, cls, message);
    return httplib::Server::HandlerResponse::Handled;
  };
  svr.set_error_handler(on_error);
  svr.set_exception_handler([](const httplib::Request& req, httplib::Response& res,
                               const std::exception_ptr& ep) {
    std::string what = "unknown exception";
    try {
      if (ep) std::rethrow_exception(ep);
    } catch (const std::exception& e) {
      what = e.what();
    } catch (...) {
    }
    AGG_LOGE(kCat, "%s %s: exception: %s", req.method.c_str(), Printable(req.path).c_str(),
             what.c_str());
    SetError(res, 500, ErrorClass::kInternal, "internal error in the HTTP API; report it", what);
  });
  svr.set_logger([](const httplib::Request& req, const httplib::Response& res) {
    AGG_LOGD(kCat, "%s %s -> %d", Printable(req.method, 16).c_str(), Printable(req.path).c_str(),
             res.status);
  });

  int port = requested_port_;
  bool bound = false;
  if (requested_port_ == 0) {
    port = svr.bind_to_any_port(address_);
    bound = port > 0;
  } else {
    bound = svr.bind_to_port(address_, requested_port_);
  }
  if (!bound) {
    server_.reset();
    impl_.reset();
    std::string gai_text;
    const int err = ProbeBindErrno(address_, requested_port_, &gai_text);
    const std::string where = "cannot listen on " + HostPort(address_, requested_port_);
    if (!gai_text.empty()) {
      return MakeError(ErrorClass::kInvalidConfig,
                       where + ": address does not resolve — check daemon.listen_address",
                       gai_text);
    }
    const std::string why = err != 0 ? std::strerror(err) : "bind failed";
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
  bound_port_ = port;

  listener_done_ = false;
  listener_ = std::thread([this] {
    if (!server_->listen_after_bind()) AGG_LOGE(kCat, "HTTP listener stopped unexpectedly");
    listener_done_ = true;
  });
  // Stop() can only interrupt a listener that has started; wait for it.
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(5);
  while (!server_->is_running() && !listener_done_ && std::chrono::steady_clock::now() < deadline) {
    std::this_thread::sleep_for(std::chrono::milliseconds(1));
  }
  AGG_LOGI(kCat, "HTTP API listening on http://%s", HostPort(address_, bound_port_).c_str());
  return OkStatus();
}

void HttpApi::Stop() {
  if (!server_) return;
  if (listener_.joinable()) {
    // Server::stop() is a no-op until the listener runs, and must be called once.
    while (!listener_done_) {
      if (server_->is_running()) {
        server_->stop();
        break;
      }
      std::this_thread::sleep_for(std::chrono::milliseconds(1));
    }
    listener_.join();
  }
  server_.reset();
  impl_.reset();
  bound_port_ = 0;
}

}  // namespace aggscan
