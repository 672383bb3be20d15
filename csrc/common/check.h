// What the one input check of an op (csrc/<op>/check.h) needs to know about the kernels it guards.  Each op checks
// its arguments in one function that its CPU and its CUDA registration both call; only this differs by device.
#pragma once

#include <ATen/ATen.h>

namespace modi_ext {

struct Backend {
  const char* name;                      // "CPU" or "CUDA", as the messages name the device and the kernel
  bool (*on_device)(const at::Tensor&);  // is a tensor where these kernels run (the emulated CUDA kernels: the CPU)
  bool cuda;                             // the CUDA kernels: float16 / bfloat16 as well, and their size limits
};

inline bool is_cpu_tensor(const at::Tensor& t) { return t.device().is_cpu(); }

inline constexpr Backend kCpuBackend{"CPU", &is_cpu_tensor, false};  // kCudaBackend: common/cuda_common.cuh

// The floating dtypes the backend's kernels compute in, and how a message lists them.
inline bool takes_float(const Backend& be, at::ScalarType t) {
  return t == at::kFloat || t == at::kDouble || (be.cuda && (t == at::kHalf || t == at::kBFloat16));
}

inline const char* float_names(const Backend& be) {
  return be.cuda ? "float32, float64, float16 or bfloat16" : "float32 or float64";
}

}  // namespace modi_ext
