// The one registration unit: declares every modi_ext operator schema.
// Implementations register per dispatch key in their op's folder (<op>/cpu.cpp, <op>/cuda.cu).
#include <torch/library.h>

#include "common/ops.h"

TORCH_LIBRARY(modi_ext, m) {
  modi_ext::define_skeletal_ops(m);
  modi_ext::define_fk_ops(m);
  modi_ext::define_demod_ops(m);
}
