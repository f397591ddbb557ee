// The worker's one parallel loop: every item once, per-thread slots, and an
// exception from an item comes back to the caller instead of ending the
// process.
#include "pipeline/core/parallel_for.h"

#include <gtest/gtest.h>

#include <atomic>
#include <chrono>
#include <mutex>
#include <set>
#include <stdexcept>
#include <thread>
#include <vector>

namespace aggscan {
namespace {

TEST(ParallelFor, EveryItemExactlyOnce) {
  for (int threads : {0, 1, 2, 3, 8}) {
    for (size_t n : {0u, 1u, 2u, 7u, 1000u}) {
      std::vector<std::atomic<int>> seen(n);
      ParallelFor(n, threads, [&](size_t i) { ++seen[i]; });
      for (size_t i = 0; i < n; ++i) EXPECT_EQ(seen[i].load(), 1) << i << " of " << n;
    }
  }
}

TEST(ParallelFor, ThreadIndexSelectsAPerThreadSlot) {
  constexpr int kThreads = 3;
  std::vector<long> sums(kThreads, 0);
  std::set<std::thread::id> ids;
  std::mutex mu;
  ParallelFor(3000, kThreads, [&](size_t i, int t) {
    ASSERT_GE(t, 0);
    ASSERT_LT(t, kThreads);
    sums[t] += static_cast<long>(i);  // no lock: slot t is this thread's alone
    std::lock_guard<std::mutex> lock(mu);
    ids.insert(std::this_thread::get_id());
  });
  EXPECT_EQ(sums[0] + sums[1] + sums[2], 3000L * 2999 / 2);
  EXPECT_LE(ids.size(), static_cast<size_t>(kThreads));
}

TEST(ParallelFor, OneThreadRunsInOrderOnTheCaller) {
  std::vector<size_t> order;
  const auto caller = std::this_thread::get_id();
  ParallelFor(5, 1, [&](size_t i) {
    EXPECT_EQ(std::this_thread::get_id(), caller);
    order.push_back(i);
  });
  EXPECT_EQ(order, (std::vector<size_t>{0, 1, 2, 3, 4}));
}

TEST(ParallelFor, AnExceptionReachesTheCallerAndStopsNewItems) {
  // Item 0 throws at once; every other item takes 1 ms, so without the stop
  // the other thread would run on for ~5 s. A stop reaches it within the
  // item it is in, whichever thread took item 0 and however the two are
  // scheduled, short of a stall of seconds.
  std::atomic<int> ran{0};
  try {
    ParallelFor(10000, 2, [&](size_t i) {
      ++ran;
      if (i == 0) throw std::runtime_error("item 0 failed");
      std::this_thread::sleep_for(std::chrono::milliseconds(1));
    });
    FAIL() << "no exception";
  } catch (const std::runtime_error& e) {
    EXPECT_STREQ(e.what(), "item 0 failed");
  }
  EXPECT_LT(ran.load(), 5000);
}

}  // namespace
}  // namespace aggscan
