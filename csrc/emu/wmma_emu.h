// nvcuda::wmma for the emulator (cuda_emu.h): the 16 x 16 x 16 (bf16 / half) and 16 x 16 x 8 (precision::tf32)
// fragments of <mma.h> as plain arrays, so a tensor-core kernel compiles and runs unchanged on the CPU.
//
// A fragment's element-to-lane mapping is unspecified on a GPU, so here every lane holds the whole tile: kernels that
// only load, multiply, fill and store (no per-element access that assumes a mapping) compute the same thing.
// What the emulator checks, as a GPU requires and would not report: every lane of the warp takes part and passes the
// same pointer, leading dimension and layout (a warp barrier, like the other *_sync intrinsics); the pointer is
// 256-bit aligned; ldm is a multiple of 16 bytes.  Arithmetic: bf16 / half operands are exact in fp32, so products
// are exact and the sum over k runs in fp32 in k order (a tensor core sums in an unspecified order at fp32 or better;
// a tolerance of K fp32 ulps covers both).  TF32: fragment elements are floats that the kernel must have rounded with
// __float_to_tf32 (round to nearest, ties away from zero, to 10 explicit mantissa bits: cvt.rna.tf32.f32); the tensor
// core reads only those bits, so mma_sync here refuses an operand with any lower bit set instead of guessing what a GPU
// would make of it.  Products of two tf32 values (11-bit significands) are exact in fp32, as for bf16.
#pragma once

#ifndef MODI_EXT_EMULATE_CUDA
#error "wmma_emu.h is only for the emulated (host C++) build of the CUDA sources"
#endif

#include <c10/util/BFloat16.h>
#include <c10/util/Half.h>

#include <cstdint>
#include <cstring>
#include <initializer_list>
#include <string>
#include <type_traits>

using __nv_bfloat16 = c10::BFloat16;
using __half = c10::Half;

namespace nvcuda {
namespace wmma {

namespace precision {
struct tf32 {};  // operand format tag: elements are stored as float
}  // namespace precision

struct matrix_a {};
struct matrix_b {};
struct accumulator {};
struct row_major {};
struct col_major {};
enum layout_t { mem_row_major, mem_col_major };

template <typename T>
struct storage_element {
  using type = T;
};
template <>
struct storage_element<precision::tf32> {
  using type = float;
};

template <typename Use, int M, int N, int K, typename T, typename Layout = void>
struct fragment {
  static_assert(M == 16 && N == 16 && (K == 16 || K == 8),
                "the emulator models the 16 x 16 x 16 and 16 x 16 x 8 shapes");
  static_assert(std::is_same_v<Use, accumulator>
                    ? std::is_same_v<T, float>
                    : (K == 16 ? (std::is_same_v<T, __nv_bfloat16> || std::is_same_v<T, __half>)
                               : std::is_same_v<T, precision::tf32>),
                "emulated fragments: bf16 / half operands at k = 16, tf32 at k = 8, fp32 accumulators");
  using element_type = typename storage_element<T>::type;
  static constexpr int rows = std::is_same_v<Use, matrix_b> ? K : M;
  static constexpr int cols = std::is_same_v<Use, matrix_a> ? K : N;
  static constexpr int num_elements = rows * cols;
  element_type x[num_elements];  // row-major here; opaque to the kernels
};

// float -> tf32 (kept in a float): round to nearest on the 13 dropped mantissa bits, ties away from zero (adding half
// a tf32 ulp to the magnitude bits, then truncating; a carry into the exponent is the correct rounding up).  NaN and
// infinity pass unchanged.
inline float __float_to_tf32(float in) {
  uint32_t b;
  std::memcpy(&b, &in, sizeof(b));
  if ((b & 0x7f800000u) == 0x7f800000u) return in;
  b = (b + 0x1000u) & ~0x1fffu;
  float out;
  std::memcpy(&out, &b, sizeof(out));
  return out;
}

}  // namespace wmma
}  // namespace nvcuda

namespace modi_emu {
[[noreturn]] void fail(const std::string& what);
unsigned warp_exchange(unsigned mask, const void* v, size_t n, void* all, int line);

// One warp-collective WMMA call: all 32 lanes, the same arguments, an aligned pointer and ldm (CUDA's rules).
inline void wmma_collective(const char* what, const void* p, unsigned ldm, int layout, size_t elem, int line) {
  // two exchanges of 8 bytes (the most one warp exchange carries): the pointer, then ldm and the layout
  const uint64_t mine[2] = {static_cast<uint64_t>(reinterpret_cast<uintptr_t>(p)),
                            (uint64_t(ldm) << 32) | static_cast<uint32_t>(layout)};
  for (const uint64_t v : mine) {
    uint64_t all[32];
    const unsigned took = warp_exchange(0xffffffffu, &v, sizeof(v), all, line);
    if (took != 0xffffffffu) fail(std::string(what) + ": not every lane of the warp took part");
    for (const uint64_t a : all) {
      if (a != v) fail(std::string(what) + " at line " + std::to_string(line) + ": lanes passed different arguments");
    }
  }
  if (p && reinterpret_cast<uintptr_t>(p) % 32) {
    fail(std::string(what) + " at line " + std::to_string(line) + ": pointer not 256-bit aligned");
  }
  if ((ldm * elem) % 16) {
    fail(std::string(what) + " at line " + std::to_string(line) + ": ldm " + std::to_string(ldm) +
         " is not a multiple of 16 bytes");
  }
}

template <typename Frag>
constexpr bool kColMajor = false;
template <typename Use, int M, int N, int K, typename T>
constexpr bool kColMajor<nvcuda::wmma::fragment<Use, M, N, K, T, nvcuda::wmma::col_major>> = true;
}  // namespace modi_emu

namespace nvcuda {
namespace wmma {

template <typename Use, int M, int N, int K, typename T, typename L, typename V>
void fill_fragment(fragment<Use, M, N, K, T, L>& f, const V& v, int line = __builtin_LINE()) {
  ::modi_emu::wmma_collective("fill_fragment", nullptr, 0, 0, 1, line);
  using V2 = typename fragment<Use, M, N, K, T, L>::element_type;
  for (int i = 0; i < f.num_elements; ++i) f.x[i] = static_cast<V2>(v);
}

// matrix_a / matrix_b: element (r, c) at p[r * ldm + c] (row_major) or p[c * ldm + r] (col_major).
template <typename Use, int M, int N, int K, typename T, typename L>
void load_matrix_sync(fragment<Use, M, N, K, T, L>& f, const typename fragment<Use, M, N, K, T, L>::element_type* p,
                      unsigned ldm, int line = __builtin_LINE()) {
  static_assert(!std::is_same_v<Use, accumulator>, "accumulators load with a layout_t");
  using F = fragment<Use, M, N, K, T, L>;
  constexpr bool col = ::modi_emu::kColMajor<F>;
  ::modi_emu::wmma_collective("load_matrix_sync", p, ldm, col, sizeof(*p), line);
  for (int r = 0; r < F::rows; ++r)
    for (int c = 0; c < F::cols; ++c) f.x[r * F::cols + c] = col ? p[c * ldm + r] : p[r * ldm + c];
}

template <int K>
void load_matrix_sync(fragment<accumulator, 16, 16, K, float>& f, const float* p, unsigned ldm, layout_t layout,
                      int line = __builtin_LINE()) {
  ::modi_emu::wmma_collective("load_matrix_sync", p, ldm, layout, sizeof(float), line);
  for (int r = 0; r < 16; ++r)
    for (int c = 0; c < 16; ++c) f.x[r * 16 + c] = layout == mem_col_major ? p[c * ldm + r] : p[r * ldm + c];
}

template <int K>
void store_matrix_sync(float* p, const fragment<accumulator, 16, 16, K, float>& f, unsigned ldm, layout_t layout,
                       int line = __builtin_LINE()) {
  ::modi_emu::wmma_collective("store_matrix_sync", p, ldm, layout, sizeof(float), line);
  for (int r = 0; r < 16; ++r)
    for (int c = 0; c < 16; ++c) (layout == mem_col_major ? p[c * ldm + r] : p[r * ldm + c]) = f.x[r * 16 + c];
}

// d = a b + c: exact products of the 16-bit (or tf32) operands, summed in fp32.
template <int K, typename T, typename LA, typename LB>
void mma_sync(fragment<accumulator, 16, 16, K, float>& d, const fragment<matrix_a, 16, 16, K, T, LA>& a,
              const fragment<matrix_b, 16, 16, K, T, LB>& b, const fragment<accumulator, 16, 16, K, float>& c,
              int line = __builtin_LINE()) {
  ::modi_emu::wmma_collective("mma_sync", nullptr, 0, 0, 1, line);
  if constexpr (std::is_same_v<T, precision::tf32>) {
    for (const float* x : {a.x, b.x})
      for (int i = 0; i < 16 * K; ++i) {
        if (!(__float_to_tf32(x[i]) == x[i]) && x[i] == x[i]) {
          ::modi_emu::fail("mma_sync at line " + std::to_string(line) +
                           ": a tf32 operand was not rounded with __float_to_tf32 (its low 13 mantissa bits are set)");
        }
      }
  }
  float out[256];
  for (int i = 0; i < 16; ++i)
    for (int j = 0; j < 16; ++j) {
      float s = c.x[i * 16 + j];
      for (int k = 0; k < K; ++k) s += static_cast<float>(a.x[i * K + k]) * static_cast<float>(b.x[k * 16 + j]);
      out[i * 16 + j] = s;
    }
  for (int i = 0; i < 256; ++i) d.x[i] = out[i];
}

}  // namespace wmma
}  // namespace nvcuda
