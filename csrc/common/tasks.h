// Dynamic task distribution for the CPU kernels.
//
// Why not at::parallel_for: its static split hands every thread one contiguous share up front, and its region ends
// with a join that waits for every thread to arrive.  When another process holds a core, the thread on that core
// runs at half speed, or not at all for a scheduler time slice (milliseconds), and every region waits for it; on a
// quiet machine the same split leaves threads idle whenever tasks differ in cost.  Here:
//
// * every thread claims the next unstarted task from one atomic counter, so a slow thread takes fewer tasks;
//   callers list tasks largest first (the longest-processing-time rule: the tail is one small task);
// * a call is one job of up to four stages (operand layout, then the products that read it): a stage starts when
//   the earlier stages' claimed tasks are finished -- one wake-up per call, no barrier;
// * the threads: MODI_EXT_CPU_POOL=own (what modi_ext/runtime/omp_wait.py sets when OpenMP threads spin only briefly, as
//   it chooses when another process keeps a CPU busy) runs jobs on this file's own helper threads: the caller never
//   waits for a helper that has claimed nothing, helpers sleep when idle, and they are kept off the caller's CPU
//   (Pool::place_helpers), so with one core busy two threads beat one.  MODI_EXT_CPU_POOL=omp runs them on torch's
//   OpenMP team (at::parallel_for over one chunk per thread), the choice when libgomp keeps its default spin of
//   milliseconds after every torch op: its spinning workers would hold the cores the helpers need (measured:
//   benchmarks/RESULTS.md, "Busy machine").  Both use the user's thread count (torch.set_num_threads).
//
// Calls below a work threshold run on the calling thread, where waking threads costs more than it saves.  Results
// never depend on which thread runs a task: a task writes its own outputs, and the slot index it receives only
// selects scratch memory.  Every wait spins for a bounded time (microseconds, not a count of pause instructions,
// whose cost differs tenfold between CPUs) before it yields or sleeps.
#pragma once

#include <ATen/Parallel.h>

#include <pthread.h>
#include <sched.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <exception>
#include <initializer_list>
#include <memory>
#include <mutex>
#include <thread>
#include <vector>

namespace modi_ext {
namespace cpu_tasks {

// One list of independent tasks: call(ctx, task, slot) for task in [0, n).
struct Phase {
  int64_t n = 0;
  const void* ctx = nullptr;
  void (*call)(const void*, int64_t, int) = nullptr;
};

// A phase running f(task, slot); f must outlive the run that uses it.
template <class F>
Phase phase(int64_t n, const F& f) {
  return Phase{n, &f, [](const void* c, int64_t t, int s) { (*static_cast<const F*>(c))(t, s); }};
}

// Phases whose tasks may start once every task of the previous stage is finished.
struct Stage {
  const Phase* phases = nullptr;
  size_t n = 0;
};
inline Stage stage(const std::vector<Phase>& v) { return Stage{v.data(), v.size()}; }

inline bool& in_job() {
  thread_local bool flag = false;
  return flag;
}

// Slots a task may receive: scratch arrays indexed by slot need this many entries.
inline int slots() {
  return (at::in_parallel_region() || in_job()) ? 1 : std::max(1, at::get_num_threads());
}

inline void cpu_relax() {
#if defined(__x86_64__) || defined(__i386__)
  __builtin_ia32_pause();
#endif
}

// Spin until ready() or about `micros` microseconds have passed; true if ready.
template <class Ready>
bool spin_for(int64_t micros, const Ready& ready) {
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::microseconds(micros);
  for (int i = 1;; ++i) {
    if (ready()) return true;
    cpu_relax();
    if ((i & 63) == 0 && std::chrono::steady_clock::now() >= deadline) return ready();
  }
}

// One call's tasks, shared (by reference count) between the caller and the helpers that joined it: a helper that
// wakes late may still read it after the caller returned, but never runs a task then (all are claimed and done).
struct Job {
  static constexpr size_t kMaxStages = 4;
  Stage stages[kMaxStages];
  int64_t total[kMaxStages] = {0, 0, 0, 0}, end[kMaxStages] = {0, 0, 0, 0};
  size_t n_stages = 0;
  int64_t all = 0;
  int max_helpers = 0;
  std::atomic<int64_t> next{0};
  std::atomic<int64_t> done[kMaxStages];
  std::atomic<int64_t> finished{0};
  std::atomic<int> stage_waiters{0};
  std::mutex m;
  std::condition_variable cv;
  bool complete = false;
  std::exception_ptr error;
  std::atomic<bool> failed{false};

  Job() {
    for (auto& d : done) d.store(0, std::memory_order_relaxed);
  }

  void exec(size_t s, int64_t t, int slot) {
    const Stage& st = stages[s];
    for (size_t i = 0; i < st.n; ++i) {
      const Phase& p = st.phases[i];
      if (t < p.n) {
        p.call(p.ctx, t, slot);
        return;
      }
      t -= p.n;
    }
  }

  // Claim and run tasks until none is left.
  void work(int slot) {
    size_t s = 0;
    for (;;) {
      const int64_t t = next.fetch_add(1, std::memory_order_relaxed);
      if (t >= all) return;
      while (t >= end[s]) ++s;
      if (s > 0) wait_stage(s - 1);  // every earlier stage is complete once the previous one is
      if (!failed.load(std::memory_order_relaxed)) {
        try {
          exec(s, t - (s > 0 ? end[s - 1] : 0), slot);
        } catch (...) {
          std::lock_guard<std::mutex> lk(m);
          if (!error) error = std::current_exception();
          failed.store(true, std::memory_order_relaxed);
        }
      }
      // seq_cst here and in wait_stage: a waiter's registration and the last completion are ordered either way
      const bool stage_done = done[s].fetch_add(1, std::memory_order_seq_cst) + 1 == total[s];
      const bool all_done = finished.fetch_add(1, std::memory_order_acq_rel) + 1 == all;
      if (all_done || (stage_done && stage_waiters.load(std::memory_order_seq_cst) > 0)) {
        std::lock_guard<std::mutex> lk(m);
        if (all_done) complete = true;
        cv.notify_all();
      }
    }
  }

  // A task of stage s+1 waits for the last tasks of stage s.  Spin briefly, then yield (a thread that holds the
  // missing task and waits for this core runs), then sleep after 1 ms: on a busy machine the thread that holds it
  // may be descheduled on another core, and a waiter that keeps spinning keeps the core it needs.  Sleeping sooner
  // costs a quiet machine a wake-up per stage (measured: fk 25% slower).
  void wait_stage(size_t s) {
    const auto ready = [&] { return done[s].load(std::memory_order_acquire) >= total[s]; };
    if (spin_for(20, ready)) return;
    const auto deadline = std::chrono::steady_clock::now() + std::chrono::milliseconds(1);
    while (std::chrono::steady_clock::now() < deadline) {
      if (ready()) return;
      std::this_thread::yield();
    }
    std::unique_lock<std::mutex> lk(m);
    stage_waiters.fetch_add(1, std::memory_order_seq_cst);
    cv.wait(lk, [&] { return done[s].load(std::memory_order_seq_cst) >= total[s]; });
    stage_waiters.fetch_sub(1, std::memory_order_relaxed);
  }

  // The caller: after its own claims, wait for the tasks still running elsewhere (a short spin, then sleep).
  void wait_complete() {
    if (spin_for(50, [&] { return finished.load(std::memory_order_acquire) == all; })) return;
    std::unique_lock<std::mutex> lk(m);
    cv.wait(lk, [&] { return complete; });
  }
};

// The helper threads.  One per process (re-created in a forked child, where the parent's threads do not exist);
// one job at a time (a second caller meanwhile runs its job on its own thread).
class Pool {
 public:
  static Pool& get() {
    static std::mutex create;
    static Pool* pool = nullptr;
    std::lock_guard<std::mutex> lk(create);
    if (pool == nullptr || pool->pid_ != getpid()) pool = new Pool();  // a forked child's copy is abandoned
    return *pool;
  }

  // Run `job` with up to job->max_helpers helpers; false if the pool is busy with another caller's job.
  bool run(const std::shared_ptr<Job>& job) {
    std::unique_lock<std::mutex> owner(owner_, std::try_to_lock);
    if (!owner.owns_lock()) return false;
    grow(job->max_helpers);
    place_helpers();
    {
      std::lock_guard<std::mutex> lk(m_);
      current_ = job;
      epoch_.fetch_add(1, std::memory_order_release);
      if (sleepers_ > 0) cv_.notify_all();
    }
    in_job() = true;
    job->work(0);
    in_job() = false;
    job->wait_complete();
    {
      std::lock_guard<std::mutex> lk(m_);
      if (current_ == job) current_.reset();
    }
    return true;
  }

 private:
  Pool() : pid_(getpid()) {}

  void grow(int n) {
    while (static_cast<int>(threads_) < n) {
      const int index = static_cast<int>(threads_++);
      std::thread t([this, index] { loop(index); });
      handles_.push_back(t.native_handle());
      t.detach();
    }
  }

  // Keep the helpers off the CPU the caller runs on.  A helper sleeps between jobs, and the caller wakes it.  If
  // every other CPU is busy then (another process holds it), Linux places the woken thread beside the thread that
  // woke it: caller and helper share one core, and two threads run no faster than one (measured in
  // benchmarks/RESULTS.md, "Helpers off the caller's CPU").  Off the caller's CPU, a helper shares a core with the
  // other process at worst.  The mask is reset only when the caller has moved since the last job (one syscall per
  // helper then).  MODI_EXT_HELPER_AFFINITY=0 leaves the helpers anywhere in the process's CPU set.
  void place_helpers() {
#ifdef __linux__
    const char* env = std::getenv("MODI_EXT_HELPER_AFFINITY");
    const bool off = env != nullptr && std::strcmp(env, "0") == 0;
    int cpu = off ? -1 : sched_getcpu();
    if (cpu == placed_cpu_ && handles_.size() == placed_n_) return;
    if (!allowed_ready_) {
      CPU_ZERO(&allowed_);
      if (sched_getaffinity(0, sizeof(allowed_), &allowed_) != 0) return;
      allowed_ready_ = true;
    }
    cpu_set_t mask = allowed_;
    if (cpu >= 0 && CPU_COUNT(&allowed_) >= 2 && CPU_ISSET(cpu, &allowed_))
      CPU_CLR(cpu, &mask);
    else
      cpu = -1;  // nowhere else to go, or no CPU number: the whole set
    for (pthread_t h : handles_) pthread_setaffinity_np(h, sizeof(mask), &mask);
    placed_cpu_ = cpu;
    placed_n_ = handles_.size();
#endif
  }

  void loop(int index) {
    in_job() = true;  // kernels called from a task run serially
    uint64_t seen = epoch_.load(std::memory_order_acquire);
    for (;;) {
      // a short spin (0.1 ms) catches back-to-back jobs (forward then backward, small layers in a row); then sleep,
      // so an idle helper costs nothing
      spin_for(100, [&] { return epoch_.load(std::memory_order_acquire) != seen; });
      std::shared_ptr<Job> job;
      {
        std::unique_lock<std::mutex> lk(m_);
        if (epoch_.load(std::memory_order_relaxed) == seen) {
          ++sleepers_;
          cv_.wait(lk, [&] { return epoch_.load(std::memory_order_relaxed) != seen; });
          --sleepers_;
        }
        seen = epoch_.load(std::memory_order_relaxed);
        job = current_;
      }
      if (job && index < job->max_helpers) job->work(index + 1);
    }
  }

  const pid_t pid_;
  std::mutex owner_;  // held by the caller whose job runs
  std::mutex m_;
  std::condition_variable cv_;
  std::atomic<uint64_t> epoch_{0};
  std::shared_ptr<Job> current_;
  int sleepers_ = 0;
  size_t threads_ = 0;
  std::vector<pthread_t> handles_;
#ifdef __linux__
  cpu_set_t allowed_;  // the CPUs this process may use, read at the first placement
#endif
  bool allowed_ready_ = false;
  int placed_cpu_ = -1;  // the caller's CPU the helpers were kept off at the last placement; -1: none
  size_t placed_n_ = 0;
};

inline bool use_omp_team() {
  const char* env = std::getenv("MODI_EXT_CPU_POOL");
  return env == nullptr || std::strcmp(env, "own") != 0;  // unset only when loaded without modi_ext's __init__
}

// Run the stages' tasks, each exactly once.  parallel=false (small work) runs them in order on the calling thread.
inline void run_stages(std::initializer_list<Stage> stages, bool parallel) {
  auto job = std::make_shared<Job>();
  job->n_stages = std::min(stages.size(), Job::kMaxStages);
  for (size_t s = 0; s < job->n_stages; ++s) {
    job->stages[s] = stages.begin()[s];
    for (size_t i = 0; i < job->stages[s].n; ++i) job->total[s] += job->stages[s].phases[i].n;
    job->all += job->total[s];
    job->end[s] = job->all;
  }
  if (job->all <= 0) return;
  const int nt = slots();
  if (!parallel || nt <= 1 || job->all == 1) {
    for (size_t s = 0; s < job->n_stages; ++s)
      for (int64_t t = 0; t < job->total[s]; ++t) job->exec(s, t, 0);
    return;
  }
  job->max_helpers = nt - 1;
  if (use_omp_team()) {
    at::parallel_for(0, nt, 1, [&](int64_t, int64_t) { job->work(std::min(at::get_thread_num(), nt - 1)); });
  } else if (!Pool::get().run(job)) {
    job->work(0);  // another caller's job holds the helpers
  }
  if (job->error) std::rethrow_exception(job->error);
}

inline void run_phases(const Phase* phases, size_t n_phases, bool parallel) {
  run_stages({Stage{phases, n_phases}}, parallel);
}

inline void run_phases(std::initializer_list<Phase> phases, bool parallel) {
  run_phases(phases.begin(), phases.size(), parallel);
}

}  // namespace cpu_tasks
}  // namespace modi_ext
