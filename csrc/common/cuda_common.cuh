// Shared helpers of the modi_ext CUDA kernels (skeletal/cuda.cu, fk/cuda.cu).
//
// Only torch/ATen/c10-cuda and CUDA runtime headers: <ATen/cuda/CUDAContext.h> is deliberately avoided (it pulls
// cuBLAS/cuSPARSE headers that a bare nvcc install lacks; see .ci/cuda_compile_check).  Nothing here synchronises
// with the host, so every op built on it can be captured in a CUDA graph.
#pragma once

#include <ATen/ATen.h>

#include <atomic>
#include <cstdint>
#include <utility>

#include "common/check.h"

#ifdef MODI_EXT_EMULATE_CUDA
// Test-only build: the same sources as host C++ on the CPU emulator (csrc/emu, tests/test_cuda_emulated.py).
#include "emu/cuda_emu.h"
#define MODI_CUDA_LIB MODI_EMU_LIB  // its own op namespace, CPU dispatch key only: never real CUDA tensors
#define MODI_CUDA_KEY CPU
#else
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>
#include <cuda_runtime.h>
#define MODI_CUDA_LIB modi_ext
#define MODI_CUDA_KEY CUDA
#endif

// The one launch site of every kernel: `<<<>>>` under nvcc, the emulator's launch otherwise.  Parenthesise a
// template kernel name: MODI_LAUNCH((kernel<T, 32>), grid, block, smem, stream, args...).
#ifdef MODI_EXT_EMULATE_CUDA
#define MODI_LAUNCH(K, grid, block, smem, stream, ...) \
  ((void)(stream), ::modi_emu::launch<K>(grid, block, smem, __VA_ARGS__))
#else
#define MODI_LAUNCH(K, grid, block, smem, stream, ...) \
  ::modi_ext::cuda::launch_kernel(K, grid, block, smem, stream, __VA_ARGS__)
#endif

// Shared memory declarations, one text for both builds: MODI_SHARED(float, As, [2][16][65]) is
// `__shared__ float As[2][16][65]` under nvcc and a bounds-checked, poisoned block-local array in the emulator;
// MODI_DYNAMIC_SHARED(unsigned char, raw) is the `extern __shared__` buffer of the launch's dynamic size.
#ifdef MODI_EXT_EMULATE_CUDA
#define MODI_SHARED(T, name, dims) const auto name = ::modi_emu::shared_array<T dims>(#name, __LINE__)
#define MODI_DYNAMIC_SHARED(T, name) T* const name = reinterpret_cast<T*>(::modi_emu::dynamic_shared())
#else
#define MODI_SHARED(T, name, dims) __shared__ T name dims
#define MODI_DYNAMIC_SHARED(T, name) extern __shared__ __align__(16) T name[]
#endif

// Test-only defects of the emulator, chosen at run time (csrc/emu/cuda_emu.h: off_by_one, global_oob,
// wrong_scale, split_edge, wrong_slope, mma_fragment_offset, mma_tile_edge,
// mma_wgrad_fragment_offset, mma_wgrad_tile_edge): 0 in every other build, so the CUDA build
// compiles to the same code.
#ifdef MODI_EXT_EMULATE_CUDA
#define MODI_EMU_OFF_BY_ONE (::modi_emu::injected_defect() == MODI_EMU_INJECT_OFF_BY_ONE_ID ? 1 : 0)
#define MODI_EMU_GLOBAL_OOB (::modi_emu::injected_defect() == MODI_EMU_INJECT_GLOBAL_OOB_ID ? 1 : 0)
#define MODI_EMU_WRONG_SCALE (::modi_emu::injected_defect() == MODI_EMU_INJECT_WRONG_SCALE_ID ? 1 : 0)
#define MODI_EMU_SPLIT_EDGE (::modi_emu::injected_defect() == MODI_EMU_INJECT_SPLIT_EDGE_ID ? 1 : 0)
#define MODI_EMU_WRONG_SLOPE (::modi_emu::injected_defect() == MODI_EMU_INJECT_WRONG_SLOPE_ID ? 1 : 0)
#define MODI_EMU_MMA_FRAGMENT_OFFSET \
  (::modi_emu::injected_defect() == MODI_EMU_INJECT_MMA_FRAGMENT_OFFSET_ID ? 1 : 0)
#define MODI_EMU_MMA_TILE_EDGE (::modi_emu::injected_defect() == MODI_EMU_INJECT_MMA_TILE_EDGE_ID ? 1 : 0)
#define MODI_EMU_MMA_WGRAD_FRAGMENT_OFFSET \
  (::modi_emu::injected_defect() == MODI_EMU_INJECT_MMA_WGRAD_FRAGMENT_OFFSET_ID ? 1 : 0)
#define MODI_EMU_MMA_WGRAD_TILE_EDGE \
  (::modi_emu::injected_defect() == MODI_EMU_INJECT_MMA_WGRAD_TILE_EDGE_ID ? 1 : 0)
#else
#define MODI_EMU_OFF_BY_ONE 0
#define MODI_EMU_GLOBAL_OOB 0
#define MODI_EMU_WRONG_SCALE 0
#define MODI_EMU_SPLIT_EDGE 0
#define MODI_EMU_WRONG_SLOPE 0
#define MODI_EMU_MMA_FRAGMENT_OFFSET 0
#define MODI_EMU_MMA_TILE_EDGE 0
#define MODI_EMU_MMA_WGRAD_FRAGMENT_OFFSET 0
#define MODI_EMU_MMA_WGRAD_TILE_EDGE 0
#endif

namespace modi_ext {
namespace cuda {

#ifndef MODI_EXT_EMULATE_CUDA
template <typename... P, typename... Args>
inline void launch_kernel(void (*kernel)(P...), dim3 grid, dim3 block, size_t smem, cudaStream_t stream,
                          Args&&... args) {
  kernel<<<grid, block, smem, stream>>>(std::forward<Args>(args)...);
}
#endif

// Tensors the kernels run on: CUDA tensors (CPU tensors in the emulator build).
inline bool on_device(const at::Tensor& t) {
#ifdef MODI_EXT_EMULATE_CUDA
  return t.is_cpu();
#else
  return t.is_cuda();
#endif
}

}  // namespace cuda

// What the ops' input checks (csrc/<op>/check.h) know of the CUDA kernels.
inline constexpr Backend kCudaBackend{"CUDA", &cuda::on_device, true};

namespace cuda {

// Accumulator type: fp32 for float / half / bfloat16, fp64 for double (gradcheck).
template <typename T>
struct AccT {
  using type = float;
};
template <>
struct AccT<double> {
  using type = double;
};
template <typename T>
using acc_t = typename AccT<T>::type;

template <typename T>
__device__ __forceinline__ acc_t<T> ld(const T* p) {
  return static_cast<acc_t<T>>(*p);
}
template <typename T, typename A>
__device__ __forceinline__ void st(T* p, A v) {
  *p = static_cast<T>(v);
}

// V consecutive elements as one aligned vector: a single V * sizeof(T)-byte load on the GPU (what CUTLASS's
// AlignedArray relies on).  Callers check vec_aligned first and fall back to scalar loads otherwise.
template <int V, typename T>
struct alignas(V * sizeof(T)) Vec {
  T v[V];
};

template <int V, typename T>
__device__ __forceinline__ bool vec_aligned(const T* p) {
  return reinterpret_cast<uintptr_t>(p) % (V * sizeof(T)) == 0;
}

// out[i] = p[i], i < V, with p aligned to V elements (a misaligned vector load faults on a GPU; the emulator says so).
template <int V, typename T>
__device__ __forceinline__ void ld_vec(const T* p, acc_t<T> (&out)[V]) {
#ifdef MODI_EXT_EMULATE_CUDA
  if (!vec_aligned<V>(p)) ::modi_emu::fail("misaligned vector load");
#endif
  const Vec<V, T> v = *reinterpret_cast<const Vec<V, T>*>(p);
#pragma unroll
  for (int i = 0; i < V; ++i) out[i] = static_cast<acc_t<T>>(v.v[i]);
}

inline at::ScalarType acc_scalar_type(at::ScalarType t) {
  return t == at::kDouble ? at::kDouble : at::kFloat;
}

// Multiprocessor count of a device, queried once (a plain attribute query: legal during stream capture).
inline int sm_count(int device) {
#ifdef MODI_EXT_EMULATE_CUDA
  return modi_emu::sm_count();  // settable from the tests (it steers the split-K choice)
#endif
  static std::atomic<int> cache[64];
  if (device < 0 || device >= 64) return 108;
  int v = cache[device].load(std::memory_order_relaxed);
  if (v > 0) return v;
  if (cudaDeviceGetAttribute(&v, cudaDevAttrMultiProcessorCount, device) != cudaSuccess || v <= 0) {
    (void)cudaGetLastError();  // clear the sticky-free error so the next launch check does not report it
    v = 108;
  }
  cache[device].store(v, std::memory_order_relaxed);
  return v;
}

inline int64_t ceil_div(int64_t a, int64_t b) { return (a + b - 1) / b; }

// Warp sum (all 32 lanes must call it).
template <typename A>
__device__ __forceinline__ A warp_sum(A v) {
#pragma unroll
  for (int o = 16; o > 0; o >>= 1) v += __shfl_xor_sync(0xffffffffu, v, o);
  return v;
}

// Block sum for blockDim.x a multiple of 32 and <= 1024; the result is valid in thread 0.
// `scratch` is a shared array of 32 values; the function ends with the block synchronised, so it can be called again.
template <typename A, typename Scratch>
__device__ __forceinline__ A block_sum(A v, Scratch& scratch) {
  const int lane = threadIdx.x & 31, warp = threadIdx.x >> 5, nwarps = blockDim.x >> 5;
  v = warp_sum(v);
  if (lane == 0) scratch[warp] = v;
  __syncthreads();
  A r = A(0);
  if (warp == 0) {
    r = lane < nwarps ? scratch[lane] : A(0);
    r = warp_sum(r);
  }
  __syncthreads();
  return r;
}

}  // namespace cuda
}  // namespace modi_ext
