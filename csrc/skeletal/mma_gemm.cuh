// Tensor-core (WMMA) form of the skeletal GEMMs: bf16 operands (16 x 16 x 16 fragments) for bf16 inputs, TF32
// operands (16 x 16 x 8, precision::tf32) for float32 inputs; fp32 accumulation either way.  Opt-in:
// MODI_EXT_CUDA_MMA=1, and for float32 only while torch allows TF32 (cuda.cu: mma_for).
//
// Included by skeletal/cuda.cu inside its anonymous namespace, after the types and kernels it shares with the SIMT
// path: GemmArgs / WArgs (the gathered operand and the topology), read_fwd / read_tr, the epilogue Epi / epi_store_at
// (scale, style, bias, bias activation, or the style gradient's fp32 workspace) and split_reduce.
//
//   mma_gemm_kernel<T, kTr, kBlur>: out[b, m, j, t] = sum_k W_j[m, k] X_j[k, (b, t)] -- gemm_block's products:
//     forward conv / down <false, false>, forward up <true, true>, input gradient of conv / down <true, false>,
//     input gradient of up <false, true> (the row GEMM read through the blur's adjoint).
//   mma_wgrad_kernel<T, kBlurAdj>: gW[m, k] = sum_(b, t) L[m, (b, t)] G[k, (b, t)] -- wgrad_kernel's products.
//
// Block (both): 4 warps in 2 x 2 over a 32 x 64 output tile, each warp 16 x 32 outputs (two accumulator fragments).
// Operands are staged in shared memory already rounded to the fragment format (bf16, or tf32 by __float_to_tf32), so
// each gathered value is decoded (neighbour, channel, tap, padding, stride or its adjoint, blur, style / demodulation
// factor) and rounded once per block, then read by every warp's fragments.  The accumulators go through shared memory
// to the per-element epilogue.
//   * mma_gemm_kernel: entity blockIdx.z, rows m0 = blockIdx.y * kBM, column tiles blockIdx.x, + gridDim.x, ... of
//     the N = B x L columns.  The weight rows are staged in panels of kKP reduction columns; a panel stays resident
//     while the block walks its column tiles (with K <= kKP, most skeletal layers, it is read once per block).
//   * mma_wgrad_kernel: grid (k-tile slot, m tile, split of batch x time) as wgrad_kernel's plan (launch_plan.h); one
//     split writes gW, several write fp32 partials that split_reduce_kernel sums in split order: deterministic, no
//     atomics.
// Single-buffered stages: the shape of the computation first; pipelining (cp.async, double buffers) once a GPU can
// time it.
namespace tc {

constexpr int kBM = 32;  // output rows (channels) per block
constexpr int kBN = 64;  // output columns per tile (mma_gemm: batch x time; mma_wgrad: weight columns)
constexpr int kThreads = 128;
constexpr int kLdb = kBN + 8, kLdc = kBN + 4;  // padded leading dimensions: multiples of 16 bytes, as WMMA requires

// The operand format of T's tensor-core GEMMs: E the shared-memory element, F the fragment's element type, kK the
// fragment depth (the reduction depth of one stage), kKP the resident weight panel's width (fits 48 KB of static
// shared memory with the other tiles), cvt the rounding into E.
template <typename T>
struct Op;

template <>
struct Op<at::BFloat16> {
  using E = __nv_bfloat16;
  using F = __nv_bfloat16;
  static constexpr int kK = 16, kKP = 512;
  static __device__ __forceinline__ E cvt(float v) { return __float2bfloat16(v); }
};

template <>
struct Op<float> {
  using E = float;
  static constexpr int kK = 8, kKP = 256;
#if !defined(__CUDA_ARCH__) || __CUDA_ARCH__ >= 800  // <mma.h> declares tf32 for sm_80 on (the kernels trap below)
  using F = nvcuda::wmma::precision::tf32;
  // cvt.rna.tf32.f32 (round to nearest, ties away from zero): the fragments must hold tf32 values
  static __device__ __forceinline__ E cvt(float v) { return nvcuda::wmma::__float_to_tf32(v); }
#endif
};

template <typename T>
constexpr int kLdw = Op<T>::kKP + 8;  // the weight panel [kBM][kLdw]
template <typename T>
constexpr int kLdl = Op<T>::kK + 8;   // mma_wgrad's left-operand stage [kBM][kLdl]

template <typename T>
constexpr bool fits_static_smem() {
  using E = typename Op<T>::E;
  return kBM * kLdw<T> * sizeof(E) + Op<T>::kK * kLdb * sizeof(E) + kBM * kLdc * sizeof(float) <= 48 * 1024;
}
static_assert(fits_static_smem<at::BFloat16>() && fits_static_smem<float>(), "static shared memory");
static_assert(Op<at::BFloat16>::kKP % Op<at::BFloat16>::kK == 0 && Op<float>::kKP % Op<float>::kK == 0,
              "panels hold whole stages");

}  // namespace tc

template <typename T, bool kTr, bool kBlur>
__global__ void __launch_bounds__(tc::kThreads) mma_gemm_kernel(const GemmArgs<T> a) {
#if defined(__CUDA_ARCH__) && __CUDA_ARCH__ < 800
  (void)a;
  __trap();  // bf16 / tf32 WMMA needs sm_80; the launcher refuses older devices
#else
  namespace wmma = nvcuda::wmma;
  using O = tc::Op<T>;
  using E = typename O::E;
  constexpr int KK = O::kK, KP = O::kKP, LDW = tc::kLdw<T>;
  MODI_SHARED_WMMA(E, Ws, [tc::kBM][LDW]);
  MODI_SHARED_WMMA(E, Bs, [KK][tc::kLdb]);
  MODI_SHARED_WMMA(float, Cs, [tc::kBM][tc::kLdc]);
  const int tid = threadIdx.x, warp = tid / 32;
  const int wm = warp / 2, wn = warp % 2;  // this warp's 16 x 32 outputs: rows 16 wm, columns 32 wn
  const int ent = blockIdx.z, m0 = blockIdx.y * tc::kBM;
  const int* const eoff = kTr ? a.toff : a.off;  // the entity's neighbours (transposed: readers) q0 ...
  const int q0 = eoff[ent];
  const int CU = a.C * a.U;
  const int K = (eoff[ent + 1] - q0) * CU;  // transposed: 0 for an entity nobody reads (its outputs get the bias)
  const int nk = (K + KK - 1) / KK;
  [[maybe_unused]] const T* const wblk = a.w + int64_t(q0) * CU;  // row GEMM: the entity's block, row m at + m * lda
  const int64_t ntiles = (a.N + tc::kBN - 1) / tc::kBN;

  wmma::fragment<wmma::matrix_a, 16, 16, KK, typename O::F, wmma::row_major> fa;
  wmma::fragment<wmma::matrix_b, 16, 16, KK, typename O::F, wmma::row_major> fb;
  wmma::fragment<wmma::accumulator, 16, 16, KK, float> acc[2];
  int panel = -1;  // the weight panel in Ws (block-uniform)
  for (int64_t nt = blockIdx.x; nt < ntiles; nt += gridDim.x) {
    const int64_t n0 = nt * tc::kBN;
    wmma::fill_fragment(acc[0], 0.0f);
    wmma::fill_fragment(acc[1], 0.0f);
    for (int kt = 0; kt < nk; ++kt) {
      const int k0 = kt * KK;
      if (k0 / KP != panel) {  // every warp is past its last read of Ws: the previous stage ended in a barrier
        panel = k0 / KP;
        const int kp0 = panel * KP;
        const int kw = K - kp0 < KP ? (K - kp0 + KK - 1) / KK * KK : KP;  // whole stages, zeros past K
        for (int i = tid; i < tc::kBM * kw; i += tc::kThreads) {
          const int r = i / kw, c = i - r * kw;
          const int m = m0 + r, k = kp0 + c;
          float v = 0.0f;
          if (m < a.M && k < K) {
            if constexpr (!kTr) {
              v = ld(wblk + int64_t(m) * a.lda + k);
            } else {  // w[ci, pair, m, u], read transposed
              const int rr = k / CU, rem = k - rr * CU;
              const int ci = rem / a.U, u = rem - ci * a.U;
              v = ld(a.w + ((int64_t(ci) * a.nnz + a.tpair[q0 + rr]) * a.M + m) * a.U + u);
            }
          }
          Ws[r][c] = O::cvt(v);
        }
      }
      // Stage row kk, column j: reduction index k0 + kk (zero past K), column n0 + j (zero past N); threads run
      // along j, i.e. along time, so neighbouring threads read neighbouring frames.
      // MODI_EMU_MMA_TILE_EDGE is 0 outside the emulator's defect injection (common/cuda_common.cuh).
      const int k_end = K - MODI_EMU_MMA_TILE_EDGE;
      for (int i = tid; i < KK * tc::kBN; i += tc::kThreads) {
        const int kk = i / tc::kBN, j = i - kk * tc::kBN;
        const int k = k0 + kk;
        const int64_t n = n0 + j;
        float v = 0.0f;
        if (k < k_end && n < a.N) {
          const int b = static_cast<int>(n / a.L), t = static_cast<int>(n - int64_t(b) * a.L);
          const int r = k / CU, rem = k - r * CU;
          const int c = rem / a.U, u = rem - c * a.U;
          if constexpr (!kTr) {
            const int e = a.idx[q0 + r];
            v = read_fwd<T, kBlur>(a.src.row(b, c, e), a.src.L, a.s * t + u - a.h, a.reflect) * a.fac.at(b, c, e);
          } else {
            const int e = a.tent[q0 + r];
            v = read_tr<T, kBlur>(a.src.row(b, c, e), a.src.L, a.L, t, a.h - u, a.s, a.reflect) * a.fac.at(b, c, e);
          }
        }
        Bs[kk][j] = O::cvt(v);
      }
      __syncthreads();
      wmma::load_matrix_sync(fa, &Ws[16 * wm][k0 - panel * KP], LDW);
#pragma unroll
      for (int f = 0; f < 2; ++f) {
        // MODI_EMU_MMA_FRAGMENT_OFFSET is 0 outside the emulator's defect injection (common/cuda_common.cuh)
        wmma::load_matrix_sync(fb, &Bs[0][32 * wn + 16 * (f ^ MODI_EMU_MMA_FRAGMENT_OFFSET)], tc::kLdb);
        wmma::mma_sync(acc[f], fa, fb, acc[f]);
      }
      __syncthreads();  // Bs (and at a panel change Ws) are rewritten next
    }
#pragma unroll
    for (int f = 0; f < 2; ++f) {
      wmma::store_matrix_sync(&Cs[16 * wm][32 * wn + 16 * f], acc[f], tc::kLdc, wmma::mem_row_major);
    }
    __syncthreads();
    for (int i = tid; i < tc::kBM * tc::kBN; i += tc::kThreads) {
      const int r = i / tc::kBN, j = i - r * tc::kBN;
      const int m = m0 + r;
      const int64_t n = n0 + j;
      if (m >= a.M || n >= a.N) continue;
      const int b = static_cast<int>(n / a.L), t = static_cast<int>(n - int64_t(b) * a.L);
      epi_store_at(a.epi, a.M, a.L, ((int64_t(b) * a.M + m) * a.epi.E + ent) * a.L + t, Cs[r][j]);
    }
    __syncthreads();  // Cs is rewritten by the next column tile
  }
#endif
}

// gW[m * lda + p0 * C * U + k] = sum_{n = (b, t)} L[m, n] G[k, n] over this block's split of the N = B x L columns:
// L[m, n] = lsrc[b, m, row, t] * lfac(b, m, row), G[k, n] the row GEMM's gathered operand of `row` (wgrad_kernel's).
// Stage s: Ls[r][c] = L[m0 + r, n_s + c] and Gs[c][j] = G[kc0 + j, n_s + c], c < kK, both rounded to the fragment
// format; the warp's A fragment reads Ls (rows m, depth n), its B fragments Gs (depth n, columns k).
template <typename T, bool kBlurAdj>
__global__ void __launch_bounds__(tc::kThreads) mma_wgrad_kernel(const WArgs<T> a) {
#if defined(__CUDA_ARCH__) && __CUDA_ARCH__ < 800
  (void)a;
  __trap();  // bf16 / tf32 WMMA needs sm_80; the launcher refuses older devices
#else
  namespace wmma = nvcuda::wmma;
  using O = tc::Op<T>;
  using E = typename O::E;
  constexpr int KK = O::kK, LDL = tc::kLdl<T>;
  MODI_SHARED_WMMA(E, Ls, [tc::kBM][LDL]);
  MODI_SHARED_WMMA(E, Gs, [KK][tc::kLdb]);
  MODI_SHARED_WMMA(float, Cs, [tc::kBM][tc::kLdc]);
  const int tid = threadIdx.x, warp = tid / 32;
  const int wm = warp / 2, wn = warp % 2;
  const int CU = a.C * a.U;
  int row = -1, kc0 = 0;  // this block's k tile: columns kc0 ... kc0 + kBN - 1 of `row`'s weight block
  for (int r = 0, slot = blockIdx.x; r < a.rows; ++r) {
    const int nt = ((a.off[r + 1] - a.off[r]) * CU + tc::kBN - 1) / tc::kBN;
    if (slot < nt) {
      row = r;
      kc0 = slot * tc::kBN;
      break;
    }
    slot -= nt;
  }
  if (row < 0) return;  // past the last tile: the whole block, before any barrier
  const int m0 = blockIdx.y * tc::kBM;
  const int split = blockIdx.z;
  const int64_t nb = int64_t(split) * a.n_chunk;
  const int64_t ne = nb + a.n_chunk < a.N ? nb + a.n_chunk : a.N;
  // MODI_EMU_MMA_WGRAD_TILE_EDGE is 0 outside the emulator's defect injection (common/cuda_common.cuh)
  const int64_t n_end = ne - MODI_EMU_MMA_WGRAD_TILE_EDGE;
  const int p0 = a.off[row];
  const int K = (a.off[row + 1] - p0) * CU;
  const int64_t nsteps = ne > nb ? (ne - nb + KK - 1) / KK : 0;

  wmma::fragment<wmma::matrix_a, 16, 16, KK, typename O::F, wmma::row_major> fa;
  wmma::fragment<wmma::matrix_b, 16, 16, KK, typename O::F, wmma::row_major> fb;
  wmma::fragment<wmma::accumulator, 16, 16, KK, float> acc[2];
  wmma::fill_fragment(acc[0], 0.0f);
  wmma::fill_fragment(acc[1], 0.0f);
  for (int64_t stage = 0; stage < nsteps; ++stage) {
    const int64_t n0 = nb + stage * KK;
    // threads run along n (time) in both stages, so neighbouring threads read neighbouring frames
    for (int i = tid; i < tc::kBM * KK; i += tc::kThreads) {
      const int r = i / KK, c = i - r * KK;
      const int m = m0 + r;
      const int64_t n = n0 + c;
      float v = 0.0f;
      if (m < a.M && n < n_end) {
        const int b = static_cast<int>(n / a.L), t = static_cast<int>(n - int64_t(b) * a.L);
        v = ld(a.lsrc + ((int64_t(b) * a.M + m) * a.El + row) * a.L + t) * a.lfac.at(b, m, row);
      }
      Ls[r][c] = O::cvt(v);
    }
    for (int i = tid; i < KK * tc::kBN; i += tc::kThreads) {
      const int j = i / KK, c = i - j * KK;
      const int kc = kc0 + j;
      const int64_t n = n0 + c;
      float v = 0.0f;
      if (kc < K && n < n_end) {
        const int b = static_cast<int>(n / a.L), t = static_cast<int>(n - int64_t(b) * a.L);
        const int r = kc / CU, rem = kc - r * CU;
        const int ci = rem / a.U, u = rem - ci * a.U;
        const int e = a.idx[p0 + r];
        v = read_fwd<T, kBlurAdj>(a.src.row(b, ci, e), a.src.L, a.s * t + u - a.h, a.reflect) * a.fac.at(b, ci, e);
      }
      Gs[c][j] = O::cvt(v);
    }
    __syncthreads();
    wmma::load_matrix_sync(fa, &Ls[16 * wm][0], LDL);
#pragma unroll
    for (int f = 0; f < 2; ++f) {
      // MODI_EMU_MMA_WGRAD_FRAGMENT_OFFSET is 0 outside the emulator's defect injection (common/cuda_common.cuh)
      wmma::load_matrix_sync(fb, &Gs[0][32 * wn + 16 * (f ^ MODI_EMU_MMA_WGRAD_FRAGMENT_OFFSET)], tc::kLdb);
      wmma::mma_sync(acc[f], fa, fb, acc[f]);
    }
    __syncthreads();  // Ls and Gs are rewritten next
  }
#pragma unroll
  for (int f = 0; f < 2; ++f) {
    wmma::store_matrix_sync(&Cs[16 * wm][32 * wn + 16 * f], acc[f], tc::kLdc, wmma::mem_row_major);
  }
  __syncthreads();
  for (int i = tid; i < tc::kBM * tc::kBN; i += tc::kThreads) {
    const int r = i / tc::kBN, j = i - r * tc::kBN;
    const int m = m0 + r, kc = kc0 + j;
    if (m >= a.M || kc >= K) continue;
    const int64_t o = int64_t(m) * a.lda + int64_t(p0) * CU + kc;
    if (a.ws) {
      a.ws[int64_t(split) * a.wnumel + o] = Cs[r][j];
    } else {
      st(a.gw + o, Cs[r][j]);
    }
  }
#endif
}

// The row GEMM (kTr = false) over `ents` row entities or the transposed GEMM over `ents` column entities, of `a`
// (bf16 or float32) on the tensor cores.
template <typename T, bool kTr, bool kBlur>
void launch_mma_gemm(const GemmArgs<T>& a, int64_t ents, int device, cudaStream_t stream) {
  TORCH_CHECK(cuda::cc_major(device) >= 8,
              "modi_ext: MODI_EXT_CUDA_MMA=1 needs bf16 / tf32 tensor cores (compute capability 8.0 or later)");
  const int64_t ntiles = ceil_div(a.N, tc::kBN), mtiles = ceil_div(a.M, tc::kBM);
  // about two waves of blocks; the rest of the column tiles are walked by each block with its weights resident
  const int64_t want = ceil_div(2 * int64_t(cuda::sm_count(device)), mtiles * std::max<int64_t>(ents, 1));
  const int64_t gx = std::max<int64_t>(1, std::min(ntiles, want));
  const dim3 grid(static_cast<unsigned>(gx), static_cast<unsigned>(mtiles), static_cast<unsigned>(ents));
  MODI_LAUNCH((mma_gemm_kernel<T, kTr, kBlur>), grid, tc::kThreads, 0, stream, a);
  C10_CUDA_KERNEL_LAUNCH_CHECK();
}

// The weight gradient of `a` into gw on the tensor cores: wgrad_kernel's k-tile slots and splits of batch x time
// (plan::wgrad_plan, whose kBN-wide k tiles are this kernel's), 32-row m tiles; with several splits the fp32 partials
// are summed in split order.
template <typename T, bool kBlurAdj>
void launch_mma_wgrad(WArgs<T> a, int64_t rows, int64_t nnz, const at::Tensor& gw, int device, cudaStream_t stream) {
  static_assert(tc::kBN == skeletal::plan::kBN, "the plan's k tiles are the kernel's column tiles");
  TORCH_CHECK(cuda::cc_major(device) >= 8,
              "modi_ext: MODI_EXT_CUDA_MMA=1 needs bf16 / tf32 tensor cores (compute capability 8.0 or later)");
  const auto p = skeletal::plan::wgrad_plan(a.N, rows, nnz, int64_t(a.C) * a.U, a.M, cuda::sm_count(device));
  a.rows = static_cast<int>(rows);
  a.n_chunk = p.n_chunk;
  a.gw = gw.data_ptr<T>();
  a.wnumel = gw.numel();
  at::Tensor ws;
  if (p.splits > 1) {
    ws = at::empty({p.splits * a.wnumel}, gw.options().dtype(at::kFloat));
    a.ws = ws.data_ptr<float>();
  }
  const dim3 grid(static_cast<unsigned>(p.ktiles), static_cast<unsigned>(ceil_div(a.M, tc::kBM)),
                  static_cast<unsigned>(p.splits));
  MODI_LAUNCH((mma_wgrad_kernel<T, kBlurAdj>), grid, tc::kThreads, 0, stream, a);
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  if (p.splits > 1) {
    Epi<T> out;
    out.out = a.gw;
    out.E = 1;
    launch_split_reduce<T>(a.ws, p.splits, a.wnumel, out, 1, 1, stream);
  }
}
