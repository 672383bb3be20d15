// The fp32 fast path of the skeletal operators' CPU kernels: its entry points (fastk.cpp: the passes, which lay the
// operands out and run the products) and the GEMM drivers they call (fastk_gemm.cpp: the AVX2 / AVX-512 kernels).
//
// Indirect GEMM on AVX2/FMA (AVX-512 variants where the CPU has them), used for float32 when the CPU has AVX2
// (MODI_EXT_CPU_KERNEL=blas forces the BLAS path of cpu.cpp, =avx2 the AVX2 kernels).  Instead of gathering a
// (K x N) panel per entity and letting BLAS repack it, every input is laid out once per call in "column" form: row
// (phase, channel, entity) holds all batch elements back to back, each padded in time (zero / reflect, or the front
// zeros of a transposed conv) and, for stride 2, split into even/odd phases.  A time shift u is then just a pointer
// offset, so an entity's operand is a table of K row pointers, and the register-blocked kernels of fastk_gemm.cpp
// read those rows in place: columns = batch x padded time, the long GEMM side.
#pragma once

#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <vector>

#include "skeletal/cpu_common.h"

namespace modi_ext {
namespace skeletal {
namespace fastk {

constexpr int64_t MR = 4, NR = 24;  // NN tile: 4 output rows x 24 columns = 12 ymm accumulators
constexpr int64_t TM = 4, TK = 3;   // NT tile: 4 x 3 dot products, 8 lanes each
constexpr int64_t kNarrowRows = 10; // weight-gradient rows up to which the indirect NT kernel beats BLAS (measured:
                                    // 9 rows 1.2x faster at MoDi's batch 16, 12 rows 1.4x slower; GANimator 3-9)

inline bool wanted() {
#if defined(__x86_64__)
  static const bool cpu = __builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma");
  const char* env = std::getenv("MODI_EXT_CPU_KERNEL");
  if (env != nullptr && std::strcmp(env, "blas") == 0) return false;
  return cpu;
#else
  return false;
#endif
}

// The fewest frames (the product's columns per batch element: output frames of conv / down, input frames of up) at
// which a pass takes the indirect kernels rather than cpu.cpp's gather + BLAS path.  Below 16 the padded columns
// (2h per element) usually cost more than the kernels gain, with two exceptions at MoDi's coarse levels (measured
// on AVX-512 and AVX2: docs/results.md): the up forward wins at every size, since the BLAS path there gathers a
// panel and folds each row apart; and the conv backward wins from 8 frames (at 4 it loses).
inline int64_t min_frames(SkeletalKind kind, bool backward) {
  if (kind == kUp && !backward) return 1;
  if (kind == kConv && backward) return 8;
  return 16;
}

inline int64_t round_up(int64_t a, int64_t m) { return (a + m - 1) / m * m; }

// The AVX-512 kernels: where the CPU has AVX-512F, unless MODI_EXT_CPU_KERNEL=avx2.
inline bool use512() {
#if defined(__x86_64__)
  static const bool cpu = __builtin_cpu_supports("avx512f");
  if (!cpu) return false;
  const char* env = std::getenv("MODI_EXT_CPU_KERNEL");
  return env == nullptr || std::strcmp(env, "avx2") != 0;
#else
  return false;
#endif
}

// The column step of nn_gemm's kernels: a pair of NR tiles on AVX-512, one on AVX2 (batch_tile's col_tile).
inline int64_t nn_col_tile() {
  return use512() ? 2 * NR : NR;
}

// ---- GEMM drivers (fastk_gemm.cpp)

// acc (round_up(M,4) x ldacc) = packed A (panels of 4 rows x K) * pointer rows, columns [0, N) (tiles of 24; the
// columns past N are computed and ignored, rows past M are left untouched).  AVX2: column chunks keep the
// pointed-to data in L2 (the AVX-512 kernels prefetch it instead).
void nn_gemm(const float* apack, int64_t M, int64_t K, const float* const* ptr, int64_t N, float* acc, int64_t ldacc);

// AVX-512, M <= kDirectRows: acc (M x ldacc) = A (M rows of K, row r at a + r * lda: the compact weight read in
// place) * pointer rows, columns [0, N) in tiles of 48 (24 for an odd last one).  No packing pass: with GANimator's
// 5-9 output channels packing the weight was ~10% of a forward call at 129 frames, done anew on every call.
constexpr int64_t kDirectRows = 9;
void nn_gemm_direct(const float* a, int64_t lda, int64_t M, int64_t K, const float* const* ptr, int64_t N,
                    float* acc, int64_t ldacc);

// C (M x K, ldc) = L (M pointer rows) * P^T (K pointer rows) over columns [0, N), AVX-512 only: L is transposed
// once into 32-wide blocks (scratch: round_up(M, 32) * N floats) and every 12 rows of P are broadcast against it --
// an NN product, which reaches the FMA throughput that the dot-product form (nt_gemm) cannot for wide layers.
void wgrad512(const float* const* l, int64_t M, const float* const* p, int64_t K, int64_t N, float* C, int64_t ldc,
              float* scratch);

// C (M x K, ldc) += L (M pointer rows) * P^T (K pointer rows), contraction over columns [0, N).
void nt_gemm(const float* const* l, int64_t M, const float* const* p, int64_t K, int64_t N, float* C, int64_t ldc);

// ---- row passes (fastk_rows.cpp)

// One output row of an up pass: the padded row P (length L + 2h; its even positions in a0 and odd ones in a1, read
// in place) folded onto [0, L), blurred with [1 3 3 1] / 4, times fs plus bb, into dst.  The same terms as fold_row
// + blur_row of cpu_common.h, vectorised at the kernels' ISA.  up_row_fn() picks the ISA once (the choice reads the
// environment), so a pass calls it once, not per row.
using UpRowFn = void (*)(const float* a0, const float* a1, float* dst, int64_t L, int64_t h, bool reflect, float fs,
                         float bb);
UpRowFn up_row_fn();

// ---- the passes (fastk.cpp)

// y = the forward of a conv / down / up call (fp32), with its style, demodulation and bias.
void forward(const Geo& g, const Csr& csr, const float* x, const float* w, const float* bias,
             const Scale<float>& sty, const float* scale, float* y);

// Input, style and weight gradients.  For conv/down the output gradient is gy * gsc (gsc = d); for up it is
// blur^T(gy) * gsc on the fine grid, formed while the operand rows are laid out.  gx / gs_part / gw may be null.
// `prep` and `compute` carry the caller's phases (bias / scale gradients, a BLAS weight gradient, ...), run in the
// same two regions as this pass's own.
void backward(const Geo& g, const Csr& csr, const float* gy, const Scale<float>& gsc, const float* x, const float* w,
              const float* style, float* gx, float* gw, float* gs_part, std::vector<Phase> prep,
              std::vector<Phase> compute);

}  // namespace fastk
}  // namespace skeletal
}  // namespace modi_ext
