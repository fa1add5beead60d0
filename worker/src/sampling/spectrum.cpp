#include "sampling/spectrum.h"

#include <algorithm>
#include <cmath>

namespace rf {

namespace {

// The density's shape 1 / cosh^2(a (l - mu)); its integral is tanh(a (l - mu)) / a.
constexpr double kA = 0.0072, kMu = 538.0;
const double kT0 = std::tanh(kA * (double(kLambdaMin) - kMu));
const double kT1 = std::tanh(kA * (double(kLambdaMax) - kMu));

// One lobe of the fit: alpha exp(-(l - mu)^2 / (2 sigma^2)), sigma1 below mu, sigma2 above.
double lobe(double l, double alpha, double mu, double sigma1, double sigma2) {
  const double t = (l - mu) / (l < mu ? sigma1 : sigma2);
  return alpha * std::exp(-0.5 * t * t);
}

void xyz_fit(double l, double out[3]) {
  // Wyman, Sloan and Shirley 2013, "Simple Analytic Approximations to the CIE XYZ Color
  // Matching Functions", Table 1 (multi-lobe fit of the 1931 2-degree observer).
  out[0] = lobe(l, 1.056, 599.8, 37.9, 31.0) + lobe(l, 0.362, 442.0, 16.0, 26.7) +
           lobe(l, -0.065, 501.1, 20.4, 26.2);
  out[1] = lobe(l, 0.821, 568.8, 46.9, 40.5) + lobe(l, 0.286, 530.9, 16.3, 31.1);
  out[2] = lobe(l, 1.217, 437.0, 11.8, 36.0) + lobe(l, 0.681, 459.0, 26.0, 13.8);
}

// XYZ to linear Rec. 709 (sRGB primaries, D65), as for KHR_materials_iridescence.
void xyz_to_rgb(const double xyz[3], double rgb[3]) {
  rgb[0] = 3.2404542 * xyz[0] - 1.5371385 * xyz[1] - 0.4985314 * xyz[2];
  rgb[1] = -0.9692660 * xyz[0] + 1.8760108 * xyz[1] + 0.0415560 * xyz[2];
  rgb[2] = 0.0556434 * xyz[0] - 0.2040259 * xyz[1] + 1.0572252 * xyz[2];
}

// N_c: the integrals of the RGB matching functions over the range (Simpson's rule, 1/10 nm).
struct Normalization {
  double n[3] = {0.0, 0.0, 0.0};
  Normalization() {
    const int steps = 4700;
    const double h = (double(kLambdaMax) - double(kLambdaMin)) / steps;
    for (int i = 0; i <= steps; ++i) {
      double xyz[3], rgb[3];
      xyz_fit(kLambdaMin + i * h, xyz);
      xyz_to_rgb(xyz, rgb);
      const double w = (i == 0 || i == steps) ? 1.0 : (i % 2 ? 4.0 : 2.0);
      for (int c = 0; c < 3; ++c) n[c] += w * rgb[c] * h / 3.0;
    }
  }
};

const Normalization& normalization() {
  static const Normalization n;
  return n;
}

}  // namespace

float sample_visible_wavelength(float u) {
  const double t = kT0 + double(u) * (kT1 - kT0);
  const double l = kMu + std::atanh(t) / kA;
  return float(std::min(double(kLambdaMax), std::max(double(kLambdaMin), l)));
}

float visible_wavelength_pdf(float lambda) {
  if (!(lambda >= kLambdaMin && lambda <= kLambdaMax)) return 0.f;
  const double c = std::cosh(kA * (double(lambda) - kMu));
  return float(kA / ((kT1 - kT0) * c * c));
}

Vec3 cie_xyz(float lambda) {
  double xyz[3];
  xyz_fit(lambda, xyz);
  return Vec3(float(xyz[0]), float(xyz[1]), float(xyz[2]));
}

Vec3 wavelength_weight(float lambda) {
  const double p = visible_wavelength_pdf(lambda);
  if (!(p > 0.0)) return {0.f, 0.f, 0.f};
  double xyz[3], rgb[3];
  xyz_fit(lambda, xyz);
  xyz_to_rgb(xyz, rgb);
  const Normalization& n = normalization();
  return Vec3(float(rgb[0] / (p * n.n[0])), float(rgb[1] / (p * n.n[1])),
              float(rgb[2] / (p * n.n[2])));
}

float dispersion_ior(float n_d, float dispersion, float lambda) {
  // (n_d - 1) / V_d with V_d = 20 / dispersion.
  const float spread = (n_d - 1.f) * dispersion / 20.f;
  return std::max(n_d + spread * (523655.f / (lambda * lambda) - 1.5168f), 1.f);
}

}  // namespace rf
