#include "daemon/event_hub.h"

#include <charconv>
#include <chrono>

#include "common/clock.h"

namespace aggscan {

EventHub::EventHub(size_t keep) : keep_(keep == 0 ? 1 : keep) {
  const auto us = std::chrono::duration_cast<std::chrono::microseconds>(
                      std::chrono::system_clock::now().time_since_epoch())
                      .count();
  run_ = std::to_string(us);
}

uint64_t EventHub::Publish(const std::string& type, nlohmann::json data) {
  data["utc"] = NowUtcString();
  uint64_t seq = 0;
  {
    std::lock_guard<std::mutex> lock(mu_);
    seq = ++last_seq_;
    // dump() escapes control characters: the data stays on one line, as SSE needs.
    events_.push_back(
        LiveEvent{seq, type, data.dump(-1, ' ', false, nlohmann::json::error_handler_t::replace)});
    while (events_.size() > keep_) events_.pop_front();
  }
  std::lock_guard<std::mutex> lock(listener_mu_);
  if (listener_) listener_();
  return seq;
}

void EventHub::SetListener(std::function<void()> listener) {
  std::lock_guard<std::mutex> lock(listener_mu_);
  listener_ = std::move(listener);
}

std::string EventHub::IdOf(uint64_t seq) const { return run_ + "-" + std::to_string(seq); }

std::optional<uint64_t> EventHub::SeqAfter(std::string_view id) const {
  const size_t dash = id.find('-');
  if (dash == std::string_view::npos || id.substr(0, dash) != run_) return std::nullopt;
  const std::string_view digits = id.substr(dash + 1);
  uint64_t seq = 0;
  const auto [end, ec] = std::from_chars(digits.data(), digits.data() + digits.size(), seq);
  if (ec != std::errc() || end != digits.data() + digits.size()) return std::nullopt;
  if (seq > last_seq()) return std::nullopt;
  return seq;
}

std::vector<LiveEvent> EventHub::Since(uint64_t seq, bool* gap) const {
  std::lock_guard<std::mutex> lock(mu_);
  std::vector<LiveEvent> out;
  *gap = !events_.empty() && events_.front().seq > seq + 1;
  for (const LiveEvent& e : events_)
    if (e.seq > seq) out.push_back(e);
  return out;
}

uint64_t EventHub::last_seq() const {
  std::lock_guard<std::mutex> lock(mu_);
  return last_seq_;
}

std::string FormatSse(const std::string& id, const std::string& type, const std::string& data) {
  std::string out;
  out.reserve(id.size() + type.size() + data.size() + 24);
  if (!id.empty()) out += "id: " + id + "\n";
  out += "event: " + type + "\n";
  out += "data: " + data + "\n\n";
  return out;
}

}  // namespace aggscan
