// CPU kernels of the skeletal operators.
//
// Every pass is "one small GEMM per entity": for a row entity j and a tile of batch elements, gather the
// time-shifted inputs of j's neighbors into a contiguous (K x N) panel (rows = neighbor x channel x tap, columns =
// batch x time, time innermost), multiply by the entity's weight block (a strided view of the compact weight, or a
// once-per-call transposed copy), and write the tile out with the style / demodulation / bias / fold / blur applied
// in the epilogue.  The GEMM is the BLAS that libtorch ships (sgemm_/dgemm_, single-threaded inside the parallel
// region), with an ATen fallback when it is not exported; fp32 with AVX2/FMA uses the indirect kernels below.
//
// Work distribution (common/tasks.h): each call is one parallel region of two stages, preparation (operand layouts,
// packed weights, bias / scale gradients) then compute (forward tiles; or input-gradient tiles and weight-gradient
// blocks together), the second waiting only for claimed preparation tasks.  Tasks are claimed dynamically, largest first, with per-slot scratch; every output element is
// written by exactly one task, and the tiling depends on the shapes only, so results are the same for any thread
// count and schedule.  The weight gradient is split by entity (and by output-row block when entities are few)
// instead of accumulating thread-local copies.
#include <algorithm>
#include <cstdlib>
#include <cstring>
#include <memory>
#include <mutex>
#include <numeric>
#include <vector>

#if defined(__x86_64__)
#include <immintrin.h>
#endif

#include <ATen/Parallel.h>
#include <torch/library.h>

#include "skeletal/skeletal.h"
#include "common/tasks.h"

extern "C" {
void sgemm_(const char* transa, const char* transb, const int* m, const int* n, const int* k, const float* alpha,
            const float* a, const int* lda, const float* b, const int* ldb, const float* beta, float* c,
            const int* ldc) __attribute__((weak));
void dgemm_(const char* transa, const char* transb, const int* m, const int* n, const int* k, const double* alpha,
            const double* a, const int* lda, const double* b, const int* ldb, const double* beta, double* c,
            const int* ldc) __attribute__((weak));
int MKL_Set_Num_Threads_Local(int nt) __attribute__((weak));  // MKL's C entry (the lowercase one is Fortran)
}

namespace modi_ext {
namespace {

// ------------------------------------------------------------------------------------------------ GEMM
// Row-major C (M x N) = alpha * op(A) (M x K) * op(B) (K x N) + beta * C.
template <typename T>
void gemm_fallback(bool ta, bool tb, int64_t M, int64_t N, int64_t K, T alpha, const T* A, int64_t lda,
                   const T* B, int64_t ldb, T beta, T* C, int64_t ldc) {
  auto opts = at::TensorOptions().dtype(c10::CppTypeToScalarType<T>::value);
  at::Tensor a = ta ? at::from_blob(const_cast<T*>(A), {K, M}, {lda, 1}, opts).t()
                    : at::from_blob(const_cast<T*>(A), {M, K}, {lda, 1}, opts);
  at::Tensor b = tb ? at::from_blob(const_cast<T*>(B), {N, K}, {ldb, 1}, opts).t()
                    : at::from_blob(const_cast<T*>(B), {K, N}, {ldb, 1}, opts);
  at::Tensor c = at::from_blob(C, {M, N}, {ldc, 1}, opts);
  at::Tensor prod = at::mm(a, b);
  if (beta == T(0)) {
    c.copy_(prod.mul_(alpha));
  } else {
    c.mul_(beta).add_(prod, alpha);
  }
}

template <typename T>
void gemm(bool ta, bool tb, int64_t M, int64_t N, int64_t K, T alpha, const T* A, int64_t lda, const T* B,
          int64_t ldb, T beta, T* C, int64_t ldc) {
  if (M == 0 || N == 0) return;
  // Column-major view: C^T (N x M) = op(B)^T (N x K) * op(A)^T (K x M).
  const char tra = tb ? 'T' : 'N', trb = ta ? 'T' : 'N';
  const int m = static_cast<int>(N), n = static_cast<int>(M), k = static_cast<int>(K);
  const int la = static_cast<int>(ldb), lb = static_cast<int>(lda), lc = static_cast<int>(ldc);
  if constexpr (std::is_same_v<T, float>) {
    if (sgemm_ != nullptr) {
      sgemm_(&tra, &trb, &m, &n, &k, &alpha, B, &la, A, &lb, &beta, C, &lc);
      return;
    }
  } else {
    if (dgemm_ != nullptr) {
      dgemm_(&tra, &trb, &m, &n, &k, &alpha, B, &la, A, &lb, &beta, C, &lc);
      return;
    }
  }
  gemm_fallback<T>(ta, tb, M, N, K, alpha, A, lda, B, ldb, beta, C, ldc);
}

// Our tasks already fill the machine: every BLAS call must run on the calling thread alone.  MKL would otherwise
// start its own team for calls made outside an OpenMP region (the serial path for small problems), which costs
// far more than these small products.  The setting is per thread; the guard restores it.
struct BlasSequential {
  int prev = -1;
  BlasSequential() {
    if (MKL_Set_Num_Threads_Local != nullptr) prev = MKL_Set_Num_Threads_Local(1);
  }
  ~BlasSequential() {
    if (MKL_Set_Num_Threads_Local != nullptr && prev >= 0) MKL_Set_Num_Threads_Local(prev);
  }
  BlasSequential(const BlasSequential&) = delete;
  BlasSequential& operator=(const BlasSequential&) = delete;
};

// ------------------------------------------------------------------------------------------------ time maps
inline int64_t mirror(int64_t q, int64_t L) { return q < 0 ? -q : (q >= L ? 2 * (L - 1) - q : q); }
inline int64_t ceil_div_pos(int64_t a, int64_t b) { return (a + b - 1) / b; }

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

// Optional per-(b, channel, entity) factor with arbitrary strides (style: entity stride 0; demod: full).
template <typename T>
struct Scale {
  const T* p = nullptr;
  int64_t sb = 0, sc = 0, se = 0;
  inline T at(int64_t b, int64_t c, int64_t e) const { return p ? p[b * sb + c * sc + e * se] : T(1); }
};

// Panel rows (s, c, u) x columns (bl, t):  f(b,c,e_s) * src[b, c, e_s, pad(stride*t + u - h)], t in [0, Tout).
// src is (B, C, Es, Ts).  Out-of-range frames are zero or mirrored (reflect).
template <typename T>
void gather_strided(T* dst, int64_t ldd, const T* src, int64_t C, int64_t Es, int64_t Ts, const int64_t* ents,
                    int64_t k, int64_t b0, int64_t nb, int64_t Tout, int64_t stride, int64_t U, bool reflect,
                    const Scale<T>& f) {
  const int64_t h = U / 2;
  for (int64_t s = 0; s < k; ++s) {
    const int64_t e = ents[s];
    for (int64_t c = 0; c < C; ++c) {
      for (int64_t u = 0; u < U; ++u) {
        T* d = dst + ((s * C + c) * U + u) * ldd;
        const int64_t off = u - h;
        int64_t tlo = off >= 0 ? 0 : ceil_div_pos(-off, stride);
        int64_t thi = (Ts - 1 - off) >= 0 ? (Ts - 1 - off) / stride + 1 : 0;
        tlo = std::min(tlo, Tout);
        thi = std::max(std::min(thi, Tout), tlo);
        for (int64_t bl = 0; bl < nb; ++bl) {
          const int64_t b = b0 + bl;
          const T* r = src + ((b * C + c) * Es + e) * Ts;
          const T fv = f.at(b, c, e);
          T* dd = d + bl * Tout;
          for (int64_t t = 0; t < tlo; ++t) dd[t] = reflect ? fv * r[mirror(stride * t + off, Ts)] : T(0);
          if (stride == 1) {
            const T* rr = r + off;
            for (int64_t t = tlo; t < thi; ++t) dd[t] = fv * rr[t];
          } else {
            for (int64_t t = tlo; t < thi; ++t) dd[t] = fv * r[stride * t + off];
          }
          for (int64_t t = thi; t < Tout; ++t) dd[t] = reflect ? fv * r[mirror(stride * t + off, Ts)] : T(0);
        }
      }
    }
  }
}

// Transposed panel rows (s, c, u) x columns (bl, q), q in [0, Tp) of a padded output domain:
//   f(b,c,e_s) * src[b, c, e_s, (q - u) / stride] where (q - u) is a multiple of stride in range, else 0.
template <typename T>
void gather_transposed(T* dst, int64_t ldd, const T* src, int64_t C, int64_t Es, int64_t Ts, const int64_t* ents,
                       int64_t k, int64_t b0, int64_t nb, int64_t Tp, int64_t stride, int64_t U, const Scale<T>& f) {
  for (int64_t s = 0; s < k; ++s) {
    const int64_t e = ents[s];
    for (int64_t c = 0; c < C; ++c) {
      for (int64_t u = 0; u < U; ++u) {
        T* d = dst + ((s * C + c) * U + u) * ldd;
        for (int64_t bl = 0; bl < nb; ++bl) {
          const int64_t b = b0 + bl;
          const T* r = src + ((b * C + c) * Es + e) * Ts;
          const T fv = f.at(b, c, e);
          T* dd = d + bl * Tp;
          if (stride == 1) {
            const int64_t lo = std::min(u, Tp), hi = std::min(u + Ts, Tp);
            for (int64_t q = 0; q < lo; ++q) dd[q] = T(0);
            for (int64_t q = lo; q < hi; ++q) dd[q] = fv * r[q - u];
            for (int64_t q = hi; q < Tp; ++q) dd[q] = T(0);
          } else {
            std::fill(dd, dd + Tp, T(0));
            for (int64_t t = 0; t < Ts; ++t) {
              const int64_t q = stride * t + u;
              if (q >= Tp) break;
              dd[q] = fv * r[t];
            }
          }
        }
      }
    }
  }
}

// Fold a padded-domain row g (length L + 2h) onto [0, L): the adjoint of zero / reflect padding.
template <typename T>
inline void fold_row(const T* g, T* out, int64_t L, int64_t h, bool reflect) {
  for (int64_t t = 0; t < L; ++t) out[t] = g[t + h];
  if (reflect) {
    for (int64_t q = 0; q < h; ++q) out[mirror(q - h, L)] += g[q];
    for (int64_t q = L + h; q < L + 2 * h; ++q) out[mirror(q - h, L)] += g[q];
  }
}

// StyleGAN2 blur after upsampling: y[t] = (v[t-2] + 3 v[t-1] + 3 v[t] + v[t+1]) / 4, zero outside [0, L).
template <typename T>
inline void blur_row(const T* v, T* y, int64_t L) {
  for (int64_t t = 0; t < L; ++t) {
    T acc = T(3) * v[t];
    if (t >= 2) acc += v[t - 2];
    if (t >= 1) acc += T(3) * v[t - 1];
    if (t + 1 < L) acc += v[t + 1];
    y[t] = T(0.25) * acc;
  }
}

// Its adjoint: gv[s] = (g[s-1] + 3 g[s] + 3 g[s+1] + g[s+2]) / 4.
template <typename T>
inline void blur_adjoint_row(const T* g, T* gv, int64_t L) {
  for (int64_t s = 0; s < L; ++s) {
    T acc = T(3) * g[s];
    if (s >= 1) acc += g[s - 1];
    if (s + 1 < L) acc += T(3) * g[s + 1];
    if (s + 2 < L) acc += g[s + 2];
    gv[s] = T(0.25) * acc;
  }
}

// ------------------------------------------------------------------------------------------------ topology
struct Csr {
  std::vector<int64_t> off, idx;          // row entity -> input entities (pairs p in [off[j], off[j+1]))
  std::vector<int64_t> toff, tent, tpair;  // input entity -> (row entity, pair), ordered by row entity
  int64_t rows = 0, cols = 0, max_deg = 0, max_tdeg = 0;
};

Csr make_csr(const at::Tensor& index, const at::Tensor& offsets, int64_t n_cols) {
  TORCH_CHECK(index.device().is_cpu() && offsets.device().is_cpu(), "index and offsets must be CPU tensors here");
  TORCH_CHECK(index.scalar_type() == at::kLong, "index must be int64, got ", index.scalar_type());
  TORCH_CHECK(offsets.scalar_type() == at::kLong, "offsets must be int64, got ", offsets.scalar_type());
  TORCH_CHECK(index.dim() == 1, "index must be 1-D, got ", index.dim(), " dims");
  TORCH_CHECK(offsets.dim() == 1 && offsets.numel() >= 2, "offsets must be 1-D with at least 2 entries");
  Csr g;
  g.rows = offsets.numel() - 1;
  g.cols = n_cols;
  auto oc = offsets.contiguous();
  auto ic = index.contiguous();
  const int64_t* o = oc.data_ptr<int64_t>();
  const int64_t* ix = ic.data_ptr<int64_t>();
  const int64_t nnz = index.numel();
  TORCH_CHECK(o[0] == 0 && o[g.rows] == nnz, "offsets must run from 0 to index.numel()=", nnz, ", got ", o[0],
              "..", o[g.rows]);
  g.off.assign(o, o + g.rows + 1);
  g.idx.assign(ix, ix + nnz);
  for (int64_t j = 0; j < g.rows; ++j) {
    const int64_t deg = o[j + 1] - o[j];
    TORCH_CHECK(deg > 0, "offsets: entity ", j, " has no neighbors");
    g.max_deg = std::max(g.max_deg, deg);
  }
  std::vector<int64_t> cnt(n_cols, 0);
  for (int64_t p = 0; p < nnz; ++p) {
    TORCH_CHECK(ix[p] >= 0 && ix[p] < n_cols, "index[", p, "] = ", ix[p], " is out of range [0, ", n_cols, ")");
    cnt[ix[p]]++;
  }
  g.toff.assign(n_cols + 1, 0);
  for (int64_t n = 0; n < n_cols; ++n) {
    g.toff[n + 1] = g.toff[n] + cnt[n];
    g.max_tdeg = std::max(g.max_tdeg, cnt[n]);
  }
  g.tent.resize(nnz);
  g.tpair.resize(nnz);
  std::vector<int64_t> pos(g.toff.begin(), g.toff.end() - 1);
  for (int64_t j = 0; j < g.rows; ++j)
    for (int64_t p = o[j]; p < o[j + 1]; ++p) {
      const int64_t q = pos[ix[p]]++;
      g.tent[q] = j;
      g.tpair[q] = p;
    }
  return g;
}

// (C0, nnz, C1, U) -> (C1, nnz, C0, U) with pairs in transposed order: out[c1, q, c0, u] = w[c0, tpair[q], c1, u].
// One task per c1 (a preparation phase of the pass that reads it).
template <typename T>
void transpose_weight_row(T* out, const T* w, int64_t C0, int64_t nnz, int64_t C1, int64_t U,
                          const std::vector<int64_t>& tpair, int64_t c1) {
  for (int64_t q = 0; q < nnz; ++q)
    for (int64_t c0 = 0; c0 < C0; ++c0) {
      const T* src = w + ((c0 * nnz + tpair[q]) * C1 + c1) * U;
      T* dst = out + ((c1 * nnz + q) * C0 + c0) * U;
      for (int64_t u = 0; u < U; ++u) dst[u] = src[u];
    }
}

// ------------------------------------------------------------------------------------------------ geometry
struct Geo {
  int64_t kind, B, Cin, Cout, Ein, Eout, Tin, Tout, U, h, nnz;
  bool reflect;
  double macs;  // multiply-adds of one GEMM pass (forward, input or weight gradient)
};

bool parse_padding(c10::string_view mode) {
  if (mode == "zeros") return false;
  if (mode == "reflect") return true;
  TORCH_CHECK(false, "padding_mode must be 'zeros' or 'reflect', got '", std::string(mode), "'");
  return false;
}

void check_float(const at::Tensor& t, const char* name, const at::Tensor& x) {
  TORCH_CHECK(t.device() == x.device(), name, " is on ", t.device(), " but x is on ", x.device());
  TORCH_CHECK(t.scalar_type() == x.scalar_type(), name, " has dtype ", t.scalar_type(), " but x has ",
              x.scalar_type());
  TORCH_CHECK(t.is_contiguous(), name, " must be contiguous");
}

Geo check_inputs(int64_t kind, const at::Tensor& x, const at::Tensor& weight, const std::optional<at::Tensor>& bias,
                 const at::Tensor& index, const at::Tensor& offsets, int64_t n_out,
                 const std::optional<at::Tensor>& style, const std::optional<at::Tensor>& scale,
                 c10::string_view padding_mode) {
  TORCH_CHECK(x.device().is_cpu(), "x must be a CPU tensor for the CPU kernel, got ", x.device());
  TORCH_CHECK(x.dim() == 4, "x must be 4-D (B, C, E, T), got ", x.dim(), " dims");
  TORCH_CHECK(x.scalar_type() == at::kFloat || x.scalar_type() == at::kDouble, "x must be float32 or float64, got ",
              x.scalar_type());
  TORCH_CHECK(x.is_contiguous(), "x must be contiguous");
  TORCH_CHECK(weight.dim() == 4, "weight must be 4-D compact (C0, nnz, C1, U), got ", weight.dim(), " dims");
  check_float(weight, "weight", x);
  Geo g{};
  g.kind = kind;
  g.reflect = parse_padding(padding_mode);
  g.B = x.size(0);
  g.Tin = x.size(3);
  TORCH_CHECK(g.B > 0, "x has an empty batch (B == 0)");
  TORCH_CHECK(g.Tin > 0, "x has zero frames (T == 0)");
  g.U = weight.size(3);
  TORCH_CHECK(g.U % 2 == 1, "weight kernel width U=", g.U, " must be odd");
  g.h = g.U / 2;
  g.nnz = weight.size(1);
  TORCH_CHECK(index.dim() == 1 && index.numel() == g.nnz, "weight has ", g.nnz, " pairs (dim 1) but index has ",
              index.numel(), " entries");
  TORCH_CHECK(offsets.dim() == 1 && offsets.numel() >= 2, "offsets must be 1-D with at least 2 entries");
  const int64_t rows = offsets.numel() - 1;
  if (kind == kUp) {
    g.Cin = weight.size(0);
    g.Cout = weight.size(2);
    TORCH_CHECK(x.size(2) == rows, "x has ", x.size(2), " coarse entities but offsets describes ", rows);
    TORCH_CHECK(n_out > 0, "n_out must be positive, got ", n_out);
    g.Ein = rows;
    g.Eout = n_out;
    g.Tout = 2 * g.Tin;
    TORCH_CHECK(!g.reflect || g.h < g.Tout, "reflect padding of ", g.h, " frames needs more than ", g.h,
                " frames, got ", g.Tout);
  } else {
    g.Cout = weight.size(0);
    g.Cin = weight.size(2);
    g.Ein = x.size(2);
    g.Eout = rows;
    if (kind == kConv) {
      TORCH_CHECK(g.Ein == rows, "x has ", g.Ein, " entities but the neighbor lists (offsets) describe ", rows);
      g.Tout = g.Tin;
    } else {
      TORCH_CHECK(g.Tin >= 2, "x needs at least 2 frames to downsample, got ", g.Tin);
      g.Tout = g.Tin / 2;
    }
    TORCH_CHECK(!g.reflect || g.h < g.Tin, "reflect padding of ", g.h, " frames needs more than ", g.h,
                " frames, got ", g.Tin);
  }
  TORCH_CHECK(x.size(1) == g.Cin, "x has ", x.size(1), " channels but weight expects ", g.Cin);
  g.macs = double(g.B) * double(g.kind == kUp ? g.Tin : g.Tout) * double(g.Cout) * double(g.nnz) * double(g.Cin) *
           double(g.U);
  if (bias.has_value()) {
    check_float(*bias, "bias", x);
    TORCH_CHECK(bias->dim() == 1 && bias->size(0) == g.Cout, "bias must have shape (", g.Cout, "), got ",
                bias->sizes());
  }
  if (style.has_value()) {
    check_float(*style, "style", x);
    TORCH_CHECK(style->dim() == 2 && style->size(0) == g.B && style->size(1) == g.Cin, "style must be (B, Cin) = (",
                g.B, ", ", g.Cin, "), got ", style->sizes());
  }
  if (scale.has_value()) {
    check_float(*scale, "scale", x);
    TORCH_CHECK(scale->dim() == 3 && scale->size(0) == g.B && scale->size(1) == g.Cout && scale->size(2) == g.Eout,
                "scale must be (B, Cout, E_out) = (", g.B, ", ", g.Cout, ", ", g.Eout, "), got ", scale->sizes());
  }
  return g;
}

// Batch elements per tile: about `target` panel columns, at least kMinTasks tasks (entities x tiles) when the batch
// allows, tiles as even as the count permits.  Depends on the shapes only (never on the thread count), so the
// same products are computed whatever the threads.
int64_t batch_tile(int64_t B, int64_t cols_per_b, int64_t n_entities, int64_t target = 512) {
  constexpr int64_t kMinCols = 32;  // narrower products waste more in per-call overhead than balance gains
  int64_t nb = std::max<int64_t>(1, target / std::max<int64_t>(1, cols_per_b));
  nb = std::min(nb, B);
  while (nb > 1 && ((B + nb - 1) / nb) * n_entities < kMinTasks && ((nb + 1) / 2) * cols_per_b >= kMinCols)
    nb = (nb + 1) / 2;
  const int64_t nbt = (B + nb - 1) / nb;
  return (B + nbt - 1) / nbt;
}

template <typename T>
Scale<T> style_scale(const std::optional<at::Tensor>& style, int64_t C) {
  Scale<T> s;
  if (style.has_value()) {
    s.p = style->data_ptr<T>();
    s.sb = C;
    s.sc = 1;
    s.se = 0;
  }
  return s;
}

template <typename T>
Scale<T> entity_scale(const T* p, int64_t C, int64_t E) {
  Scale<T> s;
  s.p = p;
  s.sb = C * E;
  s.sc = E;
  s.se = 1;
  return s;
}

// ------------------------------------------------------------------------------------------------ forward
template <typename T>
void forward_conv_down(const Geo& g, const Csr& csr, const T* x, const T* w, const T* bias, const Scale<T>& sty,
                       const T* scale, T* y) {
  const int64_t stride = g.kind == kDown ? 2 : 1;
  const int64_t nb = batch_tile(g.B, g.Tout, g.Eout);
  const int64_t maxK = csr.max_deg * g.Cin * g.U, cols = nb * g.Tout;
  const int64_t lda = g.nnz * g.Cin * g.U;
  const std::vector<int64_t> order = lpt_tiles(g.B, nb, g.Eout, csr.off);
  SlotScratch<T> panels, accs;
  auto task = [&](int64_t t, int slot) {
    BlasSequential blas_guard;
    T* panel = panels.get(slot, static_cast<size_t>(maxK * cols));
    T* acc = accs.get(slot, static_cast<size_t>(g.Cout * cols));
    const int64_t bt = order[t] / g.Eout, j = order[t] % g.Eout;
    const int64_t b0 = bt * nb, nbl = std::min(nb, g.B - b0), N = nbl * g.Tout;
    const int64_t p0 = csr.off[j], k = csr.off[j + 1] - p0, K = k * g.Cin * g.U;
    gather_strided<T>(panel, N, x, g.Cin, g.Ein, g.Tin, csr.idx.data() + p0, k, b0, nbl, g.Tout, stride, g.U,
                      g.reflect, sty);
    gemm<T>(false, false, g.Cout, N, K, T(1), w + p0 * g.Cin * g.U, lda, panel, N, T(0), acc, N);
    for (int64_t bl = 0; bl < nbl; ++bl) {
      const int64_t b = b0 + bl;
      for (int64_t o = 0; o < g.Cout; ++o) {
        const T f = scale ? scale[(b * g.Cout + o) * g.Eout + j] : T(1);
        const T bb = bias ? bias[o] : T(0);
        const T* src = acc + o * N + bl * g.Tout;
        T* dst = y + ((b * g.Cout + o) * g.Eout + j) * g.Tout;
        for (int64_t t2 = 0; t2 < g.Tout; ++t2) dst[t2] = src[t2] * f + bb;
      }
    }
  };
  run_phases({phase(static_cast<int64_t>(order.size()), task)}, worth_threads(g.macs));
}

template <typename T>
void forward_up(const Geo& g, const Csr& csr, const T* x, const T* w, const T* bias, const Scale<T>& sty,
                const T* scale, T* y) {
  // For fine entity f: V (Cout x nb*Tp) = Wt_f (Cout x k*Cin*U) * transposed panel of its coarse sources.
  const bool par = worth_threads(g.macs);
  Buf<T> wt;
  wt.alloc(static_cast<size_t>(g.Cin * g.nnz * g.Cout * g.U));
  auto tr = [&](int64_t c1, int) { transpose_weight_row<T>(wt.data(), w, g.Cin, g.nnz, g.Cout, g.U, csr.tpair, c1); };
  const Phase prep[] = {phase(g.Cout, tr)};
  const int64_t Tp = g.Tout + 2 * g.h;
  const int64_t nb = batch_tile(g.B, Tp, g.Eout);
  const int64_t maxK = csr.max_tdeg * g.Cin * g.U, cols = nb * Tp;
  const int64_t lda = g.nnz * g.Cin * g.U;
  const std::vector<int64_t> order = lpt_tiles(g.B, nb, g.Eout, csr.toff);
  SlotScratch<T> panels, accs, rows;
  auto task = [&](int64_t t, int slot) {
    BlasSequential blas_guard;
    const int64_t bt = order[t] / g.Eout, f = order[t] % g.Eout;
    const int64_t b0 = bt * nb, nbl = std::min(nb, g.B - b0), N = nbl * Tp;
    const int64_t q0 = csr.toff[f], k = csr.toff[f + 1] - q0, K = k * g.Cin * g.U;
    if (k == 0) {
      for (int64_t bl = 0; bl < nbl; ++bl)
        for (int64_t o = 0; o < g.Cout; ++o) {
          T* dst = y + (((b0 + bl) * g.Cout + o) * g.Eout + f) * g.Tout;
          std::fill(dst, dst + g.Tout, bias ? bias[o] : T(0));
        }
      return;
    }
    T* panel = panels.get(slot, static_cast<size_t>(maxK * cols));
    T* acc = accs.get(slot, static_cast<size_t>(g.Cout * cols));
    T* v = rows.get(slot, static_cast<size_t>(2 * g.Tout));
    T* bl_out = v + g.Tout;
    gather_transposed<T>(panel, N, x, g.Cin, g.Ein, g.Tin, csr.tent.data() + q0, k, b0, nbl, Tp, 2, g.U, sty);
    gemm<T>(false, false, g.Cout, N, K, T(1), wt.data() + q0 * g.Cin * g.U, lda, panel, N, T(0), acc, N);
    for (int64_t bl = 0; bl < nbl; ++bl) {
      const int64_t b = b0 + bl;
      for (int64_t o = 0; o < g.Cout; ++o) {
        const T fs = scale ? scale[(b * g.Cout + o) * g.Eout + f] : T(1);
        const T bb = bias ? bias[o] : T(0);
        fold_row<T>(acc + o * N + bl * Tp, v, g.Tout, g.h, g.reflect);
        blur_row<T>(v, bl_out, g.Tout);
        T* dst = y + ((b * g.Cout + o) * g.Eout + f) * g.Tout;
        for (int64_t t2 = 0; t2 < g.Tout; ++t2) dst[t2] = bl_out[t2] * fs + bb;
      }
    }
  };
  const Phase compute[] = {phase(static_cast<int64_t>(order.size()), task)};
  run_stages({{prep, 1}, {compute, 1}}, par);
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

// ================================================================================================ fp32 fast path
// Indirect GEMM on AVX2/FMA (AVX-512 variants where the CPU has them), used for float32 when the CPU has AVX2
// (MODI_EXT_CPU_KERNEL=blas forces the BLAS path above, =avx2 the AVX2 kernels).  Instead of gathering a (K x N) panel per entity and letting BLAS repack it, every input is laid out
// once per call in "column" form: row (phase, channel, entity) holds all batch elements back to back, each padded
// in time (zero / reflect, or the front zeros of a transposed conv) and, for stride 2, split into even/odd phases.
// A time shift u is then just a pointer offset, so an entity's operand is a table of K row pointers, and the
// register-blocked kernels below read those rows in place: columns = batch x padded time, the long GEMM side.
namespace fastk {

constexpr int64_t MR = 4, NR = 24;  // NN tile: 4 output rows x 24 columns = 12 ymm accumulators
constexpr int64_t TM = 4, TK = 3;   // NT tile: 4 x 3 dot products, 8 lanes each
constexpr int64_t kMinFrames = 16;  // below this the padded columns waste more than the kernels gain
constexpr int64_t kNarrowRows = 10; // weight-gradient rows up to which the indirect NT kernel beats BLAS (measured:
                                    // 9 rows 1.2x faster at MoDi's batch 16, 12 rows 1.4x slower; GANimator 3-9)

inline bool wanted() {
#if defined(__x86_64__)
  static const bool cpu = __builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma");
  const char* env = std::getenv("MODI_EXT_CPU_KERNEL");
  if (env != nullptr && std::strcmp(env, "blas") == 0) return false;
  return cpu;
#else
  return false;
#endif
}

inline int64_t round_up(int64_t a, int64_t m) { return (a + m - 1) / m * m; }

#if defined(__x86_64__)
// The NN kernels read a short strip of a different pointer row at every step: hundreds of streams per product,
// more than the hardware prefetchers follow, so the loads wait on L2.  Each step asks for the strip that the step
// kPrefetchSteps ahead will read (finest-level skeletal conv fwd+bwd 8% faster, interleaved A/B; distances 8-32
// measured alike).
constexpr int64_t kPrefetchSteps = 16;
template <int FLOATS>
inline void prefetch_strip(const float* p) {
  const char* q = reinterpret_cast<const char*>(p);
  for (int b = 0; b < FLOATS * 4; b += 64) _mm_prefetch(q + b, _MM_HINT_T0);
  _mm_prefetch(q + FLOATS * 4 - 1, _MM_HINT_T0);  // the strip is unaligned: its last line
}

// C[0:4, col:col+24] = sum_k a[k*4 + r] * ptr[k][col : col+24]   (a: one packed 4-row panel)
__attribute__((target("avx2,fma"))) void nn_kernel(int64_t K, const float* a, const float* const* ptr, int64_t col,
                                                    float* c, int64_t ldc) {
  __m256 c00 = _mm256_setzero_ps(), c01 = c00, c02 = c00, c10 = c00, c11 = c00, c12 = c00;
  __m256 c20 = c00, c21 = c00, c22 = c00, c30 = c00, c31 = c00, c32 = c00;
  for (int64_t k = 0; k < K; ++k) {
    const float* p = ptr[k] + col;
    if (k + kPrefetchSteps < K) prefetch_strip<24>(ptr[k + kPrefetchSteps] + col);
    const __m256 b0 = _mm256_loadu_ps(p), b1 = _mm256_loadu_ps(p + 8), b2 = _mm256_loadu_ps(p + 16);
    __m256 av = _mm256_broadcast_ss(a);
    c00 = _mm256_fmadd_ps(av, b0, c00);
    c01 = _mm256_fmadd_ps(av, b1, c01);
    c02 = _mm256_fmadd_ps(av, b2, c02);
    av = _mm256_broadcast_ss(a + 1);
    c10 = _mm256_fmadd_ps(av, b0, c10);
    c11 = _mm256_fmadd_ps(av, b1, c11);
    c12 = _mm256_fmadd_ps(av, b2, c12);
    av = _mm256_broadcast_ss(a + 2);
    c20 = _mm256_fmadd_ps(av, b0, c20);
    c21 = _mm256_fmadd_ps(av, b1, c21);
    c22 = _mm256_fmadd_ps(av, b2, c22);
    av = _mm256_broadcast_ss(a + 3);
    c30 = _mm256_fmadd_ps(av, b0, c30);
    c31 = _mm256_fmadd_ps(av, b1, c31);
    c32 = _mm256_fmadd_ps(av, b2, c32);
    a += 4;
  }
  _mm256_storeu_ps(c, c00);
  _mm256_storeu_ps(c + 8, c01);
  _mm256_storeu_ps(c + 16, c02);
  c += ldc;
  _mm256_storeu_ps(c, c10);
  _mm256_storeu_ps(c + 8, c11);
  _mm256_storeu_ps(c + 16, c12);
  c += ldc;
  _mm256_storeu_ps(c, c20);
  _mm256_storeu_ps(c + 8, c21);
  _mm256_storeu_ps(c + 16, c22);
  c += ldc;
  _mm256_storeu_ps(c, c30);
  _mm256_storeu_ps(c + 8, c31);
  _mm256_storeu_ps(c + 16, c32);
}

// The last panel's live rows only (M % 4 of them): narrow layers (GANimator's 5-9 channels) would otherwise spend up
// to 3/4 of that panel's multiply-adds on padding rows.
template <int R>
__attribute__((target("avx2,fma"))) void nn_rows(int64_t K, const float* a, const float* const* ptr, int64_t col,
                                                  float* c, int64_t ldc) {
  __m256 acc[R][3];
  for (int r = 0; r < R; ++r) acc[r][0] = acc[r][1] = acc[r][2] = _mm256_setzero_ps();
  for (int64_t k = 0; k < K; ++k) {
    const float* p = ptr[k] + col;
    if (k + kPrefetchSteps < K) prefetch_strip<24>(ptr[k + kPrefetchSteps] + col);
    const __m256 b0 = _mm256_loadu_ps(p), b1 = _mm256_loadu_ps(p + 8), b2 = _mm256_loadu_ps(p + 16);
    for (int r = 0; r < R; ++r) {
      const __m256 av = _mm256_broadcast_ss(a + r);
      acc[r][0] = _mm256_fmadd_ps(av, b0, acc[r][0]);
      acc[r][1] = _mm256_fmadd_ps(av, b1, acc[r][1]);
      acc[r][2] = _mm256_fmadd_ps(av, b2, acc[r][2]);
    }
    a += 4;
  }
  for (int r = 0; r < R; ++r) {
    _mm256_storeu_ps(c + r * ldc, acc[r][0]);
    _mm256_storeu_ps(c + r * ldc + 8, acc[r][1]);
    _mm256_storeu_ps(c + r * ldc + 16, acc[r][2]);
  }
}

__attribute__((target("avx2,fma"))) inline float hsum(__m256 v) {
  __m128 s = _mm_add_ps(_mm256_castps256_ps128(v), _mm256_extractf128_ps(v, 1));
  s = _mm_hadd_ps(s, s);
  s = _mm_hadd_ps(s, s);
  return _mm_cvtss_f32(s);
}

// C[i][j] += sum_{col in [c0, c0+n)} l[i][col] * p[j][col]  for a 4 x 3 tile.
__attribute__((target("avx2,fma"))) void nt_kernel(const float* const* l, const float* const* p, int64_t c0,
                                                    int64_t n, float* C, int64_t ldc) {
  __m256 a00 = _mm256_setzero_ps(), a01 = a00, a02 = a00, a10 = a00, a11 = a00, a12 = a00;
  __m256 a20 = a00, a21 = a00, a22 = a00, a30 = a00, a31 = a00, a32 = a00;
  const float *l0 = l[0], *l1 = l[1], *l2 = l[2], *l3 = l[3], *p0 = p[0], *p1 = p[1], *p2 = p[2];
  int64_t c = c0;
  const int64_t end = c0 + n;
#define MODI_NT_STEP(x0, x1, x2, x3, y0, y1, y2)                                                      \
  do {                                                                                                 \
    const __m256 X0 = (x0), X1 = (x1), X2 = (x2), X3 = (x3), Y0 = (y0), Y1 = (y1), Y2 = (y2);          \
    a00 = _mm256_fmadd_ps(X0, Y0, a00);                                                                \
    a01 = _mm256_fmadd_ps(X0, Y1, a01);                                                                \
    a02 = _mm256_fmadd_ps(X0, Y2, a02);                                                                \
    a10 = _mm256_fmadd_ps(X1, Y0, a10);                                                                \
    a11 = _mm256_fmadd_ps(X1, Y1, a11);                                                                \
    a12 = _mm256_fmadd_ps(X1, Y2, a12);                                                                \
    a20 = _mm256_fmadd_ps(X2, Y0, a20);                                                                \
    a21 = _mm256_fmadd_ps(X2, Y1, a21);                                                                \
    a22 = _mm256_fmadd_ps(X2, Y2, a22);                                                                \
    a30 = _mm256_fmadd_ps(X3, Y0, a30);                                                                \
    a31 = _mm256_fmadd_ps(X3, Y1, a31);                                                                \
    a32 = _mm256_fmadd_ps(X3, Y2, a32);                                                                \
  } while (0)
  for (; c + 8 <= end; c += 8)
    MODI_NT_STEP(_mm256_loadu_ps(l0 + c), _mm256_loadu_ps(l1 + c), _mm256_loadu_ps(l2 + c), _mm256_loadu_ps(l3 + c),
                 _mm256_loadu_ps(p0 + c), _mm256_loadu_ps(p1 + c), _mm256_loadu_ps(p2 + c));
  if (c < end) {
    const __m256i m = _mm256_cmpgt_epi32(_mm256_set1_epi32(static_cast<int>(end - c)),
                                         _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7));
    MODI_NT_STEP(_mm256_maskload_ps(l0 + c, m), _mm256_maskload_ps(l1 + c, m), _mm256_maskload_ps(l2 + c, m),
                 _mm256_maskload_ps(l3 + c, m), _mm256_maskload_ps(p0 + c, m), _mm256_maskload_ps(p1 + c, m),
                 _mm256_maskload_ps(p2 + c, m));
  }
#undef MODI_NT_STEP
  C[0] += hsum(a00);
  C[1] += hsum(a01);
  C[2] += hsum(a02);
  C[ldc] += hsum(a10);
  C[ldc + 1] += hsum(a11);
  C[ldc + 2] += hsum(a12);
  C[2 * ldc] += hsum(a20);
  C[2 * ldc + 1] += hsum(a21);
  C[2 * ldc + 2] += hsum(a22);
  C[3 * ldc] += hsum(a30);
  C[3 * ldc + 1] += hsum(a31);
  C[3 * ldc + 2] += hsum(a32);
}
#else
void nn_kernel(int64_t, const float*, const float* const*, int64_t, float*, int64_t) {}
template <int R>
void nn_rows(int64_t, const float*, const float* const*, int64_t, float*, int64_t) {}
void nt_kernel(const float* const*, const float* const*, int64_t, int64_t, float*, int64_t) {}
#endif

// Edge tiles of the NT product (fewer than 4 rows or 3 pointer rows), vectorised like the full tile.  GANimator's
// layers have 3-9 output channels, so an edge row is a large share of the weight gradient there.
#if defined(__x86_64__)
template <int MT, int KT>
__attribute__((target("avx2,fma"))) void nt_tile(const float* const* l, const float* const* p, int64_t c0, int64_t n,
                                                  float* C, int64_t ldc) {
  __m256 a[MT][KT];
  for (int i = 0; i < MT; ++i)
    for (int j = 0; j < KT; ++j) a[i][j] = _mm256_setzero_ps();
  int64_t c = c0;
  const int64_t end = c0 + n;
  for (; c + 8 <= end; c += 8) {
    __m256 X[MT], Y[KT];
    for (int i = 0; i < MT; ++i) X[i] = _mm256_loadu_ps(l[i] + c);
    for (int j = 0; j < KT; ++j) Y[j] = _mm256_loadu_ps(p[j] + c);
    for (int i = 0; i < MT; ++i)
      for (int j = 0; j < KT; ++j) a[i][j] = _mm256_fmadd_ps(X[i], Y[j], a[i][j]);
  }
  if (c < end) {
    const __m256i m = _mm256_cmpgt_epi32(_mm256_set1_epi32(static_cast<int>(end - c)),
                                         _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7));
    __m256 X[MT], Y[KT];
    for (int i = 0; i < MT; ++i) X[i] = _mm256_maskload_ps(l[i] + c, m);
    for (int j = 0; j < KT; ++j) Y[j] = _mm256_maskload_ps(p[j] + c, m);
    for (int i = 0; i < MT; ++i)
      for (int j = 0; j < KT; ++j) a[i][j] = _mm256_fmadd_ps(X[i], Y[j], a[i][j]);
  }
  for (int i = 0; i < MT; ++i)
    for (int j = 0; j < KT; ++j) C[i * ldc + j] += hsum(a[i][j]);
}

void nt_edge(const float* const* l, int64_t mr, const float* const* p, int64_t kr, int64_t c0, int64_t n, float* C,
             int64_t ldc) {
  using Fn = void (*)(const float* const*, const float* const*, int64_t, int64_t, float*, int64_t);
  static constexpr Fn table[TM][TK] = {{nt_tile<1, 1>, nt_tile<1, 2>, nt_tile<1, 3>},
                                       {nt_tile<2, 1>, nt_tile<2, 2>, nt_tile<2, 3>},
                                       {nt_tile<3, 1>, nt_tile<3, 2>, nt_tile<3, 3>},
                                       {nt_tile<4, 1>, nt_tile<4, 2>, nt_tile<4, 3>}};
  table[mr - 1][kr - 1](l, p, c0, n, C, ldc);
}
#else
void nt_edge(const float* const*, int64_t, const float* const*, int64_t, int64_t, int64_t, float*, int64_t) {}
#endif

// AVX-512 variants of the two kernels (same operands, twice the lanes), used when the CPU has AVX-512F
// (MODI_EXT_CPU_KERNEL=avx2 keeps the AVX2 ones).  NN: R rows x 48 columns (two NR tiles) per call.
#if defined(__x86_64__)
#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Wuninitialized"  // GCC 12's avx512fintrin.h masked-intrinsic false positive
#pragma GCC diagnostic ignored "-Wmaybe-uninitialized"
__attribute__((target("avx512f"))) inline float hsum512(__m512 v) {
  __m512 t = _mm512_add_ps(v, _mm512_shuffle_f32x4(v, v, _MM_SHUFFLE(1, 0, 3, 2)));
  t = _mm512_add_ps(t, _mm512_shuffle_f32x4(t, t, _MM_SHUFFLE(2, 3, 0, 1)));
  __m128 s = _mm512_castps512_ps128(t);
  s = _mm_add_ps(s, _mm_movehl_ps(s, s));
  s = _mm_add_ss(s, _mm_shuffle_ps(s, s, 1));
  return _mm_cvtss_f32(s);
}

// R rows (up to 9: 27 accumulators) x 48 columns (two NR tiles).  Row r comes from packed panel r / 4 (panels ps
// floats apart), so one call covers the last 5-9 rows of a product -- GANimator's 5-9 channels in one pass over the
// pointer rows instead of a 4- or 8-row pass plus a 1-row pass that is bound by its loads.  Direct: A is read in
// place, row r at a + r * ps (a row-major weight, no packing pass; each k broadcasts from R rows instead of from
// one packed group -- the same number of loads).
template <int R, bool Direct = false>
__attribute__((target("avx512f"))) void nn512rows(int64_t K, const float* a, int64_t ps, const float* const* ptr,
                                                   int64_t col, float* c, int64_t ldc) {
  static_assert(R >= 1 && R <= 9, "27 accumulators + 3 operands + 1 broadcast fill the 32 registers");
  __m512 acc[R][3];
  for (int r = 0; r < R; ++r) acc[r][0] = acc[r][1] = acc[r][2] = _mm512_setzero_ps();
  const float* ap[3] = {a, a + ps, a + 2 * ps};
  const float* ar[R];
  for (int r = 0; r < R; ++r) ar[r] = a + r * ps;
  for (int64_t k = 0; k < K; ++k) {
    const float* p = ptr[k] + col;
    if (k + kPrefetchSteps < K) prefetch_strip<48>(ptr[k + kPrefetchSteps] + col);
    const __m512 b0 = _mm512_loadu_ps(p), b1 = _mm512_loadu_ps(p + 16), b2 = _mm512_loadu_ps(p + 32);
    for (int r = 0; r < R; ++r) {
      const __m512 av = _mm512_set1_ps(Direct ? ar[r][k] : ap[r / 4][k * MR + r % 4]);
      acc[r][0] = _mm512_fmadd_ps(av, b0, acc[r][0]);
      acc[r][1] = _mm512_fmadd_ps(av, b1, acc[r][1]);
      acc[r][2] = _mm512_fmadd_ps(av, b2, acc[r][2]);
    }
  }
  for (int r = 0; r < R; ++r) {
    _mm512_storeu_ps(c + r * ldc, acc[r][0]);
    _mm512_storeu_ps(c + r * ldc + 16, acc[r][1]);
    _mm512_storeu_ps(c + r * ldc + 32, acc[r][2]);
  }
}

// One NR tile (24 columns: a full and a half-masked vector) for R rows (up to 9, panels as nn512rows): the odd
// last tile of a product, which the 4-row AVX2 kernel would do at half the width.
template <int R, bool Direct = false>
__attribute__((target("avx512f"))) void nn512_tail(int64_t K, const float* a, int64_t ps, const float* const* ptr,
                                                    int64_t col, float* c, int64_t ldc) {
  constexpr __mmask16 half = 0x00FF;
  __m512 acc[R][2];
  for (int r = 0; r < R; ++r) acc[r][0] = acc[r][1] = _mm512_setzero_ps();
  const float* ap[3] = {a, a + ps, a + 2 * ps};
  const float* ar[R];
  for (int r = 0; r < R; ++r) ar[r] = a + r * ps;
  for (int64_t k = 0; k < K; ++k) {
    const float* p = ptr[k] + col;
    if (k + kPrefetchSteps < K) prefetch_strip<NR>(ptr[k + kPrefetchSteps] + col);
    const __m512 b0 = _mm512_loadu_ps(p), b1 = _mm512_maskz_loadu_ps(half, p + 16);
    for (int r = 0; r < R; ++r) {
      const __m512 av = _mm512_set1_ps(Direct ? ar[r][k] : ap[r / 4][k * MR + r % 4]);
      acc[r][0] = _mm512_fmadd_ps(av, b0, acc[r][0]);
      acc[r][1] = _mm512_fmadd_ps(av, b1, acc[r][1]);
    }
  }
  for (int r = 0; r < R; ++r) {
    _mm512_storeu_ps(c + r * ldc, acc[r][0]);
    _mm512_mask_storeu_ps(c + r * ldc + 16, half, acc[r][1]);
  }
}

// NT: C[i][j] += sum_{col in [c0, c0+n)} l[i][col] * p[j][col] for an MT x KT tile, 16 lanes.
template <int MT, int KT>
__attribute__((target("avx512f"))) void nt512(const float* const* l, const float* const* p, int64_t c0, int64_t n,
                                               float* C, int64_t ldc) {
  __m512 a[MT][KT];
  for (int i = 0; i < MT; ++i)
    for (int j = 0; j < KT; ++j) a[i][j] = _mm512_setzero_ps();
  int64_t c = c0;
  const int64_t end = c0 + n;
  for (; c + 16 <= end; c += 16) {
    __m512 X[MT], Y[KT];
    for (int i = 0; i < MT; ++i) X[i] = _mm512_loadu_ps(l[i] + c);
    for (int j = 0; j < KT; ++j) Y[j] = _mm512_loadu_ps(p[j] + c);
    for (int i = 0; i < MT; ++i)
      for (int j = 0; j < KT; ++j) a[i][j] = _mm512_fmadd_ps(X[i], Y[j], a[i][j]);
  }
  if (c < end) {
    const __mmask16 m = static_cast<__mmask16>((1u << (end - c)) - 1u);
    __m512 X[MT], Y[KT];
    for (int i = 0; i < MT; ++i) X[i] = _mm512_maskz_loadu_ps(m, l[i] + c);
    for (int j = 0; j < KT; ++j) Y[j] = _mm512_maskz_loadu_ps(m, p[j] + c);
    for (int i = 0; i < MT; ++i)
      for (int j = 0; j < KT; ++j) a[i][j] = _mm512_fmadd_ps(X[i], Y[j], a[i][j]);
  }
  if constexpr (KT == 4) {  // four sums of a row at once (13 shuffles / adds instead of four hsum512)
    for (int i = 0; i < MT; ++i) {
      const __m512 ab = _mm512_add_ps(_mm512_unpacklo_ps(a[i][0], a[i][1]), _mm512_unpackhi_ps(a[i][0], a[i][1]));
      const __m512 cd = _mm512_add_ps(_mm512_unpacklo_ps(a[i][2], a[i][3]), _mm512_unpackhi_ps(a[i][2], a[i][3]));
      // per 128-bit lane: [a, b, c, d] partial sums
      __m512 t = _mm512_add_ps(_mm512_castpd_ps(_mm512_unpacklo_pd(_mm512_castps_pd(ab), _mm512_castps_pd(cd))),
                               _mm512_castpd_ps(_mm512_unpackhi_pd(_mm512_castps_pd(ab), _mm512_castps_pd(cd))));
      t = _mm512_add_ps(t, _mm512_shuffle_f32x4(t, t, _MM_SHUFFLE(1, 0, 3, 2)));
      t = _mm512_add_ps(t, _mm512_shuffle_f32x4(t, t, _MM_SHUFFLE(2, 3, 0, 1)));
      float* c = C + i * ldc;
      _mm_storeu_ps(c, _mm_add_ps(_mm_loadu_ps(c), _mm512_castps512_ps128(t)));
    }
  } else {
    for (int i = 0; i < MT; ++i)
      for (int j = 0; j < KT; ++j) C[i * ldc + j] += hsum512(a[i][j]);
  }
}

void nt512_tile(const float* const* l, int64_t mr, const float* const* p, int64_t kr, int64_t c0, int64_t n,
                float* C, int64_t ldc) {
  using Fn = void (*)(const float* const*, const float* const*, int64_t, int64_t, float*, int64_t);
  static constexpr Fn table[4][4] = {{nt512<1, 1>, nt512<1, 2>, nt512<1, 3>, nt512<1, 4>},
                                     {nt512<2, 1>, nt512<2, 2>, nt512<2, 3>, nt512<2, 4>},
                                     {nt512<3, 1>, nt512<3, 2>, nt512<3, 3>, nt512<3, 4>},
                                     {nt512<4, 1>, nt512<4, 2>, nt512<4, 3>, nt512<4, 4>}};
  table[mr - 1][kr - 1](l, p, c0, n, C, ldc);
}

// Weight-gradient tile in NN form: out[r][0:32] = sum_{n < N} x[r][n] * lt[n][0:32] for R pointer rows x (the K
// side, broadcast) and a packed 32-wide block lt of the transposed left operand.  24 accumulators at R = 12.
template <int R>
__attribute__((target("avx512f"))) void wg512(int64_t N, const float* const* x, const float* lt, float* out) {
  __m512 acc[R][2];
  for (int r = 0; r < R; ++r) acc[r][0] = acc[r][1] = _mm512_setzero_ps();
  const float* xr[R];
  for (int r = 0; r < R; ++r) xr[r] = x[r];
  for (int64_t n = 0; n < N; ++n) {
    const __m512 g0 = _mm512_loadu_ps(lt + n * 32), g1 = _mm512_loadu_ps(lt + n * 32 + 16);
    for (int r = 0; r < R; ++r) {
      const __m512 av = _mm512_set1_ps(xr[r][n]);
      acc[r][0] = _mm512_fmadd_ps(av, g0, acc[r][0]);
      acc[r][1] = _mm512_fmadd_ps(av, g1, acc[r][1]);
    }
  }
  for (int r = 0; r < R; ++r) {
    _mm512_storeu_ps(out + r * 32, acc[r][0]);
    _mm512_storeu_ps(out + r * 32 + 16, acc[r][1]);
  }
}

#pragma GCC diagnostic pop

inline bool use512() {
  static const bool cpu = __builtin_cpu_supports("avx512f");
  if (!cpu) return false;
  const char* env = std::getenv("MODI_EXT_CPU_KERNEL");
  return env == nullptr || std::strcmp(env, "avx2") != 0;
}
#else
template <int R>
void wg512(int64_t, const float* const*, const float*, float*) {}
template <int R, bool Direct = false>
void nn512rows(int64_t, const float*, int64_t, const float* const*, int64_t, float*, int64_t) {}
template <int R, bool Direct = false>
void nn512_tail(int64_t, const float*, int64_t, const float* const*, int64_t, float*, int64_t) {}
void nt512_tile(const float* const*, int64_t, const float* const*, int64_t, int64_t, int64_t, float*, int64_t) {}
inline bool use512() { return false; }
#endif

// acc (round_up(M,4) x ldacc) = packed A (panels of 4 rows x K) * pointer rows, columns [0, N) (tiles of 24; the
// columns past N are computed and ignored, rows past M are left untouched).  AVX2: column chunks keep the
// pointed-to data in L2 (the AVX-512 kernels prefetch it instead).
void nn_gemm(const float* apack, int64_t M, int64_t K, const float* const* ptr, int64_t N, float* acc,
             int64_t ldacc) {
  const int64_t panels = (M + MR - 1) / MR, tiles = (N + NR - 1) / NR;
  if (K == 0) {
    std::fill(acc, acc + panels * MR * ldacc, 0.f);
    return;
  }
  if (use512()) {
    // Pairs of NR tiles (48 columns) outermost; rows 8 at a time while more than 9 remain, then the rest in one
    // call; the odd last tile alike, at 24 columns.
    using Fn = void (*)(int64_t, const float*, int64_t, const float* const*, int64_t, float*, int64_t);
    static constexpr Fn pair[9] = {nn512rows<1>, nn512rows<2>, nn512rows<3>, nn512rows<4>, nn512rows<5>,
                                   nn512rows<6>, nn512rows<7>, nn512rows<8>, nn512rows<9>};
    static constexpr Fn tail[9] = {nn512_tail<1>, nn512_tail<2>, nn512_tail<3>, nn512_tail<4>, nn512_tail<5>,
                                   nn512_tail<6>, nn512_tail<7>, nn512_tail<8>, nn512_tail<9>};
    const int64_t ps = K * MR;
    for (int64_t t = 0; t < tiles; t += 2) {
      const Fn* fns = t + 1 < tiles ? pair : tail;
      for (int64_t m0 = 0; m0 < M;) {
        const int64_t R = M - m0 > 9 ? 8 : M - m0;
        fns[R - 1](K, apack + (m0 / MR) * ps, ps, ptr, t * NR, acc + m0 * ldacc + t * NR, ldacc);
        m0 += R;
      }
    }
    return;
  }
  const int64_t chunk = std::max<int64_t>(1, (160 * 1024) / (K * NR * 4));
  for (int64_t t0 = 0; t0 < tiles; t0 += chunk) {
    const int64_t t1 = std::min(tiles, t0 + chunk);
    for (int64_t pn = 0; pn < panels; ++pn) {
      const int64_t live = std::min<int64_t>(MR, M - pn * MR);
      const float* ap = apack + pn * K * MR;
      float* cp = acc + pn * MR * ldacc;
      for (int64_t t = t0; t < t1; ++t) {
        if (live == 4) nn_kernel(K, ap, ptr, t * NR, cp + t * NR, ldacc);
        else if (live == 3) nn_rows<3>(K, ap, ptr, t * NR, cp + t * NR, ldacc);
        else if (live == 2) nn_rows<2>(K, ap, ptr, t * NR, cp + t * NR, ldacc);
        else nn_rows<1>(K, ap, ptr, t * NR, cp + t * NR, ldacc);
      }
    }
  }
}

// AVX-512, M <= kDirectRows: acc (M x ldacc) = A (M rows of K, row r at a + r * lda: the compact weight read in
// place) * pointer rows, columns [0, N) in tiles of 48 (24 for an odd last one).  No packing pass: with GANimator's
// 5-9 output channels packing the weight was ~10% of a forward call at 129 frames, done anew on every call.
constexpr int64_t kDirectRows = 9;
void nn_gemm_direct(const float* a, int64_t lda, int64_t M, int64_t K, const float* const* ptr, int64_t N,
                    float* acc, int64_t ldacc) {
  using Fn = void (*)(int64_t, const float*, int64_t, const float* const*, int64_t, float*, int64_t);
  static constexpr Fn pair[9] = {nn512rows<1, true>, nn512rows<2, true>, nn512rows<3, true>,
                                 nn512rows<4, true>, nn512rows<5, true>, nn512rows<6, true>,
                                 nn512rows<7, true>, nn512rows<8, true>, nn512rows<9, true>};
  static constexpr Fn tail[9] = {nn512_tail<1, true>, nn512_tail<2, true>, nn512_tail<3, true>,
                                 nn512_tail<4, true>, nn512_tail<5, true>, nn512_tail<6, true>,
                                 nn512_tail<7, true>, nn512_tail<8, true>, nn512_tail<9, true>};
  const int64_t tiles = (N + NR - 1) / NR;
  for (int64_t t = 0; t < tiles; t += 2) (t + 1 < tiles ? pair : tail)[M - 1](K, a, lda, ptr, t * NR, acc + t * NR, ldacc);
}

// C (M x K, ldc) = L (M pointer rows) * P^T (K pointer rows) over columns [0, N), AVX-512 only: L is transposed
// once into 32-wide blocks (scratch: round_up(M, 32) * N floats) and every 12 rows of P are broadcast against it --
// an NN product, which reaches the FMA throughput that the dot-product form (nt_gemm) cannot for wide layers.
void wgrad512(const float* const* l, int64_t M, const float* const* p, int64_t K, int64_t N, float* C, int64_t ldc,
              float* scratch) {
  using Fn = void (*)(int64_t, const float* const*, const float*, float*);
  static constexpr Fn table[12] = {wg512<1>, wg512<2>, wg512<3>, wg512<4>, wg512<5>,  wg512<6>,
                                   wg512<7>, wg512<8>, wg512<9>, wg512<10>, wg512<11>, wg512<12>};
  const int64_t nmb = (M + 31) / 32;
  float out[12 * 32];
  for (int64_t mb = 0; mb < nmb; ++mb) {
    float* lt = scratch;
    const int64_t live = std::min<int64_t>(32, M - mb * 32);
    for (int64_t n0 = 0; n0 < N; n0 += 16) {  // transpose in 16-column strips (stays in L1)
      const int64_t n1 = std::min(N, n0 + 16);
      for (int64_t o = 0; o < live; ++o) {
        const float* src = l[mb * 32 + o];
        for (int64_t n = n0; n < n1; ++n) lt[n * 32 + o] = src[n];
      }
      for (int64_t o = live; o < 32; ++o)
        for (int64_t n = n0; n < n1; ++n) lt[n * 32 + o] = 0.f;
    }
    for (int64_t r0 = 0; r0 < K; r0 += 12) {
      const int64_t R = std::min<int64_t>(12, K - r0);
      table[R - 1](N, p + r0, lt, out);
      for (int64_t r = 0; r < R; ++r)
        for (int64_t o = 0; o < live; ++o) C[(mb * 32 + o) * ldc + r0 + r] = out[r * 32 + o];
    }
  }
}

// C (M x K, ldc) += L (M pointer rows) * P^T (K pointer rows), contraction over columns [0, N).
void nt_gemm(const float* const* l, int64_t M, const float* const* p, int64_t K, int64_t N, float* C, int64_t ldc) {
  const bool wide = use512();
  // AVX-512: rows in tiles of at most 4 as even as M allows (9 = 3+3+3, not 4+4+1: a 1-row tile is bound by its
  // loads) by 4 pointer rows (reduced four at a time), each tile over all the columns (column chunks sized for L2
  // measured 5-15% slower on GANimator's layers: the reductions cost more than the re-reads save); AVX2: 4 x 3
  // tiles over column chunks that keep the pointed-to data in L2.
  const int64_t CH = wide ? std::max<int64_t>(N, 1)
                          : std::max<int64_t>(64, round_up((320 * 1024) / std::max<int64_t>(1, (K + M) * 4), 16));
  const int64_t row_tiles = (M + TM - 1) / TM, kt = wide ? 4 : TK;
  for (int64_t c0 = 0; c0 < N; c0 += CH) {
    const int64_t n = std::min(CH, N - c0);
    for (int64_t rt = 0, m0 = 0; rt < row_tiles; ++rt) {
      const int64_t mr = wide ? (M - m0 + (row_tiles - rt) - 1) / (row_tiles - rt) : std::min(TM, M - m0);
      for (int64_t k0 = 0; k0 < K; k0 += kt) {
        const int64_t kr = std::min(kt, K - k0);
        if (wide)
          nt512_tile(l + m0, mr, p + k0, kr, c0, n, C + m0 * ldc + k0, ldc);
        else if (mr == TM && kr == TK)
          nt_kernel(l + m0, p + k0, c0, n, C + m0 * ldc + k0, ldc);
        else
          nt_edge(l + m0, mr, p + k0, kr, c0, n, C + m0 * ldc + k0, ldc);
      }
      m0 += mr;
    }
  }
}

// Column layout of a (B, C, E, Ts) tensor: row (phase, c, e) of length row_len; at b*Tq + m it holds
// f(b,c,e) * src[b, c, e, q] for padded position p = S*m + phase < Lp, q = p - F; q outside [0, Ts) reads the
// mirror image (reflect) or 0.  Past Lp, before Z (stride 1 only), between batch blocks and in the slack after the
// last block: 0.
// blur_adjoint: the source row of (b, c, e) is blur^T(src row) (the up op's backward), computed on the fly.
struct ColsSrc {
  const float* src = nullptr;
  int64_t B = 0, Ts = 0;
  Scale<float> f;
  int64_t F = 0, Lp = 0, Z = 0;
  bool reflect = false, blur_adjoint = false;
};

struct Cols {
  Buf<float> buf;
  int64_t C = 0, E = 0, Tq = 0, row_len = 0, rows = 0;
  const float* row(int64_t ph, int64_t c, int64_t e) const { return buf.data() + ((ph * C + c) * E + e) * row_len; }
};

// Builds a Cols as a preparation phase: tasks of whole rows.  Must stay in place while its phase runs.
struct ColsBuild {
  Cols cl;
  ColsSrc cs;
  int64_t S = 1, chunk = 1;
  mutable SlotScratch<float> tmp;
  ColsBuild(const ColsSrc& src, int64_t C, int64_t E, int64_t S_, int64_t Tq, int64_t max_shift) : cs(src), S(S_) {
    cl.C = C;
    cl.E = E;
    cl.Tq = Tq;
    int64_t len = round_up(cs.B * Tq + NR + max_shift + 8, 8);
    if ((len * 4) % 4096 == 0) len += 16;  // avoid rows aliasing in the same cache sets
    cl.row_len = len;
    cl.rows = S * C * E;
    cl.buf.alloc(static_cast<size_t>(cl.rows * len));
    chunk = chunk_items(len);
  }
  ColsBuild(const ColsBuild&) = delete;
  ColsBuild& operator=(const ColsBuild&) = delete;

  void fill(int64_t r, int slot) const {
    const int64_t C = cl.C, E = cl.E, Tq = cl.Tq, B = cs.B, Ts = cs.Ts, F = cs.F, Lp = cs.Lp;
    const bool reflect = cs.reflect;
    const int64_t ph = r / (C * E), c = (r / E) % C, e = r % E;
    float* dst = cl.buf.data() + r * cl.row_len;
    float* blurred = cs.blur_adjoint ? tmp.get(slot, static_cast<size_t>(Ts)) : nullptr;
    for (int64_t b = 0; b < B; ++b) {
      const float fv = cs.f.at(b, c, e);
      const float* s = cs.src + ((b * C + c) * E + e) * Ts;
      if (blurred) {
        blur_adjoint_row<float>(s, blurred, Ts);
        s = blurred;
      }
      float* d = dst + b * Tq;
      if (S == 1) {
        const int64_t lo_m = std::min(std::max<int64_t>(F, 0), Tq), hi_m = std::max(lo_m, std::min({Tq, Lp, F + Ts}));
        for (int64_t m = 0; m < lo_m; ++m) d[m] = (m >= cs.Z && m < Lp && reflect) ? fv * s[mirror(m - F, Ts)] : 0.f;
        for (int64_t m = lo_m; m < hi_m; ++m) d[m] = fv * s[m - F];
        for (int64_t m = hi_m; m < Tq; ++m) d[m] = (m < Lp && reflect) ? fv * s[mirror(m - F, Ts)] : 0.f;
      } else {
        for (int64_t m = 0; m < Tq; ++m) {
          const int64_t p = S * m + ph;
          float v = 0.f;
          if (p < Lp) {
            const int64_t q = p - F;
            if (q >= 0 && q < Ts)
              v = s[q];
            else if (reflect)
              v = s[mirror(q, Ts)];
          }
          d[m] = fv * v;
        }
      }
    }
    std::fill(dst + B * Tq, dst + cl.row_len, 0.f);
  }
  void operator()(int64_t t, int slot) const {
    for (int64_t r = t * chunk, end = std::min(cl.rows, (t + 1) * chunk); r < end; ++r) fill(r, slot);
  }
  Phase phase() const { return cpu_tasks::phase((cl.rows + chunk - 1) / chunk, *this); }
};

// A operands are packed once per call into 4-row panels: panel pn holds out[(pn*K + kk)*4 + r] = A[pn*4 + r][kk]
// (rows past M are 0), so the NN kernel reads its 4 broadcasts from one cache line.
// Plain: A[m][kk] = src[m*lda + kk].
void pack_plain(float* out, int64_t M, int64_t K, const float* src, int64_t lda) {
  const int64_t panels = (M + MR - 1) / MR;
  for (int64_t pn = 0; pn < panels; ++pn)
    for (int64_t r = 0; r < MR; ++r) {
      const int64_t m = pn * MR + r;
      float* o = out + pn * K * MR + r;
      if (m < M) {
        const float* row = src + m * lda;
        for (int64_t kk = 0; kk < K; ++kk) o[kk * MR] = row[kk];
      } else {
        for (int64_t kk = 0; kk < K; ++kk) o[kk * MR] = 0.f;
      }
    }
}

// Grouped: columns come in groups of Rp taps; A[m][g*Rp + r] = base[g][m*mstride + tap0 + tap_step*r].
void pack_groups(float* out, int64_t M, int64_t K, const float* const* base, int64_t n_groups, int64_t Rp,
                 int64_t mstride, int64_t tap0, int64_t tap_step) {
  const int64_t panels = (M + MR - 1) / MR;
  if (panels * MR > M) std::fill(out, out + panels * MR * K, 0.f);
  for (int64_t gi = 0; gi < n_groups; ++gi)
    for (int64_t m = 0; m < M; ++m) {
      const float* src = base[gi] + m * mstride + tap0;
      float* o = out + ((m / MR) * K + gi * Rp) * MR + (m % MR);
      for (int64_t r = 0; r < Rp; ++r) o[r * MR] = src[r * tap_step];
    }
}

// All entities' packed operands of one pass (and phase), addressed by entity * phases + phase.
struct Packs {
  Buf<float> buf;
  std::vector<int64_t> off;
  const float* at(int64_t i) const { return buf.data() + off[i]; }
};

// Transposed pass: for output entity n and phase ph the operand row m, column (s, c, r) is
// w_t(m, pair of transposed entry q0+s, c, tap) with tap = r (stride 1) or ph + 2r (stride 2).  `group_base(q, c)`
// returns a pointer such that element (m, tap) sits at base[m*mstride + tap].  A preparation phase (one task per
// entity and phase); must stay in place while it runs.
template <typename GroupBase>
struct PackTransposed {
  Packs pk;
  const Csr& csr;
  int64_t stride, U, M, Csrc, mstride;
  GroupBase group_base;
  mutable SlotScratch<const float*> bases;
  PackTransposed(const Csr& csr_, int64_t n_ent, int64_t stride_, int64_t U_, int64_t M_, int64_t Csrc_,
                 int64_t mstride_, GroupBase gb)
      : csr(csr_), stride(stride_), U(U_), M(M_), Csrc(Csrc_), mstride(mstride_), group_base(gb) {
    const int64_t rows = round_up(M, MR);
    pk.off.assign(static_cast<size_t>(n_ent * stride + 1), 0);
    for (int64_t n = 0; n < n_ent; ++n)
      for (int64_t ph = 0; ph < stride; ++ph) {
        const int64_t Rp = stride == 1 ? U : (U - ph + 1) / 2;
        const int64_t k = csr.toff[n + 1] - csr.toff[n];
        pk.off[n * stride + ph + 1] = pk.off[n * stride + ph] + rows * k * Csrc * Rp;
      }
    pk.buf.alloc(static_cast<size_t>(pk.off.back()));
  }
  PackTransposed(const PackTransposed&) = delete;
  PackTransposed& operator=(const PackTransposed&) = delete;
  void operator()(int64_t e, int slot) const {
    const int64_t n = e / stride, ph = e % stride;
    const int64_t Rp = stride == 1 ? U : (U - ph + 1) / 2;
    const int64_t q0 = csr.toff[n], k = csr.toff[n + 1] - q0;
    const float** base = bases.get(slot, static_cast<size_t>(std::max<int64_t>(1, csr.max_tdeg * Csrc)));
    for (int64_t s = 0; s < k; ++s)
      for (int64_t c = 0; c < Csrc; ++c) base[s * Csrc + c] = group_base(q0 + s, c);
    pack_groups(pk.buf.data() + pk.off[e], M, k * Csrc * Rp, base, k * Csrc, Rp, mstride, stride == 1 ? 0 : ph,
                stride == 1 ? 1 : 2);
  }
  Phase phase() const { return cpu_tasks::phase(static_cast<int64_t>(pk.off.size()) - 1, *this); }
};

// Plain pass: entity j's operand is rows [0, M) of the strided view src + off[j]*colw (row stride lda), K_j wide.
struct PackEntities {
  Packs pk;
  const Csr& csr;
  int64_t M;
  const float* src;
  int64_t lda, colw;
  PackEntities(const Csr& csr_, int64_t M_, const float* src_, int64_t lda_, int64_t colw_)
      : csr(csr_), M(M_), src(src_), lda(lda_), colw(colw_) {
    const int64_t rows = round_up(M, MR);
    pk.off.assign(static_cast<size_t>(csr.rows + 1), 0);
    for (int64_t j = 0; j < csr.rows; ++j) pk.off[j + 1] = pk.off[j] + rows * (csr.off[j + 1] - csr.off[j]) * colw;
    pk.buf.alloc(static_cast<size_t>(pk.off.back()));
  }
  PackEntities(const PackEntities&) = delete;
  PackEntities& operator=(const PackEntities&) = delete;
  void operator()(int64_t j, int) const {
    pack_plain(pk.buf.data() + pk.off[j], M, (csr.off[j + 1] - csr.off[j]) * colw, src + csr.off[j] * colw, lda);
  }
  Phase phase() const { return cpu_tasks::phase(csr.rows, *this); }
};

// Output of a stride-2 transposed pass lives in two phase accumulators; rebuild a padded row of length Lp.
inline void interleave_row(const float* a0, const float* a1, float* out, int64_t Lp) {
  for (int64_t q = 0; q < Lp; ++q) out[q] = (q & 1) ? a1[q >> 1] : a0[q >> 1];
}

// Transposed pass (output entity list = transposed CSR): acc rows = Mrows channels of output entity n; the
// inputs are `src` rows of the entities that read n.  stride 1: one product over taps u (pointer shift U-1-u);
// stride 2: one product per output phase over taps u = phase + 2r (pointer shift R-1-r).
void transposed_products(const Cols& src, int64_t Csrc, const Csr& csr, int64_t n, int64_t b0, int64_t stride,
                         int64_t U, int64_t Mrows, const Packs& pk, const float** ptr, float* const* acc, int64_t N,
                         int64_t ldacc) {
  const int64_t q0 = csr.toff[n], k = csr.toff[n + 1] - q0;
  const int64_t R = stride == 1 ? U : (U + 1) / 2;
  for (int64_t ph = 0; ph < stride; ++ph) {
    const int64_t Rp = stride == 1 ? U : (U - ph + 1) / 2;  // taps of this phase
    const int64_t K = k * Csrc * Rp;
    for (int64_t s = 0; s < k; ++s)
      for (int64_t c = 0; c < Csrc; ++c) {
        const float* rowp = src.row(0, c, csr.tent[q0 + s]) + b0 * src.Tq;
        for (int64_t r = 0; r < Rp; ++r) ptr[(s * Csrc + c) * Rp + r] = rowp + (stride == 1 ? (U - 1 - r) : (R - 1 - r));
      }
    nn_gemm(pk.at(n * stride + ph), Mrows, K, ptr, N, acc[ph], ldacc);
  }
}

void forward(const Geo& g, const Csr& csr, const float* x, const float* w, const float* bias,
             const Scale<float>& sty, const float* scale, float* y) {
  const int64_t U = g.U, h = g.h, Ci = g.Cin, Co = g.Cout;
  const bool par = worth_threads(g.macs);
  if (g.kind != kUp) {
    const int64_t S = g.kind == kDown ? 2 : 1;
    const int64_t Lp = g.Tin + 2 * h, Tq = (Lp + S - 1) / S;
    ColsSrc src;
    src.src = x;
    src.B = g.B;
    src.Ts = g.Tin;
    src.f = sty;
    src.F = h;
    src.Lp = Lp;
    src.reflect = g.reflect;
    const ColsBuild xb(src, Ci, g.Ein, S, Tq, U);
    const bool direct = Co <= kDirectRows && use512();
    const PackEntities pe(csr, direct ? 0 : Co, w, g.nnz * Ci * U, Ci * U);
    const Phase prep[] = {xb.phase(), pe.phase()};
    const Cols& xc = xb.cl;
    const int64_t nb = batch_tile(g.B, Tq, g.Eout);
    const int64_t ldacc = round_up(nb * Tq, NR), rows = round_up(Co, MR), maxK = csr.max_deg * Ci * U;
    const std::vector<int64_t> order = lpt_tiles(g.B, nb, g.Eout, csr.off);
    SlotScratch<float> accs;
    SlotScratch<const float*> ptrs;
    auto task = [&](int64_t t, int slot) {
      float* acc = accs.get(slot, static_cast<size_t>(rows * ldacc));
      const float** ptr = ptrs.get(slot, static_cast<size_t>(maxK));
      const int64_t bt = order[t] / g.Eout, j = order[t] % g.Eout;
      const int64_t b0 = bt * nb, nbl = std::min(nb, g.B - b0), N = nbl * Tq;
      const int64_t p0 = csr.off[j], k = csr.off[j + 1] - p0, K = k * Ci * U;
      for (int64_t s = 0; s < k; ++s)
        for (int64_t c = 0; c < Ci; ++c)
          for (int64_t u = 0; u < U; ++u)
            ptr[(s * Ci + c) * U + u] = xc.row(u % S, c, csr.idx[p0 + s]) + b0 * Tq + u / S;
      if (direct)
        nn_gemm_direct(w + p0 * Ci * U, g.nnz * Ci * U, Co, K, ptr, N, acc, ldacc);
      else
        nn_gemm(pe.pk.at(j), Co, K, ptr, N, acc, ldacc);
      for (int64_t bl = 0; bl < nbl; ++bl) {
        const int64_t b = b0 + bl;
        for (int64_t o = 0; o < Co; ++o) {
          const float f = scale ? scale[(b * Co + o) * g.Eout + j] : 1.f;
          const float bb = bias ? bias[o] : 0.f;
          const float* src_row = acc + o * ldacc + bl * Tq;
          float* dst = y + ((b * Co + o) * g.Eout + j) * g.Tout;
          for (int64_t t2 = 0; t2 < g.Tout; ++t2) dst[t2] = src_row[t2] * f + bb;
        }
      }
    };
    const Phase compute[] = {phase(static_cast<int64_t>(order.size()), task)};
    run_stages({{prep, size_t{direct ? 1u : 2u}}, {compute, 1}}, par);  // direct: no packing phase
    return;
  }
  // up: fine entity f gathers its coarse sources through the transposed CSR, two output phases
  const int64_t R = (U + 1) / 2, Lpf = g.Tout + 2 * h, Mq = (Lpf + 1) / 2, Tq = Mq + R - 1;
  ColsSrc src;
  src.src = x;
  src.B = g.B;
  src.Ts = g.Tin;
  src.f = sty;
  src.F = R - 1;
  src.Lp = Tq;
  const ColsBuild xb(src, Ci, g.Ein, 1, Tq, U);
  // operand row o, column (s, i, r): w_up[i, pair, o, tap]
  auto base = [&](int64_t q, int64_t i) { return w + (i * g.nnz + csr.tpair[q]) * Co * U; };
  const PackTransposed<decltype(base)> pt(csr, g.Eout, 2, U, Co, Ci, U, base);
  const Phase prep[] = {xb.phase(), pt.phase()};
  const Cols& xc = xb.cl;
  const int64_t nb = batch_tile(g.B, Tq, g.Eout);
  const int64_t ldacc = round_up(nb * Tq, NR), rows = round_up(Co, MR), maxK = csr.max_tdeg * Ci * R;
  const std::vector<int64_t> order = lpt_tiles(g.B, nb, g.Eout, csr.toff);
  SlotScratch<float> accs, rowbuf;
  SlotScratch<const float*> ptrs;
  auto task = [&](int64_t t, int slot) {
    float* a0 = accs.get(slot, static_cast<size_t>(2 * rows * ldacc));
    float* const acc[2] = {a0, a0 + rows * ldacc};
    const float** ptr = ptrs.get(slot, static_cast<size_t>(std::max<int64_t>(maxK, 1)));
    float* vp = rowbuf.get(slot, static_cast<size_t>(Lpf + 2 * g.Tout));
    float* v = vp + Lpf;
    float* vb = v + g.Tout;
    const int64_t bt = order[t] / g.Eout, f = order[t] % g.Eout;
    const int64_t b0 = bt * nb, nbl = std::min(nb, g.B - b0), N = nbl * Tq;
    transposed_products(xc, Ci, csr, f, b0, 2, U, Co, pt.pk, ptr, acc, N, ldacc);
    for (int64_t bl = 0; bl < nbl; ++bl) {
      const int64_t b = b0 + bl;
      for (int64_t o = 0; o < Co; ++o) {
        const float fs = scale ? scale[(b * Co + o) * g.Eout + f] : 1.f;
        const float bb = bias ? bias[o] : 0.f;
        interleave_row(acc[0] + o * ldacc + bl * Tq, acc[1] + o * ldacc + bl * Tq, vp, Lpf);
        fold_row<float>(vp, v, g.Tout, h, g.reflect);
        blur_row<float>(v, vb, g.Tout);
        float* dst = y + ((b * Co + o) * g.Eout + f) * g.Tout;
        for (int64_t t2 = 0; t2 < g.Tout; ++t2) dst[t2] = vb[t2] * fs + bb;
      }
    }
  };
  const Phase compute[] = {phase(static_cast<int64_t>(order.size()), task)};
  run_stages({{prep, 2}, {compute, 1}}, par);
}

// Input, style and weight gradients.  For conv/down the output gradient is gy * gsc (gsc = d); for up it is
// blur^T(gy) * gsc on the fine grid, formed while the operand rows are laid out.  gx / gs_part / gw may be null.
// `prep` and `compute` carry the caller's phases (bias / scale gradients, a BLAS weight gradient, ...), run in the
// same two regions as this pass's own.
void backward(const Geo& g, const Csr& csr, const float* gy, const Scale<float>& gsc, const float* x, const float* w,
              const float* style, float* gx, float* gw, float* gs_part, std::vector<Phase> prep,
              std::vector<Phase> compute) {
  const int64_t U = g.U, h = g.h, Ci = g.Cin, Co = g.Cout, Ei = g.Ein, Eo = g.Eout, B = g.B;
  const bool par = worth_threads(g.macs);
  Scale<float> sty;
  if (style) {
    sty.p = style;
    sty.sb = Ci;
    sty.sc = 1;
  }
  const bool want_input = gx != nullptr || gs_part != nullptr;
  auto finish = [&](const float* row, int64_t b, int64_t i, int64_t n, int64_t L) {
    const int64_t xo = ((b * Ci + i) * Ei + n) * L;
    finish_input_row<float>(row, x + xo, style ? style[b * Ci + i] : 1.f, gx ? gx + xo : nullptr,
                            gs_part ? gs_part + (n * B + b) * Ci + i : nullptr, L);
  };
  SlotScratch<float> accs, rowbuf, aux;
  SlotScratch<const float*> ptrs;
  // wide layers' weight gradient on the AVX-512 NN form; narrow ones (<= kNarrowRows rows) on nt_gemm
  const bool wide_w = use512() && (g.kind == kUp ? Ci : Co) > kNarrowRows;
  if (g.kind == kUp) {
    // gv = blur^T(gy) * d on the fine grid, read like a down-sampler's input: stride 2, padding per mode
    const int64_t Tc = g.Tin, Lp = g.Tout + 2 * h, Tq = Tc + h;
    ColsSrc gs;
    gs.src = gy;
    gs.B = B;
    gs.Ts = g.Tout;
    gs.f = gsc;
    gs.F = h;
    gs.Lp = Lp;
    gs.reflect = g.reflect;
    gs.blur_adjoint = true;
    const ColsBuild gvb(gs, Co, Eo, 2, Tq, U);
    ColsSrc xs;
    xs.src = x;
    xs.B = B;
    xs.Ts = Tc;
    xs.f = sty;
    xs.F = 0;
    xs.Lp = Tc;
    const ColsBuild xlb(xs, gw ? Ci : 0, gw ? Ei : 0, 1, Tq, U);
    const int64_t lda = g.nnz * Co * U, maxK = csr.max_deg * Co * U;
    const PackEntities pe(csr, want_input ? Ci : 0, w, lda, Co * U);
    prep.push_back(gvb.phase());
    if (gw) prep.push_back(xlb.phase());
    if (want_input) prep.push_back(pe.phase());
    const Cols& gvc = gvb.cl;
    auto set_ptrs = [&](const float** ptr, int64_t c, int64_t b0) {
      const int64_t p0 = csr.off[c], k = csr.off[c + 1] - p0;
      for (int64_t s = 0; s < k; ++s)
        for (int64_t o = 0; o < Co; ++o)
          for (int64_t u = 0; u < U; ++u)
            ptr[(s * Co + o) * U + u] = gvc.row(u % 2, o, csr.idx[p0 + s]) + b0 * Tq + u / 2;
      return k * Co * U;
    };
    const int64_t nb = batch_tile(B, Tq, Ei);
    const int64_t ldacc = round_up(nb * Tq, NR), rows = round_up(Ci, MR);
    const std::vector<int64_t> order = want_input ? lpt_tiles(B, nb, Ei, csr.off) : std::vector<int64_t>{};
    auto input_task = [&](int64_t t, int slot) {
      float* acc = accs.get(slot, static_cast<size_t>(rows * ldacc));
      const float** ptr = ptrs.get(slot, static_cast<size_t>(maxK + Ci));
      const int64_t bt = order[t] / Ei, c = order[t] % Ei, b0 = bt * nb, nbl = std::min(nb, B - b0);
      const int64_t K = set_ptrs(ptr, c, b0);
      nn_gemm(pe.pk.at(c), Ci, K, ptr, nbl * Tq, acc, ldacc);
      for (int64_t bl = 0; bl < nbl; ++bl)
        for (int64_t i = 0; i < Ci; ++i) finish(acc + i * ldacc + bl * Tq, b0 + bl, i, c, Tc);
    };
    // weight: gW[i, pairs of c, o, u] over the whole batch, rows i split into blocks when entities are few
    const RowBlocks wb = gw ? weight_blocks(Ei, Ci, csr.off, TM) : RowBlocks{};
    auto weight_task = [&](int64_t t, int slot) {
      const float** ptr = ptrs.get(slot, static_cast<size_t>(maxK + Ci));
      const float** lrow = ptr + maxK;
      const int64_t c = wb.order[t] / wb.nrb, r0 = (wb.order[t] % wb.nrb) * wb.rb, nr = std::min(wb.rb, Ci - r0);
      const int64_t K = set_ptrs(ptr, c, 0);
      for (int64_t i = 0; i < nr; ++i) lrow[i] = xlb.cl.row(0, r0 + i, c);
      float* C = gw + r0 * lda + csr.off[c] * Co * U;
      if (wide_w) {
        wgrad512(lrow, nr, ptr, K, B * Tq, C, lda, accs.get(slot, static_cast<size_t>(round_up(nr, 32) * B * Tq)));
        return;
      }
      for (int64_t i = 0; i < nr; ++i) std::fill(C + i * lda, C + i * lda + K, 0.f);
      nt_gemm(lrow, nr, ptr, K, B * Tq, C, lda);
    };
    std::vector<Phase> own;
    if (gw) own.push_back(phase(static_cast<int64_t>(wb.order.size()), weight_task));
    own.insert(own.end(), compute.begin(), compute.end());
    if (want_input) own.push_back(phase(static_cast<int64_t>(order.size()), input_task));
    run_stages({stage(prep), stage(own)}, par);
    return;
  }
  const int64_t S = g.kind == kDown ? 2 : 1;
  // input gradient: transposed pass over the readers of each input entity; output on the padded domain, then folded
  const int64_t Lp = g.Tin + 2 * h;
  const int64_t R = S == 1 ? U : (U + 1) / 2;
  const int64_t Mq = S == 1 ? Lp : (Lp + 1) / 2;
  const int64_t Tqi = Mq + R - 1;
  ColsSrc zs;
  zs.src = gy;
  zs.B = B;
  zs.Ts = g.Tout;
  zs.f = gsc;
  zs.F = R - 1;
  zs.Lp = Tqi;
  const ColsBuild gzb(zs, want_input ? Co : 0, want_input ? Eo : 0, 1, Tqi, U);
  // operand row i, column (s, o, r): w[o, pair, i, tap]
  auto base = [&](int64_t q, int64_t o) { return w + (o * g.nnz + csr.tpair[q]) * Ci * U; };
  const PackTransposed<decltype(base)> pt(csr, want_input ? Ei : 0, S, U, Ci, Co, U, base);
  // weight gradient operands: x laid out like the forward's, gy * d in plain rows.  Stride 1 with both gradients:
  // the input gradient's layout of gy (U-1 leading zeros per batch element) serves both passes, with x laid out U-1
  // frames later to match (zeros before), so gy is laid out once instead of twice (one 3.5 MB pass less at MoDi's
  // finest level) for (U-1)/(T+2h) more weight-gradient columns.
  const bool shared_gy = S == 1 && want_input && gw;
  const int64_t Tqw = shared_gy ? Tqi : (Lp + S - 1) / S;
  ColsSrc xs;
  xs.src = x;
  xs.B = B;
  xs.Ts = g.Tin;
  xs.f = sty;
  xs.F = shared_gy ? h + U - 1 : h;
  xs.Lp = shared_gy ? Tqi : Lp;
  xs.Z = shared_gy ? U - 1 : 0;
  xs.reflect = g.reflect;
  const ColsBuild xcb(xs, gw ? Ci : 0, gw ? Ei : 0, S, Tqw, U);
  ColsSrc ls;
  ls.src = gy;
  ls.B = B;
  ls.Ts = g.Tout;
  ls.f = gsc;
  ls.F = 0;
  ls.Lp = g.Tout;
  const ColsBuild glb(ls, gw && !shared_gy ? Co : 0, gw && !shared_gy ? Eo : 0, 1, Tqw, U);
  const Cols& gl = shared_gy ? gzb.cl : glb.cl;
  if (want_input) {
    prep.push_back(gzb.phase());
    prep.push_back(pt.phase());
  }
  if (gw) {
    prep.push_back(xcb.phase());
    if (!shared_gy) prep.push_back(glb.phase());
  }

  const int64_t nb = batch_tile(B, Tqi, Ei);
  const int64_t ldacc = round_up(nb * Tqi, NR), rows = round_up(Ci, MR);
  const int64_t maxKi = std::max<int64_t>(1, csr.max_tdeg * Co * R), maxKw = csr.max_deg * Ci * U;
  const std::vector<int64_t> order = want_input ? lpt_tiles(B, nb, Ei, csr.toff) : std::vector<int64_t>{};
  auto input_task = [&](int64_t t, int slot) {
    float* a0 = accs.get(slot, static_cast<size_t>((S == 2 ? 2 : 1) * rows * ldacc));
    float* const acc[2] = {a0, S == 2 ? a0 + rows * ldacc : nullptr};
    const float** ptr = ptrs.get(slot, static_cast<size_t>(std::max(maxKi, maxKw + Co)));
    float* gp = rowbuf.get(slot, static_cast<size_t>(Lp + g.Tin));
    float* row = gp + Lp;
    const int64_t bt = order[t] / Ei, n = order[t] % Ei, b0 = bt * nb, nbl = std::min(nb, B - b0);
    if (csr.toff[n + 1] == csr.toff[n]) {  // nobody reads this entity
      for (int64_t bl = 0; bl < nbl; ++bl)
        for (int64_t i = 0; i < Ci; ++i) {
          std::fill(row, row + g.Tin, 0.f);
          finish(row, b0 + bl, i, n, g.Tin);
        }
      return;
    }
    transposed_products(gzb.cl, Co, csr, n, b0, S, U, Ci, pt.pk, ptr, acc, nbl * Tqi, ldacc);
    for (int64_t bl = 0; bl < nbl; ++bl)
      for (int64_t i = 0; i < Ci; ++i) {
        const float* r0 = acc[0] + i * ldacc + bl * Tqi;
        if (S == 2) {
          interleave_row(r0, acc[1] + i * ldacc + bl * Tqi, gp, Lp);
          r0 = gp;
        }
        fold_row<float>(r0, row, g.Tin, h, g.reflect);
        finish(row, b0 + bl, i, n, g.Tin);
      }
  };
  // weight: gW[o, pairs of j, i, u] over the whole batch, rows o split into blocks when entities are few
  const int64_t ldw = g.nnz * Ci * U;
  const RowBlocks wb = gw ? weight_blocks(Eo, Co, csr.off, TM) : RowBlocks{};
  auto weight_task = [&](int64_t t, int slot) {
    const float** ptr = ptrs.get(slot, static_cast<size_t>(std::max(maxKi, maxKw + Co)));
    const float** lrow = ptr + maxKw;
    const int64_t j = wb.order[t] / wb.nrb, r0 = (wb.order[t] % wb.nrb) * wb.rb, nr = std::min(wb.rb, Co - r0);
    const int64_t p0 = csr.off[j], k = csr.off[j + 1] - p0, K = k * Ci * U;
    for (int64_t s = 0; s < k; ++s)
      for (int64_t c = 0; c < Ci; ++c)
        for (int64_t u = 0; u < U; ++u) ptr[(s * Ci + c) * U + u] = xcb.cl.row(u % S, c, csr.idx[p0 + s]) + u / S;
    for (int64_t o = 0; o < nr; ++o) lrow[o] = gl.row(0, r0 + o, j);
    float* C = gw + r0 * ldw + p0 * Ci * U;
    if (wide_w) {
      wgrad512(lrow, nr, ptr, K, B * Tqw, C, ldw, aux.get(slot, static_cast<size_t>(round_up(nr, 32) * B * Tqw)));
      return;
    }
    for (int64_t o = 0; o < nr; ++o) std::fill(C + o * ldw, C + o * ldw + K, 0.f);
    nt_gemm(lrow, nr, ptr, K, B * Tqw, C, ldw);
  };
  std::vector<Phase> own;
  if (gw) own.push_back(phase(static_cast<int64_t>(wb.order.size()), weight_task));
  own.insert(own.end(), compute.begin(), compute.end());
  if (want_input) own.push_back(phase(static_cast<int64_t>(order.size()), input_task));
  run_stages({stage(prep), stage(own)}, par);
}

}  // namespace fastk

template <typename T>
void forward_dispatch(const Geo& g, const Csr& csr, const T* x, const T* w, const T* bias, const Scale<T>& sty,
                      const T* scale, T* y) {
  if constexpr (std::is_same_v<T, float>) {
    const int64_t frames = g.kind == kUp ? g.Tin : g.Tout;  // columns per batch element of the product
    if (frames >= fastk::kMinFrames && fastk::wanted()) {
      fastk::forward(g, csr, x, w, bias, sty, scale, y);
      return;
    }
  }
  if (g.kind == kUp)
    forward_up<T>(g, csr, x, w, bias, sty, scale, y);
  else
    forward_conv_down<T>(g, csr, x, w, bias, sty, scale, y);
}

at::Tensor forward_any(int64_t kind, const at::Tensor& x, const at::Tensor& weight,
                       const std::optional<at::Tensor>& bias, const at::Tensor& index, const at::Tensor& offsets,
                       int64_t n_out, const std::optional<at::Tensor>& style, const std::optional<at::Tensor>& scale,
                       c10::string_view padding_mode) {
  const Geo g = check_inputs(kind, x, weight, bias, index, offsets, n_out, style, scale, padding_mode);
  const Csr csr = make_csr(index, offsets, kind == kUp ? g.Eout : g.Ein);
  at::Tensor y = at::empty({g.B, g.Cout, g.Eout, g.Tout}, x.options());
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "skeletal_forward", [&] {
    using T = scalar_t;
    const T* bp = bias.has_value() ? bias->data_ptr<T>() : nullptr;
    const T* sp = scale.has_value() ? scale->data_ptr<T>() : nullptr;
    const Scale<T> sty = style_scale<T>(style, g.Cin);
    forward_dispatch<T>(g, csr, x.data_ptr<T>(), weight.data_ptr<T>(), bp, sty, sp, y.data_ptr<T>());
  });
  return y;
}

// ------------------------------------------------------------------------------------------------ backward
template <typename T>
void backward_impl(const Geo& g, const Csr& csr, const T* gy, const T* out, const T* x, const T* w, const T* bias,
                   const T* style, const T* scale, T* gx, T* gw, T* gb, T* gs, T* gd) {
  const int64_t Bq = g.B, Co = g.Cout, Ci = g.Cin, Eo = g.Eout, Ei = g.Ein, U = g.U, h = g.h;
  const bool par = worth_threads(g.macs);
  const Scale<T> sty = [&] {
    Scale<T> s;
    if (style) { s.p = style; s.sb = Ci; s.sc = 1; s.se = 0; }
    return s;
  }();
  const Scale<T> dsc = scale ? entity_scale<T>(scale, Co, Eo) : Scale<T>{};
  std::vector<Phase> prep, compute;

  // bias and scale gradients: plain reductions over the output, run with the preparation phases.
  auto bias_task = [&](int64_t o, int) {
    T acc = T(0);
    for (int64_t b = 0; b < Bq; ++b) {
      const T* r = gy + (b * Co + o) * Eo * g.Tout;
      for (int64_t i = 0; i < Eo * g.Tout; ++i) acc += r[i];
    }
    gb[o] = acc;
  };
  const int64_t out_rows = Bq * Co * Eo, row_chunk = chunk_items(g.Tout);
  auto scale_task = [&](int64_t t, int) {  // y = d * z + bias  =>  dL/dd = sum_t gy * (y - bias) / d
    for (int64_t r = t * row_chunk, end = std::min(out_rows, (t + 1) * row_chunk); r < end; ++r) {
      const int64_t o = (r / Eo) % Co;
      const T bb = bias ? bias[o] : T(0);
      const T* a = gy + r * g.Tout;
      const T* yv = out + r * g.Tout;
      T acc = T(0);
      for (int64_t t2 = 0; t2 < g.Tout; ++t2) acc += a[t2] * (yv[t2] - bb);
      gd[r] = acc / scale[r];
    }
  };
  if (gb) prep.push_back(phase(Co, bias_task));
  if (gd) prep.push_back(phase((out_rows + row_chunk - 1) / row_chunk, scale_task));
  if (!gx && !gw && !gs) {
    run_phases(prep.data(), prep.size(), par);
    return;
  }
  std::vector<T> gs_part;
  if (gs) gs_part.assign(static_cast<size_t>(Ei * Bq * Ci), T(0));

  // The fp32 indirect kernels win on the input gradient when there are enough frames (little padding waste).
  // The weight gradient: with AVX-512, the NN-form kernel (wgrad512) beats BLAS's gather + packed product on every
  // MoDi layer measured (finest conv fwd+bwd 10% faster, level1 20%); with AVX2 only it stays on BLAS, whose packed
  // product beats our dot-product kernel -- except for narrow layers (GANimator: 3-9 channels per entity), where
  // BLAS gets a 3-9-row product after gathering a panel as large as the product itself, and the indirect kernel,
  // which reads the inputs in place, wins.
  bool fast_input = false, fast_weight = false;
  if constexpr (std::is_same_v<T, float>) {
    const bool fast_ok = fastk::wanted() && g.Tin >= fastk::kMinFrames;
    fast_weight = gw && fast_ok && ((g.kind == kUp ? Ci : Co) <= fastk::kNarrowRows || fastk::use512());
    fast_input = (gx || gs) && fast_ok;
  }
  T* const gx_b = fast_input ? nullptr : gx;  // what is left for the BLAS passes
  T* const gs_b = fast_input ? nullptr : gs;
  T* const gw_b = fast_weight ? nullptr : gw;
  const bool input_b = gx_b || gs_b;

  // ---- BLAS passes, as phases: preparation (transposed weight, up's blurred gradient) and compute tasks
  SlotScratch<T> panels, accs, aux;
  // up: gv = blur^T(gy) * d on the fine grid (B, Co, Eo, 2T); per coarse entity c the strided panel of gv
  // feeds gx'_c = W_c * GV_c and gW_c = X'_c * GV_c^T.
  Buf<T> gv;
  const bool need_gv = g.kind == kUp && (input_b || gw_b);
  if (need_gv) gv.alloc(static_cast<size_t>(out_rows * g.Tout));
  auto gv_task = [&](int64_t t, int) {
    for (int64_t r = t * row_chunk, end = std::min(out_rows, (t + 1) * row_chunk); r < end; ++r) {
      T* dst = gv.data() + r * g.Tout;
      blur_adjoint_row<T>(gy + r * g.Tout, dst, g.Tout);
      if (scale) {
        const T f = scale[r];
        for (int64_t t2 = 0; t2 < g.Tout; ++t2) dst[t2] *= f;
      }
    }
  };
  if (need_gv) prep.push_back(phase((out_rows + row_chunk - 1) / row_chunk, gv_task));
  // conv/down input gradient reads the weight transposed to (Ci, nnz, Co, U) in transposed pair order
  Buf<T> wt;
  const bool need_wt = g.kind != kUp && input_b;
  if (need_wt) wt.alloc(static_cast<size_t>(Co * g.nnz * Ci * U));
  auto wt_task = [&](int64_t c1, int) { transpose_weight_row<T>(wt.data(), w, Co, g.nnz, Ci, U, csr.tpair, c1); };
  if (need_wt) prep.push_back(phase(Ci, wt_task));

  const int64_t stride = g.kind == kDown ? 2 : 1;
  const int64_t Tc = g.Tin;  // up: coarse frames
  // input-gradient tiles
  const int64_t Tp = g.Tin + 2 * h;
  const int64_t nbi = g.kind == kUp ? batch_tile(Bq, Tc, Ei) : batch_tile(Bq, Tp, Ei);
  const std::vector<int64_t> iorder =
      input_b ? lpt_tiles(Bq, nbi, Ei, g.kind == kUp ? csr.off : csr.toff) : std::vector<int64_t>{};
  auto input_task = [&](int64_t t, int slot) {
    BlasSequential blas_guard;
    const int64_t bt = iorder[t] / Ei, n = iorder[t] % Ei;
    const int64_t b0 = bt * nbi, nbl = std::min(nbi, Bq - b0);
    if (g.kind == kUp) {
      const int64_t N = nbl * Tc, lda = g.nnz * Co * U;
      const int64_t p0 = csr.off[n], k = csr.off[n + 1] - p0, K = k * Co * U;
      T* panel = panels.get(slot, static_cast<size_t>(csr.max_deg * Co * U * nbi * Tc));
      T* acc = accs.get(slot, static_cast<size_t>(Ci * nbi * Tc));
      gather_strided<T>(panel, N, gv.data(), Co, Eo, g.Tout, csr.idx.data() + p0, k, b0, nbl, Tc, 2, U, g.reflect,
                        Scale<T>{});
      gemm<T>(false, false, Ci, N, K, T(1), w + p0 * Co * U, lda, panel, N, T(0), acc, N);
      for (int64_t bl = 0; bl < nbl; ++bl) {
        const int64_t b = b0 + bl;
        for (int64_t i = 0; i < Ci; ++i) {
          const int64_t xo = ((b * Ci + i) * Ei + n) * Tc;
          finish_input_row<T>(acc + i * N + bl * Tc, x + xo, style ? style[b * Ci + i] : T(1),
                              gx_b ? gx_b + xo : nullptr, gs_b ? &gs_part[(n * Bq + b) * Ci + i] : nullptr, Tc);
        }
      }
      return;
    }
    // conv/down: for input entity n, G (Ci x nb*Tp) = Wt_n * transposed panel of gy*d over its readers
    const int64_t N = nbl * Tp, lda = g.nnz * Co * U;
    const int64_t q0 = csr.toff[n], k = csr.toff[n + 1] - q0, K = k * Co * U;
    if (k == 0) {  // nobody reads this entity
      for (int64_t bl = 0; bl < nbl; ++bl)
        for (int64_t i = 0; i < Ci; ++i)
          if (gx_b) {
            T* dst = gx_b + (((b0 + bl) * Ci + i) * Ei + n) * g.Tin;
            std::fill(dst, dst + g.Tin, T(0));
          }
      return;
    }
    T* panel = panels.get(slot, static_cast<size_t>(csr.max_tdeg * Co * U * nbi * Tp));
    T* acc = accs.get(slot, static_cast<size_t>(Ci * nbi * Tp));
    T* row = aux.get(slot, static_cast<size_t>(g.Tin));
    gather_transposed<T>(panel, N, gy, Co, Eo, g.Tout, csr.tent.data() + q0, k, b0, nbl, Tp, stride, U, dsc);
    gemm<T>(false, false, Ci, N, K, T(1), wt.data() + q0 * Co * U, lda, panel, N, T(0), acc, N);
    for (int64_t bl = 0; bl < nbl; ++bl) {
      const int64_t b = b0 + bl;
      for (int64_t i = 0; i < Ci; ++i) {
        fold_row<T>(acc + i * N + bl * Tp, row, g.Tin, h, g.reflect);
        const int64_t xo = ((b * Ci + i) * Ei + n) * g.Tin;
        finish_input_row<T>(row, x + xo, style ? style[b * Ci + i] : T(1), gx_b ? gx_b + xo : nullptr,
                            gs_b ? &gs_part[(n * Bq + b) * Ci + i] : nullptr, g.Tin);
      }
    }
  };
  // Weight-gradient blocks: entity (and row block) tasks over the whole batch, batch tiles accumulated in order.
  //   conv/down: gW_j[o-rows] = (gy*d)_j (rows x N) * X_j^T (N x K)      up: gW_c[i-rows] = X'_c * GV_c^T
  const int64_t wrows = g.kind == kUp ? Ci : Co;
  const int64_t wents = g.kind == kUp ? Ei : Eo;
  const int64_t wcols_b = g.kind == kUp ? Tc : g.Tout;  // panel columns per batch element
  const int64_t nbw = batch_tile(Bq, wcols_b, kMinTasks);
  // (row blocks of at least 64: every block gathers the whole panel again)
  const RowBlocks wb = gw_b ? weight_blocks(wents, wrows, csr.off, 64) : RowBlocks{};
  auto weight_task = [&](int64_t t, int slot) {
    BlasSequential blas_guard;
    const int64_t e = wb.order[t] / wb.nrb, r0 = (wb.order[t] % wb.nrb) * wb.rb, nr = std::min(wb.rb, wrows - r0);
    const int64_t p0 = csr.off[e], k = csr.off[e + 1] - p0;
    const int64_t cin_k = g.kind == kUp ? Co : Ci;  // channels of the panel rows
    const int64_t K = k * cin_k * U, ldw = g.nnz * cin_k * U;
    T* panel = panels.get(slot, static_cast<size_t>(csr.max_deg * cin_k * U * nbw * wcols_b));
    T* lhs = accs.get(slot, static_cast<size_t>(wrows * nbw * wcols_b));
    T* C = gw_b + r0 * ldw + p0 * cin_k * U;
    for (int64_t bt = 0; bt * nbw < Bq; ++bt) {
      const int64_t b0 = bt * nbw, nbl = std::min(nbw, Bq - b0), N = nbl * wcols_b;
      if (g.kind == kUp) {
        gather_strided<T>(panel, N, gv.data(), Co, Eo, g.Tout, csr.idx.data() + p0, k, b0, nbl, Tc, 2, U,
                          g.reflect, Scale<T>{});
        gather_strided<T>(lhs, N, x, Ci, Ei, Tc, &e, 1, b0, nbl, Tc, 1, 1, false, sty);
      } else {
        gather_strided<T>(panel, N, x, Ci, Ei, g.Tin, csr.idx.data() + p0, k, b0, nbl, g.Tout, stride, U,
                          g.reflect, sty);
        gather_strided<T>(lhs, N, gy, Co, Eo, g.Tout, &e, 1, b0, nbl, g.Tout, 1, 1, false, dsc);
      }
      gemm<T>(false, true, nr, K, N, T(1), lhs + r0 * N, N, panel, N, bt == 0 ? T(0) : T(1), C, ldw);
    }
  };
  if (gw_b) compute.push_back(phase(static_cast<int64_t>(wb.order.size()), weight_task));
  if (input_b) compute.push_back(phase(static_cast<int64_t>(iorder.size()), input_task));

  bool done = false;
  if constexpr (std::is_same_v<T, float>) {
    if (fast_input || fast_weight) {
      fastk::backward(g, csr, gy, dsc, x, w, style, fast_input ? gx : nullptr, fast_weight ? gw : nullptr,
                      fast_input && gs ? gs_part.data() : nullptr, std::move(prep), std::move(compute));
      done = true;
    }
  }
  if (!done) {
    run_stages({stage(prep), stage(compute)}, par);
  }
  if (gs) {
    for (int64_t bi = 0; bi < Bq * Ci; ++bi) {
      T acc = T(0);
      for (int64_t n = 0; n < Ei; ++n) acc += gs_part[n * Bq * Ci + bi];
      gs[bi] = acc;
    }
  }
}

}  // namespace

at::Tensor skeletal_conv_cpu(const at::Tensor& x, const at::Tensor& weight, const std::optional<at::Tensor>& bias,
                             const at::Tensor& index, const at::Tensor& offsets,
                             const std::optional<at::Tensor>& style, const std::optional<at::Tensor>& scale,
                             c10::string_view padding_mode) {
  return forward_any(kConv, x, weight, bias, index, offsets, 0, style, scale, padding_mode);
}

at::Tensor skeletal_down_cpu(const at::Tensor& x, const at::Tensor& weight, const std::optional<at::Tensor>& bias,
                             const at::Tensor& index, const at::Tensor& offsets,
                             const std::optional<at::Tensor>& style, const std::optional<at::Tensor>& scale,
                             c10::string_view padding_mode) {
  return forward_any(kDown, x, weight, bias, index, offsets, 0, style, scale, padding_mode);
}

at::Tensor skeletal_up_cpu(const at::Tensor& x, const at::Tensor& weight, const std::optional<at::Tensor>& bias,
                           const at::Tensor& index, const at::Tensor& offsets, int64_t n_out,
                           const std::optional<at::Tensor>& style, const std::optional<at::Tensor>& scale,
                           c10::string_view padding_mode) {
  return forward_any(kUp, x, weight, bias, index, offsets, n_out, style, scale, padding_mode);
}

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor> skeletal_backward_cpu(
    const at::Tensor& grad, const at::Tensor& out, const at::Tensor& x, const at::Tensor& weight,
    const std::optional<at::Tensor>& bias, const at::Tensor& index, const at::Tensor& offsets,
    const std::optional<at::Tensor>& style, const std::optional<at::Tensor>& scale, c10::string_view padding_mode,
    int64_t kind, int64_t n_out, std::array<bool, 4> output_mask) {
  TORCH_CHECK(kind == kConv || kind == kDown || kind == kUp, "kind must be 0 (conv), 1 (down) or 2 (up), got ",
              kind);
  const Geo g = check_inputs(kind, x, weight, bias, index, offsets, n_out, style, scale, padding_mode);
  const Csr csr = make_csr(index, offsets, kind == kUp ? g.Eout : g.Ein);
  for (const auto& [t, name] : {std::pair<const at::Tensor*, const char*>{&grad, "grad"}, {&out, "out"}}) {
    check_float(*t, name, x);
    TORCH_CHECK(t->dim() == 4 && t->size(0) == g.B && t->size(1) == g.Cout && t->size(2) == g.Eout &&
                    t->size(3) == g.Tout,
                name, " must have the output shape (", g.B, ", ", g.Cout, ", ", g.Eout, ", ", g.Tout, "), got ",
                t->sizes());
  }
  auto empty = [&] { return at::empty({0}, x.options()); };
  at::Tensor gx = output_mask[0] ? at::empty_like(x) : empty();
  at::Tensor gw = output_mask[1] ? at::empty_like(weight) : empty();
  at::Tensor gb = bias.has_value() ? at::empty_like(*bias) : empty();
  at::Tensor gs = (output_mask[2] && style.has_value()) ? at::empty_like(*style) : empty();
  at::Tensor gd = (output_mask[3] && scale.has_value()) ? at::empty_like(*scale) : empty();
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "skeletal_backward", [&] {
    using T = scalar_t;
    auto ptr = [](at::Tensor& t) -> T* { return t.numel() ? t.data_ptr<T>() : nullptr; };
    backward_impl<T>(g, csr, grad.data_ptr<T>(), out.data_ptr<T>(), x.data_ptr<T>(), weight.data_ptr<T>(),
                     bias.has_value() ? bias->data_ptr<T>() : nullptr,
                     style.has_value() ? style->data_ptr<T>() : nullptr,
                     scale.has_value() ? scale->data_ptr<T>() : nullptr, ptr(gx), ptr(gw), ptr(gb), ptr(gs), ptr(gd));
  });
  return {gx, gw, gb, gs, gd};
}

TORCH_LIBRARY_IMPL(modi_ext, CPU, m) {
  m.impl("skeletal_conv", &skeletal_conv_cpu);
  m.impl("skeletal_down", &skeletal_down_cpu);
  m.impl("skeletal_up", &skeletal_up_cpu);
  m.impl("skeletal_backward", &skeletal_backward_cpu);
}

}  // namespace modi_ext
