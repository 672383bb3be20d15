// The passes of the bf16 path (bf16k.h): each lays its inputs out once per call (channel-paired rows for the NN
// products, plain rows for the weight gradients), packs the weights as bf16 pairs and runs one indirect product per
// entity and batch tile, as preparation and compute stages of one task-pool job (common/tasks.h), as fastk.cpp does.
#include <algorithm>
#include <cstdint>
#include <vector>

#include "skeletal/bf16k.h"
#include "skeletal/fastk.h"

namespace modi_ext {
namespace skeletal {
namespace bf16k {
namespace {

// Source of a column layout: row (b, c, e) of a (B, C, E, Ts) bf16 tensor times f(b, c, e); padded position
// p = S*m + phase, q = p - F; q outside [0, Ts) reads the mirror image (reflect, from Z on) or 0; past Lp: 0.
// blur_adjoint: the source row is blur^T(row) (the up op's backward), in fp32.
struct Src {
  const bf16* src = nullptr;
  int64_t B = 0, Ts = 0;
  const bf16* f = nullptr;
  int64_t fb = 0, fc = 0, fe = 0;
  int64_t F = 0, Lp = 0, Z = 0;
  bool reflect = false, blur_adjoint = false;
  float at(int64_t b, int64_t c, int64_t e) const { return f ? to_f32(f[b * fb + c * fc + e * fe]) : 1.f; }
};

// Rows (phase, cs, e) of row_len columns, `width` bf16 per column: width 2 pairs channels (cs = c / 2, channel c at
// element 2n + c % 2), width 1 is plain (cs = c).
struct Layout {
  Buf<bf16> buf;
  int64_t C = 0, Cs = 0, E = 0, Tq = 0, row_len = 0, width = 1, rows = 0;
  const bf16* row(int64_t ph, int64_t cs, int64_t e) const {
    return buf.data() + ((ph * Cs + cs) * E + e) * row_len * width;
  }
  // Channel c's row (its elements `width` apart).
  const bf16* chan(int64_t ph, int64_t c, int64_t e) const { return row(ph, c / width, e) + c % width; }
};

struct LayoutBuild {
  Layout l;
  Src s;
  int64_t S = 1, chunk = 1;
  Cvt cvt = cvt_fns();
  mutable SlotScratch<float> tmp;
  LayoutBuild(const Src& src, int64_t C, int64_t E, int64_t S_, int64_t Tq, int64_t max_shift, bool paired)
      : s(src), S(S_) {
    l.C = C;
    l.width = paired ? 2 : 1;
    l.Cs = paired ? (C + 1) / 2 : C;
    l.E = E;
    l.Tq = Tq;
    // slack: the last 48-column tile, the largest shift and an odd column pair read past B * Tq
    int64_t len = fastk::round_up(s.B * Tq + kColTile + max_shift + 8, 32);
    if ((len * 2 * l.width) % 4096 == 0) len += 32;  // avoid rows aliasing in the same cache sets
    l.row_len = len;
    l.rows = S * l.Cs * E;
    l.buf.alloc(static_cast<size_t>(l.rows * len * l.width));
    chunk = chunk_items(S * len * l.width);
  }
  LayoutBuild(const LayoutBuild&) = delete;
  LayoutBuild& operator=(const LayoutBuild&) = delete;

  // The source row (b, c, e) in fp32 (blurred for blur_adjoint), read by every phase.
  const float* source(int64_t b, int64_t c, int64_t e, float* srow, float* blurred) const {
    const bf16* r = s.src + ((b * l.C + c) * l.E + e) * s.Ts;
    for (int64_t t = 0; t < s.Ts; ++t) srow[t] = to_f32(r[t]);  // (vectorised: a shift)
    if (!s.blur_adjoint) return srow;
    blur_adjoint_row<float>(srow, blurred, s.Ts);
    return blurred;
  }

  // Phase ph of a padded row, fv times the source v, into d[0, Tq), fp32.
  void row_values(int64_t ph, const float* v, float fv, float* d) const {
    const int64_t Tq = l.Tq, Ts = s.Ts, F = s.F, Lp = s.Lp;
    const bool reflect = s.reflect;
    if (S == 1) {
      const int64_t lo_m = std::min(std::max<int64_t>(F, 0), Tq), hi_m = std::max(lo_m, std::min({Tq, Lp, F + Ts}));
      for (int64_t m = 0; m < lo_m; ++m) d[m] = (m >= s.Z && m < Lp && reflect) ? fv * v[mirror(m - F, Ts)] : 0.f;
      for (int64_t m = lo_m; m < hi_m; ++m) d[m] = fv * v[m - F];
      for (int64_t m = hi_m; m < Tq; ++m) d[m] = (m < Lp && reflect) ? fv * v[mirror(m - F, Ts)] : 0.f;
    } else {
      auto edge = [&](int64_t m) {
        const int64_t p = S * m + ph, q = p - F;
        float x = 0.f;
        if (p < Lp) {
          if (q >= 0 && q < Ts)
            x = v[q];
          else if (reflect)
            x = v[mirror(q, Ts)];
        }
        return fv * x;
      };
      // interior: 0 <= S m + ph - F < Ts and S m + ph < Lp, without the tests (the compiler vectorises it)
      const int64_t lo_m = std::min(Tq, std::max<int64_t>(0, (F - ph + S - 1) / S));
      const int64_t hi_m = std::max(lo_m, std::min({Tq, (Lp - ph + S - 1) / S, (Ts + F - ph + S - 1) / S}));
      for (int64_t m = 0; m < lo_m; ++m) d[m] = edge(m);
      const float* vs = v + ph - F;
      for (int64_t m = lo_m; m < hi_m; ++m) d[m] = fv * vs[S * m];
      for (int64_t m = hi_m; m < Tq; ++m) d[m] = edge(m);
    }
  }

  // The rows (phase, cs, e) of every phase: unit r = cs * E + e.
  void fill(int64_t r, int slot) const {
    const int64_t Cs = l.Cs, E = l.E, Tq = l.Tq, W = l.width;
    const int64_t cs = r / E, e = r % E;
    bf16* dst = l.buf.data() + r * l.row_len * W;  // phase 0; phase ph at dst + ph * Cs * E * row_len * W
    const int64_t c0 = cs * W;
    const bool two = W == 2 && c0 + 1 < l.C;  // else the zero channel of an odd count
    if (S == 1 && !s.blur_adjoint) {  // the interior straight from the bf16 rows, the padding one value at a time
      const int64_t F = s.F, Ts = s.Ts, Lp = s.Lp;
      const int64_t lo_m = std::min(std::max<int64_t>(F, 0), Tq), hi_m = std::max(lo_m, std::min({Tq, Lp, F + Ts}));
      for (int64_t b = 0; b < s.B; ++b) {
        bf16* d = dst + b * Tq * W;
        for (int64_t j = 0; j < W; ++j) {
          const int64_t c = c0 + j;
          if (c >= l.C) {
            for (int64_t m = 0; m < lo_m; ++m) d[m * W + j] = 0;
            for (int64_t m = hi_m; m < Tq; ++m) d[m * W + j] = 0;
            continue;
          }
          const float fv = s.at(b, c, e);
          const bf16* r = s.src + ((b * l.C + c) * E + e) * Ts;
          auto pad = [&](int64_t m, bool front) {
            const bool mirrored = s.reflect && m < Lp && (!front || m >= s.Z);
            return mirrored ? to_bf16(fv * to_f32(r[mirror(m - F, Ts)])) : bf16(0);
          };
          for (int64_t m = 0; m < lo_m; ++m) d[m * W + j] = pad(m, true);
          for (int64_t m = hi_m; m < Tq; ++m) d[m * W + j] = pad(m, false);
        }
        const bf16* r0 = s.src + ((b * l.C + c0) * E + e) * Ts + (lo_m - F);
        if (W == 1) {
          cvt.scaled_row(r0, s.at(b, c0, e), d + lo_m, hi_m - lo_m);
        } else {
          cvt.scaled_pairs(r0, two ? r0 + E * Ts : nullptr, s.at(b, c0, e), two ? s.at(b, c0 + 1, e) : 0.f,
                           d + 2 * lo_m, hi_m - lo_m);
        }
      }
      std::fill(dst + s.B * Tq * W, dst + l.row_len * W, bf16(0));
      return;
    }
    // t[ph * 2 + j]: phase ph of channel c0 + j; each source row is converted (and blurred) once for all phases
    float* t = tmp.get(slot, static_cast<size_t>(2 * S * Tq + 2 * s.Ts));
    float *srow = t + 2 * S * Tq, *blurred = srow + s.Ts;
    const int64_t ph_stride = Cs * E * l.row_len * W;
    for (int64_t b = 0; b < s.B; ++b) {
      for (int64_t j = 0; j < (two ? 2 : 1); ++j) {
        const float* v = source(b, c0 + j, e, srow, blurred);
        const float fv = s.at(b, c0 + j, e);
        for (int64_t ph = 0; ph < S; ++ph) row_values(ph, v, fv, t + (ph * 2 + j) * Tq);
      }
      for (int64_t ph = 0; ph < S; ++ph) {
        const float* t0 = t + ph * 2 * Tq;
        if (W == 1)
          cvt.affine(t0, dst + ph * ph_stride + b * Tq, Tq, 1.f, 0.f);
        else
          cvt.pairs(t0, two ? t0 + Tq : nullptr, dst + ph * ph_stride + b * Tq * 2, Tq);
      }
    }
    for (int64_t ph = 0; ph < S; ++ph)
      std::fill(dst + ph * ph_stride + s.B * Tq * W, dst + ph * ph_stride + l.row_len * W, bf16(0));
  }
  void operator()(int64_t t, int slot) const {
    const int64_t units = l.Cs * l.E;
    for (int64_t r = t * chunk, end = std::min(units, (t + 1) * chunk); r < end; ++r) fill(r, slot);
  }
  Phase phase() const { return cpu_tasks::phase((l.Cs * l.E + chunk - 1) / chunk, *this); }
};

// Weights packed as bf16 pairs along channels: item i (entity x phase) holds a[kp * M + m], kp = (s * Csp + cp) *
// Rn + r, the pair (elem(i, m, s, 2cp, r), elem(i, m, s, 2cp + 1, r)) (0 past Cs).  A preparation phase, one task
// per item; must stay in place while it runs.
template <class Elem>
struct PackBuild {
  Buf<uint32_t> buf;
  std::vector<int64_t> off, ks, rs;
  int64_t M, Cs, Csp;
  Elem elem;
  PackBuild(int64_t M_, int64_t Cs_, std::vector<int64_t> ks_, std::vector<int64_t> rs_, Elem e)
      : ks(std::move(ks_)), rs(std::move(rs_)), M(M_), Cs(Cs_), Csp((Cs_ + 1) / 2), elem(e) {
    off.assign(ks.size() + 1, 0);
    for (size_t i = 0; i < ks.size(); ++i) off[i + 1] = off[i] + ks[i] * Csp * rs[i] * M;
    buf.alloc(static_cast<size_t>(off.back()));
  }
  PackBuild(const PackBuild&) = delete;
  PackBuild& operator=(const PackBuild&) = delete;
  const uint32_t* at(int64_t i) const { return buf.data() + off[i]; }
  void operator()(int64_t i, int) const {
    uint32_t* o = buf.data() + off[i];
    const int64_t k = ks[i], Rn = rs[i];
    for (int64_t s = 0; s < k; ++s)
      for (int64_t cp = 0; cp < Csp; ++cp)
        for (int64_t r = 0; r < Rn; ++r) {
          uint32_t* ok = o + ((s * Csp + cp) * Rn + r) * M;
          const bool two = 2 * cp + 1 < Cs;
          for (int64_t m = 0; m < M; ++m) {
            const uint32_t lo = elem(i, m, s, 2 * cp, r), hi = two ? elem(i, m, s, 2 * cp + 1, r) : bf16(0);
            ok[m] = lo | (hi << 16);
          }
        }
  }
  Phase phase() const { return cpu_tasks::phase(static_cast<int64_t>(ks.size()), *this); }
};

inline void interleave_row(const float* a0, const float* a1, float* out, int64_t Lp) {
  const int64_t pairs = Lp / 2;
  for (int64_t i = 0; i < pairs; ++i) {
    out[2 * i] = a0[i];
    out[2 * i + 1] = a1[i];
  }
  if (Lp & 1) out[Lp - 1] = a0[pairs];
}

template <class WeightTask, class InputTask>
void run_backward(const std::vector<Phase>& prep, const std::vector<Phase>& compute, size_t n_weight,
                  const WeightTask& weight_task, size_t n_input, const InputTask& input_task, bool par) {
  std::vector<Phase> own = compute;
  if (n_weight) own.push_back(phase(static_cast<int64_t>(n_weight), weight_task));
  if (n_input) own.push_back(phase(static_cast<int64_t>(n_input), input_task));
  run_stages({stage(prep), stage(own)}, par);
}

}  // namespace

void forward(const Geo& g, const Csr& csr, const bf16* x, const bf16* w, const bf16* bias, const bf16* style,
             const bf16* scale, bf16* y) {
  const int64_t U = g.U, h = g.h, Ci = g.Cin, Co = g.Cout, Cp = (Ci + 1) / 2;
  const bool par = worth_threads(g.macs);
  Src src;
  src.src = x;
  src.B = g.B;
  src.Ts = g.Tin;
  src.f = style;
  src.fb = Ci;
  src.fc = 1;
  auto bias_at = [&](int64_t o) { return bias ? to_f32(bias[o]) : 0.f; };
  auto scale_at = [&](int64_t b, int64_t o, int64_t e) { return scale ? to_f32(scale[(b * Co + o) * g.Eout + e]) : 1.f; };
  const Cvt cvt = cvt_fns();
  SlotScratch<float> accs;
  SlotScratch<const bf16*> ptrs;
  if (g.kind != kUp) {
    const int64_t S = g.kind == kDown ? 2 : 1;
    const int64_t Lp = g.Tin + 2 * h, Tq = (Lp + S - 1) / S;
    src.F = h;
    src.Lp = Lp;
    src.reflect = g.reflect;
    const LayoutBuild xb(src, Ci, g.Ein, S, Tq, U, true);
    std::vector<int64_t> ks(static_cast<size_t>(g.Eout)), rs(ks.size(), U);
    for (int64_t j = 0; j < g.Eout; ++j) ks[j] = csr.off[j + 1] - csr.off[j];
    const int64_t nnz = g.nnz, *off = csr.off.data();
    auto elem = [w, nnz, off, Ci, U](int64_t j, int64_t o, int64_t s, int64_t c, int64_t u) -> bf16 {
      return w[((o * nnz + off[j] + s) * Ci + c) * U + u];
    };
    const PackBuild<decltype(elem)> pk(Co, Ci, ks, rs, elem);
    const Phase prep[] = {xb.phase(), pk.phase()};
    const Layout& xc = xb.l;
    const int64_t nb = batch_tile(g.B, Tq, g.Eout, 512, kColTile);
    const int64_t ldacc = fastk::round_up(nb * Tq, kColTile), maxK = csr.max_deg * Cp * U;
    const std::vector<int64_t> order = lpt_tiles(g.B, nb, g.Eout, csr.off);
    auto task = [&](int64_t t, int slot) {
      float* acc = accs.get(slot, static_cast<size_t>(std::max<int64_t>(1, Co * ldacc)));
      const bf16** ptr = ptrs.get(slot, static_cast<size_t>(std::max<int64_t>(1, maxK)));
      const int64_t bt = order[t] / g.Eout, j = order[t] % g.Eout;
      const int64_t b0 = bt * nb, nbl = std::min(nb, g.B - b0), N = nbl * Tq;
      const int64_t p0 = csr.off[j], k = csr.off[j + 1] - p0;
      for (int64_t s = 0; s < k; ++s)
        for (int64_t cp = 0; cp < Cp; ++cp)
          for (int64_t u = 0; u < U; ++u)
            ptr[(s * Cp + cp) * U + u] = xc.row(u % S, cp, csr.idx[p0 + s]) + 2 * (b0 * Tq + u / S);
      nn_gemm(pk.at(j), Co, k * Cp * U, ptr, N, acc, ldacc);
      for (int64_t bl = 0; bl < nbl; ++bl)
        for (int64_t o = 0; o < Co; ++o) {
          float* row = acc + o * ldacc + bl * Tq;
          bf16* dst = y + (((b0 + bl) * Co + o) * g.Eout + j) * g.Tout;
          if (g.act) {  // the activation in fp32, one rounding
            const float f = scale_at(b0 + bl, o, j), bb = bias_at(o);
            for (int64_t t2 = 0; t2 < g.Tout; ++t2) row[t2] = act_fwd(row[t2] * f + bb);
            cvt.affine(row, dst, g.Tout, 1.f, 0.f);
          } else {
            cvt.affine(row, dst, g.Tout, scale_at(b0 + bl, o, j), bias_at(o));
          }
        }
    };
    const Phase compute[] = {phase(static_cast<int64_t>(order.size()), task)};
    run_stages({{prep, 2}, {compute, 1}}, par);
    return;
  }
  // up: fine entity f gathers its coarse sources through the transposed CSR, two output phases
  const int64_t R = (U + 1) / 2, Lpf = g.Tout + 2 * h, Mq = (Lpf + 1) / 2, Tq = Mq + R - 1;
  src.F = R - 1;
  src.Lp = Tq;
  const LayoutBuild xb(src, Ci, g.Ein, 1, Tq, U, true);
  std::vector<int64_t> ks(static_cast<size_t>(2 * g.Eout)), rs(ks.size());
  for (int64_t f = 0; f < g.Eout; ++f)
    for (int64_t ph = 0; ph < 2; ++ph) {
      ks[f * 2 + ph] = csr.toff[f + 1] - csr.toff[f];
      rs[f * 2 + ph] = (U - ph + 1) / 2;
    }
  const int64_t nnz = g.nnz, *toff = csr.toff.data(), *tpair = csr.tpair.data();
  // operand row o, K (s, i, r): w_up[i, pair of transposed entry q0 + s, o, tap ph + 2r]
  auto elem = [w, nnz, toff, tpair, Co, U](int64_t it, int64_t o, int64_t s, int64_t i, int64_t r) -> bf16 {
    const int64_t f = it / 2, ph = it % 2;
    return w[((i * nnz + tpair[toff[f] + s]) * Co + o) * U + ph + 2 * r];
  };
  const PackBuild<decltype(elem)> pk(Co, Ci, ks, rs, elem);
  const Phase prep[] = {xb.phase(), pk.phase()};
  const Layout& xc = xb.l;
  const int64_t nb = batch_tile(g.B, Tq, g.Eout, 512, kColTile);
  const int64_t ldacc = fastk::round_up(nb * Tq, kColTile), maxK = csr.max_tdeg * Cp * R;
  const std::vector<int64_t> order = lpt_tiles(g.B, nb, g.Eout, csr.toff);
  SlotScratch<float> rowbuf;
  const fastk::UpRowFn up_row = fastk::up_row_fn();
  auto task = [&](int64_t t, int slot) {
    float* a0 = accs.get(slot, static_cast<size_t>(std::max<int64_t>(1, 2 * Co * ldacc)));
    float* const acc[2] = {a0, a0 + Co * ldacc};
    const bf16** ptr = ptrs.get(slot, static_cast<size_t>(std::max<int64_t>(maxK, 1)));
    float* tmp = rowbuf.get(slot, static_cast<size_t>(g.Tout));
    const int64_t bt = order[t] / g.Eout, f = order[t] % g.Eout;
    const int64_t b0 = bt * nb, nbl = std::min(nb, g.B - b0), N = nbl * Tq;
    const int64_t q0 = csr.toff[f], k = csr.toff[f + 1] - q0;
    for (int64_t ph = 0; ph < 2; ++ph) {
      const int64_t Rp = (U - ph + 1) / 2;
      for (int64_t s = 0; s < k; ++s)
        for (int64_t cp = 0; cp < Cp; ++cp)
          for (int64_t r = 0; r < Rp; ++r)
            ptr[(s * Cp + cp) * Rp + r] = xc.row(0, cp, csr.tent[q0 + s]) + 2 * (b0 * Tq + R - 1 - r);
      nn_gemm(pk.at(f * 2 + ph), Co, k * Cp * Rp, ptr, N, acc[ph], ldacc);
    }
    for (int64_t bl = 0; bl < nbl; ++bl) {
      const int64_t b = b0 + bl;
      for (int64_t o = 0; o < Co; ++o) {
        up_row(acc[0] + o * ldacc + bl * Tq, acc[1] + o * ldacc + bl * Tq, tmp, g.Tout, h, g.reflect,
               scale_at(b, o, f), bias_at(o));
        if (g.act) act_row(tmp, g.Tout);
        cvt.affine(tmp, y + ((b * Co + o) * g.Eout + f) * g.Tout, g.Tout, 1.f, 0.f);
      }
    }
  };
  const Phase compute[] = {phase(static_cast<int64_t>(order.size()), task)};
  run_stages({{prep, 2}, {compute, 1}}, par);
}

void backward(const Geo& g, const Csr& csr, const bf16* gy, const bf16* out, const bf16* x, const bf16* w,
              const bf16* bias, const bf16* style, const bf16* scale, bf16* gx, bf16* gw, bf16* gb, bf16* gs,
              bf16* gd) {
  const int64_t U = g.U, h = g.h, Ci = g.Cin, Co = g.Cout, Ei = g.Ein, Eo = g.Eout, B = g.B, nnz = g.nnz;
  const bool par = worth_threads(g.macs);
  std::vector<Phase> prep, compute;
  const Cvt cvt = cvt_fns();

  // bias and scale gradients: reductions over the output in fp32, run with the preparation phases
  auto bias_task = [&](int64_t o, int) {
    float acc = 0.f;
    for (int64_t b = 0; b < B; ++b) acc += cvt.sum(gy + (b * Co + o) * Eo * g.Tout, Eo * g.Tout);
    gb[o] = to_bf16(acc);
  };
  const int64_t out_rows = B * Co * Eo, row_chunk = chunk_items(g.Tout);
  auto scale_task = [&](int64_t t, int) {  // y = d * z + bias  =>  dL/dd = sum_t gy * (y - bias) / d
    for (int64_t r = t * row_chunk, end = std::min(out_rows, (t + 1) * row_chunk); r < end; ++r) {
      const int64_t o = (r / Eo) % Co;
      const float bb = bias ? to_f32(bias[o]) : 0.f;
      gd[r] = to_bf16(cvt.gy_y(gy + r * g.Tout, out + r * g.Tout, g.Tout, bb) / to_f32(scale[r]));
    }
  };
  if (gb) prep.push_back(phase(Co, bias_task));
  if (gd) prep.push_back(phase((out_rows + row_chunk - 1) / row_chunk, scale_task));
  const bool want_input = gx != nullptr || gs != nullptr;
  if (!want_input && !gw) {
    run_phases(prep.data(), prep.size(), par);
    return;
  }
  std::vector<float> gs_part(gs ? static_cast<size_t>(Ei * B * Ci) : 0, 0.f);
  auto finish = [&](const float* row, int64_t b, int64_t i, int64_t n, int64_t L) {
    const int64_t xo = ((b * Ci + i) * Ei + n) * L;
    // the next channel's rows lie Ei * L apart, beyond what the hardware prefetchers follow
    if (i + 1 < Ci)
      for (int64_t off = 0; off < L; off += 32) {
        if (gs) __builtin_prefetch(x + xo + Ei * L + off);
        if (gx) __builtin_prefetch(gx + xo + Ei * L + off, 1);
      }
    if (gs) gs_part[(n * B + b) * Ci + i] += cvt.dot(row, x + xo, L);
    if (gx) cvt.affine(row, gx + xo, L, style ? to_f32(style[b * Ci + i]) : 1.f, 0.f);
  };
  Src sty;  // x * style
  sty.src = x;
  sty.B = B;
  sty.Ts = g.Tin;
  sty.f = style;
  sty.fb = Ci;
  sty.fc = 1;
  Src dsc;  // gy * d
  dsc.src = gy;
  dsc.B = B;
  dsc.Ts = g.Tout;
  dsc.f = scale;
  dsc.fb = Co * Eo;
  dsc.fc = Eo;
  dsc.fe = 1;
  SlotScratch<float> accs, rowbuf;
  SlotScratch<const bf16*> ptrs;
  SlotScratch<uint32_t> lts;
  const int64_t Cop = (Co + 1) / 2;

  if (g.kind == kUp) {
    // gv = blur^T(gy) * d on the fine grid, read like a down-sampler's input: stride 2, padding per mode
    const int64_t Tc = g.Tin, Lp = g.Tout + 2 * h, Tq = Tc + h;
    Src gs_src = dsc;
    gs_src.F = h;
    gs_src.Lp = Lp;
    gs_src.reflect = g.reflect;
    gs_src.blur_adjoint = true;
    const LayoutBuild gvb(gs_src, Co, Eo, 2, Tq, U, true);
    Src xs = sty;
    xs.F = 0;
    xs.Lp = Tc;
    const LayoutBuild xlb(xs, gw ? Ci : 0, gw ? Ei : 0, 1, Tq, U, false);
    std::vector<int64_t> ks(want_input ? static_cast<size_t>(Ei) : 0), rs(ks.size(), U);
    for (size_t c = 0; c < ks.size(); ++c) ks[c] = csr.off[c + 1] - csr.off[c];
    // operand row i, K (s, o, u): w[i, p0 + s, o, u]
    const int64_t* off = csr.off.data();
    auto elem = [w, nnz, off, Co, U](int64_t c, int64_t i, int64_t s, int64_t o, int64_t u) -> bf16 {
      return w[((i * nnz + off[c] + s) * Co + o) * U + u];
    };
    const PackBuild<decltype(elem)> pk(Ci, Co, ks, rs, elem);
    prep.push_back(gvb.phase());
    if (gw) prep.push_back(xlb.phase());
    if (want_input) prep.push_back(pk.phase());
    const Layout& gvc = gvb.l;
    const int64_t nb = batch_tile(B, Tq, Ei, 512, kColTile);
    const int64_t ldacc = fastk::round_up(nb * Tq, kColTile), maxK = csr.max_deg * std::max(Cop * U, Co * U);
    const std::vector<int64_t> order = want_input ? lpt_tiles(B, nb, Ei, csr.off) : std::vector<int64_t>{};
    auto input_task = [&](int64_t t, int slot) {
      float* acc = accs.get(slot, static_cast<size_t>(std::max<int64_t>(1, Ci * ldacc)));
      const bf16** ptr = ptrs.get(slot, static_cast<size_t>(maxK + Ci));
      const int64_t bt = order[t] / Ei, c = order[t] % Ei, b0 = bt * nb, nbl = std::min(nb, B - b0);
      const int64_t p0 = csr.off[c], k = csr.off[c + 1] - p0;
      for (int64_t s = 0; s < k; ++s)
        for (int64_t op = 0; op < Cop; ++op)
          for (int64_t u = 0; u < U; ++u)
            ptr[(s * Cop + op) * U + u] = gvc.row(u % 2, op, csr.idx[p0 + s]) + 2 * (b0 * Tq + u / 2);
      nn_gemm(pk.at(c), Ci, k * Cop * U, ptr, nbl * Tq, acc, ldacc);
      for (int64_t bl = 0; bl < nbl; ++bl)
        for (int64_t i = 0; i < Ci; ++i) finish(acc + i * ldacc + bl * Tq, b0 + bl, i, c, Tc);
    };
    // weight: gW[i, p0 + s, o, u] = sum over columns of x_i * gv shifted; x rows broadcast, gv rows transposed
    const int64_t ldw = nnz * Co * U, N = B * Tq;
    const RowBlocks wb = gw ? weight_blocks(Ei, Ci, csr.off, 12) : RowBlocks{};
    auto weight_task = [&](int64_t t, int slot) {
      const bf16** ptr = ptrs.get(slot, static_cast<size_t>(maxK + Ci));
      const bf16** arow = ptr + maxK;
      const int64_t c = wb.order[t] / wb.nrb, r0 = (wb.order[t] % wb.nrb) * wb.rb, nr = std::min(wb.rb, Ci - r0);
      const int64_t p0 = csr.off[c], k = csr.off[c + 1] - p0;
      for (int64_t s = 0; s < k; ++s)
        for (int64_t o = 0; o < Co; ++o)
          for (int64_t u = 0; u < U; ++u)
            ptr[(s * Co + o) * U + u] = gvc.chan(u % 2, o, csr.idx[p0 + s]) + 2 * (u / 2);
      for (int64_t i = 0; i < nr; ++i) arow[i] = xlb.l.row(0, r0 + i, c);
      wgrad(arow, nr, ptr, 2, k * Co * U, N, gw + r0 * ldw + p0 * Co * U, ldw, 1,
            lts.get(slot, static_cast<size_t>(32 * ((N + 1) / 2))));
    };
    run_backward(prep, compute, gw ? wb.order.size() : 0, weight_task, want_input ? order.size() : 0, input_task,
                 par);
  } else {
    const int64_t S = g.kind == kDown ? 2 : 1;
    // input gradient: transposed pass over the readers of each input entity; output on the padded domain, folded
    const int64_t Lp = g.Tin + 2 * h, R = S == 1 ? U : (U + 1) / 2, Mq = S == 1 ? Lp : (Lp + 1) / 2;
    const int64_t Tqi = Mq + R - 1;
    // Stride 1 with both gradients: the input gradient's layout of gy (R-1 leading zeros per element) serves the
    // weight gradient too, with x laid out U-1 frames later to match, so gy is laid out once (as fastk.cpp does).
    const bool shared_gy = S == 1 && want_input && gw;
    Src zs = dsc;
    zs.F = R - 1;
    zs.Lp = Tqi;
    const bool need_gz = want_input || shared_gy;
    const LayoutBuild gzb(zs, need_gz ? Co : 0, need_gz ? Eo : 0, 1, Tqi, U, true);
    std::vector<int64_t> ks(want_input ? static_cast<size_t>(Ei * S) : 0), rs(ks.size());
    for (size_t it = 0; it < ks.size(); ++it) {
      const int64_t n = it / S, ph = it % S;
      ks[it] = csr.toff[n + 1] - csr.toff[n];
      rs[it] = S == 1 ? U : (U - ph + 1) / 2;
    }
    // operand row i, K (s, o, r): w[o, pair of transposed entry q0 + s, i, tap], tap = r (stride 1), ph + 2r
    const int64_t *toff = csr.toff.data(), *tpair = csr.tpair.data();
    auto elem = [w, nnz, toff, tpair, Ci, U, S](int64_t it, int64_t i, int64_t s, int64_t o, int64_t r) -> bf16 {
      const int64_t n = it / S, ph = it % S;
      return w[((o * nnz + tpair[toff[n] + s]) * Ci + i) * U + (S == 1 ? r : ph + 2 * r)];
    };
    const PackBuild<decltype(elem)> pk(Ci, Co, ks, rs, elem);
    const int64_t Tqw = shared_gy ? Tqi : (Lp + S - 1) / S;
    Src xs = sty;
    xs.F = shared_gy ? h + U - 1 : h;
    xs.Lp = shared_gy ? Tqi : Lp;
    xs.Z = shared_gy ? U - 1 : 0;
    xs.reflect = g.reflect;
    const LayoutBuild xcb(xs, gw ? Ci : 0, gw ? Ei : 0, S, Tqw, U, false);
    Src ls = dsc;
    ls.F = 0;
    ls.Lp = g.Tout;
    const bool own_gl = gw && !shared_gy;
    const LayoutBuild glb(ls, own_gl ? Co : 0, own_gl ? Eo : 0, 1, Tqw, U, false);
    const Layout& gl = shared_gy ? gzb.l : glb.l;
    if (need_gz) prep.push_back(gzb.phase());
    if (want_input) prep.push_back(pk.phase());
    if (gw) prep.push_back(xcb.phase());
    if (own_gl) prep.push_back(glb.phase());

    const int64_t nb = batch_tile(B, Tqi, Ei, 512, kColTile);
    const int64_t ldacc = fastk::round_up(nb * Tqi, kColTile);
    const int64_t maxKi = std::max<int64_t>(1, csr.max_tdeg * Cop * R), maxKw = csr.max_deg * Ci * U;
    const std::vector<int64_t> order = want_input ? lpt_tiles(B, nb, Ei, csr.toff) : std::vector<int64_t>{};
    auto input_task = [&](int64_t t, int slot) {
      float* a0 = accs.get(slot, static_cast<size_t>(std::max<int64_t>(1, S * Ci * ldacc)));
      float* const acc[2] = {a0, a0 + Ci * ldacc};
      const bf16** ptr = ptrs.get(slot, static_cast<size_t>(std::max(maxKi, maxKw + Co)));
      float* gp = rowbuf.get(slot, static_cast<size_t>(Lp + g.Tin));
      float* row = gp + Lp;
      const int64_t bt = order[t] / Ei, n = order[t] % Ei, b0 = bt * nb, nbl = std::min(nb, B - b0);
      const int64_t q0 = csr.toff[n], k = csr.toff[n + 1] - q0;
      if (k == 0) {  // nobody reads this entity
        std::fill(row, row + g.Tin, 0.f);
        for (int64_t bl = 0; bl < nbl; ++bl)
          for (int64_t i = 0; i < Ci; ++i) finish(row, b0 + bl, i, n, g.Tin);
        return;
      }
      for (int64_t ph = 0; ph < S; ++ph) {
        const int64_t Rp = S == 1 ? U : (U - ph + 1) / 2;
        for (int64_t s = 0; s < k; ++s)
          for (int64_t op = 0; op < Cop; ++op) {
            const bf16* rp = gzb.l.row(0, op, csr.tent[q0 + s]) + 2 * b0 * Tqi;
            for (int64_t r = 0; r < Rp; ++r) ptr[(s * Cop + op) * Rp + r] = rp + 2 * (S == 1 ? U - 1 - r : R - 1 - r);
          }
        nn_gemm(pk.at(n * S + ph), Ci, k * Cop * Rp, ptr, nbl * Tqi, acc[ph], ldacc);
      }
      for (int64_t bl = 0; bl < nbl; ++bl)
        for (int64_t i = 0; i < Ci; ++i) {
          const float* r0 = acc[0] + i * ldacc + bl * Tqi;
          if (S == 2) {
            interleave_row(r0, acc[1] + i * ldacc + bl * Tqi, gp, Lp);
            r0 = gp;
          }
          fold_row<float>(r0, row, g.Tin, h, g.reflect);
          finish(row, b0 + bl, i, n, g.Tin);
        }
    };
    // weight: gW[o, p0 + s, i, u] = sum over columns of gy_o * x shifted; x rows broadcast, gy rows transposed
    const int64_t ldw = nnz * Ci * U, N = B * Tqw;
    const RowBlocks wb = gw ? weight_blocks(Eo, Co, csr.off, 32) : RowBlocks{};
    auto weight_task = [&](int64_t t, int slot) {
      const bf16** ptr = ptrs.get(slot, static_cast<size_t>(std::max(maxKi, maxKw + Co)));
      const bf16** lrow = ptr + maxKw;
      const int64_t j = wb.order[t] / wb.nrb, r0 = (wb.order[t] % wb.nrb) * wb.rb, nr = std::min(wb.rb, Co - r0);
      const int64_t p0 = csr.off[j], k = csr.off[j + 1] - p0, K = k * Ci * U;
      for (int64_t s = 0; s < k; ++s)
        for (int64_t c = 0; c < Ci; ++c)
          for (int64_t u = 0; u < U; ++u) ptr[(s * Ci + c) * U + u] = xcb.l.row(u % S, c, csr.idx[p0 + s]) + u / S;
      for (int64_t o = 0; o < nr; ++o) lrow[o] = gl.chan(0, r0 + o, j);
      wgrad(ptr, K, lrow, gl.width, nr, N, gw + r0 * ldw + p0 * Ci * U, 1, ldw,
            lts.get(slot, static_cast<size_t>(32 * ((N + 1) / 2))));
    };
    run_backward(prep, compute, gw ? wb.order.size() : 0, weight_task, want_input ? order.size() : 0, input_task,
                 par);
  }
  if (gs) {
    for (int64_t bi = 0; bi < B * Ci; ++bi) {
      float acc = 0.f;
      for (int64_t n = 0; n < Ei; ++n) acc += gs_part[n * B * Ci + bi];
      gs[bi] = to_bf16(acc);
    }
  }
}

}  // namespace bf16k
}  // namespace skeletal
}  // namespace modi_ext
