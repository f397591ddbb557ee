// The daemon's HTTP JSON API: a thin translation layer between HTTP requests
// and DaemonControl. It owns no capture state; every call goes through the
// DaemonControl it borrows, which is safe to call from any thread.
//
//   GET  /api/v1/status          → DaemonControl::GetStatus()
//   GET  /api/v1/health          → GetHealth(): 200 when every device is ok, else 503 (same body)
//   POST /api/v1/samples         {"id": "..."} → Arm(id)
//   GET  /api/v1/samples         → ListSamples()
//   GET  /api/v1/samples/{id}    → GetSample(id)
//   POST /api/v1/button          → Press("api")
//   POST /api/v1/calibration     → ArmCalibration(): a capture of the board, solved by the worker
//   POST /api/v1/abort           → Abort()
//   POST /api/v1/reset           → Reset()
//   POST /api/v1/session         {"user", "password"} → a session token (and cookie)
//   GET  /api/v1/session         → who the credentials are; DELETE: log out
//   GET  /api/v1/samples/{id}/images.zip → ImageArchive(): the sample's images, one ZIP (streamed)
//   GET  /api/v1/samples/{id}/sides/{side}/views/{view}[/thumbnail|/mask]
//                                → ViewFile(): the view's JPEG, a small JPEG of it, its mask PNG
//   GET  /api/v1/events          → live events (Server-Sent Events, EventHub)
//   GET  /api/v1/preview         → live camera view (MJPEG, PreviewHub)
//   GET  /api/v1/openapi.json    → this API described (OpenAPI 3)
//   GET  /metrics                → Metrics() (Prometheus text format 0.0.4)
//
// Every answer except /metrics is JSON. Errors are
// {"error": {"class": "<ErrorClassName>", "message": "..."}} with the HTTP
// status from HttpStatusFor(). Input is never trusted: sample ids are checked
// with layout::IsValidSampleId after percent-decoding, the request head and
// body are capped (431, 414, 413), the Host header must name this rig and a
// state-changing request from a browser must come from an allowed Origin, and
// a throwing handler answers 500 instead of taking the daemon down.
//
// Two layers: ApiRouter turns one complete request into one answer without
// any socket (a fuzzer drives it directly); HttpApi is the transport
// (libmicrohttpd, one event-driven polling thread), which never blocks on a
// client: a hung or trickling client costs one connection slot, for a
// bounded time, never a thread.
#pragma once

#include <chrono>
#include <memory>
#include <optional>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include "common/error.h"
#include "daemon/access.h"
#include "daemon/archive_stream.h"
#include "daemon/control.h"
#include "daemon/event_hub.h"
#include "daemon/jpeg_scale.h"
#include "daemon/preview_hub.h"

namespace aggscan {

/// The API's OpenAPI 3 document (daemon/openapi.json), as served at
/// GET /api/v1/openapi.json.
const char* OpenApiDocument();

/// HTTP status for an error class: invalid_argument 400, not_found 404,
/// conflict/invalid_state 409, device errors and timeout 503, disk_full 507,
/// others 500.
int HttpStatusFor(ErrorClass cls);

/// Limits on what one request may hold and how long it may take.
struct ApiLimits {
  /// Largest accepted request body; larger ones get 413.
  static constexpr size_t kMaxBodyBytes = size_t{64} * 1024;
  /// Most header fields in one request; more get 431.
  static constexpr size_t kMaxHeaderCount = 100;
  /// Most bytes of header names and values together; more get 431.
  static constexpr size_t kMaxHeaderBytes = size_t{16} * 1024;
  /// Longest request target (path and query); longer get 414.
  static constexpr size_t kMaxUriBytes = 2048;
};

/// One complete request, whatever carried it.
struct ApiRequest {
  std::string method;
  std::string target;  // path as sent (still percent-encoded), without the query
  std::vector<std::pair<std::string, std::string>> headers;  // in order, names as sent
  std::string body;
  /// The client's address ("192.168.1.30", "::1"); "" when unknown.
  std::string peer;
  /// Deadline and client liveness of state-changing calls.
  CallContext ctx;

  /// The first header of that name (case-insensitive), or null.
  const std::string* Header(std::string_view name) const;
};

/// One answer.
struct ApiResponse {
  int status = 500;
  std::string content_type;
  std::string body;
  std::vector<std::pair<std::string, std::string>> headers;  // Allow, Content-Disposition, ...
  bool close = false;  // close the connection after it (the request was not read to its end)
  /// A stream the transport answers with instead of `body`, once admitted:
  /// GET /api/v1/events (text/event-stream) or GET /api/v1/preview (MJPEG).
  enum class Stream { kNone, kEvents, kPreview };
  Stream stream = Stream::kNone;
  /// A body made while the client reads it (a sample's images archive),
  /// sent instead of `body` with chunked transfer encoding.
  std::shared_ptr<BodySource> source;
};

/// The JSON error answer every refusal uses.
ApiResponse ErrorResponse(int status, ErrorClass cls, const std::string& message,
                          const std::string& detail = {});

/// Which Host and Origin headers the API accepts: the defence against DNS
/// rebinding (a web page on another site whose name resolves to the rig) and
/// against cross-site form posts that would move the turntable.
class HostPolicy {
 public:
  /// `names`: host names or addresses (IPv6 in brackets), each optionally with
  /// ":port"; one without a port matches a Host without a port or with `port`.
  /// `origins`: extra allowed origins, "http[s]://host[:port]".
  HostPolicy(const std::vector<std::string>& names, const std::vector<std::string>& origins,
             int port);
  /// localhost, 127.0.0.1, [::1], `listen_address` and `extra_names`.
  static HostPolicy ForListen(const std::string& listen_address,
                              const std::vector<std::string>& extra_names,
                              const std::vector<std::string>& origins, int port);

  bool HostAllowed(std::string_view host) const;
  /// An Origin is allowed when it is one of the configured origins or its
  /// host and port are an allowed Host ("null" never is).
  bool OriginAllowed(std::string_view origin) const;

 private:
  bool Allowed(std::string_view name, int port, bool port_given) const;

  std::vector<std::pair<std::string, int>> names_;  // lowercase name, port (0 = any-of-ours)
  std::vector<std::string> origins_;                // lowercase
  int port_;
};

/// Turns one complete request into an answer by calling DaemonControl. No
/// sockets and no threads of its own; Handle never throws.
class ApiRouter {
 public:
  /// Borrows `control`, which must outlive this object.
  ApiRouter(DaemonControl& control, HostPolicy policy);

  /// Checks a request head against ApiLimits before its body is read: 431,
  /// 414, 413 (by Content-Length), 400 for an unknown method; nullopt if fine.
  static std::optional<ApiResponse> CheckHead(const ApiRequest& head);

  ApiResponse Handle(const ApiRequest& req);

  /// From now on every request needs credentials checked by `access`
  /// (borrowed; null: none needed, the loopback default). `tls`: the API is
  /// served over TLS (the session cookie is then marked Secure).
  void RequireCredentials(AccessControl* access, bool tls) {
    access_ = access;
    tls_ = tls;
  }

  /// Serves the operator's console from `web_root` (index.html at "/", the
  /// rest under "/ui/"); empty: those paths are 404. The files hold no data
  /// of the rig and are served without credentials; everything they show
  /// comes through the API, which asks for them.
  void ServeConsole(std::string web_root) { web_root_ = std::move(web_root); }

 private:
  ApiResponse HandleSession(const ApiRequest& req, const std::optional<Principal>& who);
  ApiResponse HandleUnsafe(const ApiRequest& req);
  ApiResponse ServeResultFile(const std::string& id, const std::string& name);
  ApiResponse ServeView(const std::string& id, const std::string& sub);
  ApiResponse ServeImageArchive(const std::string& id);
  ApiResponse ServeReport(const ApiRequest& req, const std::string& name, const std::string& what);
  ApiResponse ArmFromBody(const std::string& body, const CallContext& ctx);
  ApiResponse ServeConsoleFile(const ApiRequest& req, const std::string& file);

  DaemonControl& control_;
  HostPolicy policy_;
  ThumbnailCache thumbnails_;
  AccessControl* access_ = nullptr;
  bool tls_ = false;
  std::string web_root_;
};

/// Options of the HTTP API from [daemon].
struct HttpApiOptions {
  std::vector<std::string> allowed_hosts;    // in addition to the defaults (see HostPolicy)
  std::vector<std::string> allowed_origins;  // extra allowed origins
  /// The live events GET /api/v1/events streams; null: that endpoint is 404.
  /// Borrowed: must outlive the HttpApi.
  EventHub* events = nullptr;
  /// The live view GET /api/v1/preview streams; null: that endpoint is 404.
  /// Borrowed: must outlive the HttpApi.
  PreviewHub* preview = nullptr;
  /// Accounts every request is checked against; null: no credentials needed
  /// (only allowed on a loopback address, see config). Borrowed.
  AccessControl* access = nullptr;
  /// PEM certificate chain and private key: the API is served over TLS.
  /// Both empty: plain HTTP.
  std::string tls_certificate_pem;
  std::string tls_key_pem;
  /// Folder of the console's static files (see ApiRouter::ServeConsole);
  /// empty: no console.
  std::string web_root;
};

class HttpApi {
 public:
  /// Largest accepted request body; larger ones get 413.
  static constexpr size_t kMaxBodyBytes = ApiLimits::kMaxBodyBytes;
  /// Open connections at most; the rig has an operator, a CLI and a few
  /// dashboards, so this leaves room for many hung clients beside them.
  static constexpr unsigned kMaxConnections = 512;
  /// Listen queue: a burst of clients waits here instead of being refused.
  static constexpr int kListenBacklog = 512;
  /// A connection with no traffic this long is closed (keep-alive included).
  static constexpr unsigned kIdleTimeoutSec = 10;
  /// A request's head and body must arrive within this from its first byte
  /// (or from the previous answer on a keep-alive connection): a client
  /// trickling one byte a second cannot hold a slot for longer.
  static constexpr std::chrono::seconds kReceiveLimit{10};
  /// An answer must be taken by the client within this (event streams excepted).
  static constexpr std::chrono::seconds kSendLimit{60};
  /// Event streams open at once at most: each holds a connection for as long
  /// as its client wants, so they must leave room for the operator's calls.
  static constexpr size_t kMaxEventStreams = 32;
  /// Live views (GET /api/v1/preview) open at once at most; each takes a
  /// frame of some tens of KB a few times a second.
  static constexpr size_t kMaxPreviewStreams = 8;
  /// Archive downloads (GET .../images.zip) at once at most.
  static constexpr size_t kMaxDownloads = 2;
  /// An event stream with nothing to send for this long gets a comment line,
  /// so proxies and the client see that it is alive.
  static constexpr std::chrono::seconds kEventKeepAlive{15};
  /// A request fully received must have started on the capture loop within
  /// this, or it is answered 503 and never runs.
  static constexpr std::chrono::seconds kRequestBudget{4};

  /// Borrows `control`, which must outlive this object. `port` 0 picks a free
  /// port at Start() (see port()).
  HttpApi(DaemonControl& control, std::string address, int port, HttpApiOptions options = {});
  ~HttpApi();
  HttpApi(const HttpApi&) = delete;
  HttpApi& operator=(const HttpApi&) = delete;

  /// Binds the address and starts serving. Fails (kConflict) when the port is
  /// taken, with the errno text as detail.
  Status Start();
  /// The bound port (the chosen one when constructed with 0); 0 before Start().
  int port() const { return bound_port_; }
  /// Stops accepting and closes every connection, whatever the clients do;
  /// waits for in-flight control calls (bounded by kRequestBudget). Idempotent.
  void Stop();

 private:
  struct Server;

  DaemonControl& control_;
  std::string address_;
  int requested_port_;
  HttpApiOptions options_;
  int bound_port_ = 0;
  std::unique_ptr<Server> server_;
};

}  // namespace aggscan
