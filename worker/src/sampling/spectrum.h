// Wavelength sampling for KHR_materials_dispersion: a path that meets a dispersive material
// carries one wavelength from there on, drawn from a density close to the eye's response, and
// keeps its RGB throughput with a per-channel weight, so the image stays RGB and its expected
// value over the wavelength is exact.
//
// The weight of wavelength l for channel c is w_c(l) = rgb_c(l) / (p(l) N_c): rgb(l) the CIE
// 1931 colour matching functions (Wyman, Sloan and Shirley 2013's multi-lobe Gaussian fit)
// taken to linear Rec. 709 by the XYZ-to-sRGB matrix, N_c = integral of rgb_c over [360, 830]
// nm, and p the sampling density. So E[w_c] = 1 for every channel: a path whose throughput does
// not depend on the wavelength renders what it would without dispersion (an equal-energy
// spectrum is white), and a dispersive one renders, in channel c, the wavelength-dependent
// result weighted by that channel's matching function. A channel's weight is negative where its
// matching function is (red around 440-540 nm): single samples may be negative, their mean is
// not.
#pragma once

#include "math/vecmath.h"

namespace rf {

constexpr float kLambdaMin = 360.f, kLambdaMax = 830.f;  // nm

// A wavelength in [kLambdaMin, kLambdaMax] from u in [0, 1), with density
// visible_wavelength_pdf: 1 / cosh^2(0.0072 (l - 538)) normalized over the range (Radziszewski
// et al. 2009's fit to the eye's response, as pbrt-v4 samples visible wavelengths), by
// inverting its CDF in closed form.
float sample_visible_wavelength(float u);
float visible_wavelength_pdf(float lambda);

// The CIE 1931 2-degree colour matching functions at lambda (nm), the multi-lobe fit.
Vec3 cie_xyz(float lambda);

// The channel weights w(l) = rgb(l) / (p(l) N) above.
Vec3 wavelength_weight(float lambda);

// KHR_materials_dispersion: the index of refraction at lambda (nm) from the index at the
// Fraunhofer d line (n_d, KHR_materials_ior) and dispersion = 20 / V_d (the Abbe number),
//   n(l) = max(n_d + (n_d - 1) / V_d (523655 / l^2 - 1.5168), 1).
float dispersion_ior(float n_d, float dispersion, float lambda);

}  // namespace rf
