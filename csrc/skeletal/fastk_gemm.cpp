// The GEMM kernels of the fp32 fast path (fastk.h): register-blocked AVX2/FMA and AVX-512 micro-kernels that read
// their right operand through a table of row pointers (the column layout of fastk.cpp), and the drivers that tile a
// product over them.
#include <algorithm>
#include <cstdint>

#if defined(__x86_64__)
#include <immintrin.h>
#endif

#include "skeletal/fastk.h"

namespace modi_ext {
namespace skeletal {
namespace fastk {
namespace {

#if defined(__x86_64__)
// The NN kernels read a short strip of a different pointer row at every step: hundreds of streams per product,
// more than the hardware prefetchers follow, so the loads wait on L2.  Each step asks for the strip that the step
// kPrefetchSteps ahead will read (finest-level skeletal conv fwd+bwd 8% faster, interleaved A/B; distances 8-32
// measured alike).
constexpr int64_t kPrefetchSteps = 16;
template <int FLOATS>
inline void prefetch_strip(const float* p) {
  const char* q = reinterpret_cast<const char*>(p);
  for (int b = 0; b < FLOATS * 4; b += 64) _mm_prefetch(q + b, _MM_HINT_T0);
  _mm_prefetch(q + FLOATS * 4 - 1, _MM_HINT_T0);  // the strip is unaligned: its last line
}

// Keeps a loaded vector in a register.  Without it GCC folds each load of a shared operand into every FMA that
// reads it (one load per FMA), and the NT kernels' inner loops become load-bound: nt512<3, 4> issued 15 loads per
// 12 FMAs instead of 7 (GANimator's weight gradient 40% faster with the loads kept, interleaved A/B).
// (A macro, so the asm sits inside the caller's target("avx2") / target("avx512f") function.)
#define MODI_PIN_REGISTER(v) __asm__("" : "+v"(v))

// C[0:4, col:col+24] = sum_k a[k*4 + r] * ptr[k][col : col+24]   (a: one packed 4-row panel)
__attribute__((target("avx2,fma"))) void nn_kernel(int64_t K, const float* a, const float* const* ptr, int64_t col,
                                                    float* c, int64_t ldc) {
  __m256 c00 = _mm256_setzero_ps(), c01 = c00, c02 = c00, c10 = c00, c11 = c00, c12 = c00;
  __m256 c20 = c00, c21 = c00, c22 = c00, c30 = c00, c31 = c00, c32 = c00;
  for (int64_t k = 0; k < K; ++k) {
    const float* p = ptr[k] + col;
    if (k + kPrefetchSteps < K) prefetch_strip<24>(ptr[k + kPrefetchSteps] + col);
    const __m256 b0 = _mm256_loadu_ps(p), b1 = _mm256_loadu_ps(p + 8), b2 = _mm256_loadu_ps(p + 16);
    __m256 av = _mm256_broadcast_ss(a);
    c00 = _mm256_fmadd_ps(av, b0, c00);
    c01 = _mm256_fmadd_ps(av, b1, c01);
    c02 = _mm256_fmadd_ps(av, b2, c02);
    av = _mm256_broadcast_ss(a + 1);
    c10 = _mm256_fmadd_ps(av, b0, c10);
    c11 = _mm256_fmadd_ps(av, b1, c11);
    c12 = _mm256_fmadd_ps(av, b2, c12);
    av = _mm256_broadcast_ss(a + 2);
    c20 = _mm256_fmadd_ps(av, b0, c20);
    c21 = _mm256_fmadd_ps(av, b1, c21);
    c22 = _mm256_fmadd_ps(av, b2, c22);
    av = _mm256_broadcast_ss(a + 3);
    c30 = _mm256_fmadd_ps(av, b0, c30);
    c31 = _mm256_fmadd_ps(av, b1, c31);
    c32 = _mm256_fmadd_ps(av, b2, c32);
    a += 4;
  }
  _mm256_storeu_ps(c, c00);
  _mm256_storeu_ps(c + 8, c01);
  _mm256_storeu_ps(c + 16, c02);
  c += ldc;
  _mm256_storeu_ps(c, c10);
  _mm256_storeu_ps(c + 8, c11);
  _mm256_storeu_ps(c + 16, c12);
  c += ldc;
  _mm256_storeu_ps(c, c20);
  _mm256_storeu_ps(c + 8, c21);
  _mm256_storeu_ps(c + 16, c22);
  c += ldc;
  _mm256_storeu_ps(c, c30);
  _mm256_storeu_ps(c + 8, c31);
  _mm256_storeu_ps(c + 16, c32);
}

// The last panel's live rows only (M % 4 of them): narrow layers (GANimator's 5-9 channels) would otherwise spend up
// to 3/4 of that panel's multiply-adds on padding rows.
template <int R>
__attribute__((target("avx2,fma"))) void nn_rows(int64_t K, const float* a, const float* const* ptr, int64_t col,
                                                  float* c, int64_t ldc) {
  __m256 acc[R][3];
  for (int r = 0; r < R; ++r) acc[r][0] = acc[r][1] = acc[r][2] = _mm256_setzero_ps();
  for (int64_t k = 0; k < K; ++k) {
    const float* p = ptr[k] + col;
    if (k + kPrefetchSteps < K) prefetch_strip<24>(ptr[k + kPrefetchSteps] + col);
    const __m256 b0 = _mm256_loadu_ps(p), b1 = _mm256_loadu_ps(p + 8), b2 = _mm256_loadu_ps(p + 16);
    for (int r = 0; r < R; ++r) {
      const __m256 av = _mm256_broadcast_ss(a + r);
      acc[r][0] = _mm256_fmadd_ps(av, b0, acc[r][0]);
      acc[r][1] = _mm256_fmadd_ps(av, b1, acc[r][1]);
      acc[r][2] = _mm256_fmadd_ps(av, b2, acc[r][2]);
    }
    a += 4;
  }
  for (int r = 0; r < R; ++r) {
    _mm256_storeu_ps(c + r * ldc, acc[r][0]);
    _mm256_storeu_ps(c + r * ldc + 8, acc[r][1]);
    _mm256_storeu_ps(c + r * ldc + 16, acc[r][2]);
  }
}

__attribute__((target("avx2,fma"))) inline float hsum(__m256 v) {
  __m128 s = _mm_add_ps(_mm256_castps256_ps128(v), _mm256_extractf128_ps(v, 1));
  s = _mm_hadd_ps(s, s);
  s = _mm_hadd_ps(s, s);
  return _mm_cvtss_f32(s);
}

#else
void nn_kernel(int64_t, const float*, const float* const*, int64_t, float*, int64_t) {}
template <int R>
void nn_rows(int64_t, const float*, const float* const*, int64_t, float*, int64_t) {}
#endif

// The AVX2 NT tile: C[i][j] += sum_{col in [c0, c0+n)} l[i][col] * p[j][col] for MT x KT (up to 4 x 3) dot
// products, 8 lanes.  The pointer-row strips stay in registers and the left rows are loaded one at a time, so the
// full 4 x 3 tile fits the 16 registers (12 accumulators).  Edge tiles matter: GANimator's layers have 3-9 output
// channels, so an edge row is a large share of the weight gradient there.
#if defined(__x86_64__)
// One 8-column step of the tile (Masked: the last, partial one, lanes past `m` read as zeros).
template <int MT, int KT, bool Masked>
__attribute__((target("avx2,fma"), always_inline)) inline void nt_step(const float* const* l, const float* const* p,
                                                                        int64_t c, __m256i m, __m256 (&a)[MT][KT]) {
#define MODI_NT_LOAD(r) (Masked ? _mm256_maskload_ps((r) + c, m) : _mm256_loadu_ps((r) + c))
  __m256 Y[KT];
  for (int j = 0; j < KT; ++j) {
    Y[j] = MODI_NT_LOAD(p[j]);
    MODI_PIN_REGISTER(Y[j]);
  }
  for (int i = 0; i < MT; ++i) {
    const __m256 X = MODI_NT_LOAD(l[i]);
    for (int j = 0; j < KT; ++j) a[i][j] = _mm256_fmadd_ps(X, Y[j], a[i][j]);
  }
#undef MODI_NT_LOAD
}

template <int MT, int KT>
__attribute__((target("avx2,fma"))) void nt_tile(const float* const* l, const float* const* p, int64_t c0, int64_t n,
                                                  float* C, int64_t ldc) {
  __m256 a[MT][KT];
  for (int i = 0; i < MT; ++i)
    for (int j = 0; j < KT; ++j) a[i][j] = _mm256_setzero_ps();
  int64_t c = c0;
  const int64_t end = c0 + n;
  const __m256i none = _mm256_setzero_si256();
  for (; c + 8 <= end; c += 8) nt_step<MT, KT, false>(l, p, c, none, a);
  if (c < end) {
    const __m256i m = _mm256_cmpgt_epi32(_mm256_set1_epi32(static_cast<int>(end - c)),
                                         _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7));
    nt_step<MT, KT, true>(l, p, c, m, a);
  }
  for (int i = 0; i < MT; ++i)
    for (int j = 0; j < KT; ++j) C[i * ldc + j] += hsum(a[i][j]);
}

void nt_avx2(const float* const* l, int64_t mr, const float* const* p, int64_t kr, int64_t c0, int64_t n, float* C,
             int64_t ldc) {
  using Fn = void (*)(const float* const*, const float* const*, int64_t, int64_t, float*, int64_t);
  static constexpr Fn table[TM][TK] = {{nt_tile<1, 1>, nt_tile<1, 2>, nt_tile<1, 3>},
                                       {nt_tile<2, 1>, nt_tile<2, 2>, nt_tile<2, 3>},
                                       {nt_tile<3, 1>, nt_tile<3, 2>, nt_tile<3, 3>},
                                       {nt_tile<4, 1>, nt_tile<4, 2>, nt_tile<4, 3>}};
  table[mr - 1][kr - 1](l, p, c0, n, C, ldc);
}
#else
void nt_avx2(const float* const*, int64_t, const float* const*, int64_t, int64_t, int64_t, float*, int64_t) {}
#endif

// AVX-512 variants of the two kernels (same operands, twice the lanes), used when the CPU has AVX-512F
// (MODI_EXT_CPU_KERNEL=avx2 keeps the AVX2 ones).  NN: R rows x 48 columns (two NR tiles) per call.
#if defined(__x86_64__)
#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Wuninitialized"  // GCC 12's avx512fintrin.h masked-intrinsic false positive
#pragma GCC diagnostic ignored "-Wmaybe-uninitialized"
__attribute__((target("avx512f"))) inline float hsum512(__m512 v) {
  __m512 t = _mm512_add_ps(v, _mm512_shuffle_f32x4(v, v, _MM_SHUFFLE(1, 0, 3, 2)));
  t = _mm512_add_ps(t, _mm512_shuffle_f32x4(t, t, _MM_SHUFFLE(2, 3, 0, 1)));
  __m128 s = _mm512_castps512_ps128(t);
  s = _mm_add_ps(s, _mm_movehl_ps(s, s));
  s = _mm_add_ss(s, _mm_shuffle_ps(s, s, 1));
  return _mm_cvtss_f32(s);
}

// R rows (up to 9: 27 accumulators) x 48 columns (two NR tiles).  Row r comes from packed panel r / 4 (panels ps
// floats apart), so one call covers the last 5-9 rows of a product -- GANimator's 5-9 channels in one pass over the
// pointer rows instead of a 4- or 8-row pass plus a 1-row pass that is bound by its loads.  Direct: A is read in
// place, row r at a + r * ps (a row-major weight, no packing pass; each k broadcasts from R rows instead of from
// one packed group -- the same number of loads).
template <int R, bool Direct = false>
__attribute__((target("avx512f"))) void nn512rows(int64_t K, const float* a, int64_t ps, const float* const* ptr,
                                                   int64_t col, float* c, int64_t ldc) {
  static_assert(R >= 1 && R <= 9, "27 accumulators + 3 operands + 1 broadcast fill the 32 registers");
  __m512 acc[R][3];
  for (int r = 0; r < R; ++r) acc[r][0] = acc[r][1] = acc[r][2] = _mm512_setzero_ps();
  const float* ap[3] = {a, a + ps, a + 2 * ps};
  const float* ar[R];
  for (int r = 0; r < R; ++r) ar[r] = a + r * ps;
  for (int64_t k = 0; k < K; ++k) {
    const float* p = ptr[k] + col;
    if (k + kPrefetchSteps < K) prefetch_strip<48>(ptr[k + kPrefetchSteps] + col);
    const __m512 b0 = _mm512_loadu_ps(p), b1 = _mm512_loadu_ps(p + 16), b2 = _mm512_loadu_ps(p + 32);
    for (int r = 0; r < R; ++r) {
      const __m512 av = _mm512_set1_ps(Direct ? ar[r][k] : ap[r / 4][k * MR + r % 4]);
      acc[r][0] = _mm512_fmadd_ps(av, b0, acc[r][0]);
      acc[r][1] = _mm512_fmadd_ps(av, b1, acc[r][1]);
      acc[r][2] = _mm512_fmadd_ps(av, b2, acc[r][2]);
    }
  }
  for (int r = 0; r < R; ++r) {
    _mm512_storeu_ps(c + r * ldc, acc[r][0]);
    _mm512_storeu_ps(c + r * ldc + 16, acc[r][1]);
    _mm512_storeu_ps(c + r * ldc + 32, acc[r][2]);
  }
}

// One NR tile (24 columns: a full and a half-masked vector) for R rows (up to 9, panels as nn512rows): the odd
// last tile of a product, which the 4-row AVX2 kernel would do at half the width.
template <int R, bool Direct = false>
__attribute__((target("avx512f"))) void nn512_tail(int64_t K, const float* a, int64_t ps, const float* const* ptr,
                                                    int64_t col, float* c, int64_t ldc) {
  constexpr __mmask16 half = 0x00FF;
  __m512 acc[R][2];
  for (int r = 0; r < R; ++r) acc[r][0] = acc[r][1] = _mm512_setzero_ps();
  const float* ap[3] = {a, a + ps, a + 2 * ps};
  const float* ar[R];
  for (int r = 0; r < R; ++r) ar[r] = a + r * ps;
  for (int64_t k = 0; k < K; ++k) {
    const float* p = ptr[k] + col;
    if (k + kPrefetchSteps < K) prefetch_strip<NR>(ptr[k + kPrefetchSteps] + col);
    const __m512 b0 = _mm512_loadu_ps(p), b1 = _mm512_maskz_loadu_ps(half, p + 16);
    for (int r = 0; r < R; ++r) {
      const __m512 av = _mm512_set1_ps(Direct ? ar[r][k] : ap[r / 4][k * MR + r % 4]);
      acc[r][0] = _mm512_fmadd_ps(av, b0, acc[r][0]);
      acc[r][1] = _mm512_fmadd_ps(av, b1, acc[r][1]);
    }
  }
  for (int r = 0; r < R; ++r) {
    _mm512_storeu_ps(c + r * ldc, acc[r][0]);
    _mm512_mask_storeu_ps(c + r * ldc + 16, half, acc[r][1]);
  }
}

// NT: C[i][j] += sum_{col in [c0, c0+n)} l[i][col] * p[j][col] for an MT x KT tile, 16 lanes.
template <int MT, int KT>
__attribute__((target("avx512f"))) void nt512(const float* const* l, const float* const* p, int64_t c0, int64_t n,
                                               float* C, int64_t ldc) {
  __m512 a[MT][KT];
  for (int i = 0; i < MT; ++i)
    for (int j = 0; j < KT; ++j) a[i][j] = _mm512_setzero_ps();
  int64_t c = c0;
  const int64_t end = c0 + n;
  for (; c + 16 <= end; c += 16) {
    __m512 X[MT], Y[KT];
    for (int i = 0; i < MT; ++i) X[i] = _mm512_loadu_ps(l[i] + c);
    for (int j = 0; j < KT; ++j) {
      Y[j] = _mm512_loadu_ps(p[j] + c);
      MODI_PIN_REGISTER(Y[j]);
    }
    for (int i = 0; i < MT; ++i)
      for (int j = 0; j < KT; ++j) a[i][j] = _mm512_fmadd_ps(X[i], Y[j], a[i][j]);
  }
  if (c < end) {
    const __mmask16 m = static_cast<__mmask16>((1u << (end - c)) - 1u);
    __m512 X[MT], Y[KT];
    for (int i = 0; i < MT; ++i) X[i] = _mm512_maskz_loadu_ps(m, l[i] + c);
    for (int j = 0; j < KT; ++j) Y[j] = _mm512_maskz_loadu_ps(m, p[j] + c);
    for (int i = 0; i < MT; ++i)
      for (int j = 0; j < KT; ++j) a[i][j] = _mm512_fmadd_ps(X[i], Y[j], a[i][j]);
  }
  if constexpr (KT == 4) {  // four sums of a row at once (13 shuffles / adds instead of four hsum512)
    for (int i = 0; i < MT; ++i) {
      const __m512 ab = _mm512_add_ps(_mm512_unpacklo_ps(a[i][0], a[i][1]), _mm512_unpackhi_ps(a[i][0], a[i][1]));
      const __m512 cd = _mm512_add_ps(_mm512_unpacklo_ps(a[i][2], a[i][3]), _mm512_unpackhi_ps(a[i][2], a[i][3]));
      // per 128-bit lane: [a, b, c, d] partial sums
      __m512 t = _mm512_add_ps(_mm512_castpd_ps(_mm512_unpacklo_pd(_mm512_castps_pd(ab), _mm512_castps_pd(cd))),
                               _mm512_castpd_ps(_mm512_unpackhi_pd(_mm512_castps_pd(ab), _mm512_castps_pd(cd))));
      t = _mm512_add_ps(t, _mm512_shuffle_f32x4(t, t, _MM_SHUFFLE(1, 0, 3, 2)));
      t = _mm512_add_ps(t, _mm512_shuffle_f32x4(t, t, _MM_SHUFFLE(2, 3, 0, 1)));
      float* c = C + i * ldc;
      _mm_storeu_ps(c, _mm_add_ps(_mm_loadu_ps(c), _mm512_castps512_ps128(t)));
    }
  } else {
    for (int i = 0; i < MT; ++i)
      for (int j = 0; j < KT; ++j) C[i * ldc + j] += hsum512(a[i][j]);
  }
}

void nt512_tile(const float* const* l, int64_t mr, const float* const* p, int64_t kr, int64_t c0, int64_t n,
                float* C, int64_t ldc) {
  using Fn = void (*)(const float* const*, const float* const*, int64_t, int64_t, float*, int64_t);
  static constexpr Fn table[4][4] = {{nt512<1, 1>, nt512<1, 2>, nt512<1, 3>, nt512<1, 4>},
                                     {nt512<2, 1>, nt512<2, 2>, nt512<2, 3>, nt512<2, 4>},
                                     {nt512<3, 1>, nt512<3, 2>, nt512<3, 3>, nt512<3, 4>},
                                     {nt512<4, 1>, nt512<4, 2>, nt512<4, 3>, nt512<4, 4>}};
  table[mr - 1][kr - 1](l, p, c0, n, C, ldc);
}

// Weight-gradient tile in NN form: out[r][0:32] = sum_{n < N} x[r][n] * lt[n][0:32] for R pointer rows x (the K
// side, broadcast) and a packed 32-wide block lt of the transposed left operand.  24 accumulators at R = 12.
template <int R>
__attribute__((target("avx512f"))) void wg512(int64_t N, const float* const* x, const float* lt, float* out) {
  __m512 acc[R][2];
  for (int r = 0; r < R; ++r) acc[r][0] = acc[r][1] = _mm512_setzero_ps();
  const float* xr[R];
  for (int r = 0; r < R; ++r) xr[r] = x[r];
  for (int64_t n = 0; n < N; ++n) {
    const __m512 g0 = _mm512_loadu_ps(lt + n * 32), g1 = _mm512_loadu_ps(lt + n * 32 + 16);
    for (int r = 0; r < R; ++r) {
      const __m512 av = _mm512_set1_ps(xr[r][n]);
      acc[r][0] = _mm512_fmadd_ps(av, g0, acc[r][0]);
      acc[r][1] = _mm512_fmadd_ps(av, g1, acc[r][1]);
    }
  }
  for (int r = 0; r < R; ++r) {
    _mm512_storeu_ps(out + r * 32, acc[r][0]);
    _mm512_storeu_ps(out + r * 32 + 16, acc[r][1]);
  }
}

#pragma GCC diagnostic pop
#else
template <int R>
void wg512(int64_t, const float* const*, const float*, float*) {}
template <int R, bool Direct = false>
void nn512rows(int64_t, const float*, int64_t, const float* const*, int64_t, float*, int64_t) {}
template <int R, bool Direct = false>
void nn512_tail(int64_t, const float*, int64_t, const float* const*, int64_t, float*, int64_t) {}
void nt512_tile(const float* const*, int64_t, const float* const*, int64_t, int64_t, int64_t, float*, int64_t) {}
#endif

}  // namespace

void nn_gemm(const float* apack, int64_t M, int64_t K, const float* const* ptr, int64_t N, float* acc,
             int64_t ldacc) {
  const int64_t panels = (M + MR - 1) / MR, tiles = (N + NR - 1) / NR;
  if (K == 0) {
    std::fill(acc, acc + panels * MR * ldacc, 0.f);
    return;
  }
  if (use512()) {
    // Pairs of NR tiles (48 columns) outermost; rows 8 at a time while more than 9 remain, then the rest in one
    // call; the odd last tile alike, at 24 columns.
    using Fn = void (*)(int64_t, const float*, int64_t, const float* const*, int64_t, float*, int64_t);
    static constexpr Fn pair[9] = {nn512rows<1>, nn512rows<2>, nn512rows<3>, nn512rows<4>, nn512rows<5>,
                                   nn512rows<6>, nn512rows<7>, nn512rows<8>, nn512rows<9>};
    static constexpr Fn tail[9] = {nn512_tail<1>, nn512_tail<2>, nn512_tail<3>, nn512_tail<4>, nn512_tail<5>,
                                   nn512_tail<6>, nn512_tail<7>, nn512_tail<8>, nn512_tail<9>};
    const int64_t ps = K * MR;
    for (int64_t t = 0; t < tiles; t += 2) {
      const Fn* fns = t + 1 < tiles ? pair : tail;
      for (int64_t m0 = 0; m0 < M;) {
        const int64_t R = M - m0 > 9 ? 8 : M - m0;
        fns[R - 1](K, apack + (m0 / MR) * ps, ps, ptr, t * NR, acc + m0 * ldacc + t * NR, ldacc);
        m0 += R;
      }
    }
    return;
  }
  const int64_t chunk = std::max<int64_t>(1, (160 * 1024) / (K * NR * 4));
  for (int64_t t0 = 0; t0 < tiles; t0 += chunk) {
    const int64_t t1 = std::min(tiles, t0 + chunk);
    for (int64_t pn = 0; pn < panels; ++pn) {
      const int64_t live = std::min<int64_t>(MR, M - pn * MR);
      const float* ap = apack + pn * K * MR;
      float* cp = acc + pn * MR * ldacc;
      for (int64_t t = t0; t < t1; ++t) {
        if (live == 4) nn_kernel(K, ap, ptr, t * NR, cp + t * NR, ldacc);
        else if (live == 3) nn_rows<3>(K, ap, ptr, t * NR, cp + t * NR, ldacc);
        else if (live == 2) nn_rows<2>(K, ap, ptr, t * NR, cp + t * NR, ldacc);
        else nn_rows<1>(K, ap, ptr, t * NR, cp + t * NR, ldacc);
      }
    }
  }
}

void nn_gemm_direct(const float* a, int64_t lda, int64_t M, int64_t K, const float* const* ptr, int64_t N,
                    float* acc, int64_t ldacc) {
  using Fn = void (*)(int64_t, const float*, int64_t, const float* const*, int64_t, float*, int64_t);
  static constexpr Fn pair[9] = {nn512rows<1, true>, nn512rows<2, true>, nn512rows<3, true>,
                                 nn512rows<4, true>, nn512rows<5, true>, nn512rows<6, true>,
                                 nn512rows<7, true>, nn512rows<8, true>, nn512rows<9, true>};
  static constexpr Fn tail[9] = {nn512_tail<1, true>, nn512_tail<2, true>, nn512_tail<3, true>,
                                 nn512_tail<4, true>, nn512_tail<5, true>, nn512_tail<6, true>,
                                 nn512_tail<7, true>, nn512_tail<8, true>, nn512_tail<9, true>};
  const int64_t tiles = (N + NR - 1) / NR;
  for (int64_t t = 0; t < tiles; t += 2) (t + 1 < tiles ? pair : tail)[M - 1](K, a, lda, ptr, t * NR, acc + t * NR, ldacc);
}

void wgrad512(const float* const* l, int64_t M, const float* const* p, int64_t K, int64_t N, float* C, int64_t ldc,
              float* scratch) {
  using Fn = void (*)(int64_t, const float* const*, const float*, float*);
  static constexpr Fn table[12] = {wg512<1>, wg512<2>, wg512<3>, wg512<4>, wg512<5>,  wg512<6>,
                                   wg512<7>, wg512<8>, wg512<9>, wg512<10>, wg512<11>, wg512<12>};
  const int64_t nmb = (M + 31) / 32;
  float out[12 * 32];
  for (int64_t mb = 0; mb < nmb; ++mb) {
    float* lt = scratch;
    const int64_t live = std::min<int64_t>(32, M - mb * 32);
    for (int64_t n0 = 0; n0 < N; n0 += 16) {  // transpose in 16-column strips (stays in L1)
      const int64_t n1 = std::min(N, n0 + 16);
      for (int64_t o = 0; o < live; ++o) {
        const float* src = l[mb * 32 + o];
        for (int64_t n = n0; n < n1; ++n) lt[n * 32 + o] = src[n];
      }
      for (int64_t o = live; o < 32; ++o)
        for (int64_t n = n0; n < n1; ++n) lt[n * 32 + o] = 0.f;
    }
    for (int64_t r0 = 0; r0 < K; r0 += 12) {
      const int64_t R = std::min<int64_t>(12, K - r0);
      table[R - 1](N, p + r0, lt, out);
      for (int64_t r = 0; r < R; ++r)
        for (int64_t o = 0; o < live; ++o) C[(mb * 32 + o) * ldc + r0 + r] = out[r * 32 + o];
    }
  }
}

void nt_gemm(const float* const* l, int64_t M, const float* const* p, int64_t K, int64_t N, float* C, int64_t ldc) {
  const bool wide = use512();
  // AVX-512: rows in tiles of at most 4 as even as M allows (9 = 3+3+3, not 4+4+1: a 1-row tile is bound by its
  // loads) by 4 pointer rows (reduced four at a time), each tile over all the columns (column chunks sized for L2
  // measured 5-15% slower on GANimator's layers: the reductions cost more than the re-reads save); AVX2: 4 x 3
  // tiles over column chunks that keep the pointed-to data in L2.
  const int64_t CH = wide ? std::max<int64_t>(N, 1)
                          : std::max<int64_t>(64, round_up((320 * 1024) / std::max<int64_t>(1, (K + M) * 4), 16));
  const int64_t row_tiles = (M + TM - 1) / TM, kt = wide ? 4 : TK;
  for (int64_t c0 = 0; c0 < N; c0 += CH) {
    const int64_t n = std::min(CH, N - c0);
    for (int64_t rt = 0, m0 = 0; rt < row_tiles; ++rt) {
      const int64_t mr = wide ? (M - m0 + (row_tiles - rt) - 1) / (row_tiles - rt) : std::min(TM, M - m0);
      for (int64_t k0 = 0; k0 < K; k0 += kt) {
        const int64_t kr = std::min(kt, K - k0);
        (wide ? nt512_tile : nt_avx2)(l + m0, mr, p + k0, kr, c0, n, C + m0 * ldc + k0, ldc);
      }
      m0 += mr;
    }
  }
}

}  // namespace fastk
}  // namespace skeletal
}  // namespace modi_ext
