// The unchanged CUDA sources of FK, compiled as host C++ for the emulator (test-only module).
#include "fk/cuda.cu"
