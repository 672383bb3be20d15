// CPU kernels of the skeletal operators.
//
// Every pass is "one small GEMM per entity": for a row entity j and a tile of batch elements, gather the
// time-shifted inputs of j's neighbors into a contiguous (K x N) panel (rows = neighbor x channel x tap, columns =
// batch x time, time innermost), multiply by the entity's weight block (a strided view of the compact weight, or a
// once-per-call transposed copy), and write the tile out with the style / demodulation / bias / fold / blur applied
// in the epilogue.  The GEMM is the BLAS that libtorch ships (sgemm_/dgemm_, single-threaded inside the parallel
// region), with an ATen fallback when it is not exported; fp32 with AVX2/FMA uses the indirect kernels of fastk.h.
//
// Work distribution (common/tasks.h): each call is one parallel region of two stages, preparation (operand layouts,
// packed weights, bias / scale gradients) then compute (forward tiles; or input-gradient tiles and weight-gradient
// blocks together), the second waiting only for claimed preparation tasks.  Tasks are claimed dynamically, largest
// first, with per-slot scratch; every output element is written by exactly one task, and the tiling depends on the
// shapes only, so results are the same for any thread count and schedule.  The weight gradient is split by entity (and by output-row block when entities are few)
// instead of accumulating thread-local copies.
//
// Arguments: skeletal/check.h (the one check the CUDA kernels share); building blocks: skeletal/cpu_common.h.
#include <algorithm>
#include <cstdlib>
#include <cstring>
#include <memory>
#include <mutex>
#include <numeric>
#include <vector>

#include <ATen/OpMathType.h>
#include <ATen/Parallel.h>
#include <torch/library.h>

#include "common/tasks.h"
#include "skeletal/bf16k.h"
#include "skeletal/check.h"
#include "skeletal/cpu_common.h"
#include "skeletal/fastk.h"
#include "skeletal/skeletal.h"

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
namespace skeletal {
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

// ------------------------------------------------------------------------------------------------ gathers
inline int64_t ceil_div_pos(int64_t a, int64_t b) { return (a + b - 1) / b; }

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

// ------------------------------------------------------------------------------------------------ topology
// The CSR of a checked call (check_inputs), and its transpose; the values are checked here.
Csr make_csr(const at::Tensor& index, const at::Tensor& offsets, int64_t n_cols) {
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
        if (g.act) act_row(dst, g.Tout);
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
          if (g.act) act_row(dst, g.Tout);
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
        if (g.act) act_row(dst, g.Tout);
      }
    }
  };
  const Phase compute[] = {phase(static_cast<int64_t>(order.size()), task)};
  run_stages({{prep, 1}, {compute, 1}}, par);
}

template <typename T>
void forward_dispatch(const Geo& g, const Csr& csr, const T* x, const T* w, const T* bias, const Scale<T>& sty,
                      const T* scale, T* y) {
  if constexpr (std::is_same_v<T, float>) {
    const int64_t frames = g.kind == kUp ? g.Tin : g.Tout;  // columns per batch element of the product
    if (frames >= fastk::min_frames(static_cast<SkeletalKind>(g.kind), false) && fastk::wanted()) {
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
                       c10::string_view padding_mode, bool act) {
  Geo g = check_inputs(kCpuBackend, kind, x, weight, bias, index, offsets, n_out, style, scale, padding_mode);
  g.act = act;
  const Csr csr = make_csr(index, offsets, kind == kUp ? g.Eout : g.Ein);
  at::Tensor y = at::empty({g.B, g.Cout, g.Eout, g.Tout}, x.options());
  if (x.scalar_type() == at::kBFloat16) {
    using bf = bf16k::bf16;
    auto p = [](const at::Tensor& t) { return reinterpret_cast<const bf*>(t.data_ptr<at::BFloat16>()); };
    auto opt = [&](const std::optional<at::Tensor>& t) { return t.has_value() ? p(*t) : nullptr; };
    bf16k::forward(g, csr, p(x), p(weight), opt(bias), opt(style), opt(scale),
                   reinterpret_cast<bf*>(y.data_ptr<at::BFloat16>()));
    return y;
  }
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
// The backward of the bias activation (skeletal.h), one pass over the output: dL/dpre = act_slope(y) * grad, and,
// where the scale gradient needs it, pre = y / act_slope(y) (else `out` as it is: nothing reads it).
std::pair<at::Tensor, at::Tensor> act_prologue(const at::Tensor& grad, const at::Tensor& out, bool need_pre) {
  at::Tensor g_pre = at::empty_like(grad), y_pre = need_pre ? at::empty_like(out) : out;
  AT_DISPATCH_FLOATING_TYPES_AND(at::kBFloat16, grad.scalar_type(), "skeletal_act_backward", [&] {
    using A = at::opmath_type<scalar_t>;
    const scalar_t* gy = grad.data_ptr<scalar_t>();
    const scalar_t* y = out.data_ptr<scalar_t>();
    scalar_t* gp = g_pre.data_ptr<scalar_t>();
    scalar_t* yp = need_pre ? y_pre.data_ptr<scalar_t>() : nullptr;
    at::parallel_for(0, grad.numel(), 1 << 15, [&](int64_t i0, int64_t i1) {
_Pragma("omp simd")
      for (int64_t i = i0; i < i1; ++i)
        gp[i] = static_cast<scalar_t>(act_slope(static_cast<A>(y[i])) * static_cast<A>(gy[i]));
      if (yp) {
_Pragma("omp simd")
        for (int64_t i = i0; i < i1; ++i)
          yp[i] = static_cast<scalar_t>(static_cast<A>(y[i]) / act_slope(static_cast<A>(y[i])));
      }
    });
  });
  return {g_pre, y_pre};
}

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
    const bool fast_ok = fastk::wanted() && g.Tin >= fastk::min_frames(static_cast<SkeletalKind>(g.kind), true);
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
}  // namespace skeletal

at::Tensor skeletal_conv_cpu(const at::Tensor& x, const at::Tensor& weight, const std::optional<at::Tensor>& bias,
                             const at::Tensor& index, const at::Tensor& offsets,
                             const std::optional<at::Tensor>& style, const std::optional<at::Tensor>& scale,
                             c10::string_view padding_mode, bool act) {
  return skeletal::forward_any(kConv, x, weight, bias, index, offsets, 0, style, scale, padding_mode, act);
}

at::Tensor skeletal_down_cpu(const at::Tensor& x, const at::Tensor& weight, const std::optional<at::Tensor>& bias,
                             const at::Tensor& index, const at::Tensor& offsets,
                             const std::optional<at::Tensor>& style, const std::optional<at::Tensor>& scale,
                             c10::string_view padding_mode, bool act) {
  return skeletal::forward_any(kDown, x, weight, bias, index, offsets, 0, style, scale, padding_mode, act);
}

at::Tensor skeletal_up_cpu(const at::Tensor& x, const at::Tensor& weight, const std::optional<at::Tensor>& bias,
                           const at::Tensor& index, const at::Tensor& offsets, int64_t n_out,
                           const std::optional<at::Tensor>& style, const std::optional<at::Tensor>& scale,
                           c10::string_view padding_mode, bool act) {
  return skeletal::forward_any(kUp, x, weight, bias, index, offsets, n_out, style, scale, padding_mode, act);
}

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor> skeletal_backward_cpu(
    const at::Tensor& grad, const at::Tensor& out, const at::Tensor& x, const at::Tensor& weight,
    const std::optional<at::Tensor>& bias, const at::Tensor& index, const at::Tensor& offsets,
    const std::optional<at::Tensor>& style, const std::optional<at::Tensor>& scale, c10::string_view padding_mode,
    int64_t kind, int64_t n_out, std::array<bool, 4> output_mask, bool act) {
  const skeletal::Geo g = skeletal::check_backward_inputs(kCpuBackend, grad, out, x, weight, bias, index, offsets,
                                                          style, scale, padding_mode, kind, n_out);
  if (act) {  // from the pre-activation on, the backward is the one without act
    auto [g_pre, y_pre] = skeletal::act_prologue(grad, out, output_mask[3] && scale.has_value());
    return skeletal_backward_cpu(g_pre, y_pre, x, weight, bias, index, offsets, style, scale, padding_mode, kind,
                                 n_out, output_mask, false);
  }
  const skeletal::Csr csr = skeletal::make_csr(index, offsets, kind == kUp ? g.Eout : g.Ein);
  auto empty = [&] { return at::empty({0}, x.options()); };
  at::Tensor gx = output_mask[0] ? at::empty_like(x) : empty();
  at::Tensor gw = output_mask[1] ? at::empty_like(weight) : empty();
  at::Tensor gb = bias.has_value() ? at::empty_like(*bias) : empty();
  at::Tensor gs = (output_mask[2] && style.has_value()) ? at::empty_like(*style) : empty();
  at::Tensor gd = (output_mask[3] && scale.has_value()) ? at::empty_like(*scale) : empty();
  if (x.scalar_type() == at::kBFloat16) {
    using bf = skeletal::bf16k::bf16;
    auto p = [](const at::Tensor& t) { return reinterpret_cast<const bf*>(t.data_ptr<at::BFloat16>()); };
    auto opt = [&](const std::optional<at::Tensor>& t) { return t.has_value() ? p(*t) : nullptr; };
    auto o = [](at::Tensor& t) { return t.numel() ? reinterpret_cast<bf*>(t.data_ptr<at::BFloat16>()) : nullptr; };
    skeletal::bf16k::backward(g, csr, p(grad), p(out), p(x), p(weight), opt(bias), opt(style), opt(scale), o(gx),
                              o(gw), o(gb), o(gs), o(gd));
    return {gx, gw, gb, gs, gd};
  }
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "skeletal_backward", [&] {
    using T = scalar_t;
    auto ptr = [](at::Tensor& t) -> T* { return t.numel() ? t.data_ptr<T>() : nullptr; };
    skeletal::backward_impl<T>(g, csr, grad.data_ptr<T>(), out.data_ptr<T>(), x.data_ptr<T>(), weight.data_ptr<T>(),
                               bias.has_value() ? bias->data_ptr<T>() : nullptr,
                               style.has_value() ? style->data_ptr<T>() : nullptr,
                               scale.has_value() ? scale->data_ptr<T>() : nullptr, ptr(gx), ptr(gw), ptr(gb), ptr(gs),
                               ptr(gd));
  });
  return {gx, gw, gb, gs, gd};
}

// Which micro-kernels the bf16 CPU path runs in this process ("avx512_bf16" or "emulated"), for dispatch_report.
TORCH_LIBRARY_FRAGMENT(modi_ext, m) {
  m.def("skeletal_cpu_bf16_kernel() -> str", +[]() { return std::string(skeletal::bf16k::kernel_name()); });
}

TORCH_LIBRARY_IMPL(modi_ext, CPU, m) {
  m.impl("skeletal_conv", &skeletal_conv_cpu);
  m.impl("skeletal_down", &skeletal_down_cpu);
  m.impl("skeletal_up", &skeletal_up_cpu);
  m.impl("skeletal_backward", &skeletal_backward_cpu);
}

}  // namespace modi_ext
