// The demodulation coefficients of the modulated skeletal ops, and their gradient, as one CPU call each.
//
//   acc[i, o, j] = sum over pairs n of output entity j, and taps u, of W[.., n, .., u]^2
//                  (conv/down: W[o, n, i, u], j = the CSR row of n; up: W[i, n, o, u], j = index[n], a fine entity)
//   a[b, o, j]   = sum_i s[b, i]^2 acc[i, o, j]        (no style: sum_i acc[i, o, j], one row b)
//   d[b, o, j]   = 1 / sqrt(a[b, o, j] + eps)
//
// Why C++: in torch this is a dozen small ops (a pow, a reduction over the 3-5 taps, a one-hot segment product, an
// einsum, rsqrt, and about as many again in the backward), each a parallel region of its own.  On a quiet machine
// they cost a few percent of a modulated layer; when another process holds a core, every one of them waits for its
// slowest thread, and they took as long as the layer's two convolutions together (measured in benchmarks/RESULTS.md).
// Here a call is one job of the task pool (common/tasks.h): stages of tasks claimed dynamically, each writing its own
// outputs in a fixed summation order, so the result does not depend on the thread count.  Small calls run serially.
//
// Second-order gradients are not computed here: modi_ext/demod/ops.py recomputes this in torch ops when autograd needs a
// graph of the gradient (create_graph), which only regularisers (path length, R1) ask for.
#include <algorithm>
#include <array>
#include <cmath>
#include <optional>
#include <tuple>
#include <vector>

#include <ATen/ATen.h>
#include <torch/library.h>

#include "common/tasks.h"
#include "demod/check.h"

namespace modi_ext {
namespace {

using cpu_tasks::phase;
using cpu_tasks::Phase;
using cpu_tasks::run_stages;
using demod::Shape;

constexpr double kSerialWork = 1.0e6;  // multiply-adds below which waking threads costs more than it saves
constexpr int64_t kColsPerTask = 256;   // columns (o, j) per task in the products over the batch

// Layouts.  The weight is (lead, nnz, inner, U): lead = o, inner = i for conv/down; lead = i, inner = o for up.
//   sq  (lead, Eo, inner * U): squared taps summed over each output entity's pairs, in the weight's own order, so the
//       pass over the weight is one contiguous multiply-add per pair (vectorised);
//   acc (Ci, Co * Eo): sq summed over the taps and transposed, the rows the products over the batch read.
// Every loop below runs in a fixed order, whichever thread runs its task.

// sq[a] for one slab a of the weight.
template <typename T>
void square_slab(const Shape& s, const T* w, T* sq, int64_t a) {
  const int64_t row = s.inner * s.U;
  T* out = sq + a * s.Eo * row;
  std::fill(out, out + s.Eo * row, T(0));
  for (int64_t n = 0; n < s.nnz; ++n) {
    const T* wr = w + (a * s.nnz + n) * row;
    T* o = out + s.entity[n] * row;
    for (int64_t k = 0; k < row; ++k) o[k] += wr[k] * wr[k];
  }
}

// acc[i] (one row: Co * Eo) from sq.
template <typename T>
void acc_row(const Shape& s, const T* sq, T* acc, int64_t i) {
  const int64_t row = s.inner * s.U, U = s.U;
  T* out = acc + i * s.cols();
  for (int64_t o = 0; o < s.Co; ++o) {
    for (int64_t j = 0; j < s.Eo; ++j) {
      const T* q = s.up ? sq + (i * s.Eo + j) * row + o * U : sq + (o * s.Eo + j) * row + i * U;
      T v = T(0);
      for (int64_t u = 0; u < U; ++u) v += q[u];
      out[o * s.Eo + j] = v;
    }
  }
}

template <typename T>
T style_sq(const Shape& s, const T* style, int64_t b, int64_t i) {
  return s.styled ? style[b * s.Ci + i] * style[b * s.Ci + i] : T(1);
}

template <typename T>
void forward_impl(const Shape& s, const T* w, const T* style, T eps, T* sq, T* acc, T* d) {
  const int64_t C = s.cols();
  auto squares = [&](int64_t a, int) { square_slab(s, w, sq, a); };
  auto rows = [&](int64_t i, int) { acc_row(s, sq, acc, i); };
  const int64_t col_tasks = (C + kColsPerTask - 1) / kColsPerTask;
  auto demod = [&](int64_t t, int) {
    const int64_t b = t / col_tasks, c0 = (t % col_tasks) * kColsPerTask, c1 = std::min(C, c0 + kColsPerTask);
    T* out = d + b * C;
    for (int64_t c = c0; c < c1; ++c) out[c] = T(0);
    for (int64_t i = 0; i < s.Ci; ++i) {
      const T si = style_sq(s, style, b, i);
      const T* r = acc + i * C;
      for (int64_t c = c0; c < c1; ++c) out[c] += si * r[c];
    }
    for (int64_t c = c0; c < c1; ++c) out[c] = T(1) / std::sqrt(out[c] + eps);
  };
  const std::vector<Phase> st1{phase(s.lead, squares)}, st2{phase(s.Ci, rows)}, st3{phase(s.Bs * col_tasks, demod)};
  run_stages({cpu_tasks::stage(st1), cpu_tasks::stage(st2), cpu_tasks::stage(st3)}, s.work() >= kSerialWork);
}

// Gradients, with ga = dL/da = -1/2 g d^3:
//   dL/ds[b, i] = 2 s[b, i] sum_c ga[b, c] acc[i, c]
//   dL/dW[a, n, r, u] = 2 W[a, n, r, u] sum_b ga[b, o, j(n)] s[b, i]^2       ((o, i) = (a, r) conv/down, (r, a) up)
// The second factor is built once per (a, j, r) and repeated over the taps (gu), so the pass over the weight is one
// contiguous multiply per pair.
template <typename T>
void backward_impl(const Shape& s, const T* grad, const T* d, const T* w, const T* style, T* sq, T* acc, T* ga,
                   T* gat, T* gu, T* gw, T* gs) {
  const int64_t C = s.cols(), row = s.inner * s.U, U = s.U;
  auto da = [&](int64_t b, int) {
    for (int64_t c = 0; c < C; ++c) {
      const T dc = d[b * C + c];
      ga[b * C + c] = T(-0.5) * grad[b * C + c] * dc * dc * dc;
    }
    if (s.up && gat != nullptr)  // (Eo, Co) per b: the up weight's inner axis is o
      for (int64_t o = 0; o < s.Co; ++o)
        for (int64_t j = 0; j < s.Eo; ++j) gat[(b * s.Eo + j) * s.Co + o] = ga[b * C + o * s.Eo + j];
  };
  auto squares = [&](int64_t a, int) { square_slab(s, w, sq, a); };
  auto rows = [&](int64_t i, int) { acc_row(s, sq, acc, i); };
  auto factor = [&](int64_t a, int) {  // gu[a, j, r * U + u] = 2 sum_b ga[b, o, j] s[b, i]^2
    std::vector<T> v(s.inner);
    for (int64_t j = 0; j < s.Eo; ++j) {
      std::fill(v.begin(), v.end(), T(0));
      for (int64_t b = 0; b < s.Bs; ++b) {
        if (s.up) {  // a = i, r = o
          const T f = style_sq(s, style, b, a);
          const T* g = gat + (b * s.Eo + j) * s.Co;
          for (int64_t r = 0; r < s.inner; ++r) v[r] += f * g[r];
        } else {  // a = o, r = i
          const T g = ga[b * C + a * s.Eo + j];
          if (s.styled) {
            const T* sb = style + b * s.Ci;
            for (int64_t r = 0; r < s.inner; ++r) v[r] += g * sb[r] * sb[r];
          } else {
            for (int64_t r = 0; r < s.inner; ++r) v[r] += g;
          }
        }
      }
      T* out = gu + (a * s.Eo + j) * row;
      for (int64_t r = 0; r < s.inner; ++r)
        for (int64_t u = 0; u < U; ++u) out[r * U + u] = T(2) * v[r];
    }
  };
  auto weight_grad = [&](int64_t a, int) {
    for (int64_t n = 0; n < s.nnz; ++n) {
      const T* wr = w + (a * s.nnz + n) * row;
      const T* f = gu + (a * s.Eo + s.entity[n]) * row;
      T* out = gw + (a * s.nnz + n) * row;
      for (int64_t k = 0; k < row; ++k) out[k] = wr[k] * f[k];
    }
  };
  auto style_grad = [&](int64_t b, int) {
    const T* g = ga + b * C;
    for (int64_t i = 0; i < s.Ci; ++i) {
      const T* r = acc + i * C;
      T sum = T(0);
#pragma omp simd reduction(+ : sum)
      for (int64_t c = 0; c < C; ++c) sum += g[c] * r[c];
      gs[b * s.Ci + i] = T(2) * style[b * s.Ci + i] * sum;
    }
  };
  const bool want_w = gw != nullptr, want_s = gs != nullptr;
  std::vector<Phase> st1{phase(s.Bs, da)}, st2, st3;
  if (want_s) st1.push_back(phase(s.lead, squares));
  if (want_w) st2.push_back(phase(s.lead, factor));
  if (want_s) st2.push_back(phase(s.Ci, rows));
  if (want_w) st3.push_back(phase(s.lead, weight_grad));
  if (want_s) st3.push_back(phase(s.Bs, style_grad));
  run_stages({cpu_tasks::stage(st1), cpu_tasks::stage(st2), cpu_tasks::stage(st3)}, 2.0 * s.work() >= kSerialWork);
}

at::Tensor demod_scale_cpu(const at::Tensor& weight, const std::optional<at::Tensor>& style, const at::Tensor& index,
                           const at::Tensor& offsets, bool up, int64_t n_out, double eps) {
  const Shape s = demod::check_inputs(kCpuBackend, weight, style, index, offsets, up, n_out);
  const at::Tensor w = weight.contiguous();
  const at::Tensor st = style.has_value() ? style->contiguous() : at::Tensor();
  at::Tensor d = at::empty({s.Bs, s.Co, s.Eo}, weight.options());
  at::Tensor sq = at::empty({s.lead, s.Eo, s.inner * s.U}, weight.options());
  at::Tensor acc = at::empty({s.Ci, s.Co, s.Eo}, weight.options());
  AT_DISPATCH_FLOATING_TYPES(weight.scalar_type(), "demod_scale", [&] {
    using T = scalar_t;
    forward_impl<T>(s, w.data_ptr<T>(), s.styled ? st.data_ptr<T>() : nullptr, static_cast<T>(eps), sq.data_ptr<T>(),
                    acc.data_ptr<T>(), d.data_ptr<T>());
  });
  return d;
}

std::tuple<at::Tensor, at::Tensor> demod_scale_backward_cpu(const at::Tensor& grad, const at::Tensor& d,
                                                            const at::Tensor& weight,
                                                            const std::optional<at::Tensor>& style,
                                                            const at::Tensor& index, const at::Tensor& offsets,
                                                            bool up, int64_t n_out, std::array<bool, 2> output_mask) {
  const Shape s = demod::check_backward_inputs(kCpuBackend, grad, d, weight, style, index, offsets, up, n_out);
  const bool want_w = output_mask[0], want_s = output_mask[1] && s.styled;
  const at::Tensor w = weight.contiguous(), g = grad.contiguous(), dc = d.contiguous();
  const at::Tensor st = s.styled ? style->contiguous() : at::Tensor();
  auto opts = weight.options();
  at::Tensor gw = want_w ? at::empty_like(w) : at::empty({0}, opts);
  at::Tensor gs = want_s ? at::empty_like(st) : at::empty({0}, opts);
  if (!want_w && !want_s) return {gw, gs};
  at::Tensor sq = at::empty({want_s ? s.lead : 0, s.Eo, s.inner * s.U}, opts);
  at::Tensor acc = at::empty({want_s ? s.Ci : 0, s.Co, s.Eo}, opts);
  at::Tensor ga = at::empty({s.Bs, s.Co, s.Eo}, opts);
  at::Tensor gat = at::empty({want_w && up ? s.Bs : 0, s.Eo, s.Co}, opts);
  at::Tensor gu = at::empty({want_w ? s.lead : 0, s.Eo, s.inner * s.U}, opts);
  AT_DISPATCH_FLOATING_TYPES(weight.scalar_type(), "demod_scale_backward", [&] {
    using T = scalar_t;
    auto ptr = [](at::Tensor& t) -> T* { return t.numel() ? t.data_ptr<T>() : nullptr; };
    backward_impl<T>(s, g.data_ptr<T>(), dc.data_ptr<T>(), w.data_ptr<T>(), s.styled ? st.data_ptr<T>() : nullptr,
                     ptr(sq), ptr(acc), ga.data_ptr<T>(), ptr(gat), ptr(gu), want_w ? gw.data_ptr<T>() : nullptr,
                     want_s ? gs.data_ptr<T>() : nullptr);
  });
  return {gw, gs};
}

}  // namespace

TORCH_LIBRARY_IMPL(modi_ext, CPU, m) {
  m.impl("demod_scale", &demod_scale_cpu);
  m.impl("demod_scale_backward", &demod_scale_backward_cpu);
}

}  // namespace modi_ext
