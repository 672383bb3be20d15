// The unchanged CUDA sources of FK, compiled as host C++ for the emulator (test-only module).
#include "cuda/fk_cuda.cu"
