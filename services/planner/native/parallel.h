// Shared by the planner's native kernels (va_counts.cc, rollout.cc).
#pragma once

#include <algorithm>
#include <cstdint>
#include <thread>
#include <vector>

namespace vamppi {

// Runs f(begin, end) over `items` split into min(threads, items) contiguous ranges, one per
// thread, the first on the calling thread; returns when all are done.
template <class F>
void parallel_ranges(int64_t items, int64_t threads, const F& f) {
  const int64_t n = std::max<int64_t>(1, std::min<int64_t>(threads, items));
  std::vector<std::thread> pool;
  for (int64_t t = 1; t < n; ++t) pool.emplace_back(f, t * items / n, (t + 1) * items / n);
  f(int64_t{0}, items / n);
  for (auto& th : pool) th.join();
}

}  // namespace vamppi
