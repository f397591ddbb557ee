// The daemon's live events (GET /api/v1/events, Server-Sent Events): state
// changes, each view stored, the worker's stage and progress, device health
// changes and faults. The capture loop publishes; each open event stream
// reads what it has not sent yet. The last events are kept, so a client that
// reconnects with Last-Event-ID gets what it missed; ids carry the daemon's
// start, so an id from an earlier run is recognised as such (the client is
// told to reload instead of being given a wrong continuation).
#pragma once

#include <cstdint>
#include <deque>
#include <functional>
#include <mutex>
#include <nlohmann/json.hpp>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

namespace aggscan {

struct LiveEvent {
  uint64_t seq = 0;  // 1, 2, ... in this run
  std::string type;  // state | view | worker | health | fault
  std::string data;  // one line of JSON
};

class EventHub {
 public:
  /// Keeps the last `keep` events for reconnecting clients.
  explicit EventHub(size_t keep = 2048);

  /// Adds an event (any thread); returns its seq. "utc" is added to `data`.
  uint64_t Publish(const std::string& type, nlohmann::json data);

  /// The SSE id of event `seq`: "<run>-<seq>".
  std::string IdOf(uint64_t seq) const;
  /// The seq to continue after for a Last-Event-ID; nullopt when the id is
  /// not one of this run's (an earlier run's, a later seq, or garbage).
  std::optional<uint64_t> SeqAfter(std::string_view last_event_id) const;

  /// The events after `seq`, oldest first; `*gap` true when some of them are
  /// no longer kept.
  std::vector<LiveEvent> Since(uint64_t seq, bool* gap) const;
  uint64_t last_seq() const;

  /// Called after every publish, on the publisher's thread, with no lock of
  /// the events held; an empty one removes it (no call runs after that).
  void SetListener(std::function<void()> listener);

 private:
  const size_t keep_;
  std::string run_;  // the daemon's start, in microseconds since the epoch
  mutable std::mutex mu_;
  std::deque<LiveEvent> events_;
  uint64_t last_seq_ = 0;
  std::mutex listener_mu_;
  std::function<void()> listener_;
};

/// One event in the text/event-stream format ("id:", "event:", "data:" and a
/// blank line).
std::string FormatSse(const std::string& id, const std::string& type, const std::string& data);

}  // namespace aggscan
