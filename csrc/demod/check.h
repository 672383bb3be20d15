// The input check of the demodulation-coefficient ops (demod_scale, demod_scale_backward).  They have CPU kernels
// only (cpu.cpp; other devices use the torch form in modi_ext/demod/dense.py), so the check is for the CPU; it also reads
// the CSR's values, which it turns into each pair's output entity.
#pragma once

#include <ATen/ATen.h>

#include <optional>
#include <vector>

namespace modi_ext {
namespace demod {

// The geometry of a checked call.
struct Shape {
  bool up = false;
  int64_t lead = 0, nnz = 0, inner = 0, U = 0;  // weight (lead, nnz, inner, U)
  int64_t Ci = 0, Co = 0, Eo = 0, Bs = 1;
  bool styled = false;
  std::vector<int64_t> entity;  // output entity of each pair
  int64_t cols() const { return Co * Eo; }
  double work() const { return double(lead) * nnz * inner * U + 2.0 * Bs * Ci * cols(); }
};

inline Shape check_inputs(const at::Tensor& weight, const std::optional<at::Tensor>& style, const at::Tensor& index,
                          const at::Tensor& offsets, bool up, int64_t n_out) {
  TORCH_CHECK(weight.device().is_cpu(), "demod_scale: weight must be a CPU tensor here, got ", weight.device());
  TORCH_CHECK(weight.scalar_type() == at::kFloat || weight.scalar_type() == at::kDouble,
              "demod_scale: weight must be float32 or float64, got ", weight.scalar_type());
  TORCH_CHECK(weight.dim() == 4, "demod_scale: weight must be (A, nnz, C, U), got ", weight.dim(), " dims");
  TORCH_CHECK(index.scalar_type() == at::kLong && offsets.scalar_type() == at::kLong,
              "demod_scale: index and offsets must be int64");
  TORCH_CHECK(index.device().is_cpu() && offsets.device().is_cpu(),
              "demod_scale: index and offsets must be on the CPU");
  TORCH_CHECK(index.dim() == 1 && offsets.dim() == 1 && offsets.numel() >= 2,
              "demod_scale: index must be 1-D and offsets 1-D with at least 2 entries");
  Shape s;
  s.up = up;
  s.lead = weight.size(0);
  s.nnz = weight.size(1);
  s.inner = weight.size(2);
  s.U = weight.size(3);
  TORCH_CHECK(index.numel() == s.nnz, "demod_scale: weight has ", s.nnz, " pairs but index has ", index.numel());
  s.Ci = up ? s.lead : s.inner;
  s.Co = up ? s.inner : s.lead;
  const auto oc = offsets.contiguous();
  const auto ic = index.contiguous();
  const int64_t* off = oc.data_ptr<int64_t>();
  const int64_t* idx = ic.data_ptr<int64_t>();
  const int64_t rows = offsets.numel() - 1;
  TORCH_CHECK(off[0] == 0 && off[rows] == s.nnz, "demod_scale: offsets must run from 0 to ", s.nnz);
  s.entity.resize(s.nnz);
  if (up) {
    TORCH_CHECK(n_out > 0, "demod_scale: n_out must be positive for up, got ", n_out);
    s.Eo = n_out;
    for (int64_t n = 0; n < s.nnz; ++n) {
      TORCH_CHECK(idx[n] >= 0 && idx[n] < n_out, "demod_scale: index[", n, "] = ", idx[n], " is out of range [0, ",
                  n_out, ")");
      s.entity[n] = idx[n];
    }
  } else {
    s.Eo = rows;
    for (int64_t j = 0; j < rows; ++j) {
      TORCH_CHECK(off[j + 1] >= off[j], "demod_scale: offsets must not decrease");
      for (int64_t n = off[j]; n < off[j + 1]; ++n) s.entity[n] = j;
    }
  }
  if (style.has_value()) {
    const at::Tensor& st = *style;
    TORCH_CHECK(st.scalar_type() == weight.scalar_type(), "demod_scale: style must have the weight's dtype ",
                weight.scalar_type(), ", got ", st.scalar_type());
    TORCH_CHECK(st.device().is_cpu(), "demod_scale: style must be a CPU tensor here");
    TORCH_CHECK(st.dim() == 2 && st.size(1) == s.Ci, "demod_scale: style must be (B, ", s.Ci, "), got ", st.sizes());
    s.styled = true;
    s.Bs = st.size(0);
  }
  return s;
}

// demod_scale_backward: the forward's arguments, and the gradient of d and d itself in d's shape.
inline Shape check_backward_inputs(const at::Tensor& grad, const at::Tensor& d, const at::Tensor& weight,
                                   const std::optional<at::Tensor>& style, const at::Tensor& index,
                                   const at::Tensor& offsets, bool up, int64_t n_out) {
  const Shape s = check_inputs(weight, style, index, offsets, up, n_out);
  for (const auto* t : {&grad, &d}) {
    TORCH_CHECK(t->scalar_type() == weight.scalar_type() && t->device().is_cpu(),
                "demod_scale_backward: grad and d must be CPU tensors of the weight's dtype");
    TORCH_CHECK(t->dim() == 3 && t->size(0) == s.Bs && t->size(1) == s.Co && t->size(2) == s.Eo,
                "demod_scale_backward: grad and d must be (", s.Bs, ", ", s.Co, ", ", s.Eo, "), got ", t->sizes());
  }
  return s;
}

}  // namespace demod
}  // namespace modi_ext
