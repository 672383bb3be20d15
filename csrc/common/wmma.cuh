// The WMMA API (nvcuda::wmma) for the tensor-core kernels: <mma.h> under nvcc, the emulator's plain implementation
// (emu/wmma_emu.h) in the emulated build, so one kernel text serves both.  WMMA rather than inline mma.sync PTX for
// that reason: its fragments are opaque, so they can be given a CPU implementation.
#pragma once

#include "common/cuda_common.cuh"

#ifdef MODI_EXT_EMULATE_CUDA
#include "emu/wmma_emu.h"
#else
#include <cuda_bf16.h>
#include <mma.h>
#endif

// Shared arrays that WMMA loads from or stores to: the pointers it takes must be 256-bit aligned (the emulator's
// shared arrays are always 128-byte aligned and it checks every WMMA pointer).
#ifdef MODI_EXT_EMULATE_CUDA
#define MODI_SHARED_WMMA(T, name, dims) MODI_SHARED(T, name, dims)
#else
#define MODI_SHARED_WMMA(T, name, dims) __shared__ __align__(128) T name dims
#endif

namespace modi_ext {
namespace cuda {

// Major compute capability of a device (bf16 WMMA needs 8); the emulator claims 9.
inline int cc_major(int device) {
#ifdef MODI_EXT_EMULATE_CUDA
  (void)device;
  return 9;
#else
  int v = 0;
  if (cudaDeviceGetAttribute(&v, cudaDevAttrComputeCapabilityMajor, device) != cudaSuccess) {
    (void)cudaGetLastError();
    return 0;
  }
  return v;
#endif
}

}  // namespace cuda
}  // namespace modi_ext
