// Schemas of the skeletal operators (implementations register per dispatch key in cpu.cpp, cuda.cu).
#include <torch/library.h>

#include "common/ops.h"

namespace modi_ext {

void define_skeletal_ops(torch::Library& m) {
  m.def("skeletal_conv(Tensor x, Tensor weight, Tensor? bias, Tensor index, Tensor offsets, Tensor? style, "
        "Tensor? scale, str padding_mode, bool act=False) -> Tensor");
  m.def("skeletal_down(Tensor x, Tensor weight, Tensor? bias, Tensor index, Tensor offsets, Tensor? style, "
        "Tensor? scale, str padding_mode, bool act=False) -> Tensor");
  m.def("skeletal_up(Tensor x, Tensor weight, Tensor? bias, Tensor index, Tensor offsets, int n_out, "
        "Tensor? style, Tensor? scale, str padding_mode, bool act=False) -> Tensor");
  m.def("skeletal_backward(Tensor grad, Tensor out, Tensor x, Tensor weight, Tensor? bias, Tensor index, "
        "Tensor offsets, Tensor? style, Tensor? scale, str padding_mode, int kind, int n_out, bool[4] output_mask, "
        "bool act=False) -> (Tensor, Tensor, Tensor, Tensor, Tensor)");
}

}  // namespace modi_ext
