// Wavelength sampling (KHR_materials_dispersion): the matching functions against the CIE 1931
// table, the density against its sampling routine, the channel weights' mean, the extension's
// index of refraction at the Fraunhofer lines, and a dispersive pane rendered against the
// spectral integral written independently here.
#include "sampling/spectrum.h"

#include <gtest/gtest.h>

#include <cmath>

#include "render/integrators.h"
#include "render/render.h"
#include "testing/test_scenes.h"

namespace rf {
namespace {

// CIE 1931 2-degree observer, the published table (CIE 015:2018, 5 nm steps): the fit is
// within a few hundredths of it.
TEST(Spectrum, MatchingFunctionsFollowTheCieTable) {
  struct Row {
    float lambda, x, y, z;
  };
  const Row table[] = {{450.f, 0.33620f, 0.03800f, 1.77211f},
                       {500.f, 0.00490f, 0.32300f, 0.27200f},
                       {550.f, 0.43345f, 0.99495f, 0.00875f},
                       {600.f, 1.06220f, 0.63100f, 0.00080f},
                       {650.f, 0.28350f, 0.10700f, 0.00002f}};
  for (const Row& r : table) {
    const Vec3 xyz = cie_xyz(r.lambda);
    EXPECT_NEAR(xyz.x, r.x, 0.035f) << r.lambda;
    EXPECT_NEAR(xyz.y, r.y, 0.035f) << r.lambda;
    EXPECT_NEAR(xyz.z, r.z, 0.035f) << r.lambda;
  }
}

// The density integrates to 1 over [360, 830] nm, and sample_visible_wavelength(u) is its
// inverse CDF: the density integrated up to the sample is u (both by quadrature here).
TEST(Spectrum, SampledWavelengthsHaveTheStatedDensity) {
  const int n = 47000;
  const double h = (kLambdaMax - kLambdaMin) / n;
  double total = 0.0;
  for (int i = 0; i < n; ++i)
    total += visible_wavelength_pdf(float(kLambdaMin + (i + 0.5) * h)) * h;
  EXPECT_NEAR(total, 1.0, 1e-4);
  EXPECT_EQ(visible_wavelength_pdf(300.f), 0.f);
  for (float u : {0.01f, 0.2f, 0.5f, 0.77f, 0.99f}) {
    const float l = sample_visible_wavelength(u);
    ASSERT_GE(l, kLambdaMin);
    ASSERT_LE(l, kLambdaMax);
    double cdf = 0.0;
    const int m = 20000;
    const double hl = (l - kLambdaMin) / m;
    for (int i = 0; i < m; ++i)
      cdf += visible_wavelength_pdf(float(kLambdaMin + (i + 0.5) * hl)) * hl;
    EXPECT_NEAR(cdf, u, 2e-4) << u;
  }
}

// The channel weights average to 1 over sampled wavelengths (a path whose throughput does not
// depend on the wavelength renders as without dispersion), and each is the channel's matching
// function over the density: red peaks near 600 nm, green near 550, blue near 450.
TEST(Spectrum, ChannelWeightsAverageToOne) {
  const int n = 200000;
  double sum[3] = {0.0, 0.0, 0.0};
  for (int i = 0; i < n; ++i) {
    const Vec3 w = wavelength_weight(sample_visible_wavelength((i + 0.5f) / n));
    for (int c = 0; c < 3; ++c) sum[c] += w[c];
  }
  for (int c = 0; c < 3; ++c) EXPECT_NEAR(sum[c] / n, 1.0, 2e-3) << c;
  const Vec3 at600 = wavelength_weight(600.f), at550 = wavelength_weight(550.f),
             at450 = wavelength_weight(450.f);
  EXPECT_GT(at600.x, at600.y);
  EXPECT_GT(at600.x, at600.z);
  EXPECT_GT(at550.y, at550.z);
  EXPECT_GT(at450.z, at450.x);
  EXPECT_LT(wavelength_weight(500.f).x, 0.f);  // the red matching function's negative lobe
}

// KHR_materials_dispersion's n(l): n_d at the d line (587.56 nm), and n_F - n_C = (n_d - 1) /
// V_d with V_d = 20 / dispersion (F: 486.13 nm, C: 656.27 nm), the Abbe number's definition;
// no dispersion leaves n_d; never below 1.
TEST(Spectrum, DispersionIorFollowsTheAbbeNumber) {
  for (float n_d : {1.33f, 1.5f, 2.42f})
    for (float dispersion : {0.2f, 0.36f, 1.f}) {
      EXPECT_NEAR(dispersion_ior(n_d, dispersion, 587.56f), n_d, 2e-5f);
      const float v_d = 20.f / dispersion;
      const float spread =
          dispersion_ior(n_d, dispersion, 486.13f) - dispersion_ior(n_d, dispersion, 656.27f);
      EXPECT_NEAR(spread, (n_d - 1.f) / v_d, 2e-3f * (n_d - 1.f) / v_d);
      EXPECT_EQ(dispersion_ior(n_d, 0.f, 400.f), n_d);
    }
  EXPECT_EQ(dispersion_ior(1.05f, 40.f, 800.f), 1.f);
}

// The spectral integral a dispersive pane must render, written here independently of
// spectrum.cpp: the CIE fit (Wyman et al. 2013, Table 1) to Rec. 709, normalized per channel,
// against g(n(l)) by the midpoint rule.
double fit_lobe(double l, double a, double mu, double s1, double s2) {
  const double t = (l - mu) / (l < mu ? s1 : s2);
  return a * std::exp(-0.5 * t * t);
}

template <class G>
Vec3 spectral_mean(G g) {
  double num[3] = {0, 0, 0}, den[3] = {0, 0, 0};
  const int n = 9400;
  for (int i = 0; i < n; ++i) {
    const double l = 360.0 + (i + 0.5) * 470.0 / n;
    const double x = fit_lobe(l, 1.056, 599.8, 37.9, 31.0) +
                     fit_lobe(l, 0.362, 442.0, 16.0, 26.7) + fit_lobe(l, -0.065, 501.1, 20.4, 26.2);
    const double y = fit_lobe(l, 0.821, 568.8, 46.9, 40.5) + fit_lobe(l, 0.286, 530.9, 16.3, 31.1);
    const double z = fit_lobe(l, 1.217, 437.0, 11.8, 36.0) + fit_lobe(l, 0.681, 459.0, 26.0, 13.8);
    const double rgb[3] = {3.2404542 * x - 1.5371385 * y - 0.4985314 * z,
                           -0.9692660 * x + 1.8760108 * y + 0.0415560 * z,
                           0.0556434 * x - 0.2040259 * y + 1.0572252 * z};
    const double v = g(l);
    for (int c = 0; c < 3; ++c) {
      num[c] += rgb[c] * v;
      den[c] += rgb[c];
    }
  }
  return Vec3(float(num[0] / den[0]), float(num[1] / den[1]), float(num[2] / den[2]));
}

// A smooth white glass pane (ior 1.5, dispersion 20: an exaggerated Abbe number of 1) seen
// head-on under a uniform sky of radiance 1: a path reflects with probability F(n) and sees
// the sky (1), or refracts and sees it scaled by 1/n^2 (radiance entering the glass), so each
// channel is the spectral mean of F + (1 - F) / n^2, F = ((n - 1) / (n + 1))^2, n = n(l).
// Blue (n up to 2.4) reflects more and transmits less than red (n down to 1.3). Without
// dispersion the pane renders grey.
TEST(Spectrum, ADispersivePaneRendersTheSpectralIntegral) {
  for (float dispersion : {20.f, 0.f}) {
    SceneDescription desc;
    desc.source = "pane";
    Material glass;
    glass.name = "dispersive glass";
    glass.albedo = Vec3(1.f, 1.f, 1.f);
    glass.roughness = 0.f;
    glass.transmission = 1.f;
    glass.dispersion = dispersion;
    desc.materials.push_back(glass);
    testing::add_quad(&desc, {-1.f, -1.f, 0.f}, {1.f, -1.f, 0.f}, {1.f, 1.f, 0.f},
                      {-1.f, 1.f, 0.f}, 0);
    desc.camera = testing::look_at({0.f, 0.f, 2.f}, {0.f, 0.f, 0.f}, 0.002f);
    Scene scene(std::move(desc));
    RenderSettings settings;
    settings.width = settings.height = 1;
    settings.sampler = SamplerType::Sobol;
    settings.max_depth = 8;
    settings.environment = Environment::constant({1.f, 1.f, 1.f});
    const uint32_t spp = 1u << 16;
    TileBuffer tile;
    ASSERT_TRUE(render_rect(scene, settings, {0, 0, 1, 1}, 0, spp, &tile));
    const Vec3 want = spectral_mean([&](double l) {
      const double n =
          std::max(1.5 + 0.5 * dispersion / 20.0 * (523655.0 / (l * l) - 1.5168), 1.0);
      const double f = std::pow((n - 1.0) / (n + 1.0), 2.0);
      return f + (1.0 - f) / (n * n);
    });
    for (int c = 0; c < 3; ++c)
      EXPECT_NEAR(tile.rgb_sum[c] / spp, want[c], 3e-3) << dispersion << " " << c;
    if (dispersion > 0.f) {
      EXPECT_GT(want.x - want.z, 0.05f);  // the test can tell red from blue
    }
  }
}

}  // namespace
}  // namespace rf
