// The unchanged CUDA sources of the skeletal ops, compiled as host C++ for the emulator (test-only module).
#include "skeletal/cuda.cu"
