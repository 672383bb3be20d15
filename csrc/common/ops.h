#pragma once
#include <torch/library.h>

namespace modi_ext {
// Each op family declares its schemas here; called from csrc/registration.cpp only.
void define_skeletal_ops(torch::Library& m);
void define_fk_ops(torch::Library& m);
void define_demod_ops(torch::Library& m);
}  // namespace modi_ext
