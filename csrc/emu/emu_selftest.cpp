// Test-only kernels that break the CUDA programming rules on purpose, so tests can show that the emulator reports
// each violation (and that its warp intrinsics and atomics compute what CUDA defines).  Op: emu_selftest(name, n).
#include <torch/library.h>

#include <ATen/ATen.h>

#include "common/cuda_common.cuh"
#include "common/wmma.cuh"

namespace modi_ext {
namespace {

constexpr unsigned kFull = 0xffffffffu;

// Half of the block skips a barrier the other half waits at.
__global__ void divergent_barrier_kernel(float* out) {
  if (threadIdx.x < blockDim.x / 2) __syncthreads();
  out[threadIdx.x] = 1.f;
}

// Thread 31 writes s[32] of a 32-element shared array.
__global__ void shared_oob_kernel(float* out) {
  MODI_SHARED(float, s, [32]);
  s[threadIdx.x + 1] = 1.f;
  __syncthreads();
  out[threadIdx.x] = s[threadIdx.x];
}

// Reads the half of a shared array nobody wrote: NaN.
__global__ void unwritten_shared_kernel(float* out) {
  MODI_SHARED(float, s, [64]);
  s[threadIdx.x] = static_cast<float>(threadIdx.x);
  __syncthreads();
  out[threadIdx.x] = s[threadIdx.x + 32];
}

// Upper half-warps exit while the lower ones shuffle with a full mask.
__global__ void warp_exits_kernel(float* out) {
  if ((threadIdx.x & 31) >= 16) return;
  out[threadIdx.x] = __shfl_xor_sync(kFull, 1.f, 1);
}

// The last thread writes one float past the dynamic shared memory of the launch.
__global__ void dynamic_overflow_kernel(float* out) {
  MODI_DYNAMIC_SHARED(float, d);
  d[threadIdx.x] = 1.f;
  out[threadIdx.x] = 0.f;
}

// A missing barrier between a write and a neighbour's read: the result depends on the thread order.
__global__ void race_kernel(float* out) {
  MODI_SHARED(float, s, [1024]);
  s[threadIdx.x] = 0.f;
  __syncthreads();
  s[threadIdx.x] = static_cast<float>(threadIdx.x + 1);
  out[threadIdx.x] = s[(threadIdx.x + 1) % blockDim.x];
}

// Warp intrinsics and atomics, 8 values per thread (+ one counter at the end).
__global__ void intrinsics_kernel(float* out) {
  const int t = threadIdx.x, lane = t & 31;
  const float v = static_cast<float>(lane);
  float* o = out + 8 * t;
  o[0] = __shfl_xor_sync(kFull, v, 5);
  o[1] = __shfl_up_sync(kFull, v, 3);
  o[2] = __shfl_down_sync(kFull, v, 3);
  o[3] = __shfl_sync(kFull, v, 7);
  const unsigned b = __ballot_sync(kFull, lane % 3 == 0);
  o[4] = static_cast<float>(b & 0xffffu);
  o[5] = static_cast<float>(b >> 16);
  o[6] = static_cast<float>(__any_sync(kFull, lane == 31) + 2 * __all_sync(kFull, lane < 31));
  o[7] = cuda::warp_sum(v);
  atomicAdd(out + 8 * blockDim.x, 1.f);
}

// One warp multiplies TF32 fragments whose elements were never rounded with __float_to_tf32 (1 + 2^-20 has mantissa
// bits below TF32's 10): the tensor core would read only the high bits, so the emulator refuses the operands.
__global__ void tf32_unrounded_kernel(float* out) {
  namespace wmma = nvcuda::wmma;
  MODI_SHARED_WMMA(float, s, [16][8]);
  MODI_SHARED_WMMA(float, c, [16][16]);
  for (int i = threadIdx.x; i < 16 * 8; i += 32) s[i / 8][i % 8] = 1.0f + 0x1p-20f;
  __syncthreads();
  wmma::fragment<wmma::matrix_a, 16, 16, 8, wmma::precision::tf32, wmma::row_major> a;
  wmma::fragment<wmma::matrix_b, 16, 16, 8, wmma::precision::tf32, wmma::col_major> b;
  wmma::fragment<wmma::accumulator, 16, 16, 8, float> acc;
  wmma::load_matrix_sync(a, &s[0][0], 8);
  wmma::load_matrix_sync(b, &s[0][0], 8);
  wmma::fill_fragment(acc, 0.0f);
  wmma::mma_sync(acc, a, b, acc);
  wmma::store_matrix_sync(&c[0][0], acc, 16, wmma::mem_row_major);
  __syncthreads();
  out[threadIdx.x] = c[0][threadIdx.x % 16];
}

at::Tensor emu_selftest(c10::string_view name, int64_t threads) {
  TORCH_CHECK(threads >= 1 && threads <= 1024, "threads must be in [1, 1024]");
  const modi_emu::PoisonScope poison;
  at::Tensor out = at::empty({threads * 8 + 1}, at::kFloat);
  out.narrow(0, threads * 8, 1).zero_();
  float* p = out.data_ptr<float>();
  const unsigned n = static_cast<unsigned>(threads);
  const cudaStream_t stream = nullptr;
  if (name == "poisoned_empty") {  // what the host code's at::empty returns inside an emulated op
    return at::empty({threads}, at::kFloat);
  } else if (name == "poisoned_empty_int") {
    return at::empty({threads}, at::kInt);
  } else if (name == "divergent_barrier") {
    MODI_LAUNCH(divergent_barrier_kernel, 1, n, 0, stream, p);
  } else if (name == "shared_oob") {
    MODI_LAUNCH(shared_oob_kernel, 1, n, 0, stream, p);
  } else if (name == "unwritten_shared") {
    MODI_LAUNCH(unwritten_shared_kernel, 1, n, 0, stream, p);
  } else if (name == "warp_exits") {
    MODI_LAUNCH(warp_exits_kernel, 1, n, 0, stream, p);
  } else if (name == "dynamic_overflow") {
    MODI_LAUNCH(dynamic_overflow_kernel, 1, n, (n - 1) * sizeof(float), stream, p);
  } else if (name == "race") {
    MODI_LAUNCH(race_kernel, 1, n, 0, stream, p);
  } else if (name == "tf32_unrounded") {
    MODI_LAUNCH(tf32_unrounded_kernel, 1, n, 0, stream, p);
  } else if (name == "intrinsics") {
    MODI_LAUNCH(intrinsics_kernel, 1, n, 0, stream, p);
  } else {
    TORCH_CHECK(false, "unknown emulator self-test '", std::string(name), "'");
  }
  return out;
}

}  // namespace

// No tensor arguments, so no backend key to dispatch on: the one kernel serves every call.
TORCH_LIBRARY_IMPL(MODI_CUDA_LIB, CompositeExplicitAutograd, m) { m.impl("emu_selftest", &emu_selftest); }

}  // namespace modi_ext
