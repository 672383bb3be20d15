// Dynamic task distribution for the CPU kernels.
//
// Why not at::parallel_for's static split: it hands every thread one contiguous share up front, so a call lasts as
// long as the slowest thread's share.  When another process holds a core, the thread on that core runs at half
// speed (or not at all for a time slice) and every parallel region waits for it; on a quiet machine the same split
// leaves threads idle whenever tasks differ in cost (entities differ in neighbour count).  Here every thread claims
// the next unstarted task from one atomic counter until none is left, so a slow thread simply takes fewer tasks and
// the region ends one task after the last claim.  Tasks are listed largest first (callers order them), which is the
// classic longest-processing-time rule: the tail is one small task.
//
// A call may list several independent task lists ("phases") at once: one parallel region, one join, instead of one
// region per list -- every region costs a wake-up and a join that waits for the slowest thread.
//
// The thread count is the user's (at::get_num_threads()); only calls below a work threshold run on the calling
// thread, where a region would cost more than it saves.  Results never depend on which thread runs a task: a task
// writes its own outputs, and the slot index it receives only selects scratch memory.
#pragma once

#include <ATen/Parallel.h>

#include <algorithm>
#include <atomic>
#include <cstdint>
#include <initializer_list>

namespace modi_ext {
namespace cpu_tasks {

// One list of independent tasks: call(ctx, task, slot) for task in [0, n).
struct Phase {
  int64_t n = 0;
  const void* ctx = nullptr;
  void (*call)(const void*, int64_t, int) = nullptr;
};

// A phase running f(task, slot); f must outlive the run_phases call that uses it.
template <class F>
Phase phase(int64_t n, const F& f) {
  return Phase{n, &f, [](const void* c, int64_t t, int s) { (*static_cast<const F*>(c))(t, s); }};
}

// Slots a task may receive: scratch arrays indexed by slot need this many entries.
inline int slots() { return at::in_parallel_region() ? 1 : std::max(1, at::get_num_threads()); }

// Run every task of every phase once.  parallel=false (small work) runs them in order on the calling thread.
inline void run_phases(const Phase* phases, size_t n_phases, bool parallel) {
  int64_t total = 0;
  for (size_t i = 0; i < n_phases; ++i) total += phases[i].n;
  if (total <= 0) return;
  auto exec = [&](int64_t t, int slot) {
    for (size_t i = 0; i < n_phases; ++i) {
      const Phase& p = phases[i];
      if (t < p.n) {
        p.call(p.ctx, t, slot);
        return;
      }
      t -= p.n;
    }
  };
  const int nt = slots();
  if (!parallel || nt <= 1 || total == 1) {
    for (int64_t t = 0; t < total; ++t) exec(t, 0);
    return;
  }
  std::atomic<int64_t> next{0};
  // one chunk per thread; inside it, tasks are claimed one at a time
  at::parallel_for(0, nt, 1, [&](int64_t, int64_t) {
    const int slot = std::min(at::get_thread_num(), nt - 1);
    for (;;) {
      const int64_t t = next.fetch_add(1, std::memory_order_relaxed);
      if (t >= total) break;
      exec(t, slot);
    }
  });
}

inline void run_phases(std::initializer_list<Phase> phases, bool parallel) {
  run_phases(phases.begin(), phases.size(), parallel);
}

}  // namespace cpu_tasks
}  // namespace modi_ext
