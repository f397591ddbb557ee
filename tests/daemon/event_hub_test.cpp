// The live events' store: ids that name their run, replay after a
// Last-Event-ID, a gap said when the kept window has moved past it, and the
// SSE text format.
#include "daemon/event_hub.h"

#include <gtest/gtest.h>

#include <nlohmann/json.hpp>

namespace aggscan {
namespace {

TEST(EventHub, ReplaysWhatFollowsAnIdOfThisRun) {
  EventHub hub(4);
  int woken = 0;
  hub.SetListener([&woken] { ++woken; });
  for (int i = 1; i <= 3; ++i)
    EXPECT_EQ(hub.Publish("view", {{"number", i}}), static_cast<uint64_t>(i));
  EXPECT_EQ(woken, 3);
  const std::string id1 = hub.IdOf(1);
  auto after = hub.SeqAfter(id1);
  ASSERT_TRUE(after.has_value());
  EXPECT_EQ(*after, 1u);
  bool gap = true;
  auto rest = hub.Since(*after, &gap);
  EXPECT_FALSE(gap);
  ASSERT_EQ(rest.size(), 2u);
  EXPECT_EQ(rest[0].seq, 2u);
  EXPECT_EQ(rest[0].type, "view");
  auto data = nlohmann::json::parse(rest[0].data);
  EXPECT_EQ(data["number"], 2);
  EXPECT_TRUE(data.contains("utc"));
  EXPECT_TRUE(hub.Since(3, &gap).empty());

  // Ids of another run, from the future, or not ids at all.
  const std::string run = id1.substr(0, id1.find('-'));
  EXPECT_FALSE(hub.SeqAfter("1-1").has_value());
  EXPECT_FALSE(hub.SeqAfter(run + "-4").has_value());
  EXPECT_FALSE(hub.SeqAfter(run + "-x").has_value());
  EXPECT_FALSE(hub.SeqAfter(run + "-2x").has_value());
  EXPECT_FALSE(hub.SeqAfter("").has_value());
  EXPECT_EQ(hub.SeqAfter(run + "-0"), std::optional<uint64_t>(0));

  // Four are kept: after six, what followed event 1 is partly gone.
  for (int i = 4; i <= 6; ++i) hub.Publish("view", {{"number", i}});
  rest = hub.Since(1, &gap);
  EXPECT_TRUE(gap);
  ASSERT_EQ(rest.size(), 4u);
  EXPECT_EQ(rest.front().seq, 3u);
  rest = hub.Since(2, &gap);
  EXPECT_FALSE(gap);

  hub.SetListener({});
  hub.Publish("state", nlohmann::json::object());
  EXPECT_EQ(woken, 6);
}

TEST(EventHub, DataStaysOnOneLine) {
  EventHub hub;
  hub.Publish("fault", {{"message", "line one\nline two\r\n"}});
  bool gap = false;
  const auto e = hub.Since(0, &gap);
  ASSERT_EQ(e.size(), 1u);
  EXPECT_EQ(e[0].data.find('\n'), std::string::npos) << e[0].data;
  EXPECT_EQ(e[0].data.find('\r'), std::string::npos) << e[0].data;
  EXPECT_EQ(FormatSse("r-1", "fault", e[0].data),
            "id: r-1\nevent: fault\ndata: " + e[0].data + "\n\n");
  EXPECT_EQ(FormatSse("", "reset", "{}"), "event: reset\ndata: {}\n\n");
}

}  // namespace
}  // namespace aggscan
