// The unchanged CUDA sources of the demodulation op, compiled as host C++ for the emulator (test-only module).
#include "demod/cuda.cu"
