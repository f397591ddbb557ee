// GET /api/v1/events on the real aggscand and aggscan-worker: a capture and
// its reconstruction followed by Server-Sent Events alone, and a reconnect
// with Last-Event-ID that gets exactly what followed that event.
#include <gtest/gtest.h>

#include <atomic>
#include <map>
#include <mutex>
#include <set>

#include "process.h"

namespace aggscan::test {
namespace {

using nlohmann::json;

struct Sse {
  std::string id;
  std::string type;
  json data;
};

// Reads an event stream until `enough` says so (or the stream ends); the
// events as they came, comments left out.
class SseReader {
 public:
  SseReader(int port, std::vector<std::pair<std::string, std::string>> headers = {})
      : port_(port), headers_(std::move(headers)) {}

  // Returns the HTTP status (0: no answer).
  template <typename Enough>
  int Run(Enough enough, int read_timeout_s = 60) {
    httplib::Client c("127.0.0.1", port_);
    c.set_read_timeout(read_timeout_s, 0);
    httplib::Headers h;
    for (const auto& [k, v] : headers_) h.emplace(k, v);
    std::string pending;
    auto r = c.Get(
        "/api/v1/events", h,
        [&](const httplib::Response& resp) {
          status_ = resp.status;
          content_type_ = resp.get_header_value("Content-Type");
          return resp.status == 200;
        },
        [&](const char* data, size_t len) {
          pending.append(data, len);
          size_t end;
          while ((end = pending.find("\n\n")) != std::string::npos) {
            const std::string block = pending.substr(0, end);
            pending.erase(0, end + 2);
            Sse e;
            bool any = false;
            size_t pos = 0;
            while (pos <= block.size()) {
              size_t nl = block.find('\n', pos);
              if (nl == std::string::npos) nl = block.size();
              const std::string line = block.substr(pos, nl - pos);
              pos = nl + 1;
              if (line.rfind("id: ", 0) == 0) e.id = line.substr(4);
              if (line.rfind("event: ", 0) == 0) e.type = line.substr(7), any = true;
              if (line.rfind("data: ", 0) == 0)
                e.data = json::parse(line.substr(6), nullptr, false);
              if (line.rfind(": ", 0) == 0) opened_ = true;
            }
            if (any) {
              std::lock_guard<std::mutex> lock(mu_);
              events_.push_back(std::move(e));
            }
          }
          std::lock_guard<std::mutex> lock(mu_);
          return !enough(events_);
        });
    return r ? r->status : status_;
  }

  std::vector<Sse> events() {
    std::lock_guard<std::mutex> lock(mu_);
    return events_;
  }
  bool opened() const { return opened_.load(); }
  const std::string& content_type() const { return content_type_; }

 private:
  int port_;
  std::vector<std::pair<std::string, std::string>> headers_;
  std::mutex mu_;
  std::vector<Sse> events_;
  std::atomic<bool> opened_{false};
  int status_ = 0;
  std::string content_type_;
};

uint64_t SeqOf(const std::string& id) { return std::stoull(id.substr(id.find('-') + 1)); }

TEST(EventsScenario, CaptureAndReconstructionFollowedByEventsAndReplayedAfterAReconnect) {
  TempDir t;
  const std::string cfg =
      WriteConfig(t.path(), "[worker]\nheartbeat_interval = \"200ms\"\nsilent_after = \"60s\"\n");
  Daemon d(cfg, t.path());
  ASSERT_TRUE(d.ok()) << ReadAll(d.log());

  SseReader live(d.port());
  std::atomic<bool> stop{false};
  int live_status = -1;
  std::thread reader(
      [&] { live_status = live.Run([&](const std::vector<Sse>&) { return stop.load(); }); });
  for (int i = 0; i < 500 && !live.opened(); ++i)
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  ASSERT_TRUE(live.opened()) << ReadAll(d.log());
  EXPECT_EQ(live.content_type(), "text/event-stream");

  // The live view while idle: an MJPEG stream whose frames are JPEGs.
  {
    httplib::Client c("127.0.0.1", d.port());
    c.set_read_timeout(20, 0);
    std::string type, body;
    auto r = c.Get(
        "/api/v1/preview", httplib::Headers{},
        [&](const httplib::Response& resp) {
          type = resp.get_header_value("Content-Type");
          return resp.status == 200;
        },
        [&](const char* data, size_t len) {
          body.append(data, len);
          size_t parts = 0;
          for (size_t at = body.find("--aggscanframe\r\n"); at != std::string::npos;
               at = body.find("--aggscanframe\r\n", at + 1))
            ++parts;
          return parts < 3;  // two whole frames, and the start of a third
        });
    EXPECT_EQ(type, "multipart/x-mixed-replace; boundary=aggscanframe");
    const size_t first = body.find("\r\n\r\n");
    ASSERT_NE(first, std::string::npos) << body.substr(0, 200);
    EXPECT_EQ(body.substr(first + 4, 2), "\xff\xd8");  // a JPEG's SOI marker
  }

  int code = 0;
  d.Post("/api/v1/samples", R"({"id": "rock-e"})", &code);
  ASSERT_EQ(code, 200);
  d.Post("/api/v1/button", "{}", &code);
  json last;
  ASSERT_TRUE(
      d.WaitFor([](const json& s) { return s.value("state", "") == "awaiting_pose"; }, 60, &last))
      << last.dump();
  d.Post("/api/v1/button", "{}", &code);
  ASSERT_TRUE(d.WaitFor([](const json& s) { return s.value("state", "") == "idle"; }, 60, &last))
      << last.dump();
  const int wrc =
      WaitExit(Spawn({Bin("pipeline/aggscan-worker"), "--state-dir", t.path() + "/state",
                      "--config", cfg, "--once", "--poll-ms", "20"},
                     t.path() + "/worker.log"));
  ASSERT_EQ(wrc, 0) << ReadAll(t.path() + "/worker.log");
  // The worker's last report (stopped) reaches the events within 0.5 s.
  auto saw_worker_stop = [&] {
    for (const Sse& e : live.events())
      if (e.type == "worker" && e.data.value("state", "") == "stopped") return true;
    return false;
  };
  for (int i = 0; i < 300 && !saw_worker_stop(); ++i)
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  const std::vector<Sse> got = live.events();
  ASSERT_TRUE(saw_worker_stop()) << got.size() << " events";

  // Ids: of one run, strictly increasing, none skipped.
  for (size_t i = 1; i < got.size(); ++i)
    EXPECT_EQ(SeqOf(got[i].id), SeqOf(got[i - 1].id) + 1) << i;
  // Every view, in order, with its file.
  std::vector<std::pair<int, int>> views;
  std::vector<std::string> states;
  std::set<std::string> worker_stages;
  for (const Sse& e : got) {
    ASSERT_TRUE(e.data.is_object()) << e.type;
    EXPECT_TRUE(e.data.contains("utc"));
    if (e.type == "view") {
      EXPECT_EQ(e.data["sample_id"], "rock-e");
      views.emplace_back(e.data["side"].get<int>(), e.data["number"].get<int>());
      EXPECT_EQ(e.data["image"], "side" + std::to_string(e.data["side"].get<int>()) + "/view_" +
                                     (e.data["view"].get<int>() < 10 ? "00" : "0") +
                                     std::to_string(e.data["view"].get<int>()) + ".jpg");
    } else if (e.type == "state") {
      states.push_back(e.data["state"].get<std::string>());
    } else if (e.type == "worker" && e.data.value("state", "") == "busy") {
      EXPECT_EQ(e.data["job"]["sample_id"], "rock-e");
      worker_stages.insert(e.data["stage"].get<std::string>());
    }
  }
  ASSERT_EQ(views.size(), 60u);
  for (int i = 0; i < 60; ++i) EXPECT_EQ(views[i], std::make_pair(1 + i / 30, 1 + i % 30)) << i;
  ASSERT_FALSE(states.empty());
  EXPECT_EQ(states.front(), "armed");
  EXPECT_NE(std::find(states.begin(), states.end(), "awaiting_pose"), states.end());
  EXPECT_EQ(states.back(), "idle");
  bool masks = false;
  for (const std::string& st : worker_stages) masks = masks || st.rfind("masks side ", 0) == 0;
  EXPECT_TRUE(masks) << ::testing::PrintToString(worker_stages);

  // Each view event names where the view and its thumbnail are served; the
  // worker's mask of it is served beside them.
  {
    const Sse* view = nullptr;
    for (const Sse& e : got)
      if (e.type == "view" && view == nullptr) view = &e;
    ASSERT_NE(view, nullptr);
    EXPECT_EQ(view->data["url"], "/api/v1/samples/rock-e/sides/1/views/0");
    EXPECT_EQ(view->data["thumbnail"], "/api/v1/samples/rock-e/sides/1/views/0/thumbnail");
    httplib::Client c("127.0.0.1", d.port());
    for (const std::string suffix : {"", "/thumbnail", "/mask"}) {
      auto r = c.Get(view->data["url"].get<std::string>() + suffix);
      ASSERT_TRUE(r) << suffix;
      EXPECT_EQ(r->status, 200) << suffix << ": " << r->body.substr(0, 300);
      EXPECT_EQ(r->get_header_value("Content-Type"),
                suffix == "/mask" ? "image/png" : "image/jpeg");
      EXPECT_GT(r->body.size(), 100u) << suffix;
    }
    auto none = c.Get("/api/v1/samples/rock-e/sides/1/views/30");
    ASSERT_TRUE(none);
    EXPECT_EQ(none->status, 404);
  }

  // A reconnect with the id of the 10th event gets the 11th onwards, the same.
  const size_t k = 10;
  SseReader again(d.port(), {{"Last-Event-ID", got[k - 1].id}});
  const size_t want = got.size() - k;
  EXPECT_EQ(again.Run([&](const std::vector<Sse>& e) { return e.size() >= want; }, 10), 200);
  const std::vector<Sse> replay = again.events();
  ASSERT_GE(replay.size(), want);
  for (size_t i = 0; i < want; ++i) {
    EXPECT_EQ(replay[i].id, got[k + i].id) << i;
    EXPECT_EQ(replay[i].type, got[k + i].type) << i;
    EXPECT_EQ(replay[i].data, got[k + i].data) << i;
  }

  // An id from an earlier run: told to reload.
  SseReader stale(d.port(), {{"Last-Event-ID", "1-3"}});
  EXPECT_EQ(stale.Run([](const std::vector<Sse>& e) { return !e.empty(); }, 10), 200);
  ASSERT_FALSE(stale.events().empty());
  EXPECT_EQ(stale.events()[0].type, "reset");
  EXPECT_NE(stale.events()[0].data["reason"].get<std::string>().find("GET /api/v1/status"),
            std::string::npos);

  // A foreign Host is refused as on every endpoint.
  SseReader rebind(d.port(), {{"Host", "evil.example"}});
  EXPECT_EQ(rebind.Run([](const std::vector<Sse>&) { return true; }, 10), 421);

  // Stopping the daemon ends the stream it holds open.
  stop = true;
  EXPECT_EQ(d.Stop(), 0);
  reader.join();
  EXPECT_EQ(live_status, 200);
}

}  // namespace
}  // namespace aggscan::test
