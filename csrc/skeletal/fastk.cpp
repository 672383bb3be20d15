// The passes of the fp32 fast path (fastk.h): each lays its inputs out once per call in column form (ColsBuild),
// packs the weights (PackEntities, PackTransposed) and runs one indirect product per entity and batch tile on the
// kernels of fastk_gemm.cpp, as preparation and compute stages of one task-pool job (common/tasks.h).
#include <algorithm>
#include <cstdint>
#include <vector>

#include "skeletal/fastk.h"

namespace modi_ext {
namespace skeletal {
namespace fastk {
namespace {

// Column layout of a (B, C, E, Ts) tensor: row (phase, c, e) of length row_len; at b*Tq + m it holds
// f(b,c,e) * src[b, c, e, q] for padded position p = S*m + phase < Lp, q = p - F; q outside [0, Ts) reads the
// mirror image (reflect) or 0.  Past Lp, before Z (stride 1 only), between batch blocks and in the slack after the
// last block: 0.
// blur_adjoint: the source row of (b, c, e) is blur^T(src row) (the up op's backward), computed on the fly.
struct ColsSrc {
  const float* src = nullptr;
  int64_t B = 0, Ts = 0;
  Scale<float> f;
  int64_t F = 0, Lp = 0, Z = 0;
  bool reflect = false, blur_adjoint = false;
};

struct Cols {
  Buf<float> buf;
  int64_t C = 0, E = 0, Tq = 0, row_len = 0, rows = 0;
  const float* row(int64_t ph, int64_t c, int64_t e) const { return buf.data() + ((ph * C + c) * E + e) * row_len; }
};

// Builds a Cols as a preparation phase: tasks of whole rows.  Must stay in place while its phase runs.
struct ColsBuild {
  Cols cl;
  ColsSrc cs;
  int64_t S = 1, chunk = 1;
  mutable SlotScratch<float> tmp;
  ColsBuild(const ColsSrc& src, int64_t C, int64_t E, int64_t S_, int64_t Tq, int64_t max_shift) : cs(src), S(S_) {
    cl.C = C;
    cl.E = E;
    cl.Tq = Tq;
    int64_t len = round_up(cs.B * Tq + NR + max_shift + 8, 8);
    if ((len * 4) % 4096 == 0) len += 16;  // avoid rows aliasing in the same cache sets
    cl.row_len = len;
    cl.rows = S * C * E;
    cl.buf.alloc(static_cast<size_t>(cl.rows * len));
    chunk = chunk_items(len);
  }
  ColsBuild(const ColsBuild&) = delete;
  ColsBuild& operator=(const ColsBuild&) = delete;

  void fill(int64_t r, int slot) const {
    const int64_t C = cl.C, E = cl.E, Tq = cl.Tq, B = cs.B, Ts = cs.Ts, F = cs.F, Lp = cs.Lp;
    const bool reflect = cs.reflect;
    const int64_t ph = r / (C * E), c = (r / E) % C, e = r % E;
    float* dst = cl.buf.data() + r * cl.row_len;
    float* blurred = cs.blur_adjoint ? tmp.get(slot, static_cast<size_t>(Ts)) : nullptr;
    for (int64_t b = 0; b < B; ++b) {
      const float fv = cs.f.at(b, c, e);
      const float* s = cs.src + ((b * C + c) * E + e) * Ts;
      if (blurred) {
        blur_adjoint_row<float>(s, blurred, Ts);
        s = blurred;
      }
      float* d = dst + b * Tq;
      if (S == 1) {
        const int64_t lo_m = std::min(std::max<int64_t>(F, 0), Tq), hi_m = std::max(lo_m, std::min({Tq, Lp, F + Ts}));
        for (int64_t m = 0; m < lo_m; ++m) d[m] = (m >= cs.Z && m < Lp && reflect) ? fv * s[mirror(m - F, Ts)] : 0.f;
        for (int64_t m = lo_m; m < hi_m; ++m) d[m] = fv * s[m - F];
        for (int64_t m = hi_m; m < Tq; ++m) d[m] = (m < Lp && reflect) ? fv * s[mirror(m - F, Ts)] : 0.f;
      } else {
        for (int64_t m = 0; m < Tq; ++m) {
          const int64_t p = S * m + ph;
          float v = 0.f;
          if (p < Lp) {
            const int64_t q = p - F;
            if (q >= 0 && q < Ts)
              v = s[q];
            else if (reflect)
              v = s[mirror(q, Ts)];
          }
          d[m] = fv * v;
        }
      }
    }
    std::fill(dst + B * Tq, dst + cl.row_len, 0.f);
  }
  void operator()(int64_t t, int slot) const {
    for (int64_t r = t * chunk, end = std::min(cl.rows, (t + 1) * chunk); r < end; ++r) fill(r, slot);
  }
  Phase phase() const { return cpu_tasks::phase((cl.rows + chunk - 1) / chunk, *this); }
};

// A operands are packed once per call into 4-row panels: panel pn holds out[(pn*K + kk)*4 + r] = A[pn*4 + r][kk]
// (rows past M are 0), so the NN kernel reads its 4 broadcasts from one cache line.
// Plain: A[m][kk] = src[m*lda + kk].
void pack_plain(float* out, int64_t M, int64_t K, const float* src, int64_t lda) {
  const int64_t panels = (M + MR - 1) / MR;
  for (int64_t pn = 0; pn < panels; ++pn)
    for (int64_t r = 0; r < MR; ++r) {
      const int64_t m = pn * MR + r;
      float* o = out + pn * K * MR + r;
      if (m < M) {
        const float* row = src + m * lda;
        for (int64_t kk = 0; kk < K; ++kk) o[kk * MR] = row[kk];
      } else {
        for (int64_t kk = 0; kk < K; ++kk) o[kk * MR] = 0.f;
      }
    }
}

// Grouped: columns come in groups of Rp taps; A[m][g*Rp + r] = base[g][m*mstride + tap0 + tap_step*r].
void pack_groups(float* out, int64_t M, int64_t K, const float* const* base, int64_t n_groups, int64_t Rp,
                 int64_t mstride, int64_t tap0, int64_t tap_step) {
  const int64_t panels = (M + MR - 1) / MR;
  if (panels * MR > M) std::fill(out, out + panels * MR * K, 0.f);
  for (int64_t gi = 0; gi < n_groups; ++gi)
    for (int64_t m = 0; m < M; ++m) {
      const float* src = base[gi] + m * mstride + tap0;
      float* o = out + ((m / MR) * K + gi * Rp) * MR + (m % MR);
      for (int64_t r = 0; r < Rp; ++r) o[r * MR] = src[r * tap_step];
    }
}

// All entities' packed operands of one pass (and phase), addressed by entity * phases + phase.
struct Packs {
  Buf<float> buf;
  std::vector<int64_t> off;
  const float* at(int64_t i) const { return buf.data() + off[i]; }
};

// Transposed pass: for output entity n and phase ph the operand row m, column (s, c, r) is
// w_t(m, pair of transposed entry q0+s, c, tap) with tap = r (stride 1) or ph + 2r (stride 2).  `group_base(q, c)`
// returns a pointer such that element (m, tap) sits at base[m*mstride + tap].  A preparation phase (one task per
// entity and phase); must stay in place while it runs.
template <typename GroupBase>
struct PackTransposed {
  Packs pk;
  const Csr& csr;
  int64_t stride, U, M, Csrc, mstride;
  GroupBase group_base;
  mutable SlotScratch<const float*> bases;
  PackTransposed(const Csr& csr_, int64_t n_ent, int64_t stride_, int64_t U_, int64_t M_, int64_t Csrc_,
                 int64_t mstride_, GroupBase gb)
      : csr(csr_), stride(stride_), U(U_), M(M_), Csrc(Csrc_), mstride(mstride_), group_base(gb) {
    const int64_t rows = round_up(M, MR);
    pk.off.assign(static_cast<size_t>(n_ent * stride + 1), 0);
    for (int64_t n = 0; n < n_ent; ++n)
      for (int64_t ph = 0; ph < stride; ++ph) {
        const int64_t Rp = stride == 1 ? U : (U - ph + 1) / 2;
        const int64_t k = csr.toff[n + 1] - csr.toff[n];
        pk.off[n * stride + ph + 1] = pk.off[n * stride + ph] + rows * k * Csrc * Rp;
      }
    pk.buf.alloc(static_cast<size_t>(pk.off.back()));
  }
  PackTransposed(const PackTransposed&) = delete;
  PackTransposed& operator=(const PackTransposed&) = delete;
  void operator()(int64_t e, int slot) const {
    const int64_t n = e / stride, ph = e % stride;
    const int64_t Rp = stride == 1 ? U : (U - ph + 1) / 2;
    const int64_t q0 = csr.toff[n], k = csr.toff[n + 1] - q0;
    const float** base = bases.get(slot, static_cast<size_t>(std::max<int64_t>(1, csr.max_tdeg * Csrc)));
    for (int64_t s = 0; s < k; ++s)
      for (int64_t c = 0; c < Csrc; ++c) base[s * Csrc + c] = group_base(q0 + s, c);
    pack_groups(pk.buf.data() + pk.off[e], M, k * Csrc * Rp, base, k * Csrc, Rp, mstride, stride == 1 ? 0 : ph,
                stride == 1 ? 1 : 2);
  }
  Phase phase() const { return cpu_tasks::phase(static_cast<int64_t>(pk.off.size()) - 1, *this); }
};

// Plain pass: entity j's operand is rows [0, M) of the strided view src + off[j]*colw (row stride lda), K_j wide.
struct PackEntities {
  Packs pk;
  const Csr& csr;
  int64_t M;
  const float* src;
  int64_t lda, colw;
  PackEntities(const Csr& csr_, int64_t M_, const float* src_, int64_t lda_, int64_t colw_)
      : csr(csr_), M(M_), src(src_), lda(lda_), colw(colw_) {
    const int64_t rows = round_up(M, MR);
    pk.off.assign(static_cast<size_t>(csr.rows + 1), 0);
    for (int64_t j = 0; j < csr.rows; ++j) pk.off[j + 1] = pk.off[j] + rows * (csr.off[j + 1] - csr.off[j]) * colw;
    pk.buf.alloc(static_cast<size_t>(pk.off.back()));
  }
  PackEntities(const PackEntities&) = delete;
  PackEntities& operator=(const PackEntities&) = delete;
  void operator()(int64_t j, int) const {
    pack_plain(pk.buf.data() + pk.off[j], M, (csr.off[j + 1] - csr.off[j]) * colw, src + csr.off[j] * colw, lda);
  }
  Phase phase() const { return cpu_tasks::phase(csr.rows, *this); }
};

// Output of a stride-2 transposed pass lives in two phase accumulators; rebuild a padded row of length Lp.
inline void interleave_row(const float* a0, const float* a1, float* out, int64_t Lp) {
  const int64_t pairs = Lp / 2;  // in pairs, without a test per element: the compiler vectorises it
  for (int64_t i = 0; i < pairs; ++i) {
    out[2 * i] = a0[i];
    out[2 * i + 1] = a1[i];
  }
  if (Lp & 1) out[Lp - 1] = a0[pairs];
}

// Transposed pass (output entity list = transposed CSR): acc rows = Mrows channels of output entity n; the
// inputs are `src` rows of the entities that read n.  stride 1: one product over taps u (pointer shift U-1-u);
// stride 2: one product per output phase over taps u = phase + 2r (pointer shift R-1-r).
void transposed_products(const Cols& src, int64_t Csrc, const Csr& csr, int64_t n, int64_t b0, int64_t stride,
                         int64_t U, int64_t Mrows, const Packs& pk, const float** ptr, float* const* acc, int64_t N,
                         int64_t ldacc) {
  const int64_t q0 = csr.toff[n], k = csr.toff[n + 1] - q0;
  const int64_t R = stride == 1 ? U : (U + 1) / 2;
  for (int64_t ph = 0; ph < stride; ++ph) {
    const int64_t Rp = stride == 1 ? U : (U - ph + 1) / 2;  // taps of this phase
    const int64_t K = k * Csrc * Rp;
    for (int64_t s = 0; s < k; ++s)
      for (int64_t c = 0; c < Csrc; ++c) {
        const float* rowp = src.row(0, c, csr.tent[q0 + s]) + b0 * src.Tq;
        for (int64_t r = 0; r < Rp; ++r) ptr[(s * Csrc + c) * Rp + r] = rowp + (stride == 1 ? (U - 1 - r) : (R - 1 - r));
      }
    nn_gemm(pk.at(n * stride + ph), Mrows, K, ptr, N, acc[ph], ldacc);
  }
}

// One weight-gradient block C (nr rows of K, ldc) = L (nr pointer rows) * P^T (K pointer rows) over N columns:
// wide layers on the AVX-512 NN form (scratch: a 32-wide transpose of L), the others on the dot-product kernel.
inline void weight_block(bool wide, const float* const* l, int64_t nr, const float* const* p, int64_t K, int64_t N,
                         float* C, int64_t ldc, SlotScratch<float>& scratch, int slot) {
  if (wide) {
    wgrad512(l, nr, p, K, N, C, ldc, scratch.get(slot, static_cast<size_t>(round_up(nr, 32) * N)));
    return;
  }
  for (int64_t i = 0; i < nr; ++i) std::fill(C + i * ldc, C + i * ldc + K, 0.f);
  nt_gemm(l, nr, p, K, N, C, ldc);
}

// A backward pass's job: the preparation stage (the caller's phases and the layouts), then the weight-gradient
// blocks, the caller's compute phases and the input-gradient tiles.
template <class WeightTask, class InputTask>
void run_backward(const std::vector<Phase>& prep, const std::vector<Phase>& compute, size_t n_weight,
                  const WeightTask& weight_task, size_t n_input, const InputTask& input_task, bool par) {
  std::vector<Phase> own;
  if (n_weight) own.push_back(phase(static_cast<int64_t>(n_weight), weight_task));
  own.insert(own.end(), compute.begin(), compute.end());
  if (n_input) own.push_back(phase(static_cast<int64_t>(n_input), input_task));
  run_stages({stage(prep), stage(own)}, par);
}

}  // namespace

void forward(const Geo& g, const Csr& csr, const float* x, const float* w, const float* bias,
             const Scale<float>& sty, const float* scale, float* y) {
  const int64_t U = g.U, h = g.h, Ci = g.Cin, Co = g.Cout;
  const bool par = worth_threads(g.macs);
  if (g.kind != kUp) {
    const int64_t S = g.kind == kDown ? 2 : 1;
    const int64_t Lp = g.Tin + 2 * h, Tq = (Lp + S - 1) / S;
    ColsSrc src;
    src.src = x;
    src.B = g.B;
    src.Ts = g.Tin;
    src.f = sty;
    src.F = h;
    src.Lp = Lp;
    src.reflect = g.reflect;
    const ColsBuild xb(src, Ci, g.Ein, S, Tq, U);
    const bool direct = Co <= kDirectRows && use512();
    const PackEntities pe(csr, direct ? 0 : Co, w, g.nnz * Ci * U, Ci * U);
    const Phase prep[] = {xb.phase(), pe.phase()};
    const Cols& xc = xb.cl;
    const int64_t nb = batch_tile(g.B, Tq, g.Eout, 512, nn_col_tile());
    const int64_t ldacc = round_up(nb * Tq, NR), rows = round_up(Co, MR), maxK = csr.max_deg * Ci * U;
    const std::vector<int64_t> order = lpt_tiles(g.B, nb, g.Eout, csr.off);
    SlotScratch<float> accs;
    SlotScratch<const float*> ptrs;
    auto task = [&](int64_t t, int slot) {
      float* acc = accs.get(slot, static_cast<size_t>(rows * ldacc));
      const float** ptr = ptrs.get(slot, static_cast<size_t>(maxK));
      const int64_t bt = order[t] / g.Eout, j = order[t] % g.Eout;
      const int64_t b0 = bt * nb, nbl = std::min(nb, g.B - b0), N = nbl * Tq;
      const int64_t p0 = csr.off[j], k = csr.off[j + 1] - p0, K = k * Ci * U;
      for (int64_t s = 0; s < k; ++s)
        for (int64_t c = 0; c < Ci; ++c)
          for (int64_t u = 0; u < U; ++u)
            ptr[(s * Ci + c) * U + u] = xc.row(u % S, c, csr.idx[p0 + s]) + b0 * Tq + u / S;
      if (direct)
        nn_gemm_direct(w + p0 * Ci * U, g.nnz * Ci * U, Co, K, ptr, N, acc, ldacc);
      else
        nn_gemm(pe.pk.at(j), Co, K, ptr, N, acc, ldacc);
      for (int64_t bl = 0; bl < nbl; ++bl) {
        const int64_t b = b0 + bl;
        for (int64_t o = 0; o < Co; ++o) {
          const float f = scale ? scale[(b * Co + o) * g.Eout + j] : 1.f;
          const float bb = bias ? bias[o] : 0.f;
          const float* src_row = acc + o * ldacc + bl * Tq;
          float* dst = y + ((b * Co + o) * g.Eout + j) * g.Tout;
          for (int64_t t2 = 0; t2 < g.Tout; ++t2) dst[t2] = src_row[t2] * f + bb;
          if (g.act) act_row(dst, g.Tout);
        }
      }
    };
    const Phase compute[] = {phase(static_cast<int64_t>(order.size()), task)};
    run_stages({{prep, size_t{direct ? 1u : 2u}}, {compute, 1}}, par);  // direct: no packing phase
    return;
  }
  // up: fine entity f gathers its coarse sources through the transposed CSR, two output phases
  const int64_t R = (U + 1) / 2, Lpf = g.Tout + 2 * h, Mq = (Lpf + 1) / 2, Tq = Mq + R - 1;
  ColsSrc src;
  src.src = x;
  src.B = g.B;
  src.Ts = g.Tin;
  src.f = sty;
  src.F = R - 1;
  src.Lp = Tq;
  const ColsBuild xb(src, Ci, g.Ein, 1, Tq, U);
  // operand row o, column (s, i, r): w_up[i, pair, o, tap]
  auto base = [&](int64_t q, int64_t i) { return w + (i * g.nnz + csr.tpair[q]) * Co * U; };
  const PackTransposed<decltype(base)> pt(csr, g.Eout, 2, U, Co, Ci, U, base);
  const Phase prep[] = {xb.phase(), pt.phase()};
  const Cols& xc = xb.cl;
  const int64_t nb = batch_tile(g.B, Tq, g.Eout, 512, nn_col_tile());
  const int64_t ldacc = round_up(nb * Tq, NR), rows = round_up(Co, MR), maxK = csr.max_tdeg * Ci * R;
  const std::vector<int64_t> order = lpt_tiles(g.B, nb, g.Eout, csr.toff);
  SlotScratch<float> accs;
  SlotScratch<const float*> ptrs;
  const UpRowFn up_row = up_row_fn();
  auto task = [&](int64_t t, int slot) {
    float* a0 = accs.get(slot, static_cast<size_t>(2 * rows * ldacc));
    float* const acc[2] = {a0, a0 + rows * ldacc};
    const float** ptr = ptrs.get(slot, static_cast<size_t>(std::max<int64_t>(maxK, 1)));
    const int64_t bt = order[t] / g.Eout, f = order[t] % g.Eout;
    const int64_t b0 = bt * nb, nbl = std::min(nb, g.B - b0), N = nbl * Tq;
    transposed_products(xc, Ci, csr, f, b0, 2, U, Co, pt.pk, ptr, acc, N, ldacc);
    for (int64_t bl = 0; bl < nbl; ++bl) {
      const int64_t b = b0 + bl;
      for (int64_t o = 0; o < Co; ++o) {
        const float fs = scale ? scale[(b * Co + o) * g.Eout + f] : 1.f;
        const float bb = bias ? bias[o] : 0.f;
        float* dst = y + ((b * Co + o) * g.Eout + f) * g.Tout;
        up_row(acc[0] + o * ldacc + bl * Tq, acc[1] + o * ldacc + bl * Tq, dst, g.Tout, h, g.reflect, fs, bb);
        if (g.act) act_row(dst, g.Tout);
      }
    }
  };
  const Phase compute[] = {phase(static_cast<int64_t>(order.size()), task)};
  run_stages({{prep, 2}, {compute, 1}}, par);
}
void backward(const Geo& g, const Csr& csr, const float* gy, const Scale<float>& gsc, const float* x, const float* w,
              const float* style, float* gx, float* gw, float* gs_part, std::vector<Phase> prep,
              std::vector<Phase> compute) {
  const int64_t U = g.U, h = g.h, Ci = g.Cin, Co = g.Cout, Ei = g.Ein, Eo = g.Eout, B = g.B;
  const bool par = worth_threads(g.macs);
  Scale<float> sty;
  if (style) {
    sty.p = style;
    sty.sb = Ci;
    sty.sc = 1;
  }
  const bool want_input = gx != nullptr || gs_part != nullptr;
  auto finish = [&](const float* row, int64_t b, int64_t i, int64_t n, int64_t L) {
    const int64_t xo = ((b * Ci + i) * Ei + n) * L;
    finish_input_row<float>(row, x + xo, style ? style[b * Ci + i] : 1.f, gx ? gx + xo : nullptr,
                            gs_part ? gs_part + (n * B + b) * Ci + i : nullptr, L);
  };
  SlotScratch<float> accs, rowbuf, aux;
  SlotScratch<const float*> ptrs;
  // wide layers' weight gradient on the AVX-512 NN form; narrow ones (<= kNarrowRows rows) on nt_gemm
  const bool wide_w = use512() && (g.kind == kUp ? Ci : Co) > kNarrowRows;
  if (g.kind == kUp) {
    // gv = blur^T(gy) * d on the fine grid, read like a down-sampler's input: stride 2, padding per mode
    const int64_t Tc = g.Tin, Lp = g.Tout + 2 * h, Tq = Tc + h;
    ColsSrc gs;
    gs.src = gy;
    gs.B = B;
    gs.Ts = g.Tout;
    gs.f = gsc;
    gs.F = h;
    gs.Lp = Lp;
    gs.reflect = g.reflect;
    gs.blur_adjoint = true;
    const ColsBuild gvb(gs, Co, Eo, 2, Tq, U);
    ColsSrc xs;
    xs.src = x;
    xs.B = B;
    xs.Ts = Tc;
    xs.f = sty;
    xs.F = 0;
    xs.Lp = Tc;
    const ColsBuild xlb(xs, gw ? Ci : 0, gw ? Ei : 0, 1, Tq, U);
    const int64_t lda = g.nnz * Co * U, maxK = csr.max_deg * Co * U;
    const PackEntities pe(csr, want_input ? Ci : 0, w, lda, Co * U);
    prep.push_back(gvb.phase());
    if (gw) prep.push_back(xlb.phase());
    if (want_input) prep.push_back(pe.phase());
    const Cols& gvc = gvb.cl;
    auto set_ptrs = [&](const float** ptr, int64_t c, int64_t b0) {
      const int64_t p0 = csr.off[c], k = csr.off[c + 1] - p0;
      for (int64_t s = 0; s < k; ++s)
        for (int64_t o = 0; o < Co; ++o)
          for (int64_t u = 0; u < U; ++u)
            ptr[(s * Co + o) * U + u] = gvc.row(u % 2, o, csr.idx[p0 + s]) + b0 * Tq + u / 2;
      return k * Co * U;
    };
    const int64_t nb = batch_tile(B, Tq, Ei, 512, nn_col_tile());
    const int64_t ldacc = round_up(nb * Tq, NR), rows = round_up(Ci, MR);
    const std::vector<int64_t> order = want_input ? lpt_tiles(B, nb, Ei, csr.off) : std::vector<int64_t>{};
    auto input_task = [&](int64_t t, int slot) {
      float* acc = accs.get(slot, static_cast<size_t>(rows * ldacc));
      const float** ptr = ptrs.get(slot, static_cast<size_t>(maxK + Ci));
      const int64_t bt = order[t] / Ei, c = order[t] % Ei, b0 = bt * nb, nbl = std::min(nb, B - b0);
      const int64_t K = set_ptrs(ptr, c, b0);
      nn_gemm(pe.pk.at(c), Ci, K, ptr, nbl * Tq, acc, ldacc);
      for (int64_t bl = 0; bl < nbl; ++bl)
        for (int64_t i = 0; i < Ci; ++i) finish(acc + i * ldacc + bl * Tq, b0 + bl, i, c, Tc);
    };
    // weight: gW[i, pairs of c, o, u] over the whole batch, rows i split into blocks when entities are few
    const RowBlocks wb = gw ? weight_blocks(Ei, Ci, csr.off, TM) : RowBlocks{};
    auto weight_task = [&](int64_t t, int slot) {
      const float** ptr = ptrs.get(slot, static_cast<size_t>(maxK + Ci));
      const float** lrow = ptr + maxK;
      const int64_t c = wb.order[t] / wb.nrb, r0 = (wb.order[t] % wb.nrb) * wb.rb, nr = std::min(wb.rb, Ci - r0);
      const int64_t K = set_ptrs(ptr, c, 0);
      for (int64_t i = 0; i < nr; ++i) lrow[i] = xlb.cl.row(0, r0 + i, c);
      weight_block(wide_w, lrow, nr, ptr, K, B * Tq, gw + r0 * lda + csr.off[c] * Co * U, lda, accs, slot);
    };
    run_backward(prep, compute, gw ? wb.order.size() : 0, weight_task, want_input ? order.size() : 0, input_task,
                 par);
    return;
  }
  const int64_t S = g.kind == kDown ? 2 : 1;
  // input gradient: transposed pass over the readers of each input entity; output on the padded domain, then folded
  const int64_t Lp = g.Tin + 2 * h;
  const int64_t R = S == 1 ? U : (U + 1) / 2;
  const int64_t Mq = S == 1 ? Lp : (Lp + 1) / 2;
  const int64_t Tqi = Mq + R - 1;
  ColsSrc zs;
  zs.src = gy;
  zs.B = B;
  zs.Ts = g.Tout;
  zs.f = gsc;
  zs.F = R - 1;
  zs.Lp = Tqi;
  const ColsBuild gzb(zs, want_input ? Co : 0, want_input ? Eo : 0, 1, Tqi, U);
  // operand row i, column (s, o, r): w[o, pair, i, tap]
  auto base = [&](int64_t q, int64_t o) { return w + (o * g.nnz + csr.tpair[q]) * Ci * U; };
  const PackTransposed<decltype(base)> pt(csr, want_input ? Ei : 0, S, U, Ci, Co, U, base);
  // weight gradient operands: x laid out like the forward's, gy * d in plain rows.  Stride 1 with both gradients:
  // the input gradient's layout of gy (U-1 leading zeros per batch element) serves both passes, with x laid out U-1
  // frames later to match (zeros before), so gy is laid out once instead of twice (one 3.5 MB pass less at MoDi's
  // finest level) for (U-1)/(T+2h) more weight-gradient columns.
  const bool shared_gy = S == 1 && want_input && gw;
  const int64_t Tqw = shared_gy ? Tqi : (Lp + S - 1) / S;
  ColsSrc xs;
  xs.src = x;
  xs.B = B;
  xs.Ts = g.Tin;
  xs.f = sty;
  xs.F = shared_gy ? h + U - 1 : h;
  xs.Lp = shared_gy ? Tqi : Lp;
  xs.Z = shared_gy ? U - 1 : 0;
  xs.reflect = g.reflect;
  const ColsBuild xcb(xs, gw ? Ci : 0, gw ? Ei : 0, S, Tqw, U);
  ColsSrc ls;
  ls.src = gy;
  ls.B = B;
  ls.Ts = g.Tout;
  ls.f = gsc;
  ls.F = 0;
  ls.Lp = g.Tout;
  const ColsBuild glb(ls, gw && !shared_gy ? Co : 0, gw && !shared_gy ? Eo : 0, 1, Tqw, U);
  const Cols& gl = shared_gy ? gzb.cl : glb.cl;
  if (want_input) {
    prep.push_back(gzb.phase());
    prep.push_back(pt.phase());
  }
  if (gw) {
    prep.push_back(xcb.phase());
    if (!shared_gy) prep.push_back(glb.phase());
  }

  const int64_t nb = batch_tile(B, Tqi, Ei, 512, nn_col_tile());
  const int64_t ldacc = round_up(nb * Tqi, NR), rows = round_up(Ci, MR);
  const int64_t maxKi = std::max<int64_t>(1, csr.max_tdeg * Co * R), maxKw = csr.max_deg * Ci * U;
  const std::vector<int64_t> order = want_input ? lpt_tiles(B, nb, Ei, csr.toff) : std::vector<int64_t>{};
  auto input_task = [&](int64_t t, int slot) {
    float* a0 = accs.get(slot, static_cast<size_t>((S == 2 ? 2 : 1) * rows * ldacc));
    float* const acc[2] = {a0, S == 2 ? a0 + rows * ldacc : nullptr};
    const float** ptr = ptrs.get(slot, static_cast<size_t>(std::max(maxKi, maxKw + Co)));
    float* gp = rowbuf.get(slot, static_cast<size_t>(Lp + g.Tin));
    float* row = gp + Lp;
    const int64_t bt = order[t] / Ei, n = order[t] % Ei, b0 = bt * nb, nbl = std::min(nb, B - b0);
    if (csr.toff[n + 1] == csr.toff[n]) {  // nobody reads this entity
      for (int64_t bl = 0; bl < nbl; ++bl)
        for (int64_t i = 0; i < Ci; ++i) {
          std::fill(row, row + g.Tin, 0.f);
          finish(row, b0 + bl, i, n, g.Tin);
        }
      return;
    }
    transposed_products(gzb.cl, Co, csr, n, b0, S, U, Ci, pt.pk, ptr, acc, nbl * Tqi, ldacc);
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
  // weight: gW[o, pairs of j, i, u] over the whole batch, rows o split into blocks when entities are few
  const int64_t ldw = g.nnz * Ci * U;
  const RowBlocks wb = gw ? weight_blocks(Eo, Co, csr.off, TM) : RowBlocks{};
  auto weight_task = [&](int64_t t, int slot) {
    const float** ptr = ptrs.get(slot, static_cast<size_t>(std::max(maxKi, maxKw + Co)));
    const float** lrow = ptr + maxKw;
    const int64_t j = wb.order[t] / wb.nrb, r0 = (wb.order[t] % wb.nrb) * wb.rb, nr = std::min(wb.rb, Co - r0);
    const int64_t p0 = csr.off[j], k = csr.off[j + 1] - p0, K = k * Ci * U;
    for (int64_t s = 0; s < k; ++s)
      for (int64_t c = 0; c < Ci; ++c)
        for (int64_t u = 0; u < U; ++u) ptr[(s * Ci + c) * U + u] = xcb.cl.row(u % S, c, csr.idx[p0 + s]) + u / S;
    for (int64_t o = 0; o < nr; ++o) lrow[o] = gl.row(0, r0 + o, j);
    weight_block(wide_w, lrow, nr, ptr, K, B * Tqw, gw + r0 * ldw + p0 * Ci * U, ldw, aux, slot);
  };
  run_backward(prep, compute, gw ? wb.order.size() : 0, weight_task, want_input ? order.size() : 0, input_task, par);
}

}  // namespace fastk
}  // namespace skeletal
}  // namespace modi_ext
