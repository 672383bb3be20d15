// Skeletal operators (skeletal_conv, skeletal_down, skeletal_up) and their shared backward.
// Semantics and time conventions: modi_ext/skeletal/reference.py (the dense oracle these kernels match).
#pragma once

#include <array>
#include <optional>

#include <ATen/ATen.h>
#include <c10/util/string_view.h>

namespace modi_ext {

enum SkeletalKind : int64_t { kConv = 0, kDown = 1, kUp = 2 };

// y = scale * op(x * style) + bias.  weight: (Cout, nnz, Cin, U) for conv/down, (Cin, nnz, Cout, U) for up.
// (index, offsets): CSR from each row entity (output for conv/down, coarse for up) to its input entities.
at::Tensor skeletal_conv_cpu(const at::Tensor& x, const at::Tensor& weight, const std::optional<at::Tensor>& bias,
                             const at::Tensor& index, const at::Tensor& offsets,
                             const std::optional<at::Tensor>& style, const std::optional<at::Tensor>& scale,
                             c10::string_view padding_mode);
at::Tensor skeletal_down_cpu(const at::Tensor& x, const at::Tensor& weight, const std::optional<at::Tensor>& bias,
                             const at::Tensor& index, const at::Tensor& offsets,
                             const std::optional<at::Tensor>& style, const std::optional<at::Tensor>& scale,
                             c10::string_view padding_mode);
at::Tensor skeletal_up_cpu(const at::Tensor& x, const at::Tensor& weight, const std::optional<at::Tensor>& bias,
                           const at::Tensor& index, const at::Tensor& offsets, int64_t n_out,
                           const std::optional<at::Tensor>& style, const std::optional<at::Tensor>& scale,
                           c10::string_view padding_mode);

// Gradients (x, weight, bias, style, scale) given grad of the output and the forward output `out`.
// Entries not requested by output_mask (x, weight, style, scale) or whose input is absent come back empty.
std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor> skeletal_backward_cpu(
    const at::Tensor& grad, const at::Tensor& out, const at::Tensor& x, const at::Tensor& weight,
    const std::optional<at::Tensor>& bias, const at::Tensor& index, const at::Tensor& offsets,
    const std::optional<at::Tensor>& style, const std::optional<at::Tensor>& scale, c10::string_view padding_mode,
    int64_t kind, int64_t n_out, std::array<bool, 4> output_mask);

}  // namespace modi_ext
