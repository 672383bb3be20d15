// CPU kernels of the skeletal operators.
//
// Every pass is "one small GEMM per entity": for a row entity j and a tile of batch elements, gather the
// time-shifted inputs of j's neighbors into a contiguous (K x N) panel (rows = neighbor x channel x tap, columns =
// batch x time, time innermost), multiply by the entity's weight block (a strided view of the compact weight, or a
// once-per-call transposed copy), and write the tile out with the style / demodulation / bias / fold / blur applied
// in the epilogue.  Tasks (batch tile x entity) run under at::parallel_for with thread-local panels; the weight
// gradient accumulates into thread-local copies reduced at the end.  The GEMM is the BLAS that libtorch ships
// (sgemm_/dgemm_, single-threaded inside the parallel region), with an ATen fallback when it is not exported.
#include <algorithm>
#include <cstdlib>
#include <cstring>
#include <vector>

#if defined(__x86_64__)
#include <immintrin.h>
#endif

#include <ATen/Parallel.h>
#include <torch/library.h>

#include "skeletal.h"

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

// Threads only pay off above some work: waking a pool costs microseconds (milliseconds on a loaded machine).
constexpr double kSerialMacs = 1.0e6;
constexpr int64_t kSerialElems = 1 << 16;
inline int64_t task_grain(int64_t n_tasks, double macs) { return macs < kSerialMacs ? std::max<int64_t>(n_tasks, 1) : 1; }
inline int64_t elem_grain(int64_t elems_per_item) { return std::max<int64_t>(1, kSerialElems / std::max<int64_t>(1, elems_per_item)); }

// A permutation of rows 0..n-1 (cost = neighbour count from CSR offsets) such that at::parallel_for's static split
// of it into `parts` contiguous runs gives every run about the same total cost: greedy largest-first bin packing,
// then the bins concatenated with their sizes padded to the even split parallel_for makes.
inline std::vector<int64_t> balanced_order(const std::vector<int64_t>& off, int64_t n, int64_t parts) {
  std::vector<int64_t> rows(static_cast<size_t>(n));
  for (int64_t i = 0; i < n; ++i) rows[i] = i;
  if (parts <= 1 || n <= parts) return rows;
  auto cost = [&](int64_t r) { return off[r + 1] - off[r]; };
  std::stable_sort(rows.begin(), rows.end(), [&](int64_t a, int64_t b) { return cost(a) > cost(b); });
  // parallel_for splits [0, n) into chunks of ceil(n / parts); give each bin exactly that many slots
  const int64_t slots = (n + parts - 1) / parts;
  std::vector<std::vector<int64_t>> bins(static_cast<size_t>(parts));
  std::vector<int64_t> load(static_cast<size_t>(parts), 0);
  for (int64_t r : rows) {
    int64_t best = -1;
    for (int64_t p = 0; p < parts; ++p)
      if (static_cast<int64_t>(bins[p].size()) < slots && (best < 0 || load[p] < load[best])) best = p;
    bins[best].push_back(r);
    load[best] += cost(r);
  }
  std::stable_sort(bins.begin(), bins.end(), [](const auto& a, const auto& b) { return a.size() > b.size(); });
  std::vector<int64_t> out;
  out.reserve(static_cast<size_t>(n));
  for (auto& b : bins) out.insert(out.end(), b.begin(), b.end());
  return out;
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
template <typename T>
std::vector<T> transpose_weight(const T* w, int64_t C0, int64_t nnz, int64_t C1, int64_t U,
                                const std::vector<int64_t>& tpair) {
  std::vector<T> out(static_cast<size_t>(C0 * nnz * C1 * U));
  at::parallel_for(0, C1, elem_grain(nnz * C0 * U), [&](int64_t lo, int64_t hi) {
    for (int64_t c1 = lo; c1 < hi; ++c1)
      for (int64_t q = 0; q < nnz; ++q)
        for (int64_t c0 = 0; c0 < C0; ++c0) {
          const T* src = w + ((c0 * nnz + tpair[q]) * C1 + c1) * U;
          T* dst = out.data() + ((c1 * nnz + q) * C0 + c0) * U;
          for (int64_t u = 0; u < U; ++u) dst[u] = src[u];
        }
  });
  return out;
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

// Batch elements per tile: about `target` panel columns, and enough tiles to keep every thread busy.
int64_t batch_tile(int64_t B, int64_t cols_per_b, int64_t n_entities, int64_t target = 512) {
  int64_t nb = std::max<int64_t>(1, target / std::max<int64_t>(1, cols_per_b));
  nb = std::min(nb, B);
  const int64_t threads = at::get_num_threads();
  while (nb > 1 && ((B + nb - 1) / nb) * n_entities < 2 * threads) nb = (nb + 1) / 2;
  return nb;
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
  const int64_t nbt = (g.B + nb - 1) / nb;
  const int64_t maxK = csr.max_deg * g.Cin * g.U, cols = nb * g.Tout;
  const int64_t lda = g.nnz * g.Cin * g.U;
  at::parallel_for(0, nbt * g.Eout, task_grain(nbt * g.Eout, g.macs), [&](int64_t lo, int64_t hi) {
    BlasSequential blas_guard;
    std::vector<T> panel(static_cast<size_t>(maxK * cols)), acc(static_cast<size_t>(g.Cout * cols));
    for (int64_t task = lo; task < hi; ++task) {
      const int64_t bt = task / g.Eout, j = task % g.Eout;
      const int64_t b0 = bt * nb, nbl = std::min(nb, g.B - b0), N = nbl * g.Tout;
      const int64_t p0 = csr.off[j], k = csr.off[j + 1] - p0, K = k * g.Cin * g.U;
      gather_strided<T>(panel.data(), N, x, g.Cin, g.Ein, g.Tin, csr.idx.data() + p0, k, b0, nbl, g.Tout, stride,
                        g.U, g.reflect, sty);
      gemm<T>(false, false, g.Cout, N, K, T(1), w + p0 * g.Cin * g.U, lda, panel.data(), N, T(0), acc.data(), N);
      for (int64_t bl = 0; bl < nbl; ++bl) {
        const int64_t b = b0 + bl;
        for (int64_t o = 0; o < g.Cout; ++o) {
          const T f = scale ? scale[(b * g.Cout + o) * g.Eout + j] : T(1);
          const T bb = bias ? bias[o] : T(0);
          const T* src = acc.data() + o * N + bl * g.Tout;
          T* dst = y + ((b * g.Cout + o) * g.Eout + j) * g.Tout;
          for (int64_t t = 0; t < g.Tout; ++t) dst[t] = src[t] * f + bb;
        }
      }
    }
  });
}

template <typename T>
void forward_up(const Geo& g, const Csr& csr, const T* x, const T* w, const T* bias, const Scale<T>& sty,
                const T* scale, T* y) {
  // For fine entity f: V (Cout x nb*Tp) = Wt_f (Cout x k*Cin*U) * transposed panel of its coarse sources.
  const std::vector<T> wt = transpose_weight<T>(w, g.Cin, g.nnz, g.Cout, g.U, csr.tpair);
  const int64_t Tp = g.Tout + 2 * g.h;
  const int64_t nb = batch_tile(g.B, Tp, g.Eout);
  const int64_t nbt = (g.B + nb - 1) / nb;
  const int64_t maxK = csr.max_tdeg * g.Cin * g.U, cols = nb * Tp;
  const int64_t lda = g.nnz * g.Cin * g.U;
  at::parallel_for(0, nbt * g.Eout, task_grain(nbt * g.Eout, g.macs), [&](int64_t lo, int64_t hi) {
    BlasSequential blas_guard;
    std::vector<T> panel(static_cast<size_t>(maxK * cols)), acc(static_cast<size_t>(g.Cout * cols));
    std::vector<T> v(static_cast<size_t>(g.Tout)), bl_out(static_cast<size_t>(g.Tout));
    for (int64_t task = lo; task < hi; ++task) {
      const int64_t bt = task / g.Eout, f = task % g.Eout;
      const int64_t b0 = bt * nb, nbl = std::min(nb, g.B - b0), N = nbl * Tp;
      const int64_t q0 = csr.toff[f], k = csr.toff[f + 1] - q0, K = k * g.Cin * g.U;
      if (k == 0) {
        for (int64_t bl = 0; bl < nbl; ++bl)
          for (int64_t o = 0; o < g.Cout; ++o) {
            T* dst = y + (((b0 + bl) * g.Cout + o) * g.Eout + f) * g.Tout;
            std::fill(dst, dst + g.Tout, bias ? bias[o] : T(0));
          }
        continue;
      }
      gather_transposed<T>(panel.data(), N, x, g.Cin, g.Ein, g.Tin, csr.tent.data() + q0, k, b0, nbl, Tp, 2, g.U,
                           sty);
      gemm<T>(false, false, g.Cout, N, K, T(1), wt.data() + q0 * g.Cin * g.U, lda, panel.data(), N, T(0),
              acc.data(), N);
      for (int64_t bl = 0; bl < nbl; ++bl) {
        const int64_t b = b0 + bl;
        for (int64_t o = 0; o < g.Cout; ++o) {
          const T fs = scale ? scale[(b * g.Cout + o) * g.Eout + f] : T(1);
          const T bb = bias ? bias[o] : T(0);
          fold_row<T>(acc.data() + o * N + bl * Tp, v.data(), g.Tout, g.h, g.reflect);
          blur_row<T>(v.data(), bl_out.data(), g.Tout);
          T* dst = y + ((b * g.Cout + o) * g.Eout + f) * g.Tout;
          for (int64_t t = 0; t < g.Tout; ++t) dst[t] = bl_out[t] * fs + bb;
        }
      }
    }
  });
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
// Indirect GEMM on AVX2/FMA, used for float32 when the CPU has it (MODI_EXT_CPU_KERNEL=blas forces the BLAS
// path above).  Instead of gathering a (K x N) panel per entity and letting BLAS repack it, every input is laid out
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
// C[0:4, col:col+24] = sum_k a[k*4 + r] * ptr[k][col : col+24]   (a: one packed 4-row panel)
__attribute__((target("avx2,fma"))) void nn_kernel(int64_t K, const float* a, const float* const* ptr, int64_t col,
                                                    float* c, int64_t ldc) {
  __m256 c00 = _mm256_setzero_ps(), c01 = c00, c02 = c00, c10 = c00, c11 = c00, c12 = c00;
  __m256 c20 = c00, c21 = c00, c22 = c00, c30 = c00, c31 = c00, c32 = c00;
  for (int64_t k = 0; k < K; ++k) {
    const float* p = ptr[k] + col;
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

// acc (round_up(M,4) x ldacc) = packed A (panels of 4 rows x K) * pointer rows, columns [0, N) (tiles of 24; the
// columns past N are computed and ignored, rows past M are left untouched).  Column chunks keep the pointed-to data
// in L2.
void nn_gemm(const float* apack, int64_t M, int64_t K, const float* const* ptr, int64_t N, float* acc,
             int64_t ldacc) {
  const int64_t panels = (M + MR - 1) / MR, tiles = (N + NR - 1) / NR;
  if (K == 0) {
    std::fill(acc, acc + panels * MR * ldacc, 0.f);
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

// C (M x K, ldc) += L (M pointer rows) * P^T (K pointer rows), contraction over columns [0, N).
void nt_gemm(const float* const* l, int64_t M, const float* const* p, int64_t K, int64_t N, float* C, int64_t ldc) {
  const int64_t CH = std::max<int64_t>(64, round_up((320 * 1024) / std::max<int64_t>(1, (K + M) * 4), 8));
  for (int64_t c0 = 0; c0 < N; c0 += CH) {
    const int64_t n = std::min(CH, N - c0);
    for (int64_t m0 = 0; m0 < M; m0 += TM) {
      const int64_t mr = std::min(TM, M - m0);
      for (int64_t k0 = 0; k0 < K; k0 += TK) {
        const int64_t kr = std::min(TK, K - k0);
        if (mr == TM && kr == TK)
          nt_kernel(l + m0, p + k0, c0, n, C + m0 * ldc + k0, ldc);
        else
          nt_edge(l + m0, mr, p + k0, kr, c0, n, C + m0 * ldc + k0, ldc);
      }
    }
  }
}

// Column layout of a (B, C, E, Ts) tensor: row (phase, c, e) of length row_len; at b*Tq + m it holds
// f(b,c,e) * src[b, c, e, q] for padded position p = S*m + phase < Lp, q = p - F; q outside [0, Ts) reads the
// mirror image (reflect) or 0.  Past Lp, between batch blocks and in the slack after the last block: 0.
struct Cols {
  std::vector<float> buf;
  int64_t C = 0, E = 0, Tq = 0, row_len = 0;
  const float* row(int64_t ph, int64_t c, int64_t e) const { return buf.data() + ((ph * C + c) * E + e) * row_len; }
};

Cols build_cols(const float* src, int64_t B, int64_t C, int64_t E, int64_t Ts, const Scale<float>& f, int64_t S,
                int64_t F, int64_t Lp, int64_t Tq, bool reflect, int64_t max_shift) {
  Cols cl;
  cl.C = C;
  cl.E = E;
  cl.Tq = Tq;
  int64_t len = round_up(B * Tq + NR + max_shift + 8, 8);
  if ((len * 4) % 4096 == 0) len += 16;  // avoid rows aliasing in the same cache sets
  cl.row_len = len;
  cl.buf.assign(static_cast<size_t>(S * C * E * len), 0.f);
  const int64_t rows = S * C * E;
  at::parallel_for(0, rows, elem_grain(B * Tq), [&](int64_t lo, int64_t hi) {
    for (int64_t r = lo; r < hi; ++r) {
      const int64_t ph = r / (C * E), c = (r / E) % C, e = r % E;
      float* dst = cl.buf.data() + r * len;
      for (int64_t b = 0; b < B; ++b) {
        const float fv = f.at(b, c, e);
        const float* s = src + ((b * C + c) * E + e) * Ts;
        float* d = dst + b * Tq;
        if (S == 1) {
          const int64_t lo_m = std::min(std::max<int64_t>(F, 0), Tq), hi_m = std::max(lo_m, std::min({Tq, Lp, F + Ts}));
          for (int64_t m = 0; m < lo_m; ++m)
            d[m] = (m < Lp && reflect) ? fv * s[mirror(m - F, Ts)] : 0.f;
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
    }
  });
  return cl;
}

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
void pack_groups(float* out, int64_t M, int64_t K, const std::vector<const float*>& base, int64_t Rp,
                 int64_t mstride, int64_t tap0, int64_t tap_step) {
  const int64_t panels = (M + MR - 1) / MR;
  if (panels * MR > M) std::fill(out, out + panels * MR * K, 0.f);
  for (size_t gi = 0; gi < base.size(); ++gi)
    for (int64_t m = 0; m < M; ++m) {
      const float* src = base[gi] + m * mstride + tap0;
      float* o = out + ((m / MR) * K + static_cast<int64_t>(gi) * Rp) * MR + (m % MR);
      for (int64_t r = 0; r < Rp; ++r) o[r * MR] = src[r * tap_step];
    }
}

// All entities' packed operands of one pass (and phase), addressed by entity * phases + phase.
struct Packs {
  std::vector<float> buf;
  std::vector<int64_t> off;
  const float* at(int64_t i) const { return buf.data() + off[i]; }
};

// Transposed pass: for output entity n and phase ph the operand row m, column (s, c, r) is
// w_t(m, pair of transposed entry q0+s, c, tap) with tap = r (stride 1) or ph + 2r (stride 2).  `group_base(q, c)`
// returns a pointer such that element (m, tap) sits at base[m*mstride + tap].
template <typename GroupBase>
Packs pack_transposed(const Csr& csr, int64_t n_ent, int64_t stride, int64_t U, int64_t M, int64_t Csrc,
                      int64_t mstride, GroupBase group_base) {
  Packs pk;
  const int64_t rows = round_up(M, MR);
  pk.off.assign(static_cast<size_t>(n_ent * stride + 1), 0);
  for (int64_t n = 0; n < n_ent; ++n)
    for (int64_t ph = 0; ph < stride; ++ph) {
      const int64_t Rp = stride == 1 ? U : (U - ph + 1) / 2;
      const int64_t k = csr.toff[n + 1] - csr.toff[n];
      pk.off[n * stride + ph + 1] = pk.off[n * stride + ph] + rows * k * Csrc * Rp;
    }
  pk.buf.resize(static_cast<size_t>(pk.off.back()));
  at::parallel_for(0, n_ent * stride, elem_grain(M * Csrc * U * std::max<int64_t>(1, csr.max_tdeg)),
                   [&](int64_t lo, int64_t hi) {
    std::vector<const float*> base;
    for (int64_t e = lo; e < hi; ++e) {
      const int64_t n = e / stride, ph = e % stride;
      const int64_t Rp = stride == 1 ? U : (U - ph + 1) / 2;
      const int64_t q0 = csr.toff[n], k = csr.toff[n + 1] - q0;
      base.clear();
      for (int64_t s = 0; s < k; ++s)
        for (int64_t c = 0; c < Csrc; ++c) base.push_back(group_base(q0 + s, c));
      pack_groups(pk.buf.data() + pk.off[e], M, k * Csrc * Rp, base, Rp, mstride, stride == 1 ? 0 : ph,
                  stride == 1 ? 1 : 2);
    }
  });
  return pk;
}

// Plain pass: entity j's operand is rows [0, M) of the strided view src + off[j]*colw (row stride lda), K_j wide.
Packs pack_entities(const Csr& csr, int64_t M, const float* src, int64_t lda, int64_t colw) {
  Packs pk;
  const int64_t rows = round_up(M, MR);
  pk.off.assign(static_cast<size_t>(csr.rows + 1), 0);
  for (int64_t j = 0; j < csr.rows; ++j) pk.off[j + 1] = pk.off[j] + rows * (csr.off[j + 1] - csr.off[j]) * colw;
  pk.buf.resize(static_cast<size_t>(pk.off.back()));
  at::parallel_for(0, csr.rows, elem_grain(M * colw * csr.max_deg), [&](int64_t lo, int64_t hi) {
    for (int64_t j = lo; j < hi; ++j)
      pack_plain(pk.buf.data() + pk.off[j], M, (csr.off[j + 1] - csr.off[j]) * colw, src + csr.off[j] * colw, lda);
  });
  return pk;
}

// Output of a stride-2 transposed pass lives in two phase accumulators; rebuild a padded row of length Lp.
inline void interleave_row(const float* a0, const float* a1, float* out, int64_t Lp) {
  for (int64_t q = 0; q < Lp; ++q) out[q] = (q & 1) ? a1[q >> 1] : a0[q >> 1];
}

// Transposed pass (output entity list = transposed CSR): acc rows = Mrows channels of output entity n; the
// inputs are `src` rows of the entities that read n.  stride 1: one product over taps u (pointer shift U-1-u);
// stride 2: one product per output phase over taps u = phase + 2r (pointer shift R-1-r).
void transposed_products(const Cols& src, int64_t Csrc, const Csr& csr, int64_t n, int64_t b0, int64_t stride,
                         int64_t U, int64_t Mrows, const Packs& pk, std::vector<const float*>& ptr,
                         std::vector<float>* acc, int64_t N, int64_t ldacc) {
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
    nn_gemm(pk.at(n * stride + ph), Mrows, K, ptr.data(), N, acc[ph].data(), ldacc);
  }
}

void forward(const Geo& g, const Csr& csr, const float* x, const float* w, const float* bias,
             const Scale<float>& sty, const float* scale, float* y) {
  const int64_t U = g.U, h = g.h, Ci = g.Cin, Co = g.Cout;
  if (g.kind != kUp) {
    const int64_t S = g.kind == kDown ? 2 : 1;
    const int64_t Lp = g.Tin + 2 * h, Tq = (Lp + S - 1) / S;
    const Cols xc = build_cols(x, g.B, Ci, g.Ein, g.Tin, sty, S, h, Lp, Tq, g.reflect, U);
    const int64_t nb = batch_tile(g.B, Tq, g.Eout), nbt = (g.B + nb - 1) / nb;
    const int64_t ldacc = round_up(nb * Tq, NR), rows = round_up(Co, MR), maxK = csr.max_deg * Ci * U;
    const Packs pk = pack_entities(csr, Co, w, g.nnz * Ci * U, Ci * U);
    at::parallel_for(0, nbt * g.Eout, task_grain(nbt * g.Eout, g.macs), [&](int64_t lo, int64_t hi) {
      std::vector<float> acc(static_cast<size_t>(rows * ldacc));
      std::vector<const float*> ptr(static_cast<size_t>(maxK));
      for (int64_t task = lo; task < hi; ++task) {
        const int64_t bt = task / g.Eout, j = task % g.Eout;
        const int64_t b0 = bt * nb, nbl = std::min(nb, g.B - b0), N = nbl * Tq;
        const int64_t p0 = csr.off[j], k = csr.off[j + 1] - p0, K = k * Ci * U;
        for (int64_t s = 0; s < k; ++s)
          for (int64_t c = 0; c < Ci; ++c)
            for (int64_t u = 0; u < U; ++u)
              ptr[(s * Ci + c) * U + u] = xc.row(u % S, c, csr.idx[p0 + s]) + b0 * Tq + u / S;
        nn_gemm(pk.at(j), Co, K, ptr.data(), N, acc.data(), ldacc);
        for (int64_t bl = 0; bl < nbl; ++bl) {
          const int64_t b = b0 + bl;
          for (int64_t o = 0; o < Co; ++o) {
            const float f = scale ? scale[(b * Co + o) * g.Eout + j] : 1.f;
            const float bb = bias ? bias[o] : 0.f;
            const float* src = acc.data() + o * ldacc + bl * Tq;
            float* dst = y + ((b * Co + o) * g.Eout + j) * g.Tout;
            for (int64_t t = 0; t < g.Tout; ++t) dst[t] = src[t] * f + bb;
          }
        }
      }
    });
    return;
  }
  // up: fine entity f gathers its coarse sources through the transposed CSR, two output phases
  const int64_t R = (U + 1) / 2, Lpf = g.Tout + 2 * h, Mq = (Lpf + 1) / 2, Tq = Mq + R - 1;
  const Cols xc = build_cols(x, g.B, Ci, g.Ein, g.Tin, sty, 1, R - 1, Tq, Tq, false, U);
  const int64_t nb = batch_tile(g.B, Tq, g.Eout), nbt = (g.B + nb - 1) / nb;
  const int64_t ldacc = round_up(nb * Tq, NR), rows = round_up(Co, MR), maxK = csr.max_tdeg * Ci * R;
  // operand row o, column (s, i, r): w_up[i, pair, o, tap]
  const Packs pk = pack_transposed(csr, g.Eout, 2, U, Co, Ci, U,
                                   [&](int64_t q, int64_t i) { return w + (i * g.nnz + csr.tpair[q]) * Co * U; });
  at::parallel_for(0, nbt * g.Eout, task_grain(nbt * g.Eout, g.macs), [&](int64_t lo, int64_t hi) {
    std::vector<float> acc[2] = {std::vector<float>(static_cast<size_t>(rows * ldacc)),
                                 std::vector<float>(static_cast<size_t>(rows * ldacc))};
    std::vector<const float*> ptr(static_cast<size_t>(std::max<int64_t>(maxK, 1)));
    std::vector<float> vp(static_cast<size_t>(Lpf)), v(static_cast<size_t>(g.Tout)), vb(static_cast<size_t>(g.Tout));
    for (int64_t task = lo; task < hi; ++task) {
      const int64_t bt = task / g.Eout, f = task % g.Eout;
      const int64_t b0 = bt * nb, nbl = std::min(nb, g.B - b0), N = nbl * Tq;
      transposed_products(xc, Ci, csr, f, b0, 2, U, Co, pk, ptr, acc, N, ldacc);
      for (int64_t bl = 0; bl < nbl; ++bl) {
        const int64_t b = b0 + bl;
        for (int64_t o = 0; o < Co; ++o) {
          const float fs = scale ? scale[(b * Co + o) * g.Eout + f] : 1.f;
          const float bb = bias ? bias[o] : 0.f;
          interleave_row(acc[0].data() + o * ldacc + bl * Tq, acc[1].data() + o * ldacc + bl * Tq, vp.data(), Lpf);
          fold_row<float>(vp.data(), v.data(), g.Tout, h, g.reflect);
          blur_row<float>(v.data(), vb.data(), g.Tout);
          float* dst = y + ((b * Co + o) * g.Eout + f) * g.Tout;
          for (int64_t t = 0; t < g.Tout; ++t) dst[t] = vb[t] * fs + bb;
        }
      }
    }
  });
}

// Input, style and weight gradients.  gyd * gsc: gy * d for conv/down; for up gyd = blur^T(gy) * d on the fine
// grid (gsc empty).
void backward(const Geo& g, const Csr& csr, const float* gyd, const Scale<float>& gsc, const float* x, const float* w,
              const float* style, float* gx, float* gw, float* gs_part, bool direct_gw, float* gw_acc, int64_t wsize) {
  const int64_t U = g.U, h = g.h, Ci = g.Cin, Co = g.Cout, Ei = g.Ein, Eo = g.Eout, B = g.B;
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
  if (g.kind == kUp) {
    // gv on the fine grid, read like a down-sampler's input: stride 2, padding per mode
    const int64_t Tc = g.Tin, Lp = g.Tout + 2 * h, Tq = Tc + h;
    const Cols gvc = build_cols(gyd, B, Co, Eo, g.Tout, Scale<float>{}, 2, h, Lp, Tq, g.reflect, U);
    const int64_t maxK = csr.max_deg * Co * U, lda = g.nnz * Co * U;
    auto set_ptrs = [&](std::vector<const float*>& ptr, int64_t c, int64_t b0) {
      const int64_t p0 = csr.off[c], k = csr.off[c + 1] - p0;
      for (int64_t s = 0; s < k; ++s)
        for (int64_t o = 0; o < Co; ++o)
          for (int64_t u = 0; u < U; ++u)
            ptr[(s * Co + o) * U + u] = gvc.row(u % 2, o, csr.idx[p0 + s]) + b0 * Tq + u / 2;
      return k * Co * U;
    };
    if (want_input) {
      const int64_t nb = batch_tile(B, Tq, Ei), nbt = (B + nb - 1) / nb;
      const int64_t ldacc = round_up(nb * Tq, NR), rows = round_up(Ci, MR);
      const Packs pk = pack_entities(csr, Ci, w, lda, Co * U);
      at::parallel_for(0, nbt * Ei, task_grain(nbt * Ei, g.macs), [&](int64_t lo, int64_t hi) {
        std::vector<float> acc(static_cast<size_t>(rows * ldacc));
        std::vector<const float*> ptr(static_cast<size_t>(maxK));
        for (int64_t task = lo; task < hi; ++task) {
          const int64_t bt = task / Ei, c = task % Ei, b0 = bt * nb, nbl = std::min(nb, B - b0);
          const int64_t K = set_ptrs(ptr, c, b0);
          nn_gemm(pk.at(c), Ci, K, ptr.data(), nbl * Tq, acc.data(), ldacc);
          for (int64_t bl = 0; bl < nbl; ++bl)
            for (int64_t i = 0; i < Ci; ++i) finish(acc.data() + i * ldacc + bl * Tq, b0 + bl, i, c, Tc);
        }
      });
    }
    if (gw) {
      const Cols xl = build_cols(x, B, Ci, Ei, Tc, sty, 1, 0, Tc, Tq, false, U);
      const int64_t nb = direct_gw ? B : batch_tile(B, Tq, Ei), nbt = (B + nb - 1) / nb;
      const int64_t n_tasks = direct_gw ? Ei : nbt * Ei;
      at::parallel_for(0, n_tasks, task_grain(n_tasks, g.macs), [&](int64_t lo, int64_t hi) {
        std::vector<const float*> ptr(static_cast<size_t>(maxK)), lrow(static_cast<size_t>(Ci));
        float* my = direct_gw ? gw : gw_acc + at::get_thread_num() * wsize;
        for (int64_t task = lo; task < hi; ++task) {
          const int64_t c = task % Ei, bt = direct_gw ? 0 : task / Ei, b0 = bt * nb, nbl = std::min(nb, B - b0);
          const int64_t K = set_ptrs(ptr, c, b0);
          for (int64_t i = 0; i < Ci; ++i) lrow[i] = xl.row(0, i, c) + b0 * Tq;
          float* C = my + csr.off[c] * Co * U;
          if (direct_gw)
            for (int64_t i = 0; i < Ci; ++i) std::fill(C + i * lda, C + i * lda + K, 0.f);
          nt_gemm(lrow.data(), Ci, ptr.data(), K, nbl * Tq, C, lda);
        }
      });
    }
    return;
  }
  const int64_t S = g.kind == kDown ? 2 : 1;
  if (want_input) {
    // transposed pass over the readers of each input entity; output on the padded domain, then folded
    const int64_t Lp = g.Tin + 2 * h;
    const int64_t R = S == 1 ? U : (U + 1) / 2;
    const int64_t Mq = S == 1 ? Lp : (Lp + 1) / 2;
    const int64_t Tq = Mq + R - 1;
    const Cols gz = build_cols(gyd, B, Co, Eo, g.Tout, gsc, 1, R - 1, Tq, Tq, false, U);
    const int64_t nb = batch_tile(B, Tq, Ei), nbt = (B + nb - 1) / nb;
    const int64_t ldacc = round_up(nb * Tq, NR), rows = round_up(Ci, MR), maxK = std::max<int64_t>(1, csr.max_tdeg * Co * R);
    // operand row i, column (s, o, r): w[o, pair, i, tap]
    const Packs pk = pack_transposed(csr, Ei, S, U, Ci, Co, U,
                                     [&](int64_t q, int64_t o) { return w + (o * g.nnz + csr.tpair[q]) * Ci * U; });
    at::parallel_for(0, nbt * Ei, task_grain(nbt * Ei, g.macs), [&](int64_t lo, int64_t hi) {
      std::vector<float> acc[2] = {std::vector<float>(static_cast<size_t>(rows * ldacc)),
                                   std::vector<float>(static_cast<size_t>(S == 2 ? rows * ldacc : 0))};
      std::vector<const float*> ptr(static_cast<size_t>(maxK));
      std::vector<float> gp(static_cast<size_t>(Lp)), row(static_cast<size_t>(g.Tin));
      for (int64_t task = lo; task < hi; ++task) {
        const int64_t bt = task / Ei, n = task % Ei, b0 = bt * nb, nbl = std::min(nb, B - b0);
        if (csr.toff[n + 1] == csr.toff[n]) {  // nobody reads this entity
          for (int64_t bl = 0; bl < nbl; ++bl)
            for (int64_t i = 0; i < Ci; ++i) {
              std::fill(row.begin(), row.end(), 0.f);
              finish(row.data(), b0 + bl, i, n, g.Tin);
            }
          continue;
        }
        transposed_products(gz, Co, csr, n, b0, S, U, Ci, pk, ptr, acc, nbl * Tq, ldacc);
        for (int64_t bl = 0; bl < nbl; ++bl)
          for (int64_t i = 0; i < Ci; ++i) {
            const float* a0 = acc[0].data() + i * ldacc + bl * Tq;
            if (S == 2) {
              interleave_row(a0, acc[1].data() + i * ldacc + bl * Tq, gp.data(), Lp);
              a0 = gp.data();
            }
            fold_row<float>(a0, row.data(), g.Tin, h, g.reflect);
            finish(row.data(), b0 + bl, i, n, g.Tin);
          }
      }
    });
  }
  if (gw) {
    const int64_t Lp = g.Tin + 2 * h, Tq = (Lp + S - 1) / S;
    const Cols xc = build_cols(x, B, Ci, Ei, g.Tin, sty, S, h, Lp, Tq, g.reflect, U);
    const Cols gl = build_cols(gyd, B, Co, Eo, g.Tout, gsc, 1, 0, g.Tout, Tq, false, U);
    const int64_t nb = direct_gw ? B : batch_tile(B, Tq, Eo), nbt = (B + nb - 1) / nb;
    const int64_t n_tasks = direct_gw ? Eo : nbt * Eo;
    const int64_t maxK = csr.max_deg * Ci * U, ldw = g.nnz * Ci * U;
    at::parallel_for(0, n_tasks, task_grain(n_tasks, g.macs), [&](int64_t lo, int64_t hi) {
      std::vector<const float*> ptr(static_cast<size_t>(maxK)), lrow(static_cast<size_t>(Co));
      float* my = direct_gw ? gw : gw_acc + at::get_thread_num() * wsize;
      for (int64_t task = lo; task < hi; ++task) {
        const int64_t j = task % Eo, bt = direct_gw ? 0 : task / Eo, b0 = bt * nb, nbl = std::min(nb, B - b0);
        const int64_t p0 = csr.off[j], k = csr.off[j + 1] - p0, K = k * Ci * U;
        for (int64_t s = 0; s < k; ++s)
          for (int64_t c = 0; c < Ci; ++c)
            for (int64_t u = 0; u < U; ++u)
              ptr[(s * Ci + c) * U + u] = xc.row(u % S, c, csr.idx[p0 + s]) + b0 * Tq + u / S;
        for (int64_t o = 0; o < Co; ++o) lrow[o] = gl.row(0, o, j) + b0 * Tq;
        float* C = my + p0 * Ci * U;
        if (direct_gw)
          for (int64_t o = 0; o < Co; ++o) std::fill(C + o * ldw, C + o * ldw + K, 0.f);
        nt_gemm(lrow.data(), Co, ptr.data(), K, nbl * Tq, C, ldw);
      }
    });
  }
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
  const Scale<T> sty = [&] {
    Scale<T> s;
    if (style) { s.p = style; s.sb = Ci; s.sc = 1; s.se = 0; }
    return s;
  }();
  const Scale<T> dsc = scale ? entity_scale<T>(scale, Co, Eo) : Scale<T>{};

  // bias and scale gradients: plain reductions over the output.
  if (gb) {
    at::parallel_for(0, Co, elem_grain(Bq * Eo * g.Tout), [&](int64_t lo, int64_t hi) {
      for (int64_t o = lo; o < hi; ++o) {
        T acc = T(0);
        for (int64_t b = 0; b < Bq; ++b) {
          const T* r = gy + (b * Co + o) * Eo * g.Tout;
          for (int64_t i = 0; i < Eo * g.Tout; ++i) acc += r[i];
        }
        gb[o] = acc;
      }
    });
  }
  if (gd) {  // y = d * z + bias  =>  dL/dd = sum_t gy * (y - bias) / d
    at::parallel_for(0, Bq * Co * Eo, elem_grain(g.Tout), [&](int64_t lo, int64_t hi) {
      for (int64_t r = lo; r < hi; ++r) {
        const int64_t o = (r / Eo) % Co;
        const T bb = bias ? bias[o] : T(0);
        const T* a = gy + r * g.Tout;
        const T* yv = out + r * g.Tout;
        T acc = T(0);
        for (int64_t t = 0; t < g.Tout; ++t) acc += a[t] * (yv[t] - bb);
        gd[r] = acc / scale[r];
      }
    });
  }
  if (!gx && !gw && !gs) return;

  const int64_t nthreads = at::get_num_threads();
  // conv/down weight gradient without thread-local copies when entities alone keep every thread busy
  const bool direct_gw = g.kind != kUp && (Eo >= 4 * nthreads || nthreads == 1);
  std::vector<T> gw_acc;
  if (gw && !direct_gw) gw_acc.assign(static_cast<size_t>(nthreads * g.nnz * Ci * Co * U), T(0));
  std::vector<T> gs_part;
  if (gs) gs_part.assign(static_cast<size_t>(Ei * Bq * Ci), T(0));
  const int64_t wsize = g.nnz * Ci * Co * U;

  // up: gv = blur^T(gy) * d on the fine grid (B, Co, Eo, 2T); then per coarse entity c the strided panel of gv
  // feeds both gx'_c = W_c * GV_c and gW_c += X'_c * GV_c^T.
  std::vector<T> gv;
  if (g.kind == kUp) {
    gv.resize(static_cast<size_t>(Bq * Co * Eo * g.Tout));
    at::parallel_for(0, Bq * Co * Eo, elem_grain(g.Tout), [&](int64_t lo, int64_t hi) {
      for (int64_t r = lo; r < hi; ++r) {
        blur_adjoint_row<T>(gy + r * g.Tout, gv.data() + r * g.Tout, g.Tout);
        if (scale) {
          const T f = scale[r];
          for (int64_t t = 0; t < g.Tout; ++t) gv[r * g.Tout + t] *= f;
        }
      }
    });
  }
  // The fp32 indirect kernels win on the input gradient when there are enough frames (little padding waste).
  // The weight gradient stays on BLAS, whose packed NT product beats our dot-product kernel -- except for narrow
  // layers (GANimator: 3-9 channels per entity), where BLAS gets a 3-9-row product after gathering a panel as
  // large as the product itself, and the indirect kernel, which reads the inputs in place, wins.
  bool fast_input = false, fast_weight = false;
  if constexpr (std::is_same_v<T, float>) {
    const bool fast_ok = fastk::wanted() && g.Tin >= fastk::kMinFrames;
    fast_weight = gw && fast_ok && (g.kind == kUp ? Ci : Co) <= fastk::kNarrowRows;
    if (((gx || gs) && fast_ok) || fast_weight) {
      const bool fin = (gx || gs) && fast_ok;
      fastk::backward(g, csr, g.kind == kUp ? gv.data() : gy, g.kind == kUp ? Scale<float>{} : dsc, x, w, style,
                      fin ? gx : nullptr, fast_weight ? gw : nullptr, fin && gs ? gs_part.data() : nullptr,
                      g.kind != kUp && direct_gw, gw_acc.empty() ? nullptr : gw_acc.data(), wsize);
      fast_input = fin;
    }
  }
  T* const gx_b = fast_input ? nullptr : gx;  // what is left for the BLAS passes
  T* const gs_b = fast_input ? nullptr : gs;
  T* const gw_b = fast_weight ? nullptr : gw;
  if (!gx_b && !gs_b && !gw_b) {
  } else if (g.kind == kUp) {
    const int64_t Tc = g.Tin;
    const int64_t nb = batch_tile(Bq, Tc, Ei);
    const int64_t nbt = (Bq + nb - 1) / nb;
    const int64_t maxK = csr.max_deg * Co * U, cols = nb * Tc;
    const int64_t lda = g.nnz * Co * U;
    at::parallel_for(0, nbt * Ei, task_grain(nbt * Ei, 2 * g.macs), [&](int64_t lo, int64_t hi) {
      BlasSequential blas_guard;
      std::vector<T> panel(static_cast<size_t>(maxK * cols)), acc(static_cast<size_t>(Ci * cols));
      std::vector<T> xs(static_cast<size_t>(gw_b ? Ci * cols : 0));
      T* my_gw = gw_b ? gw_acc.data() + at::get_thread_num() * wsize : nullptr;
      for (int64_t task = lo; task < hi; ++task) {
        const int64_t bt = task / Ei, c = task % Ei;
        const int64_t b0 = bt * nb, nbl = std::min(nb, Bq - b0), N = nbl * Tc;
        const int64_t p0 = csr.off[c], k = csr.off[c + 1] - p0, K = k * Co * U;
        gather_strided<T>(panel.data(), N, gv.data(), Co, Eo, g.Tout, csr.idx.data() + p0, k, b0, nbl, Tc, 2, U,
                          g.reflect, Scale<T>{});
        if (gx_b || gs_b) {
          gemm<T>(false, false, Ci, N, K, T(1), w + p0 * Co * U, lda, panel.data(), N, T(0), acc.data(), N);
          for (int64_t bl = 0; bl < nbl; ++bl) {
            const int64_t b = b0 + bl;
            for (int64_t i = 0; i < Ci; ++i) {
              const int64_t xo = ((b * Ci + i) * Ei + c) * Tc;
              finish_input_row<T>(acc.data() + i * N + bl * Tc, x + xo, style ? style[b * Ci + i] : T(1),
                                  gx_b ? gx_b + xo : nullptr, gs_b ? &gs_part[(c * Bq + b) * Ci + i] : nullptr, Tc);
            }
          }
        }
        if (gw_b) {
          const int64_t one = c;
          gather_strided<T>(xs.data(), N, x, Ci, Ei, Tc, &one, 1, b0, nbl, Tc, 1, 1, false, sty);
          gemm<T>(false, true, Ci, K, N, T(1), xs.data(), N, panel.data(), N, T(1), my_gw + p0 * Co * U, lda);
        }
      }
    });
  } else {
    const int64_t stride = g.kind == kDown ? 2 : 1;
    // Input gradient: for input entity n, G (Ci x nb*Tp) = Wt_n * transposed panel of gy*d over its readers.
    if (gx_b || gs_b) {
      const std::vector<T> wt = transpose_weight<T>(w, Co, g.nnz, Ci, U, csr.tpair);
      const int64_t Tp = g.Tin + 2 * h;
      const int64_t nb = batch_tile(Bq, Tp, Ei);
      const int64_t nbt = (Bq + nb - 1) / nb;
      const int64_t maxK = csr.max_tdeg * Co * U, cols = nb * Tp;
      const int64_t lda = g.nnz * Co * U;
      at::parallel_for(0, nbt * Ei, task_grain(nbt * Ei, g.macs), [&](int64_t lo, int64_t hi) {
        BlasSequential blas_guard;
        std::vector<T> panel(static_cast<size_t>(maxK * cols)), acc(static_cast<size_t>(Ci * cols));
        std::vector<T> row(static_cast<size_t>(g.Tin));
        for (int64_t task = lo; task < hi; ++task) {
          const int64_t bt = task / Ei, n = task % Ei;
          const int64_t b0 = bt * nb, nbl = std::min(nb, Bq - b0), N = nbl * Tp;
          const int64_t q0 = csr.toff[n], k = csr.toff[n + 1] - q0, K = k * Co * U;
          if (k == 0) {  // nobody reads this entity
            for (int64_t bl = 0; bl < nbl; ++bl)
              for (int64_t i = 0; i < Ci; ++i)
                if (gx_b) {
                  T* dst = gx_b + (((b0 + bl) * Ci + i) * Ei + n) * g.Tin;
                  std::fill(dst, dst + g.Tin, T(0));
                }
            continue;
          }
          gather_transposed<T>(panel.data(), N, gy, Co, Eo, g.Tout, csr.tent.data() + q0, k, b0, nbl, Tp, stride, U,
                               dsc);
          gemm<T>(false, false, Ci, N, K, T(1), wt.data() + q0 * Co * U, lda, panel.data(), N, T(0), acc.data(), N);
          for (int64_t bl = 0; bl < nbl; ++bl) {
            const int64_t b = b0 + bl;
            for (int64_t i = 0; i < Ci; ++i) {
              fold_row<T>(acc.data() + i * N + bl * Tp, row.data(), g.Tin, h, g.reflect);
              const int64_t xo = ((b * Ci + i) * Ei + n) * g.Tin;
              finish_input_row<T>(row.data(), x + xo, style ? style[b * Ci + i] : T(1), gx_b ? gx_b + xo : nullptr,
                                  gs_b ? &gs_part[(n * Bq + b) * Ci + i] : nullptr, g.Tin);
            }
          }
        }
      });
    }
    // Weight gradient: for row entity j, gW_j += (gy*d)_j (Co x N) * X_j^T (N x K).  With enough entities each
    // task owns one entity and writes its pairs directly; otherwise tasks split the batch too and accumulate
    // into thread-local copies.
    if (gw_b) {
      const int64_t nb = batch_tile(Bq, g.Tout, direct_gw ? Bq : Eo);
      const int64_t nbt = (Bq + nb - 1) / nb;
      const int64_t maxK = csr.max_deg * Ci * U, cols = nb * g.Tout;
      const int64_t ldw = g.nnz * Ci * U;
      const int64_t n_tasks = direct_gw ? Eo : nbt * Eo;
      // Entities differ in neighbour count (work), so a contiguous split of them leaves threads idle; with direct
      // writes, tasks are visited in a cost-balanced order (bins of equal work, one contiguous run per thread).
      const std::vector<int64_t> order = direct_gw ? balanced_order(csr.off, Eo, nthreads) : std::vector<int64_t>{};
      at::parallel_for(0, n_tasks, task_grain(n_tasks, g.macs), [&](int64_t lo, int64_t hi) {
        BlasSequential blas_guard;
        std::vector<T> panel(static_cast<size_t>(maxK * cols)), gz(static_cast<size_t>(Co * cols));
        T* my_gw = direct_gw ? gw_b : gw_acc.data() + at::get_thread_num() * wsize;
        for (int64_t task = lo; task < hi; ++task) {
          const int64_t j = direct_gw ? order[task] : task % Eo;
          const int64_t bt_lo = direct_gw ? 0 : task / Eo, bt_hi = direct_gw ? nbt : bt_lo + 1;
          for (int64_t bt = bt_lo; bt < bt_hi; ++bt) {
            const int64_t b0 = bt * nb, nbl = std::min(nb, Bq - b0), N = nbl * g.Tout;
            const int64_t p0 = csr.off[j], k = csr.off[j + 1] - p0, K = k * Ci * U;
            gather_strided<T>(panel.data(), N, x, Ci, Ei, g.Tin, csr.idx.data() + p0, k, b0, nbl, g.Tout, stride,
                              U, g.reflect, sty);
            const int64_t one = j;
            gather_strided<T>(gz.data(), N, gy, Co, Eo, g.Tout, &one, 1, b0, nbl, g.Tout, 1, 1, false, dsc);
            const T beta = (direct_gw && bt == 0) ? T(0) : T(1);
            gemm<T>(false, true, Co, K, N, T(1), gz.data(), N, panel.data(), N, beta, my_gw + p0 * Ci * U, ldw);
          }
        }
      });
    }
  }

  if (gw && !direct_gw) {
    at::parallel_for(0, wsize, kSerialElems, [&](int64_t lo, int64_t hi) {
      for (int64_t i = lo; i < hi; ++i) {
        T acc = T(0);
        for (int64_t t = 0; t < nthreads; ++t) acc += gw_acc[t * wsize + i];
        gw[i] = acc;
      }
    });
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
