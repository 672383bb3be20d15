// The micro-kernels of the bf16 path (bf16k.h): AVX-512-BF16 (vdpbf16ps) and a plain-C++ emulation that reads the
// same layouts, so the indexing is tested on any CPU.
#include <algorithm>
#include <cstdint>
#include <cstdlib>
#include <cstring>

#if defined(__x86_64__)
#include <immintrin.h>
#endif

#include "skeletal/bf16k.h"

namespace modi_ext {
namespace skeletal {
namespace bf16k {
namespace {

inline float lo(uint32_t p) { return to_f32(bf16(p & 0xffffu)); }
inline float hi(uint32_t p) { return to_f32(bf16(p >> 16)); }

// Emulated vdpbf16ps lane: acc += a.hi * b.hi, then += a.lo * b.lo (the instruction's order); the products of
// two bf16 are exact in fp32.
inline float dp_lane(float acc, uint32_t a, float b0, float b1) {
  acc += hi(a) * b1;
  acc += lo(a) * b0;
  return acc;
}

template <int R>
void nn_emu(int64_t Kp, const uint32_t* a, int64_t lda, const bf16* const* ptr, int64_t col, float* c, int64_t ldc) {
  float acc[R][kColTile];
  for (int r = 0; r < R; ++r) std::fill(acc[r], acc[r] + kColTile, 0.f);
  for (int64_t kp = 0; kp < Kp; ++kp) {
    const bf16* p = ptr[kp] + 2 * col;
    float b0[kColTile], b1[kColTile];
    for (int j = 0; j < kColTile; ++j) b0[j] = to_f32(p[2 * j]), b1[j] = to_f32(p[2 * j + 1]);
    for (int r = 0; r < R; ++r) {
      const uint32_t av = a[kp * lda + r];
      for (int j = 0; j < kColTile; ++j) acc[r][j] = dp_lane(acc[r][j], av, b0[j], b1[j]);
    }
  }
  for (int r = 0; r < R; ++r) std::copy(acc[r], acc[r] + kColTile, c + r * ldc);
}

template <int R>
void wg_emu(int64_t Np, const bf16* const* a, const uint32_t* lt, float* out) {
  float acc[R][32];
  for (int r = 0; r < R; ++r) std::fill(acc[r], acc[r] + 32, 0.f);
  for (int64_t np = 0; np < Np; ++np) {
    const uint32_t* g = lt + np * 32;
    for (int r = 0; r < R; ++r) {
      uint32_t av;
      std::memcpy(&av, a[r] + 2 * np, 4);
      for (int j = 0; j < 32; ++j) acc[r][j] = dp_lane(acc[r][j], av, lo(g[j]), hi(g[j]));
    }
  }
  for (int r = 0; r < R; ++r) std::copy(acc[r], acc[r] + 32, out + r * 32);
}

#if defined(__x86_64__)
#define MODI_BF16_TARGET __attribute__((target("avx512f,avx512bw,avx512bf16")))
// As the fp32 kernels: every step reads a strip of a different pointer row, more streams than the hardware
// prefetchers follow, so each step asks for the strip kPrefetchSteps ahead.
constexpr int64_t kPrefetchSteps = 16;

// R rows (up to 9: 27 accumulators) x 48 columns (3 vectors of 16 column pairs).
template <int R>
MODI_BF16_TARGET void nn_avx(int64_t Kp, const uint32_t* a, int64_t lda, const bf16* const* ptr, int64_t col,
                             float* c, int64_t ldc) {
  __m512 acc[R][3];
  for (int r = 0; r < R; ++r) acc[r][0] = acc[r][1] = acc[r][2] = _mm512_setzero_ps();
  for (int64_t kp = 0; kp < Kp; ++kp) {
    const bf16* p = ptr[kp] + 2 * col;
    if (kp + kPrefetchSteps < Kp) {
      const char* q = reinterpret_cast<const char*>(ptr[kp + kPrefetchSteps] + 2 * col);
      _mm_prefetch(q, _MM_HINT_T0);
      _mm_prefetch(q + 64, _MM_HINT_T0);
      _mm_prefetch(q + 128, _MM_HINT_T0);
      _mm_prefetch(q + 191, _MM_HINT_T0);
    }
    const __m512bh b0 = (__m512bh)_mm512_loadu_si512(p), b1 = (__m512bh)_mm512_loadu_si512(p + 32),
                   b2 = (__m512bh)_mm512_loadu_si512(p + 64);
    const uint32_t* ak = a + kp * lda;
    for (int r = 0; r < R; ++r) {
      const __m512bh av = (__m512bh)_mm512_set1_epi32(static_cast<int>(ak[r]));
      acc[r][0] = _mm512_dpbf16_ps(acc[r][0], av, b0);
      acc[r][1] = _mm512_dpbf16_ps(acc[r][1], av, b1);
      acc[r][2] = _mm512_dpbf16_ps(acc[r][2], av, b2);
    }
  }
  for (int r = 0; r < R; ++r) {
    _mm512_storeu_ps(c + r * ldc, acc[r][0]);
    _mm512_storeu_ps(c + r * ldc + 16, acc[r][1]);
    _mm512_storeu_ps(c + r * ldc + 32, acc[r][2]);
  }
}

// out[r][0:32] = sum_np pair(a_r, np) . lt[np][0:32]: R broadcast rows (up to 12: 24 accumulators).
template <int R>
MODI_BF16_TARGET void wg_avx(int64_t Np, const bf16* const* a, const uint32_t* lt, float* out) {
  __m512 acc[R][2];
  for (int r = 0; r < R; ++r) acc[r][0] = acc[r][1] = _mm512_setzero_ps();
  const bf16* ar[R];
  for (int r = 0; r < R; ++r) ar[r] = a[r];
  for (int64_t np = 0; np < Np; ++np) {
    const __m512bh g0 = (__m512bh)_mm512_loadu_si512(lt + np * 32),
                   g1 = (__m512bh)_mm512_loadu_si512(lt + np * 32 + 16);
    for (int r = 0; r < R; ++r) {
      int v;
      std::memcpy(&v, ar[r] + 2 * np, 4);
      const __m512bh av = (__m512bh)_mm512_set1_epi32(v);
      acc[r][0] = _mm512_dpbf16_ps(acc[r][0], av, g0);
      acc[r][1] = _mm512_dpbf16_ps(acc[r][1], av, g1);
    }
  }
  for (int r = 0; r < R; ++r) {
    _mm512_storeu_ps(out + r * 32, acc[r][0]);
    _mm512_storeu_ps(out + r * 32 + 16, acc[r][1]);
  }
}
#define MODI_BF16_ROW_TARGET __attribute__((target("avx512f,avx512bw,avx512vl,avx512bf16")))
MODI_BF16_ROW_TARGET void affine_avx(const float* src, bf16* dst, int64_t n, float f, float bb) {
  const __m512 vf = _mm512_set1_ps(f), vb = _mm512_set1_ps(bb);
  int64_t i = 0;
  for (; i + 16 <= n; i += 16) {
    const __m256bh r = _mm512_cvtneps_pbh(_mm512_fmadd_ps(_mm512_loadu_ps(src + i), vf, vb));
    _mm256_storeu_si256(reinterpret_cast<__m256i*>(dst + i), (__m256i)r);
  }
  if (i < n) {
    const __mmask16 m = static_cast<__mmask16>((1u << (n - i)) - 1u);
    const __m256bh r = _mm512_cvtneps_pbh(_mm512_fmadd_ps(_mm512_maskz_loadu_ps(m, src + i), vf, vb));
    _mm256_mask_storeu_epi16(dst + i, m, (__m256i)r);
  }
}
MODI_BF16_ROW_TARGET void pairs_avx(const float* a, const float* b, bf16* dst, int64_t n) {
  int64_t i = 0;
  for (; i + 16 <= n; i += 16) {
    const __m512i lo = _mm512_cvtepu16_epi32((__m256i)_mm512_cvtneps_pbh(_mm512_loadu_ps(a + i)));
    const __m512i hi = b ? _mm512_slli_epi32(_mm512_cvtepu16_epi32((__m256i)_mm512_cvtneps_pbh(_mm512_loadu_ps(b + i))), 16)
                         : _mm512_setzero_si512();
    _mm512_storeu_si512(dst + 2 * i, _mm512_or_si512(lo, hi));
  }
  for (; i < n; ++i) {
    dst[2 * i] = to_bf16(a[i]);
    dst[2 * i + 1] = b ? to_bf16(b[i]) : bf16(0);
  }
}
MODI_BF16_ROW_TARGET inline __m512 load_bf(const bf16* p, __mmask16 m) {
  return _mm512_castsi512_ps(_mm512_slli_epi32(_mm512_cvtepu16_epi32(_mm256_maskz_loadu_epi16(m, p)), 16));
}
MODI_BF16_ROW_TARGET float dot_avx(const float* a, const bf16* x, int64_t n) {
  __m512 acc = _mm512_setzero_ps();
  for (int64_t i = 0; i < n; i += 16) {
    const __mmask16 m = n - i >= 16 ? __mmask16(0xffff) : static_cast<__mmask16>((1u << (n - i)) - 1u);
    acc = _mm512_fmadd_ps(_mm512_maskz_loadu_ps(m, a + i), load_bf(x + i, m), acc);
  }
  return _mm512_reduce_add_ps(acc);
}
MODI_BF16_ROW_TARGET float gy_y_avx(const bf16* g, const bf16* y, int64_t n, float bb) {
  __m512 acc = _mm512_setzero_ps();
  const __m512 vb = _mm512_set1_ps(bb);
  for (int64_t i = 0; i < n; i += 16) {
    const __mmask16 m = n - i >= 16 ? __mmask16(0xffff) : static_cast<__mmask16>((1u << (n - i)) - 1u);
    acc = _mm512_fmadd_ps(load_bf(g + i, m), _mm512_maskz_sub_ps(m, load_bf(y + i, m), vb), acc);
  }
  return _mm512_reduce_add_ps(acc);
}
MODI_BF16_ROW_TARGET float sum_avx(const bf16* g, int64_t n) {
  __m512 acc = _mm512_setzero_ps();
  for (int64_t i = 0; i < n; i += 16) {
    const __mmask16 m = n - i >= 16 ? __mmask16(0xffff) : static_cast<__mmask16>((1u << (n - i)) - 1u);
    acc = _mm512_add_ps(acc, load_bf(g + i, m));
  }
  return _mm512_reduce_add_ps(acc);
}
MODI_BF16_ROW_TARGET inline __m512i scaled_lanes(const bf16* p, float f, __mmask16 m) {
  return _mm512_cvtepu16_epi32((__m256i)_mm512_cvtneps_pbh(_mm512_mul_ps(load_bf(p, m), _mm512_set1_ps(f))));
}
MODI_BF16_ROW_TARGET void scaled_pairs_avx(const bf16* a, const bf16* b, float fa, float fb, bf16* dst, int64_t n) {
  for (int64_t i = 0; i < n; i += 16) {
    const __mmask16 m = n - i >= 16 ? __mmask16(0xffff) : static_cast<__mmask16>((1u << (n - i)) - 1u);
    __m512i v = scaled_lanes(a + i, fa, m);
    if (b) v = _mm512_or_si512(v, _mm512_slli_epi32(scaled_lanes(b + i, fb, m), 16));
    _mm512_mask_storeu_epi32(dst + 2 * i, m, v);
  }
}
MODI_BF16_ROW_TARGET void scaled_row_avx(const bf16* a, float fa, bf16* dst, int64_t n) {
  const __m512 vf = _mm512_set1_ps(fa);
  for (int64_t i = 0; i < n; i += 16) {
    const __mmask16 m = n - i >= 16 ? __mmask16(0xffff) : static_cast<__mmask16>((1u << (n - i)) - 1u);
    _mm256_mask_storeu_epi16(dst + i, m, (__m256i)_mm512_cvtneps_pbh(_mm512_mul_ps(load_bf(a + i, m), vf)));
  }
}
// In place: r[i][j] <- r[j][i], 16 x 16 32-bit words.
MODI_BF16_ROW_TARGET inline void transpose16(__m512i (&r)[16]) {
  __m512i t[16];
  for (int i = 0; i < 16; i += 2) {
    t[i] = _mm512_unpacklo_epi32(r[i], r[i + 1]);
    t[i + 1] = _mm512_unpackhi_epi32(r[i], r[i + 1]);
  }
  for (int i = 0; i < 16; i += 4) {
    r[i] = _mm512_unpacklo_epi64(t[i], t[i + 2]);
    r[i + 1] = _mm512_unpackhi_epi64(t[i], t[i + 2]);
    r[i + 2] = _mm512_unpacklo_epi64(t[i + 1], t[i + 3]);
    r[i + 3] = _mm512_unpackhi_epi64(t[i + 1], t[i + 3]);
  }
  for (int h = 0; h < 16; h += 8)
    for (int i = 0; i < 4; ++i) {
      t[h + i] = _mm512_shuffle_i32x4(r[h + i], r[h + i + 4], 0x88);
      t[h + i + 4] = _mm512_shuffle_i32x4(r[h + i], r[h + i + 4], 0xdd);
    }
  for (int i = 0; i < 8; ++i) {
    r[i] = _mm512_shuffle_i32x4(t[i], t[i + 8], 0x88);
    r[i + 8] = _mm512_shuffle_i32x4(t[i], t[i + 8], 0xdd);
  }
}

// lt[(n0 + k) * 32 + j] = (b_j[2(n0+k) bs], b_j[(2(n0+k)+1) bs]) for k < 16, j < 16 (rows past `rows`: 0); bs 1 or 2.
MODI_BF16_ROW_TARGET void transpose_pairs_avx(const bf16* const* b, int64_t bs, int64_t rows, int64_t n0,
                                              uint32_t* lt) {
  __m512i r[16];
  const __m512i even = _mm512_set_epi16(62, 60, 58, 56, 54, 52, 50, 48, 46, 44, 42, 40, 38, 36, 34, 32, 30, 28, 26,
                                        24, 22, 20, 18, 16, 14, 12, 10, 8, 6, 4, 2, 0);
  for (int i = 0; i < 16; ++i) {
    if (i >= rows) {
      r[i] = _mm512_setzero_si512();
    } else if (bs == 1) {
      r[i] = _mm512_loadu_si512(b[i] + 2 * n0);
    } else {  // the row's elements are every other bf16 of a paired layout
      const bf16* p = b[i] + 4 * n0;
      r[i] = _mm512_permutex2var_epi16(_mm512_loadu_si512(p), even, _mm512_loadu_si512(p + 32));
    }
  }
  transpose16(r);
  for (int k = 0; k < 16; ++k) _mm512_storeu_si512(lt + (n0 + k) * 32, r[k]);
}
#else
void transpose_pairs_avx(const bf16* const*, int64_t, int64_t, int64_t, uint32_t*) {}
void scaled_pairs_avx(const bf16*, const bf16*, float, float, bf16*, int64_t) {}
void scaled_row_avx(const bf16*, float, bf16*, int64_t) {}
float dot_avx(const float*, const bf16*, int64_t) { return 0.f; }
float gy_y_avx(const bf16*, const bf16*, int64_t, float) { return 0.f; }
float sum_avx(const bf16*, int64_t) { return 0.f; }
void affine_avx(const float*, bf16*, int64_t, float, float) {}
void pairs_avx(const float*, const float*, bf16*, int64_t) {}
template <int R>
void nn_avx(int64_t, const uint32_t*, int64_t, const bf16* const*, int64_t, float*, int64_t) {}
template <int R>
void wg_avx(int64_t, const bf16* const*, const uint32_t*, float*) {}
#endif

void affine_plain(const float* src, bf16* dst, int64_t n, float f, float bb) {
  for (int64_t i = 0; i < n; ++i) dst[i] = to_bf16(src[i] * f + bb);
}
void pairs_plain(const float* a, const float* b, bf16* dst, int64_t n) {
  for (int64_t i = 0; i < n; ++i) {
    dst[2 * i] = to_bf16(a[i]);
    dst[2 * i + 1] = b ? to_bf16(b[i]) : bf16(0);
  }
}

float dot_plain(const float* a, const bf16* x, int64_t n) {
  float acc = 0.f;
  for (int64_t i = 0; i < n; ++i) acc += a[i] * to_f32(x[i]);
  return acc;
}
float gy_y_plain(const bf16* g, const bf16* y, int64_t n, float bb) {
  float acc = 0.f;
  for (int64_t i = 0; i < n; ++i) acc += to_f32(g[i]) * (to_f32(y[i]) - bb);
  return acc;
}
float sum_plain(const bf16* g, int64_t n) {
  float acc = 0.f;
  for (int64_t i = 0; i < n; ++i) acc += to_f32(g[i]);
  return acc;
}

void scaled_pairs_plain(const bf16* a, const bf16* b, float fa, float fb, bf16* dst, int64_t n) {
  for (int64_t i = 0; i < n; ++i) {
    dst[2 * i] = to_bf16(fa * to_f32(a[i]));
    dst[2 * i + 1] = b ? to_bf16(fb * to_f32(b[i])) : bf16(0);
  }
}
void scaled_row_plain(const bf16* a, float fa, bf16* dst, int64_t n) {
  for (int64_t i = 0; i < n; ++i) dst[i] = to_bf16(fa * to_f32(a[i]));
}

using NnFn = void (*)(int64_t, const uint32_t*, int64_t, const bf16* const*, int64_t, float*, int64_t);
using WgFn = void (*)(int64_t, const bf16* const*, const uint32_t*, float*);

}  // namespace

bool use_avx512bf16() {
#if defined(__x86_64__)
  static const bool cpu = __builtin_cpu_supports("avx512f") && __builtin_cpu_supports("avx512bw") &&
                          __builtin_cpu_supports("avx512bf16");
  const char* env = std::getenv("MODI_EXT_CPU_KERNEL");
  return cpu && !(env != nullptr && std::strcmp(env, "bf16emu") == 0);
#else
  return false;
#endif
}

Cvt cvt_fns() {
  return use_avx512bf16()
             ? Cvt{affine_avx, pairs_avx, dot_avx, gy_y_avx, sum_avx, scaled_pairs_avx, scaled_row_avx}
             : Cvt{affine_plain, pairs_plain, dot_plain, gy_y_plain, sum_plain, scaled_pairs_plain, scaled_row_plain};
}

const char* kernel_name() { return use_avx512bf16() ? "avx512_bf16" : "emulated"; }

void nn_gemm(const uint32_t* a, int64_t M, int64_t Kp, const bf16* const* ptr, int64_t N, float* acc,
             int64_t ldacc) {
  const int64_t cols = (N + kColTile - 1) / kColTile * kColTile;
  if (Kp == 0) {
    for (int64_t m = 0; m < M; ++m) std::fill(acc + m * ldacc, acc + m * ldacc + cols, 0.f);
    return;
  }
  static constexpr NnFn avx[9] = {nn_avx<1>, nn_avx<2>, nn_avx<3>, nn_avx<4>, nn_avx<5>,
                                  nn_avx<6>, nn_avx<7>, nn_avx<8>, nn_avx<9>};
  static constexpr NnFn emu[9] = {nn_emu<1>, nn_emu<2>, nn_emu<3>, nn_emu<4>, nn_emu<5>,
                                  nn_emu<6>, nn_emu<7>, nn_emu<8>, nn_emu<9>};
  const NnFn* fns = use_avx512bf16() ? avx : emu;
  for (int64_t col = 0; col < cols; col += kColTile)
    for (int64_t m0 = 0; m0 < M;) {  // rows 8 at a time while more than 9 remain, then the rest in one call
      const int64_t R = M - m0 > 9 ? 8 : M - m0;
      fns[R - 1](Kp, a + m0, M, ptr, col, acc + m0 * ldacc + col, ldacc);
      m0 += R;
    }
}

void wgrad(const bf16* const* a, int64_t Ma, const bf16* const* b, int64_t bs, int64_t Mb, int64_t N, bf16* C,
           int64_t ci, int64_t cj, uint32_t* lt) {
  static constexpr WgFn avx[12] = {wg_avx<1>, wg_avx<2>, wg_avx<3>, wg_avx<4>,  wg_avx<5>,  wg_avx<6>,
                                   wg_avx<7>, wg_avx<8>, wg_avx<9>, wg_avx<10>, wg_avx<11>, wg_avx<12>};
  static constexpr WgFn emu[12] = {wg_emu<1>, wg_emu<2>, wg_emu<3>, wg_emu<4>,  wg_emu<5>,  wg_emu<6>,
                                   wg_emu<7>, wg_emu<8>, wg_emu<9>, wg_emu<10>, wg_emu<11>, wg_emu<12>};
  const WgFn* fns = use_avx512bf16() ? avx : emu;
  const int64_t Np = (N + 1) / 2;
  // AVX-512: whole groups of 16 column pairs in registers (16 x 16 word transposes), the rest one pair at a time
  const int64_t Nv = use_avx512bf16() && (bs == 1 || bs == 2) ? (N / 2) / 16 * 16 : 0;
  float out[12 * 32];
  for (int64_t j0 = 0; j0 < Mb; j0 += 32) {
    const int64_t live = std::min<int64_t>(32, Mb - j0);
    for (int64_t jg = 0; jg < 32; jg += 16) {
      const int64_t rows = std::max<int64_t>(0, std::min<int64_t>(16, live - jg));
      for (int64_t n0 = 0; n0 < Nv; n0 += 16) transpose_pairs_avx(rows ? b + j0 + jg : b, bs, rows, n0, lt + jg);
    }
    for (int64_t n0 = Nv; n0 < Np; n0 += 16) {  // transpose in strips of 16 column pairs (stays in L1)
      const int64_t n1 = std::min(Np, n0 + 16);
      for (int64_t jj = 0; jj < live; ++jj) {
        const bf16* src = b[j0 + jj];
        for (int64_t np = n0; np < n1; ++np) {
          const uint32_t l = src[2 * np * bs];
          const uint32_t h = 2 * np + 1 < N ? src[(2 * np + 1) * bs] : 0u;
          lt[np * 32 + jj] = l | (h << 16);
        }
      }
      for (int64_t jj = live; jj < 32; ++jj)
        for (int64_t np = n0; np < n1; ++np) lt[np * 32 + jj] = 0u;
    }
    for (int64_t i0 = 0; i0 < Ma; i0 += 12) {
      const int64_t R = std::min<int64_t>(12, Ma - i0);
      fns[R - 1](Np, a + i0, lt, out);
      for (int64_t r = 0; r < R; ++r)
        for (int64_t jj = 0; jj < live; ++jj) C[(i0 + r) * ci + (j0 + jj) * cj] = to_bf16(out[r * 32 + jj]);
    }
  }
}

}  // namespace bf16k
}  // namespace skeletal
}  // namespace modi_ext
