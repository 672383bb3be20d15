// A CUDA execution-model emulator for testing: compiles the unchanged kernels of csrc/<op>/cuda.cu as host C++
// (-DMODI_EXT_EMULATE_CUDA) and runs them on the CPU, so CI exercises the CUDA code without a GPU.
//
// Model: blocks run one after another (in an order permuted by the schedule seed); every thread of a block is its
// own fiber (own stack; cuda_emu.cpp switches between them), so __syncthreads() is a real barrier and warp
// intrinsics are warp barriers with an exchange.
// Between barriers the threads run in an order permuted by the seed.  What the emulator reports that a GPU would
// not: reads of unwritten shared memory / workspaces (filled with NaN, integers with their max value, before each
// launch), out-of-range shared-array indices (C++ exception -> Python RuntimeError), barriers reached by only some
// threads of a block, warp intrinsics with inactive or mismatched lanes, writes past dynamic shared memory.
// Global memory is plain host memory here; tests/test_cuda_emulated_asan.py builds this module again with
// AddressSanitizer, which then reports any access outside a tensor torch allocated.  Every kernel instantiation that
// host code can launch registers itself at load time (KernelRegistration), so tests compare launched with launchable.
// What it cannot show: real concurrency (memory-model races, atomics under contention), timing, register pressure.
#pragma once

#ifndef MODI_EXT_EMULATE_CUDA
#error "cuda_emu.h is only for the emulated (host C++) build of the CUDA sources"
#endif

// Test-only defects, chosen at run time (set_injected_defect, emu_control.h; off unless a test turns one on):
// drop_sync (the first __syncthreads() of row_gemm_kernel is skipped), off_by_one (one shared-memory index of the row
// GEMM is shifted by one), global_oob (split_reduce_kernel reads one split past the end of its global workspace),
// wrong_scale (style_finish_kernel scales the style gradient by 1 + 2^-9: finite, only a tolerance can see it),
// split_edge (every split but the first starts one step late: the weight gradient drops one batch x time column, the
// row / transposed GEMMs one 16-deep k stage, at each inner split boundary; finite), wrong_slope
// (act_backward_kernel's negative-side slope is 2^-9 off: finite), mma_fragment_offset (the tensor-core forward's two
// B fragments per warp are read at each other's column offset: finite, outputs in the wrong columns) or mma_tile_edge
// (its gathered operand's k edge is one short: the last reduction row of each entity is dropped; finite),
// mma_wgrad_fragment_offset (the tensor-core weight gradient's two B fragments per warp swapped: finite, gradients in
// the wrong weight columns) or mma_wgrad_tile_edge (its batch x time range ends one column short in every split: one
// product of every gradient element dropped; finite).
#include "emu/emu_control.h"  // the MODI_EMU_INJECT_*_ID numbers

#include <c10/core/Device.h>
#include <c10/macros/Macros.h>
#include <c10/util/BFloat16.h>
#include <c10/util/Half.h>

#include <cmath>
#include <cstddef>
#include <cstdint>
#include <cstring>
#include <functional>
#include <limits>
#include <string>
#include <tuple>
#include <type_traits>
#include <utility>

#include "emu/emu_control.h"

// ------------------------------------------------------------------------------------------------ keywords
#define __global__
#define __device__
#define __host__
#define __forceinline__ inline
#define __launch_bounds__(...)
#define __align__(n) alignas(n)

struct dim3 {
  unsigned int x, y, z;
  constexpr dim3(unsigned int vx = 1, unsigned int vy = 1, unsigned int vz = 1) : x(vx), y(vy), z(vz) {}
};

// ------------------------------------------------------------------------------------------------ runtime shims
struct CUstream_st;
using cudaStream_t = CUstream_st*;
enum cudaError_t { cudaSuccess = 0, cudaErrorInvalidValue = 1 };
enum cudaDeviceAttr { cudaDevAttrMultiProcessorCount = 16 };

namespace modi_emu {
int sm_count();  // emulated multiprocessor count (settable: it steers the split-K choice of the weight gradient)
int injected_defect();  // the run-time test defect (MODI_EMU_INJECT_*_ID), 0 = none
}

inline cudaError_t cudaDeviceGetAttribute(int* v, cudaDeviceAttr attr, int /*device*/) {
  if (attr != cudaDevAttrMultiProcessorCount) return cudaErrorInvalidValue;
  *v = modi_emu::sm_count();
  return cudaSuccess;
}
inline cudaError_t cudaGetLastError() { return cudaSuccess; }

namespace modi_emu {
// While an emulated op runs, at::empty fills new tensors with NaN (integers: their max value), as torch's
// fill_uninitialized_memory does: outputs and workspaces a kernel reads before writing show up.
class PoisonScope {
 public:
  PoisonScope();
  ~PoisonScope();
  PoisonScope(const PoisonScope&) = delete;
  PoisonScope& operator=(const PoisonScope&) = delete;

 private:
  bool det_, warn_, fill_;
};
}  // namespace modi_emu

namespace c10 {
namespace cuda {
struct CUDAStream {
  operator cudaStream_t() const { return nullptr; }
};
inline CUDAStream getCurrentCUDAStream(c10::DeviceIndex = -1) { return {}; }
// The device guard of the host code: here the scope of one emulated op (poisoned allocations).
struct CUDAGuard {
  explicit CUDAGuard(c10::Device) {}
  modi_emu::PoisonScope poison;
};
}  // namespace cuda
}  // namespace c10
#define C10_CUDA_KERNEL_LAUNCH_CHECK() ((void)0)

// ------------------------------------------------------------------------------------------------ thread context
namespace modi_emu {

struct ThreadCtx {
  dim3 thread, block, bdim, gdim;
  int linear = 0;  // linear thread index in the block
};
extern thread_local ThreadCtx* g_ctx;

[[noreturn]] void fail(const std::string& what);  // abort the launch with a clear error
void syncthreads(int line);
// Warp exchange: deposit `n` bytes for this lane, wait for every lane of `mask`, read all 32 deposits into `all`.
// Returns the bit set of the lanes that took part.
unsigned warp_exchange(unsigned mask, const void* v, size_t n, void* all, int line);
void device_assert(const char* cond, const char* msg, const char* file, int line);

}  // namespace modi_emu

#define threadIdx (::modi_emu::g_ctx->thread)
#define blockIdx (::modi_emu::g_ctx->block)
#define blockDim (::modi_emu::g_ctx->bdim)
#define gridDim (::modi_emu::g_ctx->gdim)
#define warpSize 32
#define __syncthreads() ::modi_emu::syncthreads(__LINE__)

#undef CUDA_KERNEL_ASSERT
#undef CUDA_KERNEL_ASSERT_MSG
#define CUDA_KERNEL_ASSERT(cond) \
  do {                           \
    if (!(cond)) ::modi_emu::device_assert(#cond, "", __FILE__, __LINE__); \
  } while (0)
#define CUDA_KERNEL_ASSERT_MSG(cond, msg) \
  do {                                    \
    if (!(cond)) ::modi_emu::device_assert(#cond, msg, __FILE__, __LINE__); \
  } while (0)

// ------------------------------------------------------------------------------------------------ poison
namespace modi_emu {

template <typename T>
T poison() {
  if constexpr (std::is_same_v<T, c10::Half> || std::is_same_v<T, c10::BFloat16>) {
    return T(std::numeric_limits<float>::quiet_NaN());
  } else if constexpr (std::is_floating_point_v<T>) {
    return std::numeric_limits<T>::quiet_NaN();
  } else if constexpr (std::is_integral_v<T>) {
    return std::numeric_limits<T>::max();
  } else {
    T t;
    std::memset(static_cast<void*>(&t), 0xFF, sizeof(T));
    return t;
  }
}

// ------------------------------------------------------------------------------------------------ shared memory
// Block-local storage of one __shared__ array (fresh and poisoned for every block).
void* shared_storage(const char* name, int line, size_t bytes, void (*fill)(void*, size_t));
unsigned char* dynamic_shared();
[[noreturn]] void shared_oob(const char* name, int64_t i, size_t n);

template <typename T>
void fill_poison(void* p, size_t count) {
  T* q = static_cast<T*>(p);
  const T v = poison<T>();
  for (size_t i = 0; i < count; ++i) q[i] = v;
}

// Bounds-checked view of a (multi-dimensional) shared array: every subscript is checked against its extent.
template <typename T, size_t N>
struct SharedView {
  unsigned char* base;
  const char* name;
  decltype(auto) operator[](int64_t i) const {
    if (i < 0 || static_cast<size_t>(i) >= N) shared_oob(name, i, N);
    if constexpr (std::is_array_v<T>) {
      return SharedView<std::remove_extent_t<T>, std::extent_v<T>>{base + i * sizeof(T), name};
    } else {
      return *reinterpret_cast<T*>(base + i * sizeof(T));
    }
  }
};

template <typename Arr>
SharedView<std::remove_extent_t<Arr>, std::extent_v<Arr>> shared_array(const char* name, int line) {
  static_assert(std::is_array_v<Arr> && std::extent_v<Arr> > 0, "MODI_SHARED needs a sized array type");
  using Elem = std::remove_all_extents_t<Arr>;
  auto fill = [](void* p, size_t bytes) { fill_poison<Elem>(p, bytes / sizeof(Elem)); };
  return {static_cast<unsigned char*>(shared_storage(name, line, sizeof(Arr), fill)), name};
}

// ------------------------------------------------------------------------------------------------ launch
struct LaunchSpec {
  const char* name;  // __PRETTY_FUNCTION__ of the launch: names the kernel instantiation
  dim3 grid, block;
  size_t smem;
  std::function<void()> body;  // runs the kernel for the current thread context
};
void run_launch(const LaunchSpec& spec);
std::string kernel_name(const char* pretty);
bool register_kernel(const char* pretty);  // records kernel_name(pretty) in the set of launchable instantiations

// Every kernel instantiation some host code can launch registers itself when the module is loaded: launch_as
// odr-uses this static member, whose dynamic initialisation runs at load time.  So the tests can compare the
// instantiations a payload launched with all that exist (emu_control.h: registered_kernels).
template <auto Kernel>
struct KernelRegistration {
  static const char* pretty() { return __PRETTY_FUNCTION__; }
  static inline const bool registered = register_kernel(pretty());
};

template <auto Kernel, typename... P, typename... Args>
void launch_as(void (*)(P...), dim3 grid, dim3 block, size_t smem, Args&&... args) {
  (void)KernelRegistration<Kernel>::registered;
  // Arguments are converted to the parameter types once, as the CUDA runtime copies them into the launch.
  std::tuple<std::decay_t<P>...> params(std::forward<Args>(args)...);
  LaunchSpec spec{__PRETTY_FUNCTION__, grid, block, smem, [&params] { std::apply(Kernel, params); }};
  run_launch(spec);
}

template <auto Kernel, typename... Args>
void launch(dim3 grid, dim3 block, size_t smem, Args&&... args) {
  launch_as<Kernel>(Kernel, grid, block, smem, std::forward<Args>(args)...);
}

// ------------------------------------------------------------------------------------------------ warp intrinsics
inline int lane_id() { return g_ctx->linear & 31; }

template <typename T>
T shfl_from(unsigned mask, T v, int src, int line) {
  static_assert(sizeof(T) <= 8 && std::is_trivially_copyable_v<T>, "warp shuffle of a type wider than 8 bytes");
  unsigned char all[32 * 8];
  const unsigned took = warp_exchange(mask, &v, sizeof(T), all, line);
  if (src < 0 || src > 31 || !((took >> src) & 1u)) return poison<T>();  // undefined on a GPU
  T r;
  std::memcpy(&r, all + src * sizeof(T), sizeof(T));
  return r;
}

inline int segment_base(int width) { return (lane_id() / width) * width; }

}  // namespace modi_emu

template <typename T>
T __shfl_sync(unsigned mask, T v, int src, int width = 32, int line = __builtin_LINE()) {
  const int base = ::modi_emu::segment_base(width);
  return ::modi_emu::shfl_from(mask, v, base + ((src % width) + width) % width, line);
}
template <typename T>
T __shfl_xor_sync(unsigned mask, T v, int lane_mask, int width = 32, int line = __builtin_LINE()) {
  const int lane = ::modi_emu::lane_id(), base = ::modi_emu::segment_base(width);
  int src = lane ^ lane_mask;
  if (src < base || src >= base + width) src = lane;
  return ::modi_emu::shfl_from(mask, v, src, line);
}
template <typename T>
T __shfl_up_sync(unsigned mask, T v, unsigned delta, int width = 32, int line = __builtin_LINE()) {
  const int lane = ::modi_emu::lane_id(), base = ::modi_emu::segment_base(width);
  const int src = lane - static_cast<int>(delta);
  return ::modi_emu::shfl_from(mask, v, src < base ? lane : src, line);
}
template <typename T>
T __shfl_down_sync(unsigned mask, T v, unsigned delta, int width = 32, int line = __builtin_LINE()) {
  const int lane = ::modi_emu::lane_id(), base = ::modi_emu::segment_base(width);
  const int src = lane + static_cast<int>(delta);
  return ::modi_emu::shfl_from(mask, v, src >= base + width ? lane : src, line);
}
inline unsigned __ballot_sync(unsigned mask, int pred, int line = __builtin_LINE()) {
  int all[32];
  const int p = pred != 0;
  const unsigned took = ::modi_emu::warp_exchange(mask, &p, sizeof(int), all, line);
  unsigned r = 0;
  for (int l = 0; l < 32; ++l)
    if (((took >> l) & 1u) && all[l]) r |= 1u << l;
  return r;
}
inline int __any_sync(unsigned mask, int pred, int line = __builtin_LINE()) {
  return __ballot_sync(mask, pred, line) != 0;
}
inline int __all_sync(unsigned mask, int pred, int line = __builtin_LINE()) {
  return __ballot_sync(mask, pred, line) == mask;
}
inline void __syncwarp(unsigned mask = 0xffffffffu, int line = __builtin_LINE()) {
  int dummy = 0, all[32];
  (void)::modi_emu::warp_exchange(mask, &dummy, sizeof(int), all, line);
}

// ------------------------------------------------------------------------------------------------ atomics
// Fibers switch only at barriers, so a read-modify-write cannot be interleaved: plain host operations are atomic.
namespace modi_emu {
template <typename T, typename F>
T atomic_update(T* p, const F& f) {  // *p = f(*p); returns the old value
  const T old = *p;
  *p = f(old);
  return old;
}
}  // namespace modi_emu
template <typename T>
T atomicAdd(T* p, T v) {
  return ::modi_emu::atomic_update(p, [&](T old) { return static_cast<T>(old + v); });
}
template <typename T>
T atomicSub(T* p, T v) {
  return ::modi_emu::atomic_update(p, [&](T old) { return static_cast<T>(old - v); });
}
template <typename T>
T atomicMax(T* p, T v) {
  return ::modi_emu::atomic_update(p, [&](T old) { return v > old ? v : old; });
}
template <typename T>
T atomicMin(T* p, T v) {
  return ::modi_emu::atomic_update(p, [&](T old) { return v < old ? v : old; });
}
template <typename T>
T atomicExch(T* p, T v) {
  return ::modi_emu::atomic_update(p, [&](T) { return v; });
}
template <typename T>
T atomicCAS(T* p, T compare, T v) {
  return ::modi_emu::atomic_update(p, [&](T old) { return old == compare ? v : old; });
}
inline void __threadfence() {}
inline void __threadfence_block() {}

// ------------------------------------------------------------------------------------------------ loads and math
template <typename T>
T __ldg(const T* p) {
  return *p;
}
inline float __expf(float x) { return std::exp(x); }
inline float __logf(float x) { return std::log(x); }
inline float __sinf(float x) { return std::sin(x); }
inline float __cosf(float x) { return std::cos(x); }
inline float __powf(float x, float y) { return std::pow(x, y); }
inline float __fdividef(float x, float y) { return x / y; }
inline float __frcp_rn(float x) { return 1.0f / x; }
inline float __fsqrt_rn(float x) { return std::sqrt(x); }
inline float __fmaf_rn(float a, float b, float c) { return std::fma(a, b, c); }
inline double __fma_rn(double a, double b, double c) { return std::fma(a, b, c); }
inline float __saturatef(float x) { return x < 0.f ? 0.f : (x > 1.f ? 1.f : x); }
inline float rsqrtf(float x) { return 1.0f / std::sqrt(x); }
inline double rsqrt(double x) { return 1.0 / std::sqrt(x); }
inline float __half2float(c10::Half h) { return static_cast<float>(h); }
inline c10::Half __float2half(float f) { return c10::Half(f); }
inline float __bfloat162float(c10::BFloat16 h) { return static_cast<float>(h); }
inline c10::BFloat16 __float2bfloat16(float f) { return c10::BFloat16(f); }
