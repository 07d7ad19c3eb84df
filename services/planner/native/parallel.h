// Shared by the planner's native kernels (va_counts.cc, rollout.cc).
#pragma once

#include <algorithm>
#include <atomic>
#include <cstdint>
#include <thread>
#include <vector>

namespace vamppi {

// Hands out [begin, end) ranges of at most `grain` of `items`, in order, to any thread.
class Ranges {
 public:
  Ranges(int64_t items, int64_t grain) : items_(items), grain_(std::max<int64_t>(1, grain)) {}
  bool next(int64_t& begin, int64_t& end) {
    begin = next_.fetch_add(grain_, std::memory_order_relaxed);
    end = std::min(begin + grain_, items_);
    return begin < items_;
  }

 private:
  std::atomic<int64_t> next_{0};
  const int64_t items_, grain_;
};

// Runs worker(ranges) on min(threads, items / grain) threads, the first on the calling
// thread, each pulling ranges until none is left; returns when all are done. Ranges, not
// halves: a thread the OS preempts (the sensor and the mapper share the cores) holds the
// others up by one range at most, not by its whole share.
template <class F>
void parallel_ranges(int64_t items, int64_t threads, int64_t grain, const F& worker) {
  Ranges ranges(items, grain);
  const int64_t n = std::max<int64_t>(1, std::min(threads, (items + grain - 1) / grain));
  std::vector<std::thread> pool;
  for (int64_t t = 1; t < n; ++t) pool.emplace_back([&ranges, &worker] { worker(ranges); });
  worker(ranges);
  for (auto& th : pool) th.join();
}

}  // namespace vamppi
