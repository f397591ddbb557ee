// The daemon's HTTP JSON API: a thin translation layer between HTTP requests
// and DaemonControl. It owns no capture state; every call goes through the
// DaemonControl it borrows, which is safe to call from cpp-httplib's worker
// threads.
//
//   GET  /api/v1/status          → DaemonControl::GetStatus()
//   GET  /api/v1/health          → GetHealth(): 200 when every device is ok, else 503 (same body)
//   POST /api/v1/samples         {"id": "..."} → Arm(id)
//   GET  /api/v1/samples         → ListSamples()
//   GET  /api/v1/samples/{id}    → GetSample(id)
//   POST /api/v1/button          → Press("api")
//   POST /api/v1/abort           → Abort()
//   POST /api/v1/reset           → Reset()
//   GET  /metrics                → Metrics() (Prometheus text format 0.0.4)
//
// Every answer except /metrics is JSON. Errors are
// {"error": {"class": "<ErrorClassName>", "message": "..."}} with the HTTP
// status from HttpStatusFor(). Input is never trusted: sample ids are checked
// with layout::IsValidSampleId after percent-decoding, bodies are capped at
// kMaxBodyBytes, and a throwing handler answers 500 instead of taking the
// daemon down.
#pragma once

#include <atomic>
#include <memory>
#include <string>
#include <thread>

#include "common/error.h"
#include "daemon/control.h"

namespace httplib {
class Server;
}

namespace aggscan {

/// HTTP status for an error class: invalid_argument 400, not_found 404,
/// conflict/invalid_state 409, device errors 503, disk_full 507, others 500.
int HttpStatusFor(ErrorClass cls);

class HttpApi {
 public:
  /// Largest accepted request body; larger ones get 413.
  static constexpr size_t kMaxBodyBytes = 64 * 1024;

  /// Borrows `control`, which must outlive this object. `port` 0 picks a free
  /// port at Start() (see port()).
  HttpApi(DaemonControl& control, std::string address, int port);
  ~HttpApi();
  HttpApi(const HttpApi&) = delete;
  HttpApi& operator=(const HttpApi&) = delete;

  /// Binds the address and starts serving on cpp-httplib's own thread pool.
  /// Fails (kConflict) when the port is taken, with the errno text as detail.
  Status Start();
  /// The bound port (the chosen one when constructed with 0); 0 before Start().
  int port() const { return bound_port_; }
  /// Stops accepting, waits for in-flight requests. Idempotent.
  void Stop();

 private:
  struct Impl;

  DaemonControl& control_;
  std::string address_;
  int requested_port_;
  int bound_port_ = 0;
  std::unique_ptr<httplib::Server> server_;
  std::unique_ptr<Impl> impl_;
  std::thread listener_;
  std::atomic<bool> listener_done_{false};
};

}  // namespace aggscan
