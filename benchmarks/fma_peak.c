// The fp32 FMA peak of this CPU, at 1 and 2 threads: 12 independent AVX-512 FMA chains per thread, all in
// registers (no loads), so the loop is bound by the FMA units alone.  The roofline (docs/results.md#roofline) sets
// sgemm and the kernels beside it: what the hardware could do, as against what a GEMM library reaches.
//
//   gcc -O2 -fopenmp benchmarks/fma_peak.c -o /tmp/fma_peak && /tmp/fma_peak
#include <immintrin.h>
#include <omp.h>
#include <stdio.h>
#include <time.h>

static double now(void) {
  struct timespec t;
  clock_gettime(CLOCK_MONOTONIC, &t);
  return t.tv_sec + 1e-9 * t.tv_nsec;
}

__attribute__((target("avx512f"))) static float chains(long n) {
  __m512 acc[12];
  const __m512 x = _mm512_set1_ps(1.0000001f), y = _mm512_set1_ps(0.9999999f);
  for (int i = 0; i < 12; i++) acc[i] = _mm512_set1_ps((float)i);
  for (long k = 0; k < n; k++) {
#pragma GCC unroll 12
    for (int i = 0; i < 12; i++) acc[i] = _mm512_fmadd_ps(acc[i], x, y);
  }
  __m512 s = acc[0];
  for (int i = 1; i < 12; i++) s = _mm512_add_ps(s, acc[i]);
  return _mm512_reduce_add_ps(s);  // used, so the chains are not optimised away
}

int main(void) {
  if (!__builtin_cpu_supports("avx512f")) {
    printf("this CPU has no AVX-512F\n");
    return 1;
  }
  const long n = 200000000 / 12 * 2;
  for (int threads = 1; threads <= 2; threads++) {
    double best = 0;
    for (int rep = 0; rep < 3; rep++) {
      const double t0 = now();
      float sink = 0;
#pragma omp parallel num_threads(threads) reduction(+ : sink)
      sink += chains(n);
      const double gf = threads * (double)n * 12 * 16 * 2 / (now() - t0) / 1e9;
      if (gf > best) best = gf;
      if (sink == 12345.f) printf(" ");
    }
    printf("threads %d: %.1f GF/s fp32 FMA peak (AVX-512, best of 3)\n", threads, best);
  }
  return 0;
}
