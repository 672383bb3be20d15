// Launch geometry of the skeletal CUDA GEMMs (skeletal/cuda.cu): pure host functions of the shapes and the SM count,
// so the emulator's test module can report what they decide for any shape without running a kernel.
//
// The host never reads the CSR (that would sync with the device), so every decision uses only rows, nnz and the
// channel widths.  Split counts aim at two waves of blocks (2 x SMs) and are fixed for given shapes and SM count;
// partials are summed in split order by one kernel, so results are deterministic.
#pragma once

#include <algorithm>
#include <cstdint>
#include <numeric>

namespace modi_ext {
namespace skeletal {
namespace plan {

constexpr int kBK = 16;                   // reduction depth of one shared-memory stage
constexpr int kBN = 64;                   // output columns per block (row / transposed GEMM), k columns (wgrad)
constexpr int64_t kMaxSplits = 32;        // bounds the partials workspace: splits x output numel
constexpr int64_t kMinSplitCols = 64;     // wgrad: batch x time columns per split (4 stages to pipeline)
constexpr int64_t kMinSplitStages = 8;    // row / transposed GEMM: mean k stages per split

inline int64_t cdiv(int64_t a, int64_t b) { return (a + b - 1) / b; }
inline int tile_rows(int64_t M) { return M <= 32 ? 32 : 64; }  // BM: narrow tiles for narrow GEMMs
inline int64_t waves2(int sm_count) { return 2 * int64_t(std::max(sm_count, 1)); }

// Weight gradient.  Grid (k-tile slot, m tile, split): the k range of each row (K_r = deg_r x CU columns of the
// weight) is cut into kBN-wide tiles that do not cross rows; slot -> (row, tile) is resolved on the device.  The
// host bounds the tile count without the degrees: K_r is a multiple of g = gcd(CU, kBN), so each row's last tile
// wastes at most kBN - g columns.  Slots past the real count exit at once.
struct WgradPlan {
  int64_t ktiles = 1, mtiles = 1, splits = 1, n_chunk = 0;
  int64_t ctas() const { return ktiles * mtiles * splits; }
};

inline WgradPlan wgrad_plan(int64_t N, int64_t rows, int64_t nnz, int64_t cu, int64_t M, int sm_count) {
  WgradPlan p;
  const int64_t g = std::gcd(cu, int64_t(kBN));
  p.ktiles = std::max<int64_t>(1, (nnz * cu + rows * (kBN - g)) / kBN);
  p.mtiles = cdiv(M, tile_rows(M));
  int64_t s = cdiv(waves2(sm_count), p.ktiles * p.mtiles);
  s = std::min(s, N / kMinSplitCols);
  s = std::max<int64_t>(1, std::min(s, kMaxSplits));
  // equal chunks, a multiple of 4 columns so the left operand's 4-vectors stay aligned; rounding may leave one
  // split fewer than asked (only when s > 17, as each chunk holds >= 64 columns)
  p.n_chunk = std::max<int64_t>(4, cdiv(cdiv(N, s), 4) * 4);
  p.splits = std::max<int64_t>(1, cdiv(N, p.n_chunk));  // no empty split
  return p;
}

// Row / transposed GEMM.  Grid (column tile, m tile, entity x split): when the column and row tiles leave the GPU
// idle, each entity's k stages are split into `splits` equal runs (the degree is known only on the device, so the
// host sizes the split by the mean run: nnz x CU / ents columns per entity).
struct GemmPlan {
  int64_t ntiles = 1, mtiles = 1, ents = 1, splits = 1;
  int64_t ctas() const { return ntiles * mtiles * ents * splits; }
};

inline GemmPlan gemm_plan(int64_t N, int64_t M, int64_t ents, int64_t nnz, int64_t cu, int sm_count) {
  GemmPlan p;
  p.ntiles = cdiv(N, kBN);
  p.mtiles = cdiv(M, tile_rows(M));
  p.ents = ents;
  const int64_t mean_stages = cdiv(nnz * cu, std::max<int64_t>(ents, 1) * kBK);
  int64_t s = cdiv(waves2(sm_count), p.ntiles * p.mtiles * std::max<int64_t>(ents, 1));
  s = std::min(s, mean_stages / kMinSplitStages);
  p.splits = std::max<int64_t>(1, std::min(s, kMaxSplits));
  return p;
}

}  // namespace plan
}  // namespace skeletal
}  // namespace modi_ext
