// Row passes of the fp32 fast path (fastk.h) that run after a product: the up pass's output rows.  Compiled for
// the kernels' ISA (AVX-512 / AVX2, the same choice as fastk_gemm.cpp), where the rest of the extension is built
// for x86-64-v2: the loops are plain C++ that the compiler vectorises at that width.  They compute the terms of
// cpu_common.h's fold_row + blur_row in the same order, so the values differ from those at most by the rounding of
// a fused multiply-add.
#include <algorithm>
#include <cstdint>

#include "skeletal/fastk.h"

namespace modi_ext {
namespace skeletal {
namespace fastk {
namespace {

// One up-pass output row: dst[t] = fs * blur(v)[t] + bb, v the padded row P (length L + 2h) folded onto [0, L)
// (v[t] = P[t + h], plus the pad positions' mirror images under reflect padding) and blur the [1 3 3 1] / 4 FIR
// y[t] = (3 v[t] + v[t-2] + 3 v[t-1] + v[t+1]) / 4.
//
// P's even positions are in a0 and its odd ones in a1, so P[2i + n] = src(n)[i].  The interior reads both phase
// rows in place and writes even and odd outputs in one pass: interleaving P into a scratch row first and reading it
// back at shifted offsets stalled on store forwarding (a third of the pass).
__attribute__((always_inline)) inline void up_row_body(const float* a0, const float* a1, float* dst, int64_t L,
                                                      int64_t h, bool reflect, float fs, float bb) {
  const int64_t Lp = L + 2 * h;
  auto out = [&](float v0, float vm2, float vm1, float v1) {  // the FIR's terms in cpu_common.h's order
    float acc = 3.f * v0;
    acc += vm2;
    acc += 3.f * vm1;
    acc += v1;
    return (0.25f * acc) * fs + bb;
  };
  auto src = [&](int64_t n) { return (n & 1 ? a1 : a0) + (n >> 1); };  // arithmetic shift: floor for n < 0
  auto P_at = [&](int64_t n) { return src(n)[0]; };
  auto vq = [&](int64_t q) {  // v[q], 0 outside [0, L), with fold_row's additions in its order
    if (q < 0 || q >= L) return 0.f;
    float x = P_at(q + h);
    if (reflect) {
      for (int64_t p = 0; p < h; ++p)
        if (mirror(p - h, L) == q) x += P_at(p);
      for (int64_t p = L + h; p < Lp; ++p)
        if (mirror(p - h, L) == q) x += P_at(p);
    }
    return x;
  };
  // Outputs t whose taps t-2 .. t+1 lie in [0, L) and away from the reflected positions [1, h], [L-1-h, L-2]
  // run as pairs (2i, 2i+1), i in [i_lo, i_hi); the rest one at a time.
  const int64_t t_lo = reflect ? h + 3 : 2, t_hi = reflect ? L - 2 - h : L - 1;
  const int64_t i_lo = (t_lo + 1) / 2, i_hi = std::max(i_lo, t_hi >= 2 ? t_hi / 2 : i_lo);
  const int64_t x_lo = std::min(2 * i_lo, L), x_hi = std::max(x_lo, std::min(2 * i_hi, L));
  for (int64_t t = 0; t < x_lo; ++t) dst[t] = out(vq(t), vq(t - 2), vq(t - 1), vq(t + 1));
  const float *e0 = src(h), *em2 = src(h - 2), *em1 = src(h - 1), *e1 = src(h + 1);
  const float *o0 = src(h + 1), *om2 = src(h - 1), *om1 = src(h), *o1 = src(h + 2);
  for (int64_t i = i_lo; i < i_hi; ++i) {
    dst[2 * i] = out(e0[i], em2[i], em1[i], e1[i]);
    dst[2 * i + 1] = out(o0[i], om2[i], om1[i], o1[i]);
  }
  for (int64_t t = x_hi; t < L; ++t) dst[t] = out(vq(t), vq(t - 2), vq(t - 1), vq(t + 1));
}

#if defined(__x86_64__)
__attribute__((target("avx512f,avx2,fma"))) void up_row512(const float* a0, const float* a1, float* dst, int64_t L,
                                                           int64_t h, bool reflect, float fs, float bb) {
  up_row_body(a0, a1, dst, L, h, reflect, fs, bb);
}
__attribute__((target("avx2,fma"))) void up_row256(const float* a0, const float* a1, float* dst, int64_t L, int64_t h,
                                                   bool reflect, float fs, float bb) {
  up_row_body(a0, a1, dst, L, h, reflect, fs, bb);
}
#endif
void up_row_body_plain(const float* a0, const float* a1, float* dst, int64_t L, int64_t h, bool reflect, float fs,
                       float bb) {
  up_row_body(a0, a1, dst, L, h, reflect, fs, bb);
}

}  // namespace

UpRowFn up_row_fn() {
#if defined(__x86_64__)
  if (use512()) return up_row512;
  if (wanted()) return up_row256;
#endif
  return up_row_body_plain;
}

}  // namespace fastk
}  // namespace skeletal
}  // namespace modi_ext
