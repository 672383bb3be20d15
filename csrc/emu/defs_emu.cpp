// The op schemas (csrc/skeletal/schema.cpp, csrc/fk/schema.cpp) compiled again for the emulator module: a separate
// translation unit, so its object file never collides with the main extension's in the shared build directory.
#include "fk/schema.cpp"
#include "skeletal/schema.cpp"
