// Skeletal operators (skeletal_conv, skeletal_down, skeletal_up) and their shared backward.
// Semantics and time conventions: modi_ext/skeletal/reference.py (the dense oracle these kernels match).
#pragma once

#include <array>
#include <cmath>
#include <optional>

#include <ATen/ATen.h>
#include <c10/util/string_view.h>

namespace modi_ext {

enum SkeletalKind : int64_t { kConv = 0, kDown = 1, kUp = 2 };

// `act`: StyleGAN2's bias activation in the epilogue, y = gain * leaky_relu(scale * op(x * style) + bias), slope 0.2,
// gain sqrt(2) (the second moment stays 1).  Its backward reads the derivative off y alone (y > 0 exactly where the
// pre-activation is), so the op saves nothing more; act_pre inverts it for the scale gradient.
constexpr double kActSlope = 0.2;
constexpr double kActGain = 1.4142135623730951;
#if defined(__CUDACC__)
#define MODI_ACT_HD __host__ __device__ __forceinline__
#else
#define MODI_ACT_HD inline
#endif
// v * m + |v| * d is v * gain for v > 0 and v * gain * slope for v < 0 (m and d: the two slopes' mean and half
// difference): no compare, hence no branch -- GCC keeps `v > 0 ? v * a : v * b` a branch under -ftrapping-math, and
// it mispredicts on half the elements.  A NaN stays NaN.
constexpr double kActMean = (kActGain + kActGain * kActSlope) / 2;
constexpr double kActHalfDiff = (kActGain - kActGain * kActSlope) / 2;
template <typename A>
MODI_ACT_HD A act_fwd(A v) {
#if defined(__CUDACC__)
  return v * A(kActMean) + fabs(v) * A(kActHalfDiff);
#else
  return v * A(kActMean) + std::abs(v) * A(kActHalfDiff);
#endif
}
// dL/dpre = act_slope(y) * dL/dy, and pre = y / act_slope(y)
template <typename A>
MODI_ACT_HD A act_slope(A y) { return y > A(0) ? A(kActGain) : A(kActGain * kActSlope); }

// y = scale * op(x * style) + bias (then the activation, with act).
// weight: (Cout, nnz, Cin, U) for conv/down, (Cin, nnz, Cout, U) for up.
// (index, offsets): CSR from each row entity (output for conv/down, coarse for up) to its input entities.
at::Tensor skeletal_conv_cpu(const at::Tensor& x, const at::Tensor& weight, const std::optional<at::Tensor>& bias,
                             const at::Tensor& index, const at::Tensor& offsets,
                             const std::optional<at::Tensor>& style, const std::optional<at::Tensor>& scale,
                             c10::string_view padding_mode, bool act);
at::Tensor skeletal_down_cpu(const at::Tensor& x, const at::Tensor& weight, const std::optional<at::Tensor>& bias,
                             const at::Tensor& index, const at::Tensor& offsets,
                             const std::optional<at::Tensor>& style, const std::optional<at::Tensor>& scale,
                             c10::string_view padding_mode, bool act);
at::Tensor skeletal_up_cpu(const at::Tensor& x, const at::Tensor& weight, const std::optional<at::Tensor>& bias,
                           const at::Tensor& index, const at::Tensor& offsets, int64_t n_out,
                           const std::optional<at::Tensor>& style, const std::optional<at::Tensor>& scale,
                           c10::string_view padding_mode, bool act);

// Gradients (x, weight, bias, style, scale) given grad of the output and the forward output `out` (after the
// activation, with act).
// Entries not requested by output_mask (x, weight, style, scale) or whose input is absent come back empty.
std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor> skeletal_backward_cpu(
    const at::Tensor& grad, const at::Tensor& out, const at::Tensor& x, const at::Tensor& weight,
    const std::optional<at::Tensor>& bias, const at::Tensor& index, const at::Tensor& offsets,
    const std::optional<at::Tensor>& style, const std::optional<at::Tensor>& scale, c10::string_view padding_mode,
    int64_t kind, int64_t n_out, std::array<bool, 4> output_mask, bool act);

}  // namespace modi_ext
