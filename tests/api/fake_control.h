// A DaemonControl for the API tests: records every call, answers with canned
// JSON, or with a configured error, or throws.
#pragma once

#include <arpa/inet.h>
#include <netinet/in.h>
#include <stdlib.h>
#include <sys/socket.h>
#include <unistd.h>

#include <atomic>
#include <fstream>
#include <map>
#include <mutex>
#include <optional>
#include <stdexcept>
#include <string>
#include <vector>

#include "daemon/control.h"

namespace aggscan::testing {

class FakeControl : public DaemonControl {
 public:
  nlohmann::json status = {{"state", "capturing"},
                           {"sample_id", "rock-12"},
                           {"side", 1},
                           {"view", 7},
                           {"views_per_side", 30},
                           {"sides", 2},
                           {"fault", nullptr},
                           {"status_line", "capturing rock-12 side 1 view 7/30"},
                           {"devices", {{"camera", {{"state", "ok"}}}, {"turntable", "ok"}}},
                           {"queue_depth", 2},
                           {"uptime_s", 3723}};
  nlohmann::json samples = nlohmann::json::array({{{"id", "rock-11"},
                                                   {"state", "done"},
                                                   {"created_utc", "2026-01-01T10:00:00.000Z"},
                                                   {"sides_done", 2},
                                                   {"views", 60}},
                                                  {{"id", "rock-12"},
                                                   {"state", "capturing"},
                                                   {"created_utc", "2026-01-01T10:05:00.000Z"},
                                                   {"sides_done", 0},
                                                   {"views", 7}}});

  std::optional<Error> fail;           // returned by every Result-returning method when set
  ArmRequest last_arm;                 // the last Arm's request (under mu_)
  std::atomic<bool> throw_all{false};  // every method throws std::runtime_error

  std::vector<std::string> Calls() {
    std::lock_guard<std::mutex> lock(mu_);
    return calls_;
  }
  ArmRequest LastArm() {
    std::lock_guard<std::mutex> lock(mu_);
    return last_arm;
  }
  size_t CallCount() {
    std::lock_guard<std::mutex> lock(mu_);
    return calls_.size();
  }

  nlohmann::json health = {
      {"status", "ok"},
      {"state", "idle"},
      {"devices", {{"camera", {{"state", "ok"}, {"healthy", true}, {"message", "ok"}}}}}};
  nlohmann::json GetHealth() override {
    Record("health");
    if (throw_all) throw std::runtime_error("fake failure");
    return health;
  }

  nlohmann::json GetStatus() override {
    Record("status");
    return status;
  }
  /// Every state-changing call's context, in order.
  std::vector<CallContext> Contexts() {
    std::lock_guard<std::mutex> lock(mu_);
    return contexts_;
  }

  using DaemonControl::Arm;
  Result<nlohmann::json> Arm(const ArmRequest& req, const CallContext& ctx) override {
    const std::string& id = req.id;
    {
      std::lock_guard<std::mutex> lock(mu_);
      last_arm = req;
    }
    Record("arm:" + id, &ctx);
    if (fail) return *fail;
    return nlohmann::json{{"state", "armed"}, {"sample_id", id}};
  }
  Result<nlohmann::json> ArmCalibration(const CallContext& ctx) override {
    Record("calibrate", &ctx);
    if (fail) return *fail;
    return nlohmann::json{{"state", "armed"}, {"sample_id", "calibration-20260101T100000Z"}};
  }
  Result<nlohmann::json> Press(const std::string& source, const CallContext& ctx) override {
    Record("press:" + source, &ctx);
    if (fail) return *fail;
    return nlohmann::json{{"state", "homing"}, {"sample_id", "rock-12"}};
  }
  Result<nlohmann::json> Abort(const CallContext& ctx) override {
    Record("abort", &ctx);
    if (fail) return *fail;
    return nlohmann::json{{"state", "idle"}};
  }
  Result<nlohmann::json> Reset(const CallContext& ctx) override {
    Record("reset", &ctx);
    if (fail) return *fail;
    return nlohmann::json{{"state", "idle"}};
  }
  nlohmann::json sample_result;  // GetSample's "result" when set
  nlohmann::json sample_meta;    // GetSample's "meta" when set
  nlohmann::json last_meta_doc;  // the last EditMeta's request body (under mu_)
  Result<nlohmann::json> ListSamples() override {
    Record("list");
    if (fail) return *fail;
    return samples;
  }
  Result<nlohmann::json> GetSample(const std::string& id) override {
    Record("get:" + id);
    if (fail) return *fail;
    nlohmann::json views = nlohmann::json::array();
    for (int v = 1; v <= 30; ++v) views.push_back({{"view", v}, {"angle_deg", 12.0 * (v - 1)}});
    nlohmann::json out{{"id", id},
                       {"state", "done"},
                       {"created_utc", "2026-01-01T10:00:00.000Z"},
                       {"sides", {{{"side", 1}, {"job", "done"}, {"views", views}}}}};
    if (!sample_result.is_null()) out["result"] = sample_result;
    if (!sample_meta.is_null()) out["meta"] = sample_meta;
    return out;
  }
  Result<nlohmann::json> Retry(const std::string& id) override {
    Record("retry:" + id);
    if (fail) return *fail;
    return nlohmann::json{
        {"sample_id", id},
        {"requeued", 1},
        {"jobs", {{{"side", 1}, {"state", "queued"}, {"attempts", 0}, {"error", ""}}}}};
  }
  Result<nlohmann::json> EditMeta(const std::string& id, const nlohmann::json& doc,
                                  const std::string& by, const CallContext& ctx) override {
    Record("meta:" + id + ":" + by, &ctx);
    {
      std::lock_guard<std::mutex> lock(mu_);
      last_meta_doc = doc;
    }
    if (fail) return *fail;
    return nlohmann::json{{"id", id}, {"meta", doc}, {"changed", nlohmann::json::object()}};
  }
  nlohmann::json batches = nlohmann::json::object();  // name -> GetBatch's answer
  Result<nlohmann::json> ListBatches() override {
    Record("batches");
    if (fail) return *fail;
    nlohmann::json out = {{"batches", nlohmann::json::array()}};
    for (const auto& [name, b] : batches.items()) out["batches"].push_back(b);
    return out;
  }
  Result<nlohmann::json> GetBatch(const std::string& name) override {
    Record("batch:" + name);
    if (fail) return *fail;
    if (!batches.contains(name))
      return MakeError(ErrorClass::kNotFound, "no batch \"" + name + "\"");
    return batches[name];
  }
  Result<nlohmann::json> PutBatch(const std::string& name, const nlohmann::json& doc) override {
    Record("put-batch:" + name);
    if (fail) return *fail;
    nlohmann::json b = doc;
    b["name"] = name;
    b["members"] = nlohmann::json::array();
    batches[name] = b;
    return b;
  }
  Result<nlohmann::json> DeleteBatch(const std::string& name) override {
    Record("delete-batch:" + name);
    if (fail) return *fail;
    batches.erase(name);
    return nlohmann::json{{"deleted", name}};
  }
  std::vector<ReportRequest> reports;     // every MakeReport's request
  std::vector<std::string> reports_made;  // the files it made
  std::optional<Error> report_fail;       // MakeReport's answer when set
  Result<std::string> MakeReport(const ReportRequest& r) override {
    Record("report:" + r.kind + ":" + r.name + ":" + r.format + ":" + r.spec);
    {
      std::lock_guard<std::mutex> lock(mu_);
      reports.push_back(r);
    }
    if (report_fail) return *report_fail;
    // As the real one: a file in a folder of its own, which the caller removes.
    char tmpl[] = "/tmp/aggscan-fake-report-XXXXXX";
    if (::mkdtemp(tmpl) == nullptr) return MakeError(ErrorClass::kIo, "mkdtemp");
    const std::string path = std::string(tmpl) + "/report." + r.format;
    std::ofstream(path) << (r.format == "pdf" ? "%PDF-1.7 fake" : "<html>fake</html>");
    std::lock_guard<std::mutex> lock(mu_);
    reports_made.push_back(path);
    return path;
  }
  std::map<std::string, std::string> result_files;  // "id/name" -> path
  Result<std::string> ResultFile(const std::string& id, const std::string& name) override {
    Record("result:" + id + "/" + name);
    if (fail) return *fail;
    auto it = result_files.find(id + "/" + name);
    if (it == result_files.end())
      return MakeError(ErrorClass::kNotFound, "no results yet for " + id);
    return it->second;
  }
  std::map<std::string, std::string> view_files;  // "id/side/view/image|mask" -> path
  Result<std::string> ViewFile(const std::string& id, int side, int view,
                               ViewFileKind kind) override {
    const std::string key = id + "/" + std::to_string(side) + "/" + std::to_string(view) + "/" +
                            (kind == ViewFileKind::kMask ? "mask" : "image");
    Record("view:" + key);
    if (fail) return *fail;
    auto it = view_files.find(key);
    if (it == view_files.end()) return MakeError(ErrorClass::kNotFound, "no such view: " + key);
    return it->second;
  }
  std::map<std::string, std::vector<ArchiveMember>> archives;  // id -> members
  Result<std::vector<ArchiveMember>> ImageArchive(const std::string& id) override {
    Record("archive:" + id);
    if (fail) return *fail;
    auto it = archives.find(id);
    if (it == archives.end()) return MakeError(ErrorClass::kNotFound, "no sample " + id);
    return it->second;
  }
  std::string Metrics() override {
    Record("metrics");
    return "# HELP aggscan_up 1 when the daemon runs\n# TYPE aggscan_up gauge\naggscan_up 1\n";
  }

 private:
  void Record(std::string call, const CallContext* ctx = nullptr) {
    if (throw_all) throw std::runtime_error("fake failure in " + call);
    std::lock_guard<std::mutex> lock(mu_);
    calls_.push_back(std::move(call));
    if (ctx != nullptr) contexts_.push_back(*ctx);
  }

  std::mutex mu_;
  std::vector<std::string> calls_;
  std::vector<CallContext> contexts_;
};

/// A loopback port with nothing listening on it (bound, then released).
inline int UnusedPort() {
  const int fd = ::socket(AF_INET, SOCK_STREAM, 0);
  sockaddr_in addr{};
  addr.sin_family = AF_INET;
  addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  addr.sin_port = 0;
  ::bind(fd, reinterpret_cast<sockaddr*>(&addr), sizeof addr);
  socklen_t len = sizeof addr;
  ::getsockname(fd, reinterpret_cast<sockaddr*>(&addr), &len);
  ::close(fd);
  return ntohs(addr.sin_port);
}

}  // namespace aggscan::testing
