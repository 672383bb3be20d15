// Building blocks of the skeletal operators' CPU kernels, shared by their two paths: the BLAS path (cpu.cpp, float32
// and float64) and the fp32 indirect-GEMM path (fastk.cpp).  Operand buffers and per-slot scratch from a process-wide
// cache of freed blocks, the task order and tiling of a pass (from the shapes only, never the thread count), the
// optional style / demodulation factor, the time maps (padding, fold, blur) and the CSR topology.
#pragma once

#include <algorithm>
#include <cstdint>
#include <memory>
#include <mutex>
#include <numeric>
#include <vector>

#include "common/tasks.h"
#include "skeletal/check.h"
#include "skeletal/skeletal.h"

namespace modi_ext {
namespace skeletal {


using cpu_tasks::phase;
using cpu_tasks::Phase;
using cpu_tasks::run_phases;
using cpu_tasks::run_stages;
using cpu_tasks::stage;

// Threads only pay off above some work: waking a pool costs microseconds (milliseconds on a loaded machine).
constexpr double kSerialMacs = 1.0e6;
constexpr int64_t kSerialElems = 1 << 16;
// Tasks per pass that the tiling aims for (when the batch allows), whatever the thread count: enough for the
// dynamic claiming to balance up to ~8 threads with a small tail.
constexpr int64_t kMinTasks = 16;
inline bool worth_threads(double macs) { return macs >= kSerialMacs; }
inline int64_t chunk_items(int64_t elems_per_item) {
  return std::max<int64_t>(1, (kSerialElems / 2) / std::max<int64_t>(1, elems_per_item));
}

// Per-call operand buffers and scratch (up to megabytes) come from a small process-wide cache of freed blocks: a
// fresh allocation of that size is an mmap whose pages fault in on first touch, every call (and page faults from
// several threads serialise in the kernel).
class BlockCache {
 public:
  static constexpr size_t kMaxBytes = size_t(64) << 20, kMaxBlocks = 16;
  static std::unique_ptr<char[]> take(size_t bytes, size_t& cap) {
    auto& c = local();
    std::lock_guard<std::mutex> lk(c.m);
    size_t best = c.blocks.size();
    for (size_t i = 0; i < c.blocks.size(); ++i)
      if (c.blocks[i].cap >= bytes && (best == c.blocks.size() || c.blocks[i].cap < c.blocks[best].cap)) best = i;
    if (best < c.blocks.size() && c.blocks[best].cap <= 2 * bytes + (size_t(1) << 16)) {
      std::unique_ptr<char[]> p = std::move(c.blocks[best].p);
      cap = c.blocks[best].cap;
      c.total -= cap;
      c.blocks.erase(c.blocks.begin() + static_cast<std::ptrdiff_t>(best));
      return p;
    }
    cap = bytes;
    return std::unique_ptr<char[]>(new char[bytes]);
  }
  static void give(std::unique_ptr<char[]> p, size_t cap) {
    auto& c = local();
    if (cap > kMaxBytes) return;
    std::lock_guard<std::mutex> lk(c.m);
    while (!c.blocks.empty() && (c.total + cap > kMaxBytes || c.blocks.size() >= kMaxBlocks)) {
      c.total -= c.blocks.front().cap;  // drop the oldest
      c.blocks.erase(c.blocks.begin());
    }
    c.total += cap;
    c.blocks.push_back({std::move(p), cap});
  }

 private:
  struct Block {
    std::unique_ptr<char[]> p;
    size_t cap;
  };
  struct Cache {
    std::mutex m;
    std::vector<Block> blocks;
    size_t total = 0;
  };
  static Cache& local() {
    static Cache* c = new Cache();  // never destroyed: helper threads may still return blocks at exit
    return *c;
  }
};

// Uninitialised storage (every element is written before it is read), so no memset pass over large operands.
template <typename T>
struct Buf {
  std::unique_ptr<char[]> p;
  size_t cap = 0;
  Buf() = default;
  Buf(const Buf&) = delete;
  Buf& operator=(const Buf&) = delete;
  ~Buf() { release(); }
  void alloc(size_t n) {
    release();
    if (n) p = BlockCache::take(n * sizeof(T), cap);
  }
  void release() {
    if (p) BlockCache::give(std::move(p), cap);
    p.reset();
    cap = 0;
  }
  T* data() const { return reinterpret_cast<T*>(p.get()); }
};

// Scratch per slot (cpu_tasks::slots()), taken on first use by the thread that owns the slot.
template <typename T>
struct SlotScratch {
  std::vector<Buf<T>> v;
  SlotScratch() : v(static_cast<size_t>(cpu_tasks::slots())) {}
  T* get(int slot, size_t n) {
    Buf<T>& b = v[static_cast<size_t>(slot)];
    if (b.cap < n * sizeof(T)) b.alloc(n);
    return b.data();
  }
};

// Task ids bt * E + e of a batch-tiled pass, largest first (cost ~ batch elements x (degree + 1)), so dynamic
// claiming ends with small tasks.  off: CSR offsets of the entities' neighbour lists (their degrees).
inline std::vector<int64_t> lpt_tiles(int64_t B, int64_t nb, int64_t E, const std::vector<int64_t>& off) {
  const int64_t nbt = (B + nb - 1) / nb;
  std::vector<int64_t> ids(static_cast<size_t>(nbt * E));
  std::iota(ids.begin(), ids.end(), int64_t(0));
  auto cost = [&](int64_t id) {
    const int64_t bt = id / E, e = id % E;
    return std::min(nb, B - bt * nb) * (off[e + 1] - off[e] + 1);
  };
  std::stable_sort(ids.begin(), ids.end(), [&](int64_t a, int64_t b) { return cost(a) > cost(b); });
  return ids;
}

// Weight-gradient blocks: task ids e * nrb + rb (entity e, output-row block rb of `rows` rows), largest first.
// Entities alone give enough tasks on most layers; with few entities the rows are split too (each block
// contracts the whole batch, so no partial sums are ever combined).
struct RowBlocks {
  int64_t nrb = 1, rb = 0;
  std::vector<int64_t> order;
};
inline RowBlocks weight_blocks(int64_t E, int64_t rows, const std::vector<int64_t>& off, int64_t align) {
  RowBlocks r;
  r.nrb = std::min<int64_t>((kMinTasks + E - 1) / E, std::max<int64_t>(1, rows / align));
  r.rb = (rows + r.nrb - 1) / r.nrb;
  r.rb = (r.rb + align - 1) / align * align;
  r.nrb = (rows + r.rb - 1) / r.rb;
  r.order.resize(static_cast<size_t>(E * r.nrb));
  std::iota(r.order.begin(), r.order.end(), int64_t(0));
  const int64_t nrb = r.nrb, rbs = r.rb;
  auto cost = [&](int64_t id) {
    const int64_t e = id / nrb, b = id % nrb;
    return (off[e + 1] - off[e]) * std::min(rbs, rows - b * rbs);
  };
  std::stable_sort(r.order.begin(), r.order.end(), [&](int64_t a, int64_t b) { return cost(a) > cost(b); });
  return r;
}

// Batch elements per tile: about `target` panel columns, at least kMinTasks tasks (entities x tiles) when the batch
// allows, tiles as even as the count permits.  Depends on the shapes only (never on the thread count), so the
// same products are computed whatever the threads.
//
// col_tile > 1 (the fast path's NN kernels, which step through columns col_tile at a time): of the sizes that keep
// a tile within max(2 * target, the default's) columns and give kMinTasks tasks where the default does, the one
// whose tiles pad the fewest columns (the last tile may be shorter; ties: the nearest to the default).  A tile's
// columns past a multiple of col_tile run on a narrower, slower kernel: MoDi's finest level (66 padded frames) in
// tiles of 6 batch elements (396 columns: 8 pairs of 24 and a 24-column tail) ran its forward 14% slower than in
// tiles of 8 (528 = 11 x 48).
inline int64_t batch_tile(int64_t B, int64_t cols_per_b, int64_t n_entities, int64_t target = 512,
                          int64_t col_tile = 1) {
  constexpr int64_t kMinCols = 32;  // narrower products waste more in per-call overhead than balance gains
  const int64_t cols = std::max<int64_t>(1, cols_per_b);
  int64_t nb = std::max<int64_t>(1, target / cols);
  nb = std::min(nb, B);
  while (nb > 1 && ((B + nb - 1) / nb) * n_entities < kMinTasks && ((nb + 1) / 2) * cols >= kMinCols)
    nb = (nb + 1) / 2;
  const int64_t nbt = (B + nb - 1) / nb;
  const int64_t base = (B + nbt - 1) / nbt;
  if (col_tile <= 1 || B <= 1) return base;
  auto padded = [&](int64_t n) {  // columns the kernels step through for all tiles of n batch elements
    const int64_t full = B / n, rest = B % n;
    return full * ((n * cols + col_tile - 1) / col_tile) * col_tile +
           (rest ? (rest * cols + col_tile - 1) / col_tile * col_tile : 0);
  };
  const int64_t max_cols = std::max(2 * target, base * cols);
  const int64_t min_tasks = std::min(kMinTasks, ((B + base - 1) / base) * n_entities);
  auto dist = [&](int64_t n) { return n > base ? n * 1.0 / base : base * 1.0 / n; };  // from the default, as a ratio
  int64_t best = base, best_cost = padded(base);
  for (int64_t n = 1; n <= B; ++n) {
    if (n * cols > max_cols || ((B + n - 1) / n) * n_entities < min_tasks) continue;
    const int64_t cost = padded(n);
    if (cost < best_cost || (cost == best_cost && dist(n) < dist(best))) best = n, best_cost = cost;
  }
  return best;
}

// Optional per-(b, channel, entity) factor with arbitrary strides (style: entity stride 0; demod: full).
template <typename T>
struct Scale {
  const T* p = nullptr;
  int64_t sb = 0, sc = 0, se = 0;
  inline T at(int64_t b, int64_t c, int64_t e) const { return p ? p[b * sb + c * sc + e * se] : T(1); }
};

// ------------------------------------------------------------------------------------------------ time maps
inline int64_t mirror(int64_t q, int64_t L) { return q < 0 ? -q : (q >= L ? 2 * (L - 1) - q : q); }

// Fold a padded-domain row g (length L + 2h) onto [0, L): the adjoint of zero / reflect padding.
template <typename T>
inline void fold_row(const T* g, T* out, int64_t L, int64_t h, bool reflect) {
  for (int64_t t = 0; t < L; ++t) out[t] = g[t + h];
  if (reflect) {
    for (int64_t q = 0; q < h; ++q) out[mirror(q - h, L)] += g[q];
    for (int64_t q = L + h; q < L + 2 * h; ++q) out[mirror(q - h, L)] += g[q];
  }
}

// The [1 3 3 1] / 4 FIR of a row, zero outside [0, L): y[t] = (3 v[t] + v[t+A] + 3 v[t+B] + v[t+C]) / 4, summed in
// that order.  The interior runs without the edge tests, so the compiler vectorises it (the up pass's epilogue was
// a quarter of its forward); the edges add the same terms where they exist, so every value is the same.
template <typename T, int A, int B, int C>
inline void fir1331_row(const T* v, T* y, int64_t L) {
  static_assert(A < 0 && C > 0 && A < B && B < C, "taps around t");
  auto edge = [&](int64_t t) {
    auto tap = [&](int64_t q) { return q >= 0 && q < L ? v[q] : T(0); };
    T acc = T(3) * v[t];
    acc += tap(t + A);
    acc += T(3) * tap(t + B);
    acc += tap(t + C);
    return T(0.25) * acc;
  };
  const int64_t lo = std::min<int64_t>(-A, L), hi = std::max<int64_t>(lo, L - C);
  for (int64_t t = 0; t < lo; ++t) y[t] = edge(t);
  for (int64_t t = lo; t < hi; ++t) {
    T acc = T(3) * v[t];
    acc += v[t + A];
    acc += T(3) * v[t + B];
    acc += v[t + C];
    y[t] = T(0.25) * acc;
  }
  for (int64_t t = hi; t < L; ++t) y[t] = edge(t);
}

// StyleGAN2 blur after upsampling: y[t] = (v[t-2] + 3 v[t-1] + 3 v[t] + v[t+1]) / 4.
template <typename T>
inline void blur_row(const T* v, T* y, int64_t L) {
  fir1331_row<T, -2, -1, 1>(v, y, L);
}

// Its adjoint: gv[s] = (g[s-1] + 3 g[s] + 3 g[s+1] + g[s+2]) / 4.
template <typename T>
inline void blur_adjoint_row(const T* g, T* gv, int64_t L) {
  fir1331_row<T, -1, 1, 2>(g, gv, L);
}

// Epilogue shared by the input-gradient passes: gx' row (length L) -> gx = gx' * s and the style partial.
template <typename T>
inline void finish_input_row(const T* gxp, const T* xrow, T s, T* gx_row, T* gs_acc, int64_t L) {
  if (gs_acc) {
    T dot = T(0);
    for (int64_t t = 0; t < L; ++t) dot += gxp[t] * xrow[t];
    *gs_acc += dot;
  }
  if (gx_row)
    for (int64_t t = 0; t < L; ++t) gx_row[t] = gxp[t] * s;
}

// ------------------------------------------------------------------------------------------------ topology
struct Csr {
  std::vector<int64_t> off, idx;          // row entity -> input entities (pairs p in [off[j], off[j+1]))
  std::vector<int64_t> toff, tent, tpair;  // input entity -> (row entity, pair), ordered by row entity
  int64_t rows = 0, cols = 0, max_deg = 0, max_tdeg = 0;
};

// The bias activation over one finished output row: the epilogue's last step with act (skeletal.h).
template <typename T>
inline void act_row(T* row, int64_t n) {
#pragma omp simd
  for (int64_t t = 0; t < n; ++t) row[t] = act_fwd(row[t]);
}

}  // namespace skeletal
}  // namespace modi_ext
