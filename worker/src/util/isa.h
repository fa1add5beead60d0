// The widest SIMD instruction set the worker's run-time dispatched kernels may use: Embree's
// traversal and intersection, and the sampler's lane kernels (sampling/samplers.cpp).
//
// Embree picks its kernels by the CPU, and its AVX2 and AVX-512 kernels do not find the same
// hits to the last bit (another BVH width, other intersection arithmetic): the Cornell box
// rendered with each differs by up to 5e-4 a channel. A farm whose workers' CPUs differ would
// then give an image that depends on which worker rendered which tile, where the farm promises
// the same bits from one worker or fifty. So the worker caps Embree at AVX2 by default, which
// every x86-64 CPU of the last decade runs (Intel since 2013, AMD since 2015); RENDERFARM_ISA
// changes the cap. The sampler's kernels give the same bits at every width (integer
// arithmetic) and follow the cap only so that a capped worker runs what a CPU without the
// wider set would.
#pragma once

#include <string>

namespace rf {

enum class IsaCap { Sse42, Avx2, Avx512, Native };

// "sse4.2", "avx2", "avx512" or "native" (no cap: the widest the CPU has).
const char* isa_cap_name(IsaCap cap);
bool parse_isa_cap(const std::string& name, IsaCap* out);

// The cap a value of RENDERFARM_ISA sets: avx2 if null or empty; a value that is none of the
// names above throws std::invalid_argument naming the variable.
IsaCap isa_cap_from(const char* value);

// The cap of this process: isa_cap_from(RENDERFARM_ISA), read once.
IsaCap isa_cap();

// Embree's device configuration for a cap ("max_isa=avx2"; empty for native). On a CPU
// without the capped set Embree uses the widest it has below it (and the images then differ
// from those of CPUs that have it).
std::string embree_device_config(IsaCap cap);

// Whether the cap allows kernels of an instruction set as wide as `set` (Native allows all).
inline bool isa_allows(IsaCap cap, IsaCap set) { return int(set) <= int(cap); }

}  // namespace rf
