// The input check of the demodulation-coefficient ops (demod_scale, demod_scale_backward), for the CPU kernels
// (cpu.cpp) and the CUDA kernels (cuda.cu) alike.  On the CPU it also reads the CSR's values, which it turns into each
// pair's output entity; on CUDA it reads none (that would be a device sync): the kernels find a pair's entity on the
// device and skip out-of-range entries (the Python op checks a map's values once, modi_ext.skeletal.checks).
#pragma once

#include <ATen/ATen.h>

#include "common/check.h"

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

inline Shape check_inputs(const Backend& be, const at::Tensor& weight, const std::optional<at::Tensor>& style,
                          const at::Tensor& index, const at::Tensor& offsets, bool up, int64_t n_out) {
  TORCH_CHECK(be.on_device(weight), "demod_scale: weight must be a ", be.name, " tensor here, got ", weight.device());
  TORCH_CHECK(takes_float(be, weight.scalar_type()), "demod_scale: weight must be ", float_names(be), ", got ",
              weight.scalar_type());
  TORCH_CHECK(weight.dim() == 4, "demod_scale: weight must be (A, nnz, C, U), got ", weight.dim(), " dims");
  TORCH_CHECK(index.scalar_type() == at::kLong && offsets.scalar_type() == at::kLong,
              "demod_scale: index and offsets must be int64");
  TORCH_CHECK(index.device() == weight.device() && offsets.device() == weight.device(),
              "demod_scale: index and offsets must be on the weight's device ", weight.device());
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
  if (up) TORCH_CHECK(n_out > 0, "demod_scale: n_out must be positive for up, got ", n_out);
  s.Eo = up ? n_out : offsets.numel() - 1;
  if (style.has_value()) {
    const at::Tensor& st = *style;
    TORCH_CHECK(st.scalar_type() == weight.scalar_type(), "demod_scale: style must have the weight's dtype ",
                weight.scalar_type(), ", got ", st.scalar_type());
    TORCH_CHECK(st.device() == weight.device(), "demod_scale: style must be on the weight's device ",
                weight.device());
    TORCH_CHECK(st.dim() == 2 && st.size(1) == s.Ci, "demod_scale: style must be (B, ", s.Ci, "), got ", st.sizes());
    s.styled = true;
    s.Bs = st.size(0);
  }
  if (be.cuda) return s;  // no value reads on the device (see above)
  const auto oc = offsets.contiguous();
  const auto ic = index.contiguous();
  const int64_t* off = oc.data_ptr<int64_t>();
  const int64_t* idx = ic.data_ptr<int64_t>();
  const int64_t rows = offsets.numel() - 1;
  TORCH_CHECK(off[0] == 0 && off[rows] == s.nnz, "demod_scale: offsets must run from 0 to ", s.nnz);
  s.entity.resize(s.nnz);
  if (up) {
    for (int64_t n = 0; n < s.nnz; ++n) {
      TORCH_CHECK(idx[n] >= 0 && idx[n] < n_out, "demod_scale: index[", n, "] = ", idx[n], " is out of range [0, ",
                  n_out, ")");
      s.entity[n] = idx[n];
    }
  } else {
    for (int64_t j = 0; j < rows; ++j) {
      TORCH_CHECK(off[j + 1] >= off[j], "demod_scale: offsets must not decrease");
      for (int64_t n = off[j]; n < off[j + 1]; ++n) s.entity[n] = j;
    }
  }
  return s;
}

// demod_scale_backward: the forward's arguments, and the gradient of d and d itself in d's shape.
inline Shape check_backward_inputs(const Backend& be, const at::Tensor& grad, const at::Tensor& d,
                                   const at::Tensor& weight, const std::optional<at::Tensor>& style,
                                   const at::Tensor& index, const at::Tensor& offsets, bool up, int64_t n_out) {
  const Shape s = check_inputs(be, weight, style, index, offsets, up, n_out);
  for (const auto* t : {&grad, &d}) {
    TORCH_CHECK(t->scalar_type() == weight.scalar_type() && t->device() == weight.device(),
                "demod_scale_backward: grad and d must be tensors of the weight's dtype and device");
    TORCH_CHECK(t->dim() == 3 && t->size(0) == s.Bs && t->size(1) == s.Co && t->size(2) == s.Eo,
                "demod_scale_backward: grad and d must be (", s.Bs, ", ", s.Co, ", ", s.Eo, "), got ", t->sizes());
  }
  return s;
}

}  // namespace demod
}  // namespace modi_ext
