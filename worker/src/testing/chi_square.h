// Chi-square goodness-of-fit helpers shared by the sampling tests (not part of the worker).
#pragma once

#include <cmath>

namespace rf {
namespace testing {

// Critical value of the chi-square distribution with `dof` degrees of freedom at significance
// 1e-3, by the Wilson-Hilferty approximation (accurate to a few percent for dof >= 3).
inline double chi2_critical(int dof) {
  const double k = dof, z = 3.09;
  const double t = 1.0 - 2.0 / (9.0 * k) + z * std::sqrt(2.0 / (9.0 * k));
  return k * t * t * t;
}

}  // namespace testing
}  // namespace rf
