// The worker's one parallel loop. The rig's computer has few cores (2 here,
// 4 on the ARM boards), so the loops are coarse: one item is a view, a grid
// slice or a vertex block, and the threads take the next item from a shared
// counter (items differ in cost: a view that sees more of the rock, a slice
// through its middle).
#pragma once

#include <algorithm>
#include <atomic>
#include <cstddef>
#include <exception>
#include <mutex>
#include <system_error>
#include <thread>
#include <type_traits>
#include <vector>

namespace aggscan {

/// Threads of the worker's loops that have no thread option of their own:
/// the rig computer's two cores (the worker runs below the capture daemon's
/// priority, so using both does not delay a capture). Per-thread slots are
/// sized by it.
inline constexpr int kWorkerThreads = 2;

/// Runs fn(i) for every i in [0, n), each exactly once, on up to `threads`
/// threads (the calling thread among them; threads <= 1 or n <= 1: in order,
/// on the calling thread). fn may instead take (i, t), t in [0, threads) the
/// thread running it, for per-thread accumulators. Returns when every item
/// is done. An exception thrown by fn stops the other threads from taking
/// new items and is rethrown here, on the calling thread (never
/// std::terminate from a worker thread), the first one if several threw.
template <typename Fn>
void ParallelFor(size_t n, int threads, Fn&& fn) {
  auto call = [&fn](size_t i, int t) {
    if constexpr (std::is_invocable_v<Fn&, size_t, int>) {
      fn(i, t);
    } else {
      fn(i);
    }
  };
  const int used =
      static_cast<int>(std::max<size_t>(1, std::min<size_t>(threads > 0 ? threads : 1, n)));
  if (used <= 1) {
    for (size_t i = 0; i < n; ++i) call(i, 0);
    return;
  }
  std::atomic<size_t> next{0};
  std::atomic<bool> failed{false};
  std::exception_ptr first;
  std::mutex first_mu;
  auto work = [&](int t) {
    for (size_t i = next++; i < n && !failed.load(std::memory_order_relaxed); i = next++) {
      try {
        call(i, t);
      } catch (...) {
        std::lock_guard<std::mutex> lock(first_mu);
        if (!first) first = std::current_exception();
        failed = true;
      }
    }
  };
  std::vector<std::thread> pool;
  pool.reserve(static_cast<size_t>(used - 1));
  for (int t = 1; t < used; ++t) {
    try {
      pool.emplace_back(work, t);
    } catch (const std::system_error&) {
      break;  // no thread to be had: the ones running (this one at least) do the rest
    }
  }
  work(0);
  for (auto& th : pool) th.join();
  if (first) std::rethrow_exception(first);
}

}  // namespace aggscan
