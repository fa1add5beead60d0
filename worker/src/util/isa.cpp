#include "util/isa.h"

#include <cstdlib>
#include <stdexcept>
#include <string>

namespace rf {

namespace {

// The caps by name, in IsaCap's order.
constexpr IsaCap kCaps[] = {IsaCap::Sse42, IsaCap::Avx2, IsaCap::Avx512, IsaCap::Native};
constexpr const char* kNames[] = {"sse4.2", "avx2", "avx512", "native"};
static_assert(sizeof kCaps / sizeof kCaps[0] == sizeof kNames / sizeof kNames[0],
              "a name per cap");

}  // namespace

const char* isa_cap_name(IsaCap cap) { return kNames[int(cap)]; }

bool parse_isa_cap(const std::string& name, IsaCap* out) {
  for (IsaCap cap : kCaps)
    if (name == isa_cap_name(cap)) {
      *out = cap;
      return true;
    }
  return false;
}

IsaCap isa_cap_from(const char* value) {
  if (!value || !*value) return IsaCap::Avx2;
  IsaCap cap;
  if (!parse_isa_cap(value, &cap)) {
    std::string names;
    for (const char* name : kNames) names += (names.empty() ? "" : ", ") + std::string(name);
    throw std::invalid_argument(std::string("RENDERFARM_ISA='") + value +
                                "': expected one of " + names);
  }
  return cap;
}

IsaCap isa_cap() {
  static const IsaCap cap = isa_cap_from(std::getenv("RENDERFARM_ISA"));
  return cap;
}

std::string embree_device_config(IsaCap cap) {
  return cap == IsaCap::Native ? std::string() : std::string("max_isa=") + isa_cap_name(cap);
}

}  // namespace rf
