// Schemas of the FK op family; registered from the one TORCH_LIBRARY block in csrc/registration.cpp.
// Kernels register per dispatch key in fk/cpu.cpp and fk/cuda.cu; autograd and fake kernels live in modi_ext/fk/ops.py.
#include "common/ops.h"

namespace modi_ext {

void define_fk_ops(torch::Library& m) {
  m.def(
      "fk(Tensor local_quats, Tensor offsets, int[] parents, Tensor root_positions) "
      "-> (Tensor positions, Tensor global_quats)");
  m.def(
      "fk_backward(Tensor grad_positions, Tensor? grad_global_quats, Tensor local_quats, "
      "Tensor global_quats, Tensor offsets, int[] parents, bool offsets_grad) "
      "-> (Tensor grad_local_quats, Tensor grad_root_positions, Tensor grad_offsets)");
}

}  // namespace modi_ext
