// The fp32 fast path's NN GEMM (csrc/skeletal/fastk_gemm.cpp, nn_gemm: the product the skeletal conv's forward and
// input gradient run per output entity) on its own, one thread, against torch.mm at 1024^3 on one thread in the
// same process.  The pointer rows are laid out as in MoDi's finest conv (K = 3 neighbours x 32 channels x 3 taps =
// 288 rows, 528 columns: 8 batch elements x 66 padded frames, M = 32 output channels) and stay in the caches, so
// the figure is what the micro-kernel reaches when nothing else of the conv (the column layout, the output rows,
// the op's dispatch) takes time: the bound the conv's other parts leave to it (docs/results.md#roofline).
//
//   python benchmarks/nn_kernel_rate.py        # builds this file against the installed torch, then runs it
#include <ATen/ATen.h>
#include <ATen/Parallel.h>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <functional>
#include <vector>

#include "skeletal/fastk_gemm.cpp"  // the kernels and their drivers, compiled here as in the extension

namespace {

double seconds_per_call(const std::function<void()>& fn, int calls, int reps) {
  double best = 1e30;
  for (int rep = 0; rep < reps; ++rep) {
    const auto t0 = std::chrono::steady_clock::now();
    for (int i = 0; i < calls; ++i) fn();
    const double s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count() / calls;
    best = std::min(best, s);
  }
  return best;
}

}  // namespace

int main(int argc, char** argv) {
  using namespace modi_ext::skeletal::fastk;
  at::set_num_threads(1);
  if (!use512() && !wanted()) {  // the extension runs BLAS here, not these kernels
    std::fprintf(stderr, "nn_kernel_rate: this CPU has neither AVX-512F nor AVX2+FMA (or MODI_EXT_CPU_KERNEL=blas)\n");
    return 2;
  }
  const int64_t M = argc > 1 ? std::atoll(argv[1]) : 32, K = argc > 2 ? std::atoll(argv[2]) : 288;
  const int64_t N = argc > 3 ? std::atoll(argv[3]) : 528;
  const int64_t stride = N + 16;  // the column layout's rows: N columns and the padding of the next tile
  std::vector<float> apack(static_cast<size_t>((M + MR - 1) / MR * MR * K), 0.01f);
  std::vector<float> rows(static_cast<size_t>(K * stride + 64), 1.0f), acc(static_cast<size_t>(M * (N + 64)));
  std::vector<const float*> ptr(static_cast<size_t>(K));
  for (int64_t k = 0; k < K; ++k) ptr[k] = rows.data() + (k * 97 % K) * stride;  // rows read out of order
  const at::Tensor a = at::randn({1024, 1024}), b = at::randn({1024, 1024});
  // Rounds alternate the two (the machine's clock and neighbours drift): per round the best of several calls of
  // each, then the median and the range of the rounds' ratios.
  std::vector<double> nn, mm, frac;
  for (int round = 0; round < 9; ++round) {
    const double s_nn = seconds_per_call([&] { nn_gemm(apack.data(), M, K, ptr.data(), N, acc.data(), N + 64); },
                                         20, 5);
    const double s_mm = seconds_per_call([&] { at::mm(a, b); }, 2, 3);
    nn.push_back(2.0 * M * K * N / s_nn / 1e9);
    mm.push_back(2.0 * 1024 * 1024 * 1024 / s_mm / 1e9);
    frac.push_back(nn.back() / mm.back());
  }
  auto median = [](std::vector<double> v) {
    std::sort(v.begin(), v.end());
    return v[v.size() / 2];
  };
  std::printf("{\"kernel\": \"%s\", \"M\": %ld, \"K\": %ld, \"N\": %ld, \"rounds\": %zu, \"nn_gemm_gflops\": %.1f, "
              "\"sgemm_1thread_gflops\": %.1f, \"nn_gemm_frac_sgemm\": %.3f, \"frac_range\": [%.3f, %.3f]}\n",
              use512() ? "avx512" : "avx2", static_cast<long>(M), static_cast<long>(K),
              static_cast<long>(N), frac.size(), median(nn), median(mm), median(frac),
              *std::min_element(frac.begin(), frac.end()), *std::max_element(frac.begin(), frac.end()));
  return 0;
}
