// Host-side controls of the emulator (schedule seed, launch counters), used by the test module emu_module.cpp.
#pragma once

#include <array>
#include <cstdint>
#include <map>
#include <set>
#include <string>

// The op namespace of the emulated kernels (the AddressSanitizer build gets its own).
#ifndef MODI_EMU_LIB
#define MODI_EMU_LIB modi_ext_emu
#endif

// Test-only defects (cuda_emu.h), chosen at run time (set_injected_defect).
#define MODI_EMU_INJECT_DROP_SYNC_ID 1
#define MODI_EMU_INJECT_OFF_BY_ONE_ID 2
#define MODI_EMU_INJECT_GLOBAL_OOB_ID 3
#define MODI_EMU_INJECT_WRONG_SCALE_ID 4
#define MODI_EMU_INJECT_SPLIT_EDGE_ID 5
#define MODI_EMU_INJECT_WRONG_SLOPE_ID 6
#define MODI_EMU_INJECT_MMA_FRAGMENT_OFFSET_ID 7
#define MODI_EMU_INJECT_MMA_TILE_EDGE_ID 8
#define MODI_EMU_INJECT_MMA_WGRAD_FRAGMENT_OFFSET_ID 9
#define MODI_EMU_INJECT_MMA_WGRAD_TILE_EDGE_ID 10

namespace modi_emu {
void set_seed(uint64_t seed);  // 0: threads and blocks in index order; else a seeded permutation
uint64_t get_seed();
void set_sm_count(int n);
void set_injected_defect(int id);  // test-only run-time defect (MODI_EMU_INJECT_*_ID above), 0 = none
int injected_defect();
std::map<std::string, int64_t> launch_counts();  // kernel instantiation -> launches since the last reset
void reset_launch_counts();
std::map<std::string, std::array<unsigned, 3>> last_grids();  // kernel instantiation -> grid of its latest launch
std::set<std::string> registered_kernels();  // every kernel instantiation the loaded code can launch
}  // namespace modi_emu
