// Tensor-core (WMMA) form of the forward GEMMs: bf16 operands, fp32 accumulation.  The row GEMM (kTr = false) for
// conv / down, the transposed GEMM (kTr = true: the adjoint read, then the blur) for up; the same products as
// gemm_block's.  Opt-in: MODI_EXT_CUDA_MMA=1 (read per call in forward_cuda); no default path uses it until a GPU has
// timed it.
//
// Included by skeletal/cuda.cu inside its anonymous namespace, after the types it shares with the SIMT kernels:
// GemmArgs (the gathered operand and the topology), read_fwd / read_tr, and the epilogue Epi / epi_store_at, so
// scale, style, bias and the bias activation are exactly the SIMT kernels'.
//
//   out[b, m, j, t] = sum_k W_j[m, k] X_j[k, (b, t)],   k = (r * C + c) * U + u over the r-th neighbour (reader) of j
//
// Block: entity blockIdx.z, rows m0 = blockIdx.y * kBM .. + 31, column tiles blockIdx.x, + gridDim.x, ... of the
// N = B x L columns.  4 warps in 2 x 2 over the 32 x 64 tile, each warp 16 x 32 outputs (two accumulator fragments).
//   * The weight rows are staged as bf16 in panels of kKP reduction columns.  A panel stays resident while the block
//     walks its column tiles: with K <= kKP (most skeletal layers) it is read from global memory once per block.
//   * The gathered operand is decoded (neighbour, channel, tap, padding, stride or its adjoint, blur, style) once per
//     block and 16-deep stage into a 16 x 64 bf16 tile, rounded to bf16 once, then read by every warp's fragments.
//   * The accumulators go through shared memory to the per-element epilogue.
// Single-buffered stages: the shape of the computation first; pipelining (cp.async, double buffers) once a GPU can
// time it.  Launch: grid.x is sized for about two waves, so a block walks several column tiles at large B x L.
namespace tc {

constexpr int kBM = 32;      // output rows (channels) per block
constexpr int kBN = 64;      // output columns (batch x time) per column tile
constexpr int kBK = 16;      // reduction depth of one stage (the WMMA k)
constexpr int kKP = 512;     // reduction columns of one resident weight panel
constexpr int kThreads = 128;
// Padded leading dimensions (elements): multiples of 16 bytes as WMMA requires; the pad shifts rows across banks.
constexpr int kLdw = kKP + 8, kLdb = kBN + 8, kLdc = kBN + 4;
static_assert(kKP % kBK == 0, "panels hold whole stages");
static_assert(kBM * kLdw * 2 + kBK * kLdb * 2 + kBM * kLdc * 4 <= 48 * 1024, "static shared memory");

}  // namespace tc

template <typename T, bool kTr>
__global__ void __launch_bounds__(tc::kThreads) mma_gemm_kernel(const GemmArgs<T> a) {
#if defined(__CUDA_ARCH__) && __CUDA_ARCH__ < 800
  (void)a;
  __trap();  // bf16 WMMA needs sm_80; the launcher refuses older devices
#else
  namespace wmma = nvcuda::wmma;
  using E = __nv_bfloat16;
  static_assert(std::is_same_v<T, at::BFloat16>, "bf16 operands only (TF32 for float32 is not written yet)");
  MODI_SHARED_WMMA(E, Ws, [tc::kBM][tc::kLdw]);
  MODI_SHARED_WMMA(E, Bs, [tc::kBK][tc::kLdb]);
  MODI_SHARED_WMMA(float, Cs, [tc::kBM][tc::kLdc]);
  const int tid = threadIdx.x, warp = tid / 32;
  const int wm = warp / 2, wn = warp % 2;  // this warp's 16 x 32 outputs: rows 16 wm, columns 32 wn
  const int ent = blockIdx.z, m0 = blockIdx.y * tc::kBM;
  const int* const eoff = kTr ? a.toff : a.off;  // the entity's neighbours (transposed: readers) q0 ...
  const int q0 = eoff[ent];
  const int CU = a.C * a.U;
  const int K = (eoff[ent + 1] - q0) * CU;  // transposed: 0 for an entity nobody reads (its outputs get the bias)
  const int nk = (K + tc::kBK - 1) / tc::kBK;
  [[maybe_unused]] const T* const wblk = a.w + int64_t(q0) * CU;  // row GEMM: the entity's block, row m at + m * lda
  const int64_t ntiles = (a.N + tc::kBN - 1) / tc::kBN;

  wmma::fragment<wmma::matrix_a, 16, 16, 16, E, wmma::row_major> fa;
  wmma::fragment<wmma::matrix_b, 16, 16, 16, E, wmma::row_major> fb;
  wmma::fragment<wmma::accumulator, 16, 16, 16, float> acc[2];
  int panel = -1;  // the weight panel in Ws (block-uniform)
  for (int64_t nt = blockIdx.x; nt < ntiles; nt += gridDim.x) {
    const int64_t n0 = nt * tc::kBN;
    wmma::fill_fragment(acc[0], 0.0f);
    wmma::fill_fragment(acc[1], 0.0f);
    for (int kt = 0; kt < nk; ++kt) {
      const int k0 = kt * tc::kBK;
      if (k0 / tc::kKP != panel) {  // every warp is past its last read of Ws: the previous stage ended in a barrier
        panel = k0 / tc::kKP;
        const int kp0 = panel * tc::kKP;
        const int kw = K - kp0 < tc::kKP ? (K - kp0 + tc::kBK - 1) / tc::kBK * tc::kBK : tc::kKP;  // whole stages, zeros past K
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
          Ws[r][c] = __float2bfloat16(v);
        }
      }
      // Stage row kk, column j: reduction index k0 + kk (zero past K), column n0 + j (zero past N); threads run
      // along j, i.e. along time, so neighbouring threads read neighbouring frames.
      // MODI_EMU_MMA_TILE_EDGE is 0 outside the emulator's defect injection (common/cuda_common.cuh).
      const int k_end = K - MODI_EMU_MMA_TILE_EDGE;
      for (int i = tid; i < tc::kBK * tc::kBN; i += tc::kThreads) {
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
            v = read_fwd<T, false>(a.src.row(b, c, e), a.src.L, a.s * t + u - a.h, a.reflect) * a.fac.at(b, c, e);
          } else {
            const int e = a.tent[q0 + r];
            v = read_tr<T, true>(a.src.row(b, c, e), a.src.L, a.L, t, a.h - u, a.s, a.reflect) * a.fac.at(b, c, e);
          }
        }
        Bs[kk][j] = __float2bfloat16(v);
      }
      __syncthreads();
      wmma::load_matrix_sync(fa, &Ws[16 * wm][k0 - panel * tc::kKP], tc::kLdw);
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

// The forward of `a` (bf16) on the tensor cores: the row GEMM (conv / down) over `ents` row entities, or the
// transposed GEMM (up) over `ents` column entities.
template <typename T, bool kTr>
void launch_mma_forward(const GemmArgs<T>& a, int64_t ents, int device, cudaStream_t stream) {
  TORCH_CHECK(cuda::cc_major(device) >= 8,
              "modi_ext: MODI_EXT_CUDA_MMA=1 needs bf16 tensor cores (compute capability 8.0 or later)");
  const int64_t ntiles = ceil_div(a.N, tc::kBN), mtiles = ceil_div(a.M, tc::kBM);
  // about two waves of blocks; the rest of the column tiles are walked by each block with its weights resident
  const int64_t want = ceil_div(2 * int64_t(cuda::sm_count(device)), mtiles * std::max<int64_t>(ents, 1));
  const int64_t gx = std::max<int64_t>(1, std::min(ntiles, want));
  const dim3 grid(static_cast<unsigned>(gx), static_cast<unsigned>(mtiles), static_cast<unsigned>(ents));
  MODI_LAUNCH((mma_gemm_kernel<T, kTr>), grid, tc::kThreads, 0, stream, a);
  C10_CUDA_KERNEL_LAUNCH_CHECK();
}
