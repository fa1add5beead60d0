#include "util/isa.h"

#include <cstdlib>
#include <stdexcept>

namespace rf {

const char* isa_cap_name(IsaCap cap) {
  switch (cap) {
    case IsaCap::Sse42:
      return "sse4.2";
    case IsaCap::Avx2:
      return "avx2";
    case IsaCap::Avx512:
      return "avx512";
    case IsaCap::Native:
      return "native";
  }
  return "native";
}

bool parse_isa_cap(const std::string& name, IsaCap* out) {
  for (IsaCap cap : {IsaCap::Sse42, IsaCap::Avx2, IsaCap::Avx512, IsaCap::Native})
    if (name == isa_cap_name(cap)) {
      *out = cap;
      return true;
    }
  return false;
}

IsaCap isa_cap_from(const char* value) {
  if (!value || !*value) return IsaCap::Avx2;
  IsaCap cap;
  if (!parse_isa_cap(value, &cap))
    throw std::invalid_argument(std::string("RENDERFARM_ISA='") + value +
                                "': expected one of sse4.2, avx2, avx512, native");
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
