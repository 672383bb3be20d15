// Schemas of the demodulation-coefficient ops (kernels: demod/cpu.cpp, demod/cuda.cu; other devices use the torch
// form in modi_ext/demod/dense.py); registered from the one TORCH_LIBRARY block in csrc/registration.cpp.
#include <torch/library.h>

#include "common/ops.h"

namespace modi_ext {

void define_demod_ops(torch::Library& m) {
  m.def("demod_scale(Tensor weight, Tensor? style, Tensor index, Tensor offsets, bool up, int n_out, float eps) "
        "-> Tensor");
  m.def("demod_scale_backward(Tensor grad, Tensor d, Tensor weight, Tensor? style, Tensor index, Tensor offsets, "
        "bool up, int n_out, bool[2] output_mask) -> (Tensor, Tensor)");
}

}  // namespace modi_ext
