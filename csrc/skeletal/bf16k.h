// The bfloat16 path of the skeletal operators' CPU kernels: bf16 operands, fp32 accumulation, bf16 results.
//
// The same indirect-GEMM design as the fp32 fast path (fastk.h), with the contraction paired for vdpbf16ps, which
// adds the two products of a bf16 pair into one fp32 lane:
// - NN products (forward, input gradients) pair the contraction along channels: the column layout's row-pair
//   (phase, channel pair, entity) holds x_c(col), x_{c+1}(col) adjacent (an odd channel count gets a zero channel),
//   so a time shift u is still a pointer offset (2u elements) and 32 bf16 loaded are 16 columns of a K-pair.  The
//   weight is packed as 32-bit pairs, one broadcast per output row and K-pair.
// - Weight gradients contract over columns (batch x time), which are adjacent in a plain (unpaired) row already:
//   one side is broadcast as (a[n], a[n+1]) from plain rows, the other transposed into 32-row blocks of column
//   pairs, as wgrad512 does in fp32.
// The micro-kernels run on AVX-512-BF16 where the CPU has it, else (or with MODI_EXT_CPU_KERNEL=bf16emu) on a
// plain-C++ emulation with the same layout: bf16 x bf16 products are exact in fp32, summed in fp32.  Style,
// demodulation scale and bias come in bf16 as x does (the ops take one dtype); the products of x and the style are
// rounded to bf16 when laid out, the epilogues (scale, bias, fold, blur) run in fp32 and round once.
#pragma once

#include <cstdint>
#include <cstring>

#include "skeletal/cpu_common.h"

namespace modi_ext {
namespace skeletal {
namespace bf16k {

using bf16 = uint16_t;  // raw bfloat16 bits (at::BFloat16's storage)

inline float to_f32(bf16 v) {
  const uint32_t u = uint32_t(v) << 16;
  float f;
  std::memcpy(&f, &u, 4);
  return f;
}
// Round to nearest even, as at::BFloat16 does (NaN stays NaN).
inline bf16 to_bf16(float f) {
  uint32_t u;
  std::memcpy(&u, &f, 4);
  if ((u & 0x7fffffffu) > 0x7f800000u) return bf16((u >> 16) | 0x40u);
  u += 0x7fffu + ((u >> 16) & 1u);
  return bf16(u >> 16);
}

// The micro-kernels this process runs: true for AVX-512-BF16 (CPUID), false for the plain-C++ emulation.
bool use_avx512bf16();
// "avx512_bf16" or "emulated", and why ("MODI_EXT_CPU_KERNEL=bf16emu" / "no avx512_bf16 on this CPU").
const char* kernel_name();

void forward(const Geo& g, const Csr& csr, const bf16* x, const bf16* w, const bf16* bias, const bf16* style,
             const bf16* scale, bf16* y);

// Gradients; any of gx, gw, gb, gs, gd may be null (not wanted).
void backward(const Geo& g, const Csr& csr, const bf16* gy, const bf16* out, const bf16* x, const bf16* w,
              const bf16* bias, const bf16* style, const bf16* scale, bf16* gx, bf16* gw, bf16* gb, bf16* gs,
              bf16* gd);

// ---- kernels (bf16k_gemm.cpp)

// acc (M x ldacc) = A * pointer rows over columns [0, round_up(N, 48)): a[kp * M + m] is row m's bf16 pair of
// K-pair kp; ptr[kp] points to K-pair kp's row of interleaved pairs, column n at ptr[kp][2n], ptr[kp][2n + 1].
void nn_gemm(const uint32_t* a, int64_t M, int64_t Kp, const bf16* const* ptr, int64_t N, float* acc,
             int64_t ldacc);
constexpr int64_t kColTile = 48;

// C[i * ci + j * cj] = sum_{n < N} a_i[n] * b_j[n * bs] (rounded to bf16), i < Ma, j < Mb: a rows plain (read as
// pairs, up to a_i[N] when N is odd), b rows with element stride bs, transposed into 32-row blocks (scratch:
// 32 * (N + 1) bf16).
void wgrad(const bf16* const* a, int64_t Ma, const bf16* const* b, int64_t bs, int64_t Mb, int64_t N, bf16* C,
           int64_t ci, int64_t cj, uint32_t* scratch);

// Row conversions to bf16 (AVX-512-BF16 vcvtneps2bf16 with the kernels, else to_bf16), chosen once per pass:
// affine: dst[i] = bf16(src[i] * f + bb); pairs: dst[2i] = bf16(a[i]), dst[2i + 1] = bf16(b[i]) (b null: 0).
// Reductions, in 16 fixed lanes (the same sums whatever the thread count): dot = sum a[i] * x[i];
// gy_y = sum g[i] * (y[i] - bb); sum = sum g[i].
struct Cvt {
  void (*affine)(const float* src, bf16* dst, int64_t n, float f, float bb);
  void (*pairs)(const float* a, const float* b, bf16* dst, int64_t n);
  float (*dot)(const float* a, const bf16* x, int64_t n);
  float (*gy_y)(const bf16* g, const bf16* y, int64_t n, float bb);
  float (*sum)(const bf16* g, int64_t n);
  // From bf16 rows: dst[i * W + j] = bf16(f_j * src_j[i]) for channels j < W (W = 2: src1 null gives 0).
  void (*scaled_pairs)(const bf16* a, const bf16* b, float fa, float fb, bf16* dst, int64_t n);
  void (*scaled_row)(const bf16* a, float fa, bf16* dst, int64_t n);
};
Cvt cvt_fns();

}  // namespace bf16k
}  // namespace skeletal
}  // namespace modi_ext
