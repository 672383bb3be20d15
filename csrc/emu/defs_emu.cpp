// The op schemas (csrc/skeletal/schema.cpp, csrc/fk/schema.cpp, csrc/demod/schema.cpp) compiled again for the emulator
// module: a separate translation unit, so its object file never collides with the main extension's in the shared
// build directory.
#include "demod/schema.cpp"
#include "fk/schema.cpp"
#include "skeletal/schema.cpp"
