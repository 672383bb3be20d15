// The op schemas (csrc/skeletal_defs.cpp, csrc/fk_defs.cpp) compiled again for the emulator module: a separate
// translation unit, so its object file never collides with the main extension's in the shared build directory.
#include "fk_defs.cpp"
#include "skeletal_defs.cpp"
