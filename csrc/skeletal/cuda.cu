// CUDA kernels of the skeletal operators (skeletal_conv, skeletal_down, skeletal_up, skeletal_backward).
//
// Semantics: modi_ext/skeletal/reference.py (the dense oracle) and skeletal/cpu.cpp (the CPU kernels these mirror).
// Every pass is one small GEMM per entity with the gather fused into the operand load:
//
//   row GEMM (kernel `row_gemm`)    out[b, m, row, t]  = sum_k A[m, k] G[k, (b, t)]
//       A = the row's contiguous weight block, G = time-shifted inputs of the row's CSR neighbours (read with zero /
//       reflect padding, stride 1 or 2, optionally through the adjoint of the [1,3,3,1] blur).
//       Used by: conv / down forward, up input-gradient.
//   transposed GEMM (`tr_gemm`)     out[b, m, col, t]  = sum over the readers of entity `col` (transposed CSR)
//       A = weight read transposed, G = the adjoint of the strided read: every source frame that the forward op
//       would have carried to target frame t (reflect padding folded back, optionally followed by the blur).
//       Used by: up forward, conv / down input-gradient.
//   weight-gradient GEMM (`wgrad`)  gW[m, row pairs] = sum_(b,t) L[m, (b,t)] G[k, (b,t)], one block per k tile
//       of a row, with the reduction over batch x time split across blocks into fp32 partials (no atomics).
// The three share one main loop (gemm_main_loop); the row and transposed GEMMs also one block body (gemm_block).
// The bf16 (and, where torch allows TF32, the float32) forwards and backwards can instead run their GEMMs on the
// tensor cores: skeletal/mma_gemm.cuh (opt-in, MODI_EXT_CUDA_MMA=1).
//
// Tiles: one block per (column tile of batch x time, output-channel tile, entity [x k split]); 64 x 64 (or 32 x 64
// when the GEMM has <= 32 rows) outputs per block, 4 x 4 per thread, 16-deep reduction stages double-buffered in
// shared memory (the gathered operand is staged with time innermost; contiguous aligned runs of the weight and of
// the weight gradient's left operand are read as 4-vectors).  Where those grids would leave SMs idle (small batch,
// coarse levels), the reduction is split across blocks (launch_plan.h) into partials that split_reduce_kernel sums
// in a fixed order, so results stay deterministic.  Accumulation is fp32 (fp64 for double inputs);
// inputs may be float32, float64, float16 or bfloat16.  Nothing synchronises with the host and no tensor is read on
// the host, so a training step can be captured in a CUDA graph.  Index validation happens on the device (topology
// kernel, CUDA_KERNEL_ASSERT), which also sanitises the CSR it hands to the GEMMs so no access can go out of bounds.
//
// Workspaces (all from the caching allocator, freed on return):
//   * topology: int32, (rows + 1) + nnz + (cols + 1) + 2 nnz (a few KB), kept per layer's maps (TopologyCache)
//   * style gradient: fp32 (fp64) copy of the unscaled input gradient, the size of x, only when d/dstyle is wanted
//   * weight gradient: S fp32 (fp64) partial weight gradients, S <= 32 splits of batch x time (S = 1: none)
//   * row / transposed GEMM: S fp32 (fp64) partial outputs, S <= 32 splits of each entity's k range (S = 1: none)
#include <torch/library.h>

#include <ATen/ATen.h>

#include <algorithm>
#include <cstdlib>
#include <cstring>
#include <mutex>
#include <type_traits>
#include <vector>

#include "common/cuda_common.cuh"
#include "common/wmma.cuh"
#include "skeletal/check.h"
#include "skeletal/launch_plan.h"
#include "skeletal/skeletal.h"

namespace modi_ext {
namespace {

using cuda::acc_t;
using cuda::ceil_div;
using cuda::ld;
using cuda::st;
using skeletal::check_backward_inputs;
using skeletal::check_inputs;
using skeletal::Geo;

using skeletal::plan::kBK;  // reduction depth of one shared-memory stage
using skeletal::plan::kBN;  // output columns (batch x time) per block

template <int BM>
struct Tile {
  static constexpr int TM = 4, TN = 4;
  static constexpr int TY = BM / TM;            // thread rows (8 or 16)
  static constexpr int TX = kBN / TN;           // thread columns (16)
  static constexpr int NT = TX * TY;            // threads per block (128 or 256)
  static constexpr int A_PER = BM * kBK / NT;   // A-operand elements each thread stages per stage
  static constexpr int B_PER = kBK * kBN / NT;  // B-operand elements each thread stages per stage
  static constexpr int A_STEP = NT / kBK;       // row step between a thread's A elements
  static constexpr int B_STEP = NT / kBN;       // k step between a thread's B elements (row / tr GEMM)
  static_assert((BM * kBK) % NT == 0 && (kBK * kBN) % NT == 0, "tile shape");
};

// ------------------------------------------------------------------------------------------------ operands
// Optional factor f(b, c, e) = p[b * sb + c * sc + e * se] (style: se = 0; demodulation: full); null means 1.
template <typename T>
struct Factor {
  const T* p = nullptr;
  int64_t sb = 0, sc = 0, se = 0;
  __device__ __forceinline__ acc_t<T> at(int b, int c, int e) const {
    return p ? ld(p + b * sb + c * sc + e * se) : acc_t<T>(1);
  }
};

// A contiguous (B, C, E, L) tensor.
template <typename T>
struct Src {
  const T* p = nullptr;
  int C = 0, E = 0, L = 0;
  __device__ __forceinline__ const T* row(int b, int c, int e) const {
    return p + ((int64_t(b) * C + c) * E + e) * L;
  }
};

// Forward read of frame `pos` of a row of length L: zero / mirrored outside [0, L) (h < L is checked on the host,
// so one reflection lands inside).  kBlurAdj reads the adjoint of the up-sampler's blur at that frame instead:
// (g[pos-1] + 3 g[pos] + 3 g[pos+1] + g[pos+2]) / 4, g zero outside [0, L).
template <typename T, bool kBlurAdj>
__device__ __forceinline__ acc_t<T> read_fwd(const T* row, int L, int pos, bool reflect) {
  using A = acc_t<T>;
  if (pos < 0 || pos >= L) {
    if (!reflect) return A(0);
    pos = pos < 0 ? -pos : 2 * (L - 1) - pos;
  }
  if constexpr (!kBlurAdj) {
    return ld(row + pos);
  } else {
    A v = A(3) * ld(row + pos);
    if (pos >= 1) v += ld(row + pos - 1);
    if (pos + 1 < L) v += A(3) * ld(row + pos + 1);
    if (pos + 2 < L) v += ld(row + pos + 2);
    return A(0.25) * v;
  }
}

// Source frame a / s when a is a non-negative multiple of s inside [0, Ls), else nothing (0).
template <typename T>
__device__ __forceinline__ acc_t<T> pick(const T* row, int Ls, int a, int s) {
  if (a < 0) return acc_t<T>(0);
  if (s != 1) {
    if (a % s) return acc_t<T>(0);
    a /= s;
  }
  return a < Ls ? ld(row + a) : acc_t<T>(0);
}

// Adjoint of the forward read "target position q <- source frame t with q = s*t + u - h" folded onto target frame
// tau in [0, Lt): position tau itself and, under reflect padding, the out-of-range positions that mirror onto it
// (-tau for tau >= 1, 2(Lt-1) - tau for tau <= Lt-2).  off = h - u.
template <typename T>
__device__ __forceinline__ acc_t<T> fold_at(const T* row, int Ls, int Lt, int tau, int off, int s, bool reflect) {
  acc_t<T> v = pick(row, Ls, tau + off, s);
  if (reflect) {
    if (tau >= 1) v += pick(row, Ls, -tau + off, s);
    if (tau <= Lt - 2) v += pick(row, Ls, 2 * (Lt - 1) - tau + off, s);
  }
  return v;
}

// kBlur: then the up-sampler's blur y[t] = (v[t-2] + 3 v[t-1] + 3 v[t] + v[t+1]) / 4, v zero outside [0, Lt).
template <typename T, bool kBlur>
__device__ __forceinline__ acc_t<T> read_tr(const T* row, int Ls, int Lt, int tau, int off, int s, bool reflect) {
  using A = acc_t<T>;
  if constexpr (!kBlur) {
    return fold_at<T>(row, Ls, Lt, tau, off, s, reflect);
  } else {
    A v = A(3) * fold_at<T>(row, Ls, Lt, tau, off, s, reflect);
    if (tau >= 2) v += fold_at<T>(row, Ls, Lt, tau - 2, off, s, reflect);
    if (tau >= 1) v += A(3) * fold_at<T>(row, Ls, Lt, tau - 1, off, s, reflect);
    if (tau + 1 < Lt) v += fold_at<T>(row, Ls, Lt, tau + 1, off, s, reflect);
    return A(0.25) * v;
  }
}

// Epilogue of the row / transposed GEMMs: element (b, m, e, t) of a (B, M, E, To) output.
//   ws set:   ws[...] = acc                                   (unscaled input gradient, for the style gradient)
//   else:     out[...] = acc * escale[b, m, e] * style[b, m] + bias[m]   (each factor optional), then with act
//             the bias activation (skeletal.h)
template <typename T>
struct Epi {
  T* out = nullptr;
  acc_t<T>* ws = nullptr;
  const T* escale = nullptr;  // (B, M, E)
  const T* style = nullptr;   // (B, M)
  const T* bias = nullptr;    // (M,)
  bool act = false;
  int E = 0;
};

// Element i of the (B, M, E, To) output: row r = (b * M + m) * E + ent = i / To.
template <typename T>
__device__ __forceinline__ void epi_store_at(const Epi<T>& e, int M, int To, int64_t i, acc_t<T> v) {
  if (e.ws) {
    e.ws[i] = v;
    return;
  }
  const int64_t r = i / To;
  if (e.escale) v *= ld(e.escale + r);
  const int64_t bm = r / e.E;  // b * M + m
  if (e.style) v *= ld(e.style + bm);
  if (e.bias) v += ld(e.bias + bm % M);
  if (e.act) v = act_fwd(v);
  st(e.out + i, v);
}

// acc[i][j] += sum_k As[k][ty + i*TY] * Bs[k][tx + j*TX]
// As / Bs: one stage, [kBK][BM + 1] and [kBK][kBN + 1] (a shared array's slice: any subscriptable view).
template <typename A, int BM, typename SA, typename SB>
__device__ __forceinline__ void mma_stage(const SA& As, const SB& Bs, A (&acc)[4][4], int ty, int tx) {
#pragma unroll
  for (int k = 0; k < kBK; ++k) {
    A a[4], b[4];
#pragma unroll
    for (int i = 0; i < 4; ++i) a[i] = As[k][ty + i * Tile<BM>::TY];
#pragma unroll
    for (int j = 0; j < 4; ++j) b[j] = Bs[k][tx + j * Tile<BM>::TX];
#pragma unroll
    for (int i = 0; i < 4; ++i)
#pragma unroll
      for (int j = 0; j < 4; ++j) acc[i][j] += a[i] * b[j];
  }
}

// The main loop of every GEMM kernel here: acc = the sum over nk reduction stages of kBK, each stage's operands
// double-buffered in shared memory (As / Bs: [2][kBK][BM + 1] and [2][kBK][kBN + 1]).  load(s) fetches stage s into
// registers while the products of the stage before run; store(buf) writes them to buffer buf.
template <typename A, int BM, typename Load, typename Store, typename SA, typename SB>
__device__ __forceinline__ void gemm_main_loop(int nk, const Load& load, const Store& store, const SA& As,
                                               const SB& Bs, A (&acc)[4][4], int ty, int tx) {
#pragma unroll
  for (int i = 0; i < 4; ++i)
#pragma unroll
    for (int j = 0; j < 4; ++j) acc[i][j] = A(0);
  if (nk > 0) {
    load(0);
    store(0);
  }
  __syncthreads();
  for (int kt = 0; kt < nk; ++kt) {
    const int buf = kt & 1;
    if (kt + 1 < nk) load(kt + 1);
    mma_stage<A, BM>(As[buf], Bs[buf], acc, ty, tx);
    if (kt + 1 < nk) store(buf ^ 1);
    __syncthreads();
  }
}

// A thread's place in a block of the row / transposed GEMMs: the block's output tile (rows from m0, columns from n0
// of the N = B x L columns), the A elements the thread stages (transposed GEMM: column a_k, rows a_m + i * A_STEP;
// row GEMM, one 4-vector along k: columns v_k ... v_k + 3 of row v_m) and the B elements (column b_n, rows
// b_k + i * B_STEP) with that column's batch element bb and frame tt (n_ok: a column < N), and the outputs it
// accumulates (rows ty + i * TY, columns tx + j * TX).
template <int BM>
struct TilePlace {
  static_assert(Tile<BM>::A_PER == 4 && Tile<BM>::NT == 4 * BM, "one A 4-vector per thread");
  int m0;
  int64_t n0;
  int a_k, a_m, v_k, v_m, b_n, b_k;
  bool n_ok;
  int bb, tt;
  int tx, ty;
  __device__ __forceinline__ TilePlace(int64_t N, int L) {
    const int tid = threadIdx.x;
    m0 = blockIdx.y * BM;
    n0 = int64_t(blockIdx.x) * kBN;
    a_k = tid % kBK;
    a_m = tid / kBK;
    v_k = (tid % 4) * 4;
    v_m = tid / 4;
    b_n = tid % kBN;
    b_k = tid / kBN;
    const int64_t ncol = n0 + b_n;
    n_ok = ncol < N;
    bb = n_ok ? static_cast<int>(ncol / L) : 0;
    tt = n_ok ? static_cast<int>(ncol - int64_t(bb) * L) : 0;
    tx = tid % Tile<BM>::TX;
    ty = tid / Tile<BM>::TX;
  }
};

// Epilogue of the row / transposed GEMMs: a thread's outputs (in range) to entity `ent` of the (B, M, E, L) output,
// or unscaled to `part` (the same layout) when the k range is split.
template <typename T, int BM>
__device__ __forceinline__ void store_tile(const Epi<T>& epi, acc_t<T>* part, int M, int64_t N, int L,
                                           const TilePlace<BM>& tp, int ent, const acc_t<T> (&acc)[4][4]) {
#pragma unroll
  for (int i = 0; i < 4; ++i) {
    const int m = tp.m0 + tp.ty + i * Tile<BM>::TY;
    if (m >= M) continue;
#pragma unroll
    for (int j = 0; j < 4; ++j) {
      const int64_t n = tp.n0 + tp.tx + j * Tile<BM>::TX;
      if (n >= N) continue;
      const int b = static_cast<int>(n / L);
      const int t = static_cast<int>(n - int64_t(b) * L);
      const int64_t o = ((int64_t(b) * M + m) * epi.E + ent) * L + t;
      if (part) {
        part[o] = acc[i][j];
      } else {
        epi_store_at(epi, M, L, o, acc[i][j]);
      }
    }
  }
}

// ------------------------------------------------------------------------------------------------ topology
// Device copy of the CSR as int32, validated (device-side asserts) and sanitised (every value clamped into range,
// so the GEMMs stay in bounds even if asserts were compiled out), plus optionally its transpose: for each column
// entity n the pairs p with idx[p] == n, in pair order, with their row entity.  One block; O(cols * nnz) work, which
// is tiny for skeletons (nnz is a few hundred).
__global__ void topology_kernel(const int64_t* __restrict__ offsets, const int64_t* __restrict__ index, int rows,
                                int cols, int nnz, int* __restrict__ ws, bool transpose) {
  int* off = ws;
  int* idx = off + rows + 1;
  int* toff = idx + nnz;
  int* tent = toff + cols + 1;
  int* tpair = tent + nnz;
  const int tid = threadIdx.x, nt = blockDim.x;
  if (tid == 0) {
    CUDA_KERNEL_ASSERT_MSG(offsets[0] == 0 && offsets[rows] == nnz,
                           "modi_ext: offsets must run from 0 to index.numel()");
  }
  for (int j = tid; j <= rows; j += nt) {
    const int64_t v = offsets[j];
    if (j < rows) {
      CUDA_KERNEL_ASSERT_MSG(offsets[j + 1] > v, "modi_ext: offsets: an output entity has no neighbors");
    }
    CUDA_KERNEL_ASSERT_MSG(v >= 0 && v <= nnz, "modi_ext: offsets hold a value outside [0, index.numel()]");
    off[j] = static_cast<int>(v < 0 ? 0 : (v > nnz ? nnz : v));
  }
  for (int p = tid; p < nnz; p += nt) {
    const int64_t v = index[p];
    CUDA_KERNEL_ASSERT_MSG(v >= 0 && v < cols, "modi_ext: index holds an entity out of range");
    idx[p] = static_cast<int>(v < 0 ? 0 : (v >= cols ? cols - 1 : v));
  }
  if (!transpose) return;
  __syncthreads();
  for (int n = tid; n < cols; n += nt) {
    int c = 0;
    for (int p = 0; p < nnz; ++p) c += idx[p] == n;
    toff[n + 1] = c;
  }
  __syncthreads();
  if (tid == 0) {
    toff[0] = 0;
    for (int n = 0; n < cols; ++n) toff[n + 1] += toff[n];
  }
  __syncthreads();
  for (int n = tid; n < cols; n += nt) {
    int q = toff[n];
    const int qend = toff[n + 1];
    int j = 0;
    for (int p = 0; p < nnz; ++p) {
      while (j < rows - 1 && off[j + 1] <= p) ++j;  // row entity of pair p (offsets are sorted)
      if (idx[p] == n && q < qend) {
        tent[q] = j;
        tpair[q] = p;
        ++q;
      }
    }
  }
}

struct DevTopo {
  at::Tensor buf;
  const int* off = nullptr;
  const int* idx = nullptr;
  const int* toff = nullptr;
  const int* tent = nullptr;
  const int* tpair = nullptr;
};

DevTopo build_topology(const at::Tensor& index, const at::Tensor& offsets, int64_t rows, int64_t cols, int64_t nnz,
                       cudaStream_t stream) {
  const int64_t n = (rows + 1) + nnz + (cols + 1) + 2 * nnz;
  DevTopo t;
  t.buf = at::empty({n}, index.options().dtype(at::kInt));
  int* p = t.buf.data_ptr<int>();
  MODI_LAUNCH(topology_kernel, 1, 256, 0, stream, offsets.data_ptr<int64_t>(), index.data_ptr<int64_t>(),
              static_cast<int>(rows), static_cast<int>(cols), static_cast<int>(nnz), p, true);
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  t.off = p;
  t.idx = p + rows + 1;
  t.toff = t.idx + nnz;
  t.tent = t.toff + cols + 1;
  t.tpair = t.tent + nnz;
  return t;
}

// The device CSR (and its transpose) of a layer's maps, built once and reused while they are unchanged: a layer hands
// the same index and offsets buffers to every call, and rebuilding them was a launch of a one-block kernel per op.
// An entry is keyed by the two storages -- held weakly, so a freed map's entry is dropped and its StorageImpl cannot
// be reused while the entry holds it -- their offsets and version counters (an in-place edit rebuilds), the sizes,
// the device and the stream (a build is ordered on its stream only).
class TopologyCache {
 public:
  DevTopo get(const at::Tensor& index, const at::Tensor& offsets, int64_t rows, int64_t cols, int64_t nnz,
              cudaStream_t stream) {
    const Key k{index.storage().unsafeGetStorageImpl(), offsets.storage().unsafeGetStorageImpl(),
                index.storage_offset(), offsets.storage_offset(), index._version(), offsets._version(), rows, cols,
                nnz, index.device().index(), stream};
    std::lock_guard<std::mutex> lock(mu_);
    for (const Entry& e : entries_)
      if (e.key == k && !e.index.expired() && !e.offsets.expired()) return e.topo;
    entries_.erase(std::remove_if(entries_.begin(), entries_.end(),
                                  [&](const Entry& e) {
                                    return e.index.expired() || e.offsets.expired() ||
                                           (e.key.index == k.index && e.key.offsets == k.offsets);
                                  }),
                   entries_.end());
    if (entries_.size() >= kMaxEntries) entries_.erase(entries_.begin());
    entries_.push_back(Entry{k, index.storage().getWeakStorageImpl(), offsets.storage().getWeakStorageImpl(),
                             build_topology(index, offsets, rows, cols, nnz, stream)});
    return entries_.back().topo;
  }

 private:
  struct Key {
    const void* index;
    const void* offsets;
    int64_t index_offset, offsets_offset;
    int64_t index_version, offsets_version;
    int64_t rows, cols, nnz;
    int device;
    cudaStream_t stream;
    bool operator==(const Key& o) const {
      return index == o.index && offsets == o.offsets && index_offset == o.index_offset &&
             offsets_offset == o.offsets_offset && index_version == o.index_version &&
             offsets_version == o.offsets_version && rows == o.rows && cols == o.cols && nnz == o.nnz &&
             device == o.device && stream == o.stream;
    }
  };
  struct Entry {
    Key key;
    c10::weak_intrusive_ptr<c10::StorageImpl> index, offsets;
    DevTopo topo;
  };
  static constexpr size_t kMaxEntries = 512;  // a model's layers, several models, a few streams
  std::mutex mu_;
  std::vector<Entry> entries_;
};

DevTopo device_topology(const at::Tensor& index, const at::Tensor& offsets, int64_t rows, int64_t cols,
                        int64_t nnz, cudaStream_t stream) {
  static TopologyCache cache;
  return cache.get(index, offsets, rows, cols, nnz, stream);
}

// ----------------------------------------------------------------------------------------------- row / transposed GEMM
// The gathered operand of the three GEMMs: for column n = (b, t) of the N = B x L columns and reduction index
// k = (r * C + c) * U + u, channel c of src's row of the r-th neighbour e_r, read at tap u of a stride-s window
// (h frames of zero / reflect padding), times fac(b, c, e_r).
template <typename T>
struct Gathered {
  int C = 0, U = 1, h = 0, s = 1;
  bool reflect = false;
  Src<T> src;  // (B, C, E, L_src)
  Factor<T> fac;
  int64_t N = 0;  // B * L
  int L = 0;
};

// Row GEMM (kTr = false):
//   out[b, m, row, t] = sum_{r, c, u} w[m, p0 + r, c, u] * fac(b, c, e_r) * read(src[b, c, e_r], s*t + u - h)
//   with e_r = idx[p0 + r], p0 = off[row]; k = (r * C + c) * U + u indexes the row's weight block contiguously.
// Transposed GEMM (kTr = true):
//   out[b, m, col, tau] = sum over readers q of col (pair p_q of row entity e_q), channels c, taps u of
//     w[c, p_q, m, u] * fac(b, c, e_q) * adjoint-read(src[b, c, e_q], tau; u)         (then the blur if kBlur)
//   k = (r * C + c) * U + u with r the reader's rank in the transposed CSR.
template <typename T>
struct GemmArgs : Gathered<T> {
  int M = 0;
  const T* w = nullptr;
  int64_t lda = 0;            // row GEMM: weight stride between GEMM rows m (nnz * C * U)
  int nnz = 0;                // transposed GEMM: the weight's pairs
  const int* off = nullptr;   // row GEMM: the CSR of the row entities
  const int* idx = nullptr;
  const int* toff = nullptr;  // transposed GEMM: the transposed CSR
  const int* tent = nullptr;
  const int* tpair = nullptr;
  Epi<T> epi;
  int ksplits = 1;                 // runs each entity's k stages are split into (launch_plan.h gemm_plan)
  acc_t<T>* part = nullptr;        // ksplits > 1: (ksplits, B, M, E, L) partials, reduced by split_reduce_kernel
  int64_t out_numel = 0;           // B * M * E * L
};

// One block of the row (kTr = false; kBlur: read through the blur's adjoint) or the transposed GEMM (kTr = true;
// kBlur: then the blur): the output tile of entity blockIdx.z / ksplits, rows m0.., columns n0.., over run
// blockIdx.z % ksplits of the entity's k stages.
template <typename T, int BM, bool kTr, bool kBlur>
__device__ __forceinline__ void gemm_block(const GemmArgs<T>& a) {
  using A = acc_t<T>;
  using TL = Tile<BM>;
  MODI_SHARED(A, As, [2][kBK][BM + 1]);
  MODI_SHARED(A, Bs, [2][kBK][kBN + 1]);
  const TilePlace<BM> tp(a.N, a.L);
  const int ent = blockIdx.z / a.ksplits;        // row GEMM: the row entity; transposed: the column entity
  const int ks = blockIdx.z - ent * a.ksplits;
  const int* const eoff = kTr ? a.toff : a.off;  // its neighbours (readers) q0 ... q0 + K / CU - 1
  const int q0 = eoff[ent];
  const int CU = a.C * a.U;
  const int K = (eoff[ent + 1] - q0) * CU;
  // This block's run of stages [s0, s1): equal runs in split order (an empty run still writes its zero partial).
  const int nk = (K + kBK - 1) / kBK, run = (nk + a.ksplits - 1) / a.ksplits;
  const int s0 = ks * run + (ks > 0 ? MODI_EMU_SPLIT_EDGE : 0);  // 0 outside the emulator's defect injection
  const int s1 = (ks + 1) * run < nk ? (ks + 1) * run : nk;
  [[maybe_unused]] const T* wblk = a.w + int64_t(q0) * CU;  // row GEMM only: the row's weight block
  [[maybe_unused]] const int pos0 = a.s * tp.tt - a.h;      // row GEMM only: the column's first frame

  A ra[TL::A_PER], rb[TL::B_PER];
  auto load = [&](int stage) {
    const int k0 = (s0 + stage) * kBK;
    if constexpr (!kTr) {  // A: the row's weight block, contiguous along k: one 4-vector where aligned
      const int m = tp.m0 + tp.v_m, k = k0 + tp.v_k;
      const T* p = wblk + int64_t(m < a.M ? m : 0) * a.lda + k;
      if (m < a.M && k + 3 < K && cuda::vec_aligned<4>(p)) {
        cuda::ld_vec<4>(p, ra);
      } else {
#pragma unroll
        for (int i = 0; i < 4; ++i) ra[i] = (m < a.M && k + i < K) ? ld(p + i) : A(0);
      }
    } else {  // A: the weight read transposed
      const int k = k0 + tp.a_k;
      const bool k_ok = k < K;
      int64_t base = 0;
      if (k_ok) {
        const int r = k / CU, rem = k - r * CU;
        const int c = rem / a.U, u = rem - c * a.U;
        base = (int64_t(c) * a.nnz + a.tpair[q0 + r]) * a.M * a.U + u;  // + m * U
      }
#pragma unroll
      for (int i = 0; i < TL::A_PER; ++i) {
        const int m = tp.m0 + tp.a_m + i * TL::A_STEP;
        ra[i] = (k_ok && m < a.M) ? ld(a.w + base + int64_t(m) * a.U) : A(0);
      }
    }
#pragma unroll
    for (int i = 0; i < TL::B_PER; ++i) {  // B: the gathered operand (transposed: the adjoint of its read)
      const int kk = k0 + tp.b_k + i * TL::B_STEP;
      A v = A(0);
      if (tp.n_ok && kk < K) {
        const int r = kk / CU, rem = kk - r * CU;
        const int c = rem / a.U, u = rem - c * a.U;
        if constexpr (!kTr) {
          const int e = a.idx[q0 + r];
          v = read_fwd<T, kBlur>(a.src.row(tp.bb, c, e), a.src.L, pos0 + u, a.reflect) * a.fac.at(tp.bb, c, e);
        } else {
          const int e = a.tent[q0 + r];
          v = read_tr<T, kBlur>(a.src.row(tp.bb, c, e), a.src.L, a.L, tp.tt, a.h - u, a.s, a.reflect) *
              a.fac.at(tp.bb, c, e);
        }
      }
      rb[i] = v;
    }
  };
  auto store = [&](int buf) {
    if constexpr (!kTr) {
#pragma unroll
      for (int i = 0; i < 4; ++i) As[buf][tp.v_k + i][tp.v_m] = ra[i];
    } else {
#pragma unroll
      for (int i = 0; i < TL::A_PER; ++i) As[buf][tp.a_k][tp.a_m + i * TL::A_STEP] = ra[i];
    }
    // MODI_EMU_OFF_BY_ONE (row GEMM only) is 0 outside the emulator's defect-injection build (common/cuda_common.cuh)
    constexpr int shift = kTr ? 0 : 1;
#pragma unroll
    for (int i = 0; i < TL::B_PER; ++i) Bs[buf][tp.b_k + i * TL::B_STEP][tp.b_n + shift * MODI_EMU_OFF_BY_ONE] = rb[i];
  };

  A acc[4][4];
  gemm_main_loop<A, BM>(s1 > s0 ? s1 - s0 : 0, load, store, As, Bs, acc, tp.ty, tp.tx);
  // transposed: entities with no reader get bias (or 0)
  store_tile<T, BM>(a.epi, a.part ? a.part + ks * a.out_numel : nullptr, a.M, a.N, a.L, tp, ent, acc);
}

template <typename T, int BM, bool kBlurAdj>
__global__ void __launch_bounds__(Tile<BM>::NT) row_gemm_kernel(const GemmArgs<T> a) {
  gemm_block<T, BM, false, kBlurAdj>(a);
}

template <typename T, int BM, bool kBlur>
__global__ void __launch_bounds__(Tile<BM>::NT) tr_gemm_kernel(const GemmArgs<T> a) {
  gemm_block<T, BM, true, kBlur>(a);
}

// ------------------------------------------------------------------------------------------------ weight gradient
// gW[m * lda + (p0 * C * U) + k] = sum_{n = (b, t)} L[m, n] * G[k, n]
//   L[m, n] = lsrc[b, m, row, t] * lfac(b, m, row)      (lsrc is (B, M, El, L))
//   G[k, n] = the row GEMM's gathered operand for this row.
// Grid (k-tile slot, m tile, split of the n range): slot s is the s-th kBN-wide k tile in row order (tiles do not
// cross rows); the host only bounds the slot count (launch_plan.h), so slots past the last tile exit.  One split
// writes gW directly; several write fp32 partials, reduced in split order by split_reduce_kernel.
template <typename T>
struct WArgs : Gathered<T> {
  const T* lsrc = nullptr;
  int M = 0, El = 0;
  Factor<T> lfac;
  int rows = 0;
  const int* off = nullptr;
  const int* idx = nullptr;
  int64_t n_chunk = 0;  // reduction columns per split, a multiple of 4
  int64_t lda = 0;
  T* gw = nullptr;
  acc_t<T>* ws = nullptr;  // (splits, weight numel) partials, or null to write gw
  int64_t wnumel = 0;
};

template <typename T, int BM, bool kBlurAdj>
__global__ void __launch_bounds__(Tile<BM>::NT) wgrad_kernel(const WArgs<T> a) {
  using A = acc_t<T>;
  using TL = Tile<BM>;
  constexpr int R_PER = kBN * kBK / TL::NT;  // right-operand elements per thread per stage
  constexpr int R_STEP = TL::NT / kBK;
  static_assert(TL::A_PER == 4 && TL::NT == 4 * BM, "one left-operand 4-vector per thread");
  MODI_SHARED(A, Ls, [2][kBK][BM + 1]);
  MODI_SHARED(A, Rs, [2][kBK][kBN + 1]);
  const int tid = threadIdx.x;
  const int CU = a.C * a.U;
  int row = -1, kc0 = 0;  // this block's k tile: columns kc0 ... kc0 + kBN - 1 of `row`'s weight block
  for (int r = 0, slot = blockIdx.x; r < a.rows; ++r) {
    const int nt = ((a.off[r + 1] - a.off[r]) * CU + kBN - 1) / kBN;
    if (slot < nt) {
      row = r;
      kc0 = slot * kBN;
      break;
    }
    slot -= nt;
  }
  if (row < 0) return;  // past the last tile: the whole block, before any barrier
  const int m0 = blockIdx.y * BM;
  const int split = blockIdx.z;
  // MODI_EMU_SPLIT_EDGE is 0 outside the emulator's defect injection (common/cuda_common.cuh)
  const int64_t nb = int64_t(split) * a.n_chunk + (split > 0 ? MODI_EMU_SPLIT_EDGE : 0);
  const int64_t ne = int64_t(split) * a.n_chunk + a.n_chunk < a.N ? int64_t(split) * a.n_chunk + a.n_chunk : a.N;
  const int p0 = a.off[row];
  const int K = (a.off[row + 1] - p0) * CU;

  const int l_n = tid % kBK, l_m = tid / kBK;  // right operand: fixed n offset, k columns step R_STEP
  const int v_n = (tid % 4) * 4, v_m = tid / 4;  // left operand: n offsets v_n ... v_n + 3 of row m0 + v_m
  const int tx = tid % TL::TX, ty = tid / TL::TX;
  const int nsteps = ne > nb ? static_cast<int>((ne - nb + kBK - 1) / kBK) : 0;

  // This thread's right-operand columns in the k tile: (c, u, entity), fixed across the n loop.
  int rc[R_PER], ru[R_PER], re[R_PER];
  bool rk[R_PER];
#pragma unroll
  for (int i = 0; i < R_PER; ++i) {
    const int kk = kc0 + l_m + i * R_STEP;
    rk[i] = kk < K;
    const int k = rk[i] ? kk : 0;
    const int r = k / CU, rem = k - r * CU;
    rc[i] = rem / a.U;
    ru[i] = rem - rc[i] * a.U;
    re[i] = a.idx[p0 + r];
  }
  const int lm = m0 + v_m;
  const bool lm_ok = lm < a.M;
  A rl[4], rr[R_PER];
  auto lval = [&](int64_t n) {  // L[lm, n], 0 outside the split
    if (n >= ne || !lm_ok) return A(0);
    const int b = static_cast<int>(n / a.L), t = static_cast<int>(n - int64_t(b) * a.L);
    return ld(a.lsrc + ((int64_t(b) * a.M + lm) * a.El + row) * a.L + t) * a.lfac.at(b, lm, row);
  };
  auto load = [&](int stage) {  // L: the output-side rows; R: the gathered inputs
    {  // L is contiguous along n within a batch element: one 4-vector where aligned
      const int64_t n = nb + int64_t(stage) * kBK + v_n;
      const int b = static_cast<int>(n / a.L), t = static_cast<int>(n - int64_t(b) * a.L);
      const T* p = a.lsrc + ((int64_t(b) * a.M + (lm_ok ? lm : 0)) * a.El + row) * a.L + t;
      if (lm_ok && n + 3 < ne && t + 3 < a.L && cuda::vec_aligned<4>(p)) {
        cuda::ld_vec<4>(p, rl);
        const A f = a.lfac.at(b, lm, row);
#pragma unroll
        for (int i = 0; i < 4; ++i) rl[i] *= f;
      } else {
#pragma unroll
        for (int i = 0; i < 4; ++i) rl[i] = lval(n + i);
      }
    }
    const int64_t n = nb + int64_t(stage) * kBK + l_n;
    const bool n_ok = n < ne;
    const int b = n_ok ? static_cast<int>(n / a.L) : 0;
    const int t = n_ok ? static_cast<int>(n - int64_t(b) * a.L) : 0;
    const int pos0 = a.s * t - a.h;
#pragma unroll
    for (int i = 0; i < R_PER; ++i) {
      rr[i] = (n_ok && rk[i])
                  ? read_fwd<T, kBlurAdj>(a.src.row(b, rc[i], re[i]), a.src.L, pos0 + ru[i], a.reflect) *
                        a.fac.at(b, rc[i], re[i])
                  : A(0);
    }
  };
  auto store = [&](int buf) {
#pragma unroll
    for (int i = 0; i < 4; ++i) Ls[buf][v_n + i][v_m] = rl[i];
#pragma unroll
    for (int i = 0; i < R_PER; ++i) Rs[buf][l_n][l_m + i * R_STEP] = rr[i];
  };

  A acc[4][4];
  gemm_main_loop<A, BM>(nsteps, load, store, Ls, Rs, acc, ty, tx);
#pragma unroll
  for (int i = 0; i < 4; ++i) {
    const int m = m0 + ty + i * TL::TY;
    if (m >= a.M) continue;
#pragma unroll
    for (int j = 0; j < 4; ++j) {
      const int kc = kc0 + tx + j * TL::TX;
      if (kc >= K) continue;
      const int64_t o = int64_t(m) * a.lda + int64_t(p0) * CU + kc;
      if (a.ws) {
        a.ws[int64_t(split) * a.wnumel + o] = acc[i][j];
      } else {
        st(a.gw + o, acc[i][j]);
      }
    }
  }
}

// out = sum over the splits, in split order, of the (splits, n) partials, through the epilogue (wgrad: a plain store).
template <typename T>
__global__ void split_reduce_kernel(const acc_t<T>* __restrict__ ws, int splits, int64_t n, const Epi<T> epi, int M,
                                    int To) {
  for (int64_t i = int64_t(blockIdx.x) * blockDim.x + threadIdx.x; i < n; i += int64_t(gridDim.x) * blockDim.x) {
    acc_t<T> s = 0;
    // MODI_EMU_GLOBAL_OOB is 0 outside the emulator's defect injection (common/cuda_common.cuh)
    for (int k = 0; k < splits + MODI_EMU_GLOBAL_OOB; ++k) s += ws[int64_t(k) * n + i];
    epi_store_at(epi, M, To, i, s);
  }
}

// ------------------------------------------------------------------------------------------------ small reductions
// Style gradient: block per (b, i): gs = sum_{e,t} gx'[b,i,e,t] * x[b,i,e,t]; gx = gx' * style[b,i] (if wanted).
template <typename T>
__global__ void style_finish_kernel(const acc_t<T>* __restrict__ gxp, const T* __restrict__ x,
                                    const T* __restrict__ style, int64_t len, T* __restrict__ gx,
                                    T* __restrict__ gs) {
  using A = acc_t<T>;
  MODI_SHARED(A, scratch, [32]);
  const int64_t bi = blockIdx.x;
  const A sv = ld(style + bi);
  const A* g = gxp + bi * len;
  const T* xr = x + bi * len;
  A dot = A(0);
  for (int64_t k = threadIdx.x; k < len; k += blockDim.x) {
    const A v = g[k];
    dot += v * ld(xr + k);
    if (gx) st(gx + bi * len + k, v * sv);
  }
  dot = cuda::block_sum(dot, scratch);
  if (MODI_EMU_WRONG_SCALE) dot *= A(1) + A(1) / A(512);  // 0 outside the emulator's defect injection
  if (threadIdx.x == 0) st(gs + bi, dot);
}

// The backward of the bias activation (skeletal.h), elementwise: gp = act_slope(y) * gy, and yp = y / act_slope(y)
// (the pre-activation, for the scale gradient) where yp is set.
template <typename T>
__global__ void act_backward_kernel(const T* __restrict__ gy, const T* __restrict__ y, int64_t n, T* __restrict__ gp,
                                    T* __restrict__ yp) {
  using A = acc_t<T>;
  for (int64_t i = blockIdx.x * int64_t(blockDim.x) + threadIdx.x; i < n; i += int64_t(gridDim.x) * blockDim.x) {
    const A v = ld(y + i);
    // MODI_EMU_WRONG_SLOPE: the emulator's planted fault (0 in every other build), a negative-side slope 2^-9 off
    A k = act_slope(v);
    if (MODI_EMU_WRONG_SLOPE && v < A(0)) k *= A(1) + A(1.0 / 512);
    st(gp + i, k * ld(gy + i));
    if (yp) st(yp + i, v / k);
  }
}

// Demodulation-scale gradient: warp per (b, o, j): gd = sum_t gy * (y - bias[o]) / d   (y = d * z + bias).
template <typename T>
__global__ void scale_grad_kernel(const T* __restrict__ gy, const T* __restrict__ y, const T* __restrict__ bias,
                                  const T* __restrict__ scale, int64_t rows, int Co, int Eo, int To,
                                  T* __restrict__ gd) {
  using A = acc_t<T>;
  const int64_t r = (int64_t(blockIdx.x) * blockDim.x + threadIdx.x) >> 5;
  const int lane = threadIdx.x & 31;
  if (r >= rows) return;  // uniform per warp
  const int o = static_cast<int>((r / Eo) % Co);
  const A bb = bias ? ld(bias + o) : A(0);
  A acc = A(0);
  for (int t = lane; t < To; t += 32) acc += ld(gy + r * To + t) * (ld(y + r * To + t) - bb);
  acc = cuda::warp_sum(acc);
  if (lane == 0) st(gd + r, acc / ld(scale + r));
}

// ------------------------------------------------------------------------------------------------ launchers
// f(std::integral_constant<int, BM>{}) with the tile height BM of a GEMM of M rows (plan::tile_rows).
template <typename F>
void with_tile_rows(int M, const F& f) {
  if (skeletal::plan::tile_rows(M) == 32) {
    f(std::integral_constant<int, 32>{});
  } else {
    f(std::integral_constant<int, 64>{});
  }
}

// Sums (splits, n) partials in split order into epi (M, To: the epilogue's output geometry).
template <typename T>
void launch_split_reduce(const acc_t<T>* ws, int64_t splits, int64_t n, const Epi<T>& epi, int M, int To,
                         cudaStream_t stream) {
  const int threads = 256;
  const int64_t blocks = std::min<int64_t>(ceil_div(n, threads), 4096);
  MODI_LAUNCH((split_reduce_kernel<T>), static_cast<unsigned>(blocks), threads, 0, stream, ws,
      static_cast<int>(splits), n, epi, M, To);
  C10_CUDA_KERNEL_LAUNCH_CHECK();
}

// The row (kTr = false) or the transposed GEMM over `ents` entities: grid (column tiles of the N columns, row tiles
// of the M rows, entities x k splits).  With k splits the epilogue runs in the reduction, over fp32 (fp64) partials
// of splits x output numel.
template <typename T, bool kTr, bool kBlur>
void launch_gemm(GemmArgs<T> a, int64_t ents, int64_t nnz, int device, const at::TensorOptions& opts,
                 cudaStream_t stream) {
  const auto p = skeletal::plan::gemm_plan(a.N, a.M, ents, nnz, int64_t(a.C) * a.U, cuda::sm_count(device));
  at::Tensor part;
  a.ksplits = static_cast<int>(p.splits);
  if (p.splits > 1) {
    a.out_numel = a.N * a.M * ents;
    part = at::empty({p.splits * a.out_numel}, opts.dtype(cuda::acc_scalar_type(opts.dtype().toScalarType())));
    a.part = part.data_ptr<acc_t<T>>();
  }
  with_tile_rows(a.M, [&](auto tile) {
    constexpr int BM = decltype(tile)::value;
    const dim3 grid(static_cast<unsigned>(p.ntiles), static_cast<unsigned>(p.mtiles),
                    static_cast<unsigned>(ents * p.splits));
    if constexpr (kTr) {
      MODI_LAUNCH((tr_gemm_kernel<T, BM, kBlur>), grid, Tile<BM>::NT, 0, stream, a);
    } else {
      MODI_LAUNCH((row_gemm_kernel<T, BM, kBlur>), grid, Tile<BM>::NT, 0, stream, a);
    }
  });
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  if (p.splits > 1) launch_split_reduce<T>(a.part, p.splits, a.out_numel, a.epi, a.M, a.L, stream);
}

// Weight gradient into gw (same layout as the weight): grid (k-tile slots, m tiles, splits of batch x time) of
// plan::wgrad_plan; with several splits, partials live in an fp32 (fp64) workspace of splits x weight numel.
template <typename T, bool kBlurAdj>
void launch_wgrad(WArgs<T> a, int64_t rows, int64_t nnz, const at::Tensor& gw, int device, cudaStream_t stream) {
  const auto p = skeletal::plan::wgrad_plan(a.N, rows, nnz, int64_t(a.C) * a.U, a.M, cuda::sm_count(device));
  a.rows = static_cast<int>(rows);
  a.n_chunk = p.n_chunk;
  a.gw = gw.data_ptr<T>();
  a.wnumel = gw.numel();
  at::Tensor ws;
  if (p.splits > 1) {
    ws = at::empty({p.splits * a.wnumel}, gw.options().dtype(cuda::acc_scalar_type(gw.scalar_type())));
    a.ws = ws.data_ptr<acc_t<T>>();
  }
  const dim3 grid(static_cast<unsigned>(p.ktiles), static_cast<unsigned>(p.mtiles), static_cast<unsigned>(p.splits));
  with_tile_rows(a.M, [&](auto tile) {
    constexpr int BM = decltype(tile)::value;
    MODI_LAUNCH((wgrad_kernel<T, BM, kBlurAdj>), grid, Tile<BM>::NT, 0, stream, a);
  });
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  if (p.splits > 1) {
    Epi<T> out;
    out.out = a.gw;
    out.E = 1;
    launch_split_reduce<T>(a.ws, p.splits, a.wnumel, out, 1, 1, stream);
  }
}

// The opt-in tensor-core form of the GEMMs (bf16, TF32): mma_gemm_kernel, mma_wgrad_kernel and their launchers.
#include "skeletal/mma_gemm.cuh"

cudaStream_t current_stream(const at::Tensor& x) { return c10::cuda::getCurrentCUDAStream(x.device().index()); }

// The gathered operand of one of a call's GEMMs: C channels of src times fac, read at stride s, over B x L columns.
template <typename T>
Gathered<T> gathered(const Geo& g, int64_t C, int s, const Src<T>& src, const Factor<T>& fac, int64_t L) {
  Gathered<T> in;
  in.C = static_cast<int>(C);
  in.U = static_cast<int>(g.U);
  in.h = static_cast<int>(g.h);
  in.s = s;
  in.reflect = g.reflect;
  in.src = src;
  in.fac = fac;
  in.N = g.B * L;
  in.L = static_cast<int>(L);
  return in;
}

// A row or transposed GEMM of M rows over the gathered operand `in`: the weight, the topology and the epilogue.
template <typename T>
GemmArgs<T> gemm_args(const Geo& g, const Gathered<T>& in, int64_t M, const T* w, const DevTopo& topo,
                      const Epi<T>& epi) {
  GemmArgs<T> a{in};
  a.M = static_cast<int>(M);
  a.w = w;
  a.lda = g.nnz * in.C * g.U;
  a.nnz = static_cast<int>(g.nnz);
  a.off = topo.off;
  a.idx = topo.idx;
  a.toff = topo.toff;
  a.tent = topo.tent;
  a.tpair = topo.tpair;
  a.epi = epi;
  return a;
}

// ------------------------------------------------------------------------------------------------ forward
// MODI_EXT_CUDA_MMA=1: the GEMMs of bf16 ops run on the tensor cores (skeletal/mma_gemm.cuh), and those of float32 ops
// too while torch allows TF32 (torch.backends.cudnn.allow_tf32, the switch that governs torch's own convolutions:
// TF32 rounds the operands to 10 mantissa bits, so a user who turned it off asked for float32 products).  Read per
// call, so a test or benchmark can switch it; off by default: no GPU has timed it against the SIMT kernels yet.
bool mma_requested() {
  const char* v = std::getenv("MODI_EXT_CUDA_MMA");
  return v && std::strcmp(v, "1") == 0;
}

template <typename T>
bool mma_for(int device) {
  if constexpr (std::is_same_v<T, at::BFloat16>) {
    return mma_requested();  // launch_mma_* refuse a device without bf16 tensor cores
  } else if constexpr (std::is_same_v<T, float>) {
    // without TF32 tensor cores (before sm_80) torch's switch does nothing either: float32 stays on the SIMT kernels
    return mma_requested() && at::globalContext().allowTF32CuDNN() && cuda::cc_major(device) >= 8;
  } else {
    (void)device;
    return false;
  }
}

at::Tensor forward_cuda(int64_t kind, const at::Tensor& x, const at::Tensor& weight,
                        const std::optional<at::Tensor>& bias, const at::Tensor& index, const at::Tensor& offsets,
                        int64_t n_out, const std::optional<at::Tensor>& style, const std::optional<at::Tensor>& scale,
                        c10::string_view padding_mode, bool act) {
  const Geo g = check_inputs(kCudaBackend, kind, x, weight, bias, index, offsets, n_out, style, scale, padding_mode);
  const c10::cuda::CUDAGuard guard(x.device());
  const cudaStream_t stream = current_stream(x);
  const bool up = kind == kUp;
  const int64_t rows = offsets.numel() - 1;
  const int64_t cols = up ? g.Eout : g.Ein;
  const DevTopo topo = device_topology(index, offsets, rows, cols, g.nnz, stream);
  at::Tensor y = at::empty({g.B, g.Cout, g.Eout, g.Tout}, x.options());
  AT_DISPATCH_FLOATING_TYPES_AND2(at::kHalf, at::kBFloat16, x.scalar_type(), "modi_ext::skeletal_forward_cuda", [&] {
    using T = scalar_t;
    Epi<T> epi;
    epi.out = y.data_ptr<T>();
    epi.escale = scale.has_value() ? scale->data_ptr<T>() : nullptr;
    epi.bias = bias.has_value() ? bias->data_ptr<T>() : nullptr;
    epi.act = act;
    epi.E = static_cast<int>(g.Eout);
    Factor<T> sty;
    if (style.has_value()) sty = Factor<T>{style->data_ptr<T>(), g.Cin, 1, 0};
    const Src<T> src{x.data_ptr<T>(), static_cast<int>(g.Cin), static_cast<int>(g.Ein), static_cast<int>(g.Tin)};
    // conv / down: the row GEMM over the x rows of each output entity's neighbours; up: the transposed GEMM over the
    // x rows of the coarse entities that read each fine entity
    const GemmArgs<T> a = gemm_args<T>(g, gathered<T>(g, g.Cin, kind == kConv ? 1 : 2, src, sty, g.Tout), g.Cout,
                                       weight.data_ptr<T>(), topo, epi);
    if constexpr (std::is_same_v<T, at::BFloat16> || std::is_same_v<T, float>) {
      if (mma_for<T>(x.device().index())) {
        if (!up) {
          launch_mma_gemm<T, false, false>(a, rows, x.device().index(), stream);
        } else {
          launch_mma_gemm<T, true, true>(a, cols, x.device().index(), stream);
        }
        return;
      }
    }
    if (!up) {
      launch_gemm<T, false, false>(a, rows, g.nnz, x.device().index(), x.options(), stream);
    } else {
      launch_gemm<T, true, true>(a, cols, g.nnz, x.device().index(), x.options(), stream);
    }
  });
  return y;
}

at::Tensor skeletal_conv_cuda(const at::Tensor& x, const at::Tensor& weight, const std::optional<at::Tensor>& bias,
                              const at::Tensor& index, const at::Tensor& offsets,
                              const std::optional<at::Tensor>& style, const std::optional<at::Tensor>& scale,
                              c10::string_view padding_mode, bool act) {
  return forward_cuda(kConv, x, weight, bias, index, offsets, 0, style, scale, padding_mode, act);
}

at::Tensor skeletal_down_cuda(const at::Tensor& x, const at::Tensor& weight, const std::optional<at::Tensor>& bias,
                              const at::Tensor& index, const at::Tensor& offsets,
                              const std::optional<at::Tensor>& style, const std::optional<at::Tensor>& scale,
                              c10::string_view padding_mode, bool act) {
  return forward_cuda(kDown, x, weight, bias, index, offsets, 0, style, scale, padding_mode, act);
}

at::Tensor skeletal_up_cuda(const at::Tensor& x, const at::Tensor& weight, const std::optional<at::Tensor>& bias,
                            const at::Tensor& index, const at::Tensor& offsets, int64_t n_out,
                            const std::optional<at::Tensor>& style, const std::optional<at::Tensor>& scale,
                            c10::string_view padding_mode, bool act) {
  return forward_cuda(kUp, x, weight, bias, index, offsets, n_out, style, scale, padding_mode, act);
}

// ------------------------------------------------------------------------------------------------ backward
std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor> skeletal_backward_cuda(
    const at::Tensor& grad, const at::Tensor& out, const at::Tensor& x, const at::Tensor& weight,
    const std::optional<at::Tensor>& bias, const at::Tensor& index, const at::Tensor& offsets,
    const std::optional<at::Tensor>& style, const std::optional<at::Tensor>& scale, c10::string_view padding_mode,
    int64_t kind, int64_t n_out, std::array<bool, 4> output_mask, bool act) {
  const Geo g = check_backward_inputs(kCudaBackend, grad, out, x, weight, bias, index, offsets, style, scale,
                                      padding_mode, kind, n_out);
  const c10::cuda::CUDAGuard guard(x.device());
  const cudaStream_t stream = current_stream(x);
  if (act) {  // from the pre-activation on, the backward is the one without act
    const bool need_pre = output_mask[3] && scale.has_value();
    at::Tensor g_pre = at::empty_like(grad), y_pre = need_pre ? at::empty_like(out) : out;
    const int64_t n = grad.numel();
    AT_DISPATCH_FLOATING_TYPES_AND2(at::kHalf, at::kBFloat16, x.scalar_type(), "modi_ext::skeletal_act_backward", [&] {
      using T = scalar_t;
      const int threads = 256;
      const int64_t blocks = std::max<int64_t>(1, std::min<int64_t>(ceil_div(n, threads), 4096));
      MODI_LAUNCH((act_backward_kernel<T>), static_cast<unsigned>(blocks), threads, 0, stream, grad.data_ptr<T>(),
          out.data_ptr<T>(), n, g_pre.data_ptr<T>(), need_pre ? y_pre.data_ptr<T>() : nullptr);
      C10_CUDA_KERNEL_LAUNCH_CHECK();
    });
    return skeletal_backward_cuda(g_pre, y_pre, x, weight, bias, index, offsets, style, scale, padding_mode, kind,
                                  n_out, output_mask, false);
  }
  const int device = x.device().index();
  const bool up = kind == kUp;
  const int64_t rows = offsets.numel() - 1;
  const int64_t cols = up ? g.Eout : g.Ein;

  auto empty = [&] { return at::empty({0}, x.options()); };
  const bool want_gx = output_mask[0];
  const bool want_gw = output_mask[1];
  const bool want_gs = output_mask[2] && style.has_value();
  const bool want_gd = output_mask[3] && scale.has_value();
  at::Tensor gx = want_gx ? at::empty_like(x) : empty();
  at::Tensor gw = want_gw ? at::empty_like(weight) : empty();
  at::Tensor gb = bias.has_value() ? grad.sum(at::IntArrayRef{0, 2, 3}) : empty();
  at::Tensor gs = want_gs ? at::empty_like(*style) : empty();
  at::Tensor gd = want_gd ? at::empty_like(*scale) : empty();
  const bool need_in = want_gx || want_gs;
  if (!need_in && !want_gw && !want_gd) return {gx, gw, gb, gs, gd};
  const DevTopo topo = device_topology(index, offsets, rows, cols, g.nnz, stream);

  AT_DISPATCH_FLOATING_TYPES_AND2(at::kHalf, at::kBFloat16, x.scalar_type(), "modi_ext::skeletal_backward_cuda", [&] {
    using T = scalar_t;
    using A = acc_t<T>;
    const T* gy = grad.data_ptr<T>();
    const T* sp = style.has_value() ? style->data_ptr<T>() : nullptr;
    const T* dp = scale.has_value() ? scale->data_ptr<T>() : nullptr;
    const Factor<T> sty = sp ? Factor<T>{sp, g.Cin, 1, 0} : Factor<T>{};
    const Factor<T> dsc = dp ? Factor<T>{dp, g.Cout * g.Eout, g.Eout, 1} : Factor<T>{};
    const Src<T> gsrc{gy, static_cast<int>(g.Cout), static_cast<int>(g.Eout), static_cast<int>(g.Tout)};
    const Src<T> xsrc{x.data_ptr<T>(), static_cast<int>(g.Cin), static_cast<int>(g.Ein), static_cast<int>(g.Tin)};

    if (want_gd) {
      const int64_t r = g.B * g.Cout * g.Eout;
      const int threads = 256;
      MODI_LAUNCH((scale_grad_kernel<T>), static_cast<unsigned>(ceil_div(r * 32, threads)), threads, 0, stream,
          gy, out.data_ptr<T>(), bias.has_value() ? bias->data_ptr<T>() : nullptr, dp, r,
          static_cast<int>(g.Cout), static_cast<int>(g.Eout), static_cast<int>(g.Tout), gd.data_ptr<T>());
      C10_CUDA_KERNEL_LAUNCH_CHECK();
    }

    if (need_in) {
      // Unscaled input gradient gx' (w.r.t. x * style); with a style gradient wanted it goes to an fp32 workspace
      // the size of x, from which style_finish_kernel forms gs and gx = gx' * style.
      at::Tensor ws;
      Epi<T> epi;
      epi.E = static_cast<int>(g.Ein);
      if (want_gs) {
        ws = at::empty(x.sizes(), x.options().dtype(cuda::acc_scalar_type(x.scalar_type())));
        epi.ws = ws.data_ptr<A>();
      } else {
        epi.out = gx.data_ptr<T>();
        epi.style = sp;
      }
      // up: gx'[b,i,c,t] = sum_{p in row c, o, u} w[i,p,o,u] * (d * blur^T gy)[b,o,idx[p], read(2t+u-h)] (row GEMM);
      // conv / down: gx'[b,i,n,tau] = sum over readers (j, p) of n, o, u of w[o,p,i,u] * (d * gy)[b,o,j, adjoint
      // read at tau] (transposed GEMM)
      const GemmArgs<T> a = gemm_args<T>(g, gathered<T>(g, g.Cout, kind == kConv ? 1 : 2, gsrc, dsc, g.Tin), g.Cin,
                                         weight.data_ptr<T>(), topo, epi);
      bool done = false;
      if constexpr (std::is_same_v<T, at::BFloat16> || std::is_same_v<T, float>) {
        if (mma_for<T>(device)) {
          if (up) {
            launch_mma_gemm<T, false, true>(a, rows, device, stream);
          } else {
            launch_mma_gemm<T, true, false>(a, cols, device, stream);
          }
          done = true;
        }
      }
      if (!done) {
        if (up) {
          launch_gemm<T, false, true>(a, rows, g.nnz, device, x.options(), stream);
        } else {
          launch_gemm<T, true, false>(a, cols, g.nnz, device, x.options(), stream);
        }
      }
      if (want_gs) {
        MODI_LAUNCH((style_finish_kernel<T>), static_cast<unsigned>(g.B * g.Cin), 256, 0, stream,
            epi.ws, x.data_ptr<T>(), sp, g.Ein * g.Tin, want_gx ? gx.data_ptr<T>() : nullptr, gs.data_ptr<T>());
        C10_CUDA_KERNEL_LAUNCH_CHECK();
      }
    }

    if (want_gw) {
      // up:          gW[i,p,o,u] = sum_{b,t} x[b,i,c,t] s[b,i] * (d * blur^T gy)[b,o,idx[p], read(2t+u-h)]
      // conv / down: gW[o,p,i,u] = sum_{b,t} (d * gy)[b,o,j,t] * s[b,i] x[b,i,idx[p], read(s*t+u-h)]
      WArgs<T> a{up ? gathered<T>(g, g.Cout, 2, gsrc, dsc, g.Tin)
                    : gathered<T>(g, g.Cin, kind == kConv ? 1 : 2, xsrc, sty, g.Tout)};
      a.lsrc = up ? x.data_ptr<T>() : gy;
      a.M = static_cast<int>(up ? g.Cin : g.Cout);
      a.El = static_cast<int>(up ? g.Ein : g.Eout);
      a.lfac = up ? sty : dsc;
      a.off = topo.off;
      a.idx = topo.idx;
      a.lda = g.nnz * a.C * g.U;
      bool done = false;
      if constexpr (std::is_same_v<T, at::BFloat16> || std::is_same_v<T, float>) {
        if (mma_for<T>(device)) {
          if (up) {
            launch_mma_wgrad<T, true>(a, rows, g.nnz, gw, device, stream);
          } else {
            launch_mma_wgrad<T, false>(a, rows, g.nnz, gw, device, stream);
          }
          done = true;
        }
      }
      if (!done) {
        if (up) {
          launch_wgrad<T, true>(a, rows, g.nnz, gw, device, stream);
        } else {
          launch_wgrad<T, false>(a, rows, g.nnz, gw, device, stream);
        }
      }
    }
  });
  return {gx, gw, gb, gs, gd};
}

}  // namespace

TORCH_LIBRARY_IMPL(MODI_CUDA_LIB, MODI_CUDA_KEY, m) {
  m.impl("skeletal_conv", &skeletal_conv_cuda);
  m.impl("skeletal_down", &skeletal_down_cuda);
  m.impl("skeletal_up", &skeletal_up_cuda);
  m.impl("skeletal_backward", &skeletal_backward_cuda);
}

}  // namespace modi_ext
