// CUDA kernels of the demodulation coefficients and their gradient (semantics: the header of demod/cpu.cpp).
//
// In torch ops these are about a dozen launches each way per modulated layer (modi_ext/demod/dense.py); here the
// forward is one launch and the backward one or two.  The sizes are small (batch x channels x entities), so each
// thread computes one output from its inputs directly, in a fixed order: no atomics, no shared memory, a result
// that does not depend on the schedule.  The host reads no tensor values (the op can be captured in a CUDA graph):
// a pair's output entity is found on the device (up: index[n]; conv/down: the CSR row holding n, by binary search),
// and entries out of range are skipped rather than read through.
#include <torch/library.h>

#include <ATen/ATen.h>

#include <array>
#include <optional>
#include <tuple>

#include "common/cuda_common.cuh"
#include "demod/check.h"

namespace modi_ext {
namespace {

using namespace cuda;  // acc_t, ld, st, ceil_div

constexpr int kThreads = 128;

// The geometry of a call, by value in the kernel parameters.
struct DemodGeo {
  int64_t lead = 0, nnz = 0, inner = 0, U = 0, Ci = 0, Co = 0, Eo = 0, Bs = 1, rows = 0;
  bool up = false, styled = false;
};

DemodGeo geo_of(const demod::Shape& s, const at::Tensor& offsets) {
  DemodGeo g;
  g.lead = s.lead;
  g.nnz = s.nnz;
  g.inner = s.inner;
  g.U = s.U;
  g.Ci = s.Ci;
  g.Co = s.Co;
  g.Eo = s.Eo;
  g.Bs = s.Bs;
  g.rows = offsets.numel() - 1;
  g.up = s.up;
  g.styled = s.styled;
  return g;
}

__device__ __forceinline__ int64_t clamp_pair(int64_t v, int64_t nnz) { return v < 0 ? 0 : (v > nnz ? nnz : v); }

// The CSR row (output entity of conv / down) that pair n belongs to: the last row whose start is <= n.
__device__ __forceinline__ int64_t row_of(const int64_t* off, int64_t rows, int64_t n) {
  int64_t lo = 0, hi = rows - 1;
  while (lo < hi) {
    const int64_t mid = (lo + hi + 1) / 2;
    if (off[mid] <= n) lo = mid; else hi = mid - 1;
  }
  return lo;
}

// Output entity of pair n, or -1 when the map puts it out of range.
__device__ __forceinline__ int64_t entity_of(const DemodGeo& g, const int64_t* idx, const int64_t* off, int64_t n) {
  if (g.up) {
    const int64_t j = idx[n];
    return (j >= 0 && j < g.Eo) ? j : -1;
  }
  return row_of(off, g.rows, n);
}

// sum over taps of W[a, n, r, u]^2 (the weight is (lead, nnz, inner, U)).
template <typename T>
__device__ __forceinline__ acc_t<T> taps_sq(const DemodGeo& g, const T* w, int64_t a, int64_t n, int64_t r) {
  using A = acc_t<T>;
  const T* p = w + ((a * g.nnz + n) * g.inner + r) * g.U;
  A q = A(0);
  // MODI_EMU_OFF_BY_ONE is 0 outside the emulator's defect injection (common/cuda_common.cuh): a tap dropped
  for (int64_t u = 0; u < g.U - MODI_EMU_OFF_BY_ONE; ++u) {
    const A v = ld(p + u);
    q += v * v;
  }
  return q;
}

template <typename T>
__device__ __forceinline__ acc_t<T> style_sq(const DemodGeo& g, const T* style, int64_t b, int64_t i) {
  using A = acc_t<T>;
  if (!g.styled) return A(1);
  const A s = ld(style + b * g.Ci + i);
  return s * s;
}

__device__ __forceinline__ float inv_sqrt(float v) { return 1.0f / sqrtf(v); }  // as the CPU kernel: 1 / sqrt
__device__ __forceinline__ double inv_sqrt(double v) { return 1.0 / sqrt(v); }

// d[b, o, j] = rsqrt(sum_i s[b, i]^2 sum_{n of j, u} W^2 + eps): one thread per output.
template <typename T>
__global__ void demod_forward_kernel(const T* __restrict__ w, const T* __restrict__ style,
                                     const int64_t* __restrict__ idx, const int64_t* __restrict__ off,
                                     const DemodGeo g, acc_t<T> eps, T* __restrict__ d) {
  using A = acc_t<T>;
  const int64_t t = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (t >= g.Bs * g.Co * g.Eo) return;
  const int64_t j = t % g.Eo, o = (t / g.Eo) % g.Co, b = t / (g.Eo * g.Co);
  const int64_t n0 = g.up ? 0 : clamp_pair(off[j], g.nnz), n1 = g.up ? g.nnz : clamp_pair(off[j + 1], g.nnz);
  A a = A(0);
  for (int64_t n = n0; n < n1; ++n) {
    if (g.up && idx[n] != j) continue;
    for (int64_t i = 0; i < g.Ci; ++i) {
      const A q = g.up ? taps_sq(g, w, i, n, o) : taps_sq(g, w, o, n, i);
      a += style_sq(g, style, b, i) * q;
    }
  }
  st(d + t, inv_sqrt(a + eps));
}

// ga[b, o, j] = dL/da = -1/2 grad d^3.
template <typename T>
__device__ __forceinline__ acc_t<T> grad_a(const T* grad, const T* d, int64_t k) {
  using A = acc_t<T>;
  const A dv = ld(d + k);
  return A(-0.5) * ld(grad + k) * dv * dv * dv;
}

// dL/ds[b, i] = 2 s[b, i] sum over pairs n (entity j) and outputs o of ga[b, o, j] sum_u W^2: one thread per (b, i).
template <typename T>
__global__ void demod_style_grad_kernel(const T* __restrict__ grad, const T* __restrict__ d, const T* __restrict__ w,
                                        const T* __restrict__ style, const int64_t* __restrict__ idx,
                                        const int64_t* __restrict__ off, const DemodGeo g, T* __restrict__ gs) {
  using A = acc_t<T>;
  const int64_t t = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (t >= g.Bs * g.Ci) return;
  const int64_t i = t % g.Ci, b = t / g.Ci;
  A sum = A(0);
  for (int64_t n = 0; n < g.nnz; ++n) {
    const int64_t j = entity_of(g, idx, off, n);
    if (j < 0) continue;
    for (int64_t o = 0; o < g.Co; ++o) {
      const A q = g.up ? taps_sq(g, w, i, n, o) : taps_sq(g, w, o, n, i);
      sum += grad_a(grad, d, (b * g.Co + o) * g.Eo + j) * q;
    }
  }
  st(gs + t, A(2) * ld(style + t) * sum);
}

// dL/dW[a, n, r, u] = 2 W[a, n, r, u] sum_b ga[b, o, j(n)] s[b, i]^2, (o, i) = (a, r) conv/down, (r, a) up: one
// thread per weight element.
template <typename T>
__global__ void demod_weight_grad_kernel(const T* __restrict__ grad, const T* __restrict__ d, const T* __restrict__ w,
                                         const T* __restrict__ style, const int64_t* __restrict__ idx,
                                         const int64_t* __restrict__ off, const DemodGeo g, T* __restrict__ gw) {
  using A = acc_t<T>;
  const int64_t t = int64_t(blockIdx.x) * blockDim.x + threadIdx.x;
  if (t >= g.lead * g.nnz * g.inner * g.U) return;
  const int64_t r = (t / g.U) % g.inner, n = (t / (g.U * g.inner)) % g.nnz, a = t / (g.U * g.inner * g.nnz);
  const int64_t j = entity_of(g, idx, off, n);
  A f = A(0);
  if (j >= 0) {
    const int64_t o = g.up ? r : a, i = g.up ? a : r;
    for (int64_t b = 0; b < g.Bs; ++b) f += grad_a(grad, d, (b * g.Co + o) * g.Eo + j) * style_sq(g, style, b, i);
  }
  // MODI_EMU_WRONG_SCALE is 0 outside the emulator's defect injection (common/cuda_common.cuh)
  if (MODI_EMU_WRONG_SCALE) f *= A(1) + A(1) / A(512);
  st(gw + t, A(2) * ld(w + t) * f);
}

at::Tensor demod_scale_cuda(const at::Tensor& weight, const std::optional<at::Tensor>& style, const at::Tensor& index,
                            const at::Tensor& offsets, bool up, int64_t n_out, double eps) {
  const demod::Shape s = demod::check_inputs(kCudaBackend, weight, style, index, offsets, up, n_out);
  const DemodGeo g = geo_of(s, offsets);
  const at::Tensor w = weight.contiguous(), ic = index.contiguous(), oc = offsets.contiguous();
  const at::Tensor st = s.styled ? style->contiguous() : at::Tensor();
  at::Tensor d = at::empty({s.Bs, s.Co, s.Eo}, weight.options());
  if (d.numel() == 0) return d;
  const c10::cuda::CUDAGuard guard(weight.device());
  const cudaStream_t stream = c10::cuda::getCurrentCUDAStream(weight.device().index());
  const unsigned blocks = static_cast<unsigned>(ceil_div(d.numel(), kThreads));
  AT_DISPATCH_FLOATING_TYPES_AND2(at::kHalf, at::kBFloat16, weight.scalar_type(), "modi_ext::demod_scale_cuda", [&] {
    using T = scalar_t;
    MODI_LAUNCH((demod_forward_kernel<T>), blocks, kThreads, 0, stream, w.data_ptr<T>(),
                s.styled ? st.data_ptr<T>() : nullptr, ic.data_ptr<int64_t>(), oc.data_ptr<int64_t>(), g,
                static_cast<acc_t<T>>(eps), d.data_ptr<T>());
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  });
  return d;
}

std::tuple<at::Tensor, at::Tensor> demod_scale_backward_cuda(const at::Tensor& grad, const at::Tensor& d,
                                                             const at::Tensor& weight,
                                                             const std::optional<at::Tensor>& style,
                                                             const at::Tensor& index, const at::Tensor& offsets,
                                                             bool up, int64_t n_out, std::array<bool, 2> output_mask) {
  const demod::Shape s = demod::check_backward_inputs(kCudaBackend, grad, d, weight, style, index, offsets, up, n_out);
  const DemodGeo g = geo_of(s, offsets);
  const bool want_w = output_mask[0], want_s = output_mask[1] && s.styled;
  const at::Tensor w = weight.contiguous(), gc = grad.contiguous(), dc = d.contiguous();
  const at::Tensor ic = index.contiguous(), oc = offsets.contiguous();
  const at::Tensor st = s.styled ? style->contiguous() : at::Tensor();
  at::Tensor gw = want_w ? at::empty_like(w) : at::empty({0}, weight.options());
  at::Tensor gs = want_s ? at::empty_like(st) : at::empty({0}, weight.options());
  const c10::cuda::CUDAGuard guard(weight.device());
  const cudaStream_t stream = c10::cuda::getCurrentCUDAStream(weight.device().index());
  AT_DISPATCH_FLOATING_TYPES_AND2(at::kHalf, at::kBFloat16, weight.scalar_type(), "modi_ext::demod_scale_backward_cuda",
                                  [&] {
    using T = scalar_t;
    const T* stp = s.styled ? st.data_ptr<T>() : nullptr;
    if (want_w && gw.numel() > 0) {
      MODI_LAUNCH((demod_weight_grad_kernel<T>), static_cast<unsigned>(ceil_div(gw.numel(), kThreads)), kThreads, 0,
                  stream, gc.data_ptr<T>(), dc.data_ptr<T>(), w.data_ptr<T>(), stp, ic.data_ptr<int64_t>(),
                  oc.data_ptr<int64_t>(), g, gw.data_ptr<T>());
      C10_CUDA_KERNEL_LAUNCH_CHECK();
    }
    if (want_s && gs.numel() > 0) {
      MODI_LAUNCH((demod_style_grad_kernel<T>), static_cast<unsigned>(ceil_div(gs.numel(), kThreads)), kThreads, 0,
                  stream, gc.data_ptr<T>(), dc.data_ptr<T>(), w.data_ptr<T>(), stp, ic.data_ptr<int64_t>(),
                  oc.data_ptr<int64_t>(), g, gs.data_ptr<T>());
      C10_CUDA_KERNEL_LAUNCH_CHECK();
    }
  });
  return {gw, gs};
}

}  // namespace

TORCH_LIBRARY_IMPL(MODI_CUDA_LIB, MODI_CUDA_KEY, m) {
  m.impl("demod_scale", &demod_scale_cuda);
  m.impl("demod_scale_backward", &demod_scale_backward_cuda);
}

}  // namespace modi_ext
