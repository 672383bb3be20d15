// The one input check of the skeletal operators (skeletal_conv / _down / _up and skeletal_backward), called by the
// CPU (cpu.cpp) and the CUDA (cuda.cu) registrations alike.  Every failure names the argument; a call that passes
// has the shapes, dtypes, devices and layouts the kernels read.  The CSR's values (offsets from 0 to nnz, no entity
// without neighbours, index in range) are checked where the kernels read them: on the host by make_csr (cpu.cpp),
// on the device by the topology kernel (cuda.cu), so a CUDA call never waits for the GPU to check them.
#pragma once

#include <ATen/ATen.h>
#include <c10/util/string_view.h>

#include <algorithm>
#include <optional>
#include <string>
#include <utility>

#include "common/check.h"
#include "skeletal/skeletal.h"

namespace modi_ext {
namespace skeletal {

// The geometry of a checked call.
struct Geo {
  int64_t kind, B, Cin, Cout, Ein, Eout, Tin, Tout, U, h, nnz;
  bool reflect;
  bool act = false;  // the bias activation in the epilogue (skeletal.h)
  double macs;  // multiply-adds of one GEMM pass (forward, input or weight gradient)
};

inline bool parse_padding(c10::string_view mode) {
  if (mode == "zeros") return false;
  if (mode == "reflect") return true;
  TORCH_CHECK(false, "padding_mode must be 'zeros' or 'reflect', got '", std::string(mode), "'");
  return false;
}

// A floating tensor that goes with x: its device, its dtype, contiguous.
inline void check_like_x(const at::Tensor& t, const char* name, const at::Tensor& x) {
  TORCH_CHECK(t.device() == x.device(), name, " is on ", t.device(), " but x is on ", x.device());
  TORCH_CHECK(t.scalar_type() == x.scalar_type(), name, " has dtype ", t.scalar_type(), " but x has ",
              x.scalar_type());
  TORCH_CHECK(t.is_contiguous(), name, " must be contiguous");
}

// index / offsets: int64, 1-D, on x's device.  The CUDA kernels read them in place (contiguous); the CPU kernels
// copy them into their own CSR first.
inline void check_index(const Backend& be, const at::Tensor& t, const char* name, const at::Tensor& x) {
  TORCH_CHECK(t.device() == x.device(), name, " is on ", t.device(), " but x is on ", x.device());
  TORCH_CHECK(t.scalar_type() == at::kLong, name, " must be int64, got ", t.scalar_type());
  TORCH_CHECK(t.dim() == 1, name, " must be 1-D, got ", t.dim(), " dims");
  if (be.cuda) TORCH_CHECK(t.is_contiguous(), name, " must be contiguous");
}

inline Geo check_inputs(const Backend& be, int64_t kind, const at::Tensor& x, const at::Tensor& weight,
                        const std::optional<at::Tensor>& bias, const at::Tensor& index, const at::Tensor& offsets,
                        int64_t n_out, const std::optional<at::Tensor>& style,
                        const std::optional<at::Tensor>& scale, c10::string_view padding_mode) {
  TORCH_CHECK(be.on_device(x), "x must be a ", be.name, " tensor for the ", be.name, " kernel, got ", x.device());
  TORCH_CHECK(x.dim() == 4, "x must be 4-D (B, C, E, T), got ", x.dim(), " dims");
  // The CPU kernels take bfloat16 as well (bf16k.h), which the other CPU ops do not.
  const bool cpu_bf16 = !be.cuda && x.scalar_type() == at::kBFloat16;
  TORCH_CHECK(takes_float(be, x.scalar_type()) || cpu_bf16, "x must be ",
              be.cuda ? float_names(be) : "float32, float64 or bfloat16", ", got ", x.scalar_type());
  TORCH_CHECK(x.is_contiguous(), "x must be contiguous");
  TORCH_CHECK(weight.dim() == 4, "weight must be 4-D compact (C0, nnz, C1, U), got ", weight.dim(), " dims");
  check_like_x(weight, "weight", x);
  check_index(be, index, "index", x);
  check_index(be, offsets, "offsets", x);
  Geo g{};
  g.kind = kind;
  g.reflect = parse_padding(padding_mode);
  g.B = x.size(0);
  g.Tin = x.size(3);
  TORCH_CHECK(g.B > 0, "x has an empty batch (B == 0)");
  TORCH_CHECK(x.size(1) > 0, "x has no channels (C == 0)");  // BLAS would get a zero leading dimension
  TORCH_CHECK(g.Tin > 0, "x has zero frames (T == 0)");
  g.U = weight.size(3);
  TORCH_CHECK(g.U % 2 == 1, "weight kernel width U=", g.U, " must be odd");
  g.h = g.U / 2;
  g.nnz = weight.size(1);
  TORCH_CHECK(index.numel() == g.nnz, "weight has ", g.nnz, " pairs (dim 1) but index has ", index.numel(),
              " entries");
  TORCH_CHECK(offsets.numel() >= 2, "offsets must be 1-D with at least 2 entries");
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
  if (be.cuda) TORCH_CHECK(g.Cin > 0 && g.Cout > 0, "weight has zero channels: ", weight.sizes());
  g.macs = double(g.B) * double(g.kind == kUp ? g.Tin : g.Tout) * double(g.Cout) * double(g.nnz) * double(g.Cin) *
           double(g.U);
  if (bias.has_value()) {
    check_like_x(*bias, "bias", x);
    TORCH_CHECK(bias->dim() == 1 && bias->size(0) == g.Cout, "bias must have shape (", g.Cout, "), got ",
                bias->sizes());
  }
  if (style.has_value()) {
    check_like_x(*style, "style", x);
    TORCH_CHECK(style->dim() == 2 && style->size(0) == g.B && style->size(1) == g.Cin, "style must be (B, Cin) = (",
                g.B, ", ", g.Cin, "), got ", style->sizes());
  }
  if (scale.has_value()) {
    check_like_x(*scale, "scale", x);
    TORCH_CHECK(scale->dim() == 3 && scale->size(0) == g.B && scale->size(1) == g.Cout && scale->size(2) == g.Eout,
                "scale must be (B, Cout, E_out) = (", g.B, ", ", g.Cout, ", ", g.Eout, "), got ", scale->sizes());
  }
  if (be.cuda) {
    // Launch geometry limits (grid y / z) and 32-bit frame / channel arithmetic inside the kernels.
    TORCH_CHECK(g.Ein <= 65535 && g.Eout <= 65535, "at most 65535 entities per level are supported, got ", g.Ein,
                " -> ", g.Eout);
    TORCH_CHECK(g.nnz < (int64_t(1) << 24) && g.Cin * g.U * g.nnz < (int64_t(1) << 31) &&
                    g.Cout * g.U * g.nnz < (int64_t(1) << 31),
                "weight is too large for the CUDA kernel: ", weight.sizes());
    TORCH_CHECK(g.B * std::max(g.Tin, g.Tout) < (int64_t(1) << 31) && g.Tout < (int64_t(1) << 30),
                "batch x frames is too large for the CUDA kernel: ", x.sizes());
  }
  return g;
}

// skeletal_backward: the forward's arguments, the kind, and the output gradient and output in the output's shape.
inline Geo check_backward_inputs(const Backend& be, const at::Tensor& grad, const at::Tensor& out,
                                 const at::Tensor& x, const at::Tensor& weight, const std::optional<at::Tensor>& bias,
                                 const at::Tensor& index, const at::Tensor& offsets,
                                 const std::optional<at::Tensor>& style, const std::optional<at::Tensor>& scale,
                                 c10::string_view padding_mode, int64_t kind, int64_t n_out) {
  TORCH_CHECK(kind == kConv || kind == kDown || kind == kUp, "kind must be 0 (conv), 1 (down) or 2 (up), got ",
              kind);
  const Geo g = check_inputs(be, kind, x, weight, bias, index, offsets, n_out, style, scale, padding_mode);
  for (const auto& [t, name] : {std::pair<const at::Tensor*, const char*>{&grad, "grad"}, {&out, "out"}}) {
    check_like_x(*t, name, x);
    TORCH_CHECK(t->dim() == 4 && t->size(0) == g.B && t->size(1) == g.Cout && t->size(2) == g.Eout &&
                    t->size(3) == g.Tout,
                name, " must have the output shape (", g.B, ", ", g.Cout, ", ", g.Eout, ", ", g.Tout, "), got ",
                t->sizes());
  }
  return g;
}

}  // namespace skeletal
}  // namespace modi_ext
