// Host-side controls of the emulator (schedule seed, launch counters), used by the test module emu_module.cpp.
#pragma once

#include <cstdint>
#include <map>
#include <string>

// The op namespace of the emulated kernels (variants with injected defects get their own).
#ifndef MODI_EMU_LIB
#define MODI_EMU_LIB modi_ext_emu
#endif

namespace modi_emu {
void set_seed(uint64_t seed);  // 0: threads and blocks in index order; else a seeded permutation
uint64_t get_seed();
void set_sm_count(int n);
std::map<std::string, int64_t> launch_counts();  // kernel instantiation -> launches since the last reset
void reset_launch_counts();
}  // namespace modi_emu
