// The emulator's scheduler: one fiber per CUDA thread, blocks run one at a time on the calling thread.
// See cuda_emu.h for what it checks.  Everything here is test-only code.
#include "emu/cuda_emu.h"

#include <ATen/Context.h>
#include <c10/util/Exception.h>
#include <sys/mman.h>
#include <ucontext.h>

#include <algorithm>
#include <atomic>
#include <exception>
#include <map>
#include <memory>
#include <mutex>
#include <numeric>
#include <random>
#include <set>
#include <sstream>
#include <stdexcept>
#include <vector>

#include "emu/emu_control.h"

// ------------------------------------------------------------------------------------------------ context switch
// x86-64 (not under AddressSanitizer): a minimal System V switch -- the callee-saved registers, the stack pointer and
// the SSE / x87 control words, i.e. what a function call preserves.  glibc's swapcontext also saves the signal mask
// with a system call on every switch, which made the switches most of the emulator's time.  Elsewhere, and in the
// AddressSanitizer build (which knows ucontext stacks) and under -fcf-protection (__CET__: a shadow stack would refuse
// the switch's `ret` onto another stack; glibc's swapcontext handles it), ucontext.
#if defined(__x86_64__) && !defined(__SANITIZE_ADDRESS__) && !defined(__CET__)
#define MODI_EMU_FAST_SWITCH 1
extern "C" __attribute__((visibility("hidden"))) void modi_emu_switch(void** save_sp, void* load_sp);
asm(R"(
  .text
  .p2align 4
  .globl modi_emu_switch
  .hidden modi_emu_switch
  .type modi_emu_switch,@function
modi_emu_switch:
  pushq %rbp
  pushq %rbx
  pushq %r12
  pushq %r13
  pushq %r14
  pushq %r15
  subq $16, %rsp
  stmxcsr 8(%rsp)
  fnstcw (%rsp)
  movq %rsp, (%rdi)
  movq %rsi, %rsp
  fldcw (%rsp)
  ldmxcsr 8(%rsp)
  addq $16, %rsp
  popq %r15
  popq %r14
  popq %r13
  popq %r12
  popq %rbx
  popq %rbp
  ret
  .size modi_emu_switch, .-modi_emu_switch
)");
#else
#define MODI_EMU_FAST_SWITCH 0
#endif

namespace modi_emu {

thread_local ThreadCtx* g_ctx = nullptr;

namespace {

#if MODI_EMU_FAST_SWITCH
struct Ctx {
  void* sp = nullptr;
};
// A fresh context whose first switch "returns" into entry() on the given stack (never to return from it).
void ctx_make(Ctx& c, unsigned char* stack, size_t size, void (*entry)()) {
  auto* top = reinterpret_cast<unsigned char*>(reinterpret_cast<uintptr_t>(stack + size) & ~uintptr_t(15));
  auto* sp = reinterpret_cast<uint64_t*>(top - 80);  // 16-aligned: entry() then starts with rsp = 8 (mod 16)
  uint32_t mxcsr;
  uint16_t fpcw;
  asm volatile("stmxcsr %0" : "=m"(mxcsr));
  asm volatile("fnstcw %0" : "=m"(fpcw));
  std::memset(sp, 0, 80);
  std::memcpy(sp, &fpcw, sizeof fpcw);                             // [sp + 0]  x87 control word
  std::memcpy(reinterpret_cast<unsigned char*>(sp) + 8, &mxcsr, 4);  // [sp + 8]  MXCSR
  sp[8] = reinterpret_cast<uint64_t>(entry);                        // [sp + 64] after r15..rbp: the "return"
  c.sp = sp;
}
inline void ctx_switch(Ctx& from, const Ctx& to) { modi_emu_switch(&from.sp, to.sp); }
#else
struct Ctx {
  ucontext_t uc;
};
void ctx_make(Ctx& c, unsigned char* stack, size_t size, void (*entry)()) {
  getcontext(&c.uc);
  c.uc.uc_stack.ss_sp = stack;
  c.uc.uc_stack.ss_size = size;
  c.uc.uc_link = nullptr;
  makecontext(&c.uc, entry, 0);
}
inline void ctx_switch(Ctx& from, Ctx& to) { swapcontext(&from.uc, &to.uc); }
#endif

constexpr size_t kStackBytes = 256 * 1024;
constexpr size_t kGuardBytes = 4096;
constexpr size_t kSmemLimit = 48 * 1024;  // default per-block limit (no opt-in attribute is used by the kernels)
constexpr size_t kRedzone = 256;
constexpr int kMaxThreads = 1024;

// ---- global settings and counters (Python sets / reads them between launches)
std::mutex g_mu;
uint64_t g_seed = 0;
int g_sm_count = 108;
std::atomic<int> g_defect{0};
std::map<std::string, int64_t> g_counts;
std::map<std::string, std::array<unsigned, 3>> g_grids;

enum class St { Ready, Barrier, Warp, Done };

struct Fiber {
  Ctx uc;
  ThreadCtx ctx;
  St st = St::Ready;
  int line = 0;
  unsigned char xbuf[32 * 8];  // this lane's copy of a completed warp exchange
  unsigned took = 0;
};

struct WarpState {
  unsigned arrived = 0, mask = 0;
  int line = -1;
  size_t bytes = 0;
  unsigned char deposit[32 * 8];
};

struct SharedAlloc {
  const char* name;
  int line;
  size_t bytes;
  void* p;
};

// Memory reused across blocks (refilled with poison per block).
struct Arena {
  std::vector<unsigned char*> stacks;
  std::vector<std::pair<size_t, std::unique_ptr<unsigned char[]>>> shared;  // by allocation order in a block
  std::vector<unsigned char> dyn;
  ~Arena() {
    for (unsigned char* s : stacks) munmap(s, kStackBytes + kGuardBytes);
  }
  unsigned char* stack(size_t i) {
    while (stacks.size() <= i) {
      void* p = mmap(nullptr, kStackBytes + kGuardBytes, PROT_READ | PROT_WRITE, MAP_PRIVATE | MAP_ANONYMOUS, -1, 0);
      TORCH_CHECK(p != MAP_FAILED, "modi_emu: cannot map a fiber stack");
      mprotect(p, kGuardBytes, PROT_NONE);  // a stack overflow faults instead of corrupting a neighbour
      stacks.push_back(static_cast<unsigned char*>(p));
    }
    return stacks[i] + kGuardBytes;
  }
};

struct Block {
  const LaunchSpec* spec = nullptr;
  std::string kname;
  std::vector<Fiber> f;
  Ctx sched;
  int cur = -1;
  std::exception_ptr err;
  int err_thread = -1;
  std::vector<WarpState> warps;
  std::vector<SharedAlloc> shared;
  size_t static_bytes = 0, dyn_bytes = 0;
  unsigned char* dyn = nullptr;
  bool drop_sync = false;
  int dropped_line = -1;
};

thread_local Block* g_block = nullptr;
thread_local Arena* g_arena = nullptr;

Block& block() {
  if (!g_block) throw std::logic_error("modi_emu: a CUDA device function was called outside an emulated launch");
  return *g_block;
}

void fiber_entry() {
  Block& b = *g_block;
  const int me = b.cur;
  try {
    b.spec->body();
  } catch (...) {
    if (!b.err) {
      b.err = std::current_exception();
      b.err_thread = me;
    }
  }
  b.f[me].st = St::Done;
  ctx_switch(b.f[me].uc, b.sched);  // never resumed
}

void yield_to_scheduler(Block& b) {
  Fiber& f = b.f[b.cur];
  ctx_switch(f.uc, b.sched);
  g_ctx = &f.ctx;
}

std::string dim_str(const dim3& d) {
  std::ostringstream s;
  s << "(" << d.x << ", " << d.y << ", " << d.z << ")";
  return s.str();
}

uint64_t mix(uint64_t a, uint64_t b) {
  uint64_t x = a * 0x9E3779B97F4A7C15ull ^ (b + 0x632BE59BD9B4E019ull + (a << 6) + (a >> 2));
  x ^= x >> 31;
  x *= 0xBF58476D1CE4E5B9ull;
  return x ^ (x >> 29);
}

[[noreturn]] void block_fail(const Block& b, const dim3& bid, const std::string& what) {
  TORCH_CHECK(false, "modi_emu: kernel ", b.kname, " block ", dim_str(bid), ": ", what);
}

// Run every thread of one block to completion.
void run_block(Block& b, const dim3& bid, uint64_t seed) {
  const LaunchSpec& s = *b.spec;
  const int nt = static_cast<int>(s.block.x * s.block.y * s.block.z);
  b.f.assign(nt, Fiber{});
  b.warps.assign((nt + 31) / 32, WarpState{});
  b.err = nullptr;
  b.err_thread = -1;
  b.shared.clear();
  b.static_bytes = 0;
  b.dropped_line = -1;
  // dynamic shared memory, with poisoned red zones on both sides (a write past either end is reported)
  g_arena->dyn.assign(b.dyn_bytes + 2 * kRedzone, 0xFF);
  b.dyn = g_arena->dyn.data() + kRedzone;
  for (int i = 0; i < nt; ++i) {
    Fiber& f = b.f[i];
    f.ctx.thread = dim3(i % s.block.x, (i / s.block.x) % s.block.y, i / (s.block.x * s.block.y));
    f.ctx.block = bid;
    f.ctx.bdim = s.block;
    f.ctx.gdim = s.grid;
    f.ctx.linear = i;
    ctx_make(f.uc, g_arena->stack(i), kStackBytes, fiber_entry);
  }
  std::vector<int> order(nt);
  std::iota(order.begin(), order.end(), 0);
  std::mt19937_64 rng(mix(seed, (uint64_t(bid.z) << 40) ^ (uint64_t(bid.y) << 20) ^ bid.x));
  std::vector<int> ready;
  for (;;) {
    ready.clear();
    if (seed != 0) std::shuffle(order.begin(), order.end(), rng);
    for (int i : order)
      if (b.f[i].st == St::Ready) ready.push_back(i);
    if (ready.empty()) {
      int n_bar = 0, n_warp = 0, n_done = 0, bar_line = -1, warp_line = -1, warp_thread = -1;
      bool lines_differ = false;
      for (int i = 0; i < nt; ++i) {
        const Fiber& f = b.f[i];
        if (f.st == St::Done) {
          ++n_done;
        } else if (f.st == St::Barrier) {
          if (bar_line >= 0 && bar_line != f.line) lines_differ = true;
          bar_line = bar_line < 0 ? f.line : bar_line;
          ++n_bar;
        } else if (f.st == St::Warp) {
          ++n_warp;
          warp_line = f.line;
          warp_thread = i;
        }
      }
      if (n_done == nt) break;
      if (n_warp > 0) {
        const WarpState& w = b.warps[warp_thread / 32];
        std::ostringstream m;
        m << "warp " << warp_thread / 32 << " waits forever in a warp intrinsic at line " << warp_line
          << ": mask 0x" << std::hex << w.mask << " but only lanes 0x" << w.arrived << std::dec
          << " arrived (the others exited or wait at __syncthreads())";
        block_fail(b, bid, m.str());
      }
      if (lines_differ) block_fail(b, bid, "threads wait at different __syncthreads() call sites");
      if (n_done > 0) {
        std::ostringstream m;
        m << "__syncthreads() at line " << bar_line << " reached by " << n_bar << " of " << nt << " threads; "
          << n_done << " exited without reaching it";
        block_fail(b, bid, m.str());
      }
      for (Fiber& f : b.f) f.st = St::Ready;  // the barrier opens
      continue;
    }
    for (int i : ready) {
      if (b.f[i].st != St::Ready) continue;
      b.cur = i;
      g_ctx = &b.f[i].ctx;
      ctx_switch(b.sched, b.f[i].uc);
      g_ctx = nullptr;
      b.cur = -1;
      if (b.err) break;
    }
    if (b.err) {
      const dim3 tid = b.f[b.err_thread].ctx.thread;
      try {
        std::rethrow_exception(b.err);
      } catch (const c10::Error& e) {
        block_fail(b, bid, "thread " + dim_str(tid) + ": " + e.what_without_backtrace());
      } catch (const std::exception& e) {
        block_fail(b, bid, "thread " + dim_str(tid) + ": " + e.what());
      }
    }
  }
  for (size_t i = 0; i < kRedzone; ++i) {
    if (g_arena->dyn[i] != 0xFF || g_arena->dyn[kRedzone + b.dyn_bytes + i] != 0xFF) {
      block_fail(b, bid, "a write outside the " + std::to_string(b.dyn_bytes) + " bytes of dynamic shared memory");
    }
  }
}

}  // namespace

// ------------------------------------------------------------------------------------------------ device side
[[noreturn]] void fail(const std::string& what) { throw std::runtime_error(what); }

void syncthreads(int line) {
  Block& b = block();
  // Injected defect (run-time, test-only): the first __syncthreads() of row_gemm_kernel is not there.
  if (b.drop_sync) {
    if (b.dropped_line < 0) b.dropped_line = line;
    if (line == b.dropped_line) return;
  }
  Fiber& f = b.f[b.cur];
  f.st = St::Barrier;
  f.line = line;
  yield_to_scheduler(b);
}

unsigned warp_exchange(unsigned mask, const void* v, size_t n, void* all, int line) {
  if (n > 8) fail("warp exchange of more than 8 bytes per lane at line " + std::to_string(line));
  Block& b = block();
  Fiber& f = b.f[b.cur];
  const int lane = f.ctx.linear & 31;
  if (!((mask >> lane) & 1u)) {
    fail("warp intrinsic at line " + std::to_string(line) + ": lane " + std::to_string(lane) +
         " is not in its own mask");
  }
  const int w = f.ctx.linear >> 5;
  WarpState& ws = b.warps[w];
  if (ws.arrived == 0) {
    ws.mask = mask;
    ws.line = line;
    ws.bytes = n;
  } else if (ws.mask != mask || ws.line != line || ws.bytes != n) {
    std::ostringstream m;
    m << "warp " << w << ": lanes meet in different warp intrinsics (line " << ws.line << " mask 0x" << std::hex
      << ws.mask << " vs line " << std::dec << line << " mask 0x" << std::hex << mask << ")";
    fail(m.str());
  }
  std::memcpy(ws.deposit + lane * n, v, n);
  ws.arrived |= 1u << lane;
  if (ws.arrived == mask) {
    for (int l = 0; l < 32; ++l) {
      if (!((mask >> l) & 1u)) continue;
      Fiber& o = b.f[w * 32 + l];
      std::memcpy(o.xbuf, ws.deposit, 32 * n);
      o.took = mask;
      if (o.st == St::Warp) o.st = St::Ready;
    }
    ws.arrived = 0;
  } else {
    f.st = St::Warp;
    f.line = line;
    yield_to_scheduler(b);
  }
  std::memcpy(all, f.xbuf, 32 * n);
  return f.took;
}

void device_assert(const char* cond, const char* msg, const char* file, int line) {
  fail(std::string("device-side assert `") + cond + "` failed at " + file + ":" + std::to_string(line) +
       (msg && *msg ? std::string(": ") + msg : std::string()));
}

void* shared_storage(const char* name, int line, size_t bytes, void (*fill)(void*, size_t)) {
  Block& b = block();
  for (const SharedAlloc& a : b.shared)
    if (a.line == line && std::strcmp(a.name, name) == 0) return a.p;
  const size_t k = b.shared.size();
  auto& pool = g_arena->shared;
  if (pool.size() <= k) pool.emplace_back(0, nullptr);
  // 128-byte aligned, as __align__ asks of a GPU's shared arrays (WMMA pointers must be 256-bit aligned)
  if (pool[k].first < bytes) pool[k] = {bytes, std::make_unique<unsigned char[]>(bytes + 127)};
  const auto raw = reinterpret_cast<uintptr_t>(pool[k].second.get());
  void* p = reinterpret_cast<void*>((raw + 127) & ~uintptr_t(127));
  fill(p, bytes);
  b.static_bytes += bytes;
  if (b.static_bytes + b.dyn_bytes > kSmemLimit) {
    fail("shared memory of the block (" + std::to_string(b.static_bytes) + " static + " +
         std::to_string(b.dyn_bytes) + " dynamic bytes) exceeds 48 KB");
  }
  b.shared.push_back({name, line, bytes, p});
  return p;
}

unsigned char* dynamic_shared() { return block().dyn; }

void shared_oob(const char* name, int64_t i, size_t n) {
  fail(std::string("shared array `") + name + "`: index " + std::to_string(i) + " out of range [0, " +
       std::to_string(n) + ")");
}

// ------------------------------------------------------------------------------------------------ host side
std::string kernel_name(const char* pretty) {
  std::string s(pretty);
  const std::string key = "Kernel = ";
  size_t a = s.find(key);
  if (a == std::string::npos) return s;
  a += key.size();
  int depth = 0;
  size_t e = a;
  for (; e < s.size(); ++e) {
    const char c = s[e];
    if (c == '<' || c == '(') ++depth;
    if (c == '>' || c == ')') --depth;
    if (depth == 0 && (c == ';' || c == ']')) break;
  }
  std::string k = s.substr(a, e - a);
  for (const std::string pre : {"modi_ext::{anonymous}::", "modi_ext::(anonymous namespace)::", "modi_ext::"}) {
    for (size_t p; (p = k.find(pre)) != std::string::npos;) k.erase(p, pre.size());
  }
  return k;
}

namespace {
std::mutex& registry_mutex() {
  static std::mutex mu;
  return mu;
}
std::set<std::string>& registry() {  // function-local: safe from the initialisation order of the registrations
  static std::set<std::string> names;
  return names;
}
}  // namespace

bool register_kernel(const char* pretty) {
  std::lock_guard<std::mutex> lk(registry_mutex());
  registry().insert(kernel_name(pretty));
  return true;
}

std::set<std::string> registered_kernels() {
  std::lock_guard<std::mutex> lk(registry_mutex());
  return registry();
}

void run_launch(const LaunchSpec& spec) {
  Block b;
  b.spec = &spec;
  b.kname = kernel_name(spec.name);
  const dim3 g = spec.grid, t = spec.block;
  const uint64_t nthreads = uint64_t(t.x) * t.y * t.z;
  TORCH_CHECK(g.x >= 1 && g.y >= 1 && g.z >= 1 && nthreads >= 1, "modi_emu: kernel ", b.kname,
              ": invalid configuration (grid ", dim_str(g), ", block ", dim_str(t), ")");
  TORCH_CHECK(g.x <= 2147483647u && g.y <= 65535u && g.z <= 65535u, "modi_emu: kernel ", b.kname, ": grid ",
              dim_str(g), " exceeds the CUDA limits (2^31-1, 65535, 65535)");
  TORCH_CHECK(nthreads <= kMaxThreads && t.z <= 64, "modi_emu: kernel ", b.kname, ": block ", dim_str(t),
              " exceeds 1024 threads");
  TORCH_CHECK(spec.smem <= kSmemLimit, "modi_emu: kernel ", b.kname, ": ", spec.smem,
              " bytes of dynamic shared memory exceed 48 KB");
  b.dyn_bytes = spec.smem;
  b.drop_sync = injected_defect() == MODI_EMU_INJECT_DROP_SYNC_ID && b.kname.rfind("row_gemm_kernel", 0) == 0;
  uint64_t seed;
  {
    std::lock_guard<std::mutex> lk(g_mu);
    seed = g_seed;
    ++g_counts[b.kname];
    g_grids[b.kname] = {g.x, g.y, g.z};
  }
  TORCH_CHECK(g_block == nullptr, "modi_emu: nested kernel launch");
  static thread_local std::unique_ptr<Arena> tl_arena;
  if (!tl_arena) tl_arena = std::make_unique<Arena>();
  g_arena = tl_arena.get();
  g_block = &b;
  struct Reset {
    ~Reset() {
      g_block = nullptr;
      g_ctx = nullptr;
    }
  } reset;
  // block order: permuted by the seed as well (a GPU runs blocks in any order)
  const uint64_t nblocks = uint64_t(g.x) * g.y * g.z;
  std::vector<uint64_t> border(nblocks);
  std::iota(border.begin(), border.end(), uint64_t(0));
  const uint64_t kseed = seed ? mix(seed, std::hash<std::string>{}(b.kname)) : 0;
  if (kseed) {
    std::mt19937_64 rng(kseed);
    std::shuffle(border.begin(), border.end(), rng);
  }
  for (uint64_t lin : border) {
    const dim3 bid(static_cast<unsigned>(lin % g.x), static_cast<unsigned>((lin / g.x) % g.y),
                   static_cast<unsigned>(lin / (uint64_t(g.x) * g.y)));
    run_block(b, bid, kseed);
  }
}

int sm_count() {
  std::lock_guard<std::mutex> lk(g_mu);
  return g_sm_count;
}

PoisonScope::PoisonScope() {
  auto& c = at::globalContext();
  det_ = c.deterministicAlgorithms();
  warn_ = c.deterministicAlgorithmsWarnOnly();
  fill_ = c.deterministicFillUninitializedMemory();
  c.setDeterministicAlgorithms(true, /*warn_only=*/true);
  c.setDeterministicFillUninitializedMemory(true);
}

PoisonScope::~PoisonScope() {
  auto& c = at::globalContext();
  c.setDeterministicAlgorithms(det_, warn_);
  c.setDeterministicFillUninitializedMemory(fill_);
}

// ------------------------------------------------------------------------------------------------ control
void set_seed(uint64_t seed) {
  std::lock_guard<std::mutex> lk(g_mu);
  g_seed = seed;
}
uint64_t get_seed() {
  std::lock_guard<std::mutex> lk(g_mu);
  return g_seed;
}
int injected_defect() { return g_defect.load(std::memory_order_relaxed); }
void set_injected_defect(int id) { g_defect.store(id, std::memory_order_relaxed); }

void set_sm_count(int n) {
  std::lock_guard<std::mutex> lk(g_mu);
  g_sm_count = n;
}
std::map<std::string, int64_t> launch_counts() {
  std::lock_guard<std::mutex> lk(g_mu);
  return g_counts;
}
void reset_launch_counts() {
  std::lock_guard<std::mutex> lk(g_mu);
  g_counts.clear();
  g_grids.clear();
}
std::map<std::string, std::array<unsigned, 3>> last_grids() {
  std::lock_guard<std::mutex> lk(g_mu);
  return g_grids;
}

}  // namespace modi_emu
