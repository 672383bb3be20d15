// Stand-in for the header that torch's CUDA builds generate and its CPU wheels omit.
// Used only by .ci/cuda_compile_check (compile-only gate for csrc/<op>/cuda.cu without a CUDA torch).
#pragma once
#define C10_CUDA_BUILD_SHARED_LIBS
