// KHR_materials_clearcoat, KHR_materials_sheen and KHR_materials_unlit: the spec's formulas
// (evaluated here independently, in double), the sheen albedo table against a quadrature of
// the spec's lobe, white furnace bounds by Monte Carlo over the sampling routine, reciprocity,
// chi-square of the sampling against the pdf, the packet batch against the scalar evaluation,
// the glTF loader, and tiny renders showing each extension's effect.
#include <gtest/gtest.h>

#include <cmath>
#include <cstring>
#include <random>
#include <vector>

#include "render/integrators.h"
#include "scene/environment.h"
#include "scene/materials.h"
#include "testing/chi_square.h"
#include "testing/test_scenes.h"

namespace rf {
namespace {

using testing::ChiSquareResult;
using testing::ChiSquareTest;

Vec3 spherical(double z, double phi) {
  const double r = std::sqrt(std::max(0.0, 1.0 - z * z));
  return Vec3(float(r * std::cos(phi)), float(r * std::sin(phi)), float(z));
}

// ---- The extension texts' formulas, in double, written out again here.

// KHR_materials_clearcoat, "Layering": f0 = ((1 - ior) / (1 + ior))^2 with ior 1.5,
// fr = f0 + (1 - f0) (1 - |NdotV|)^5.
double spec_clearcoat_fresnel(double n_dot_v) {
  const double f0 = std::pow((1.0 - 1.5) / (1.0 + 1.5), 2.0);
  return f0 + (1.0 - f0) * std::pow(1.0 - std::abs(n_dot_v), 5.0);
}

// KHR_materials_sheen, "Sheen distribution".
double spec_charlie_d(double n_dot_h, double alpha_g) {
  const double inv_r = 1.0 / alpha_g;
  const double sin2h = 1.0 - n_dot_h * n_dot_h;
  return (2.0 + inv_r) * std::pow(sin2h, inv_r * 0.5) / (2.0 * M_PI);
}

// KHR_materials_sheen, "Sheen visibility" (the Charlie visibility).
double spec_l(double x, double alpha_g) {
  const double t = (1.0 - alpha_g) * (1.0 - alpha_g);
  auto mix = [t](double a, double b) { return a * (1.0 - t) + b * t; };
  const double a = mix(21.5473, 25.3245), b = mix(3.82987, 3.32435), c = mix(0.19823, 0.16801);
  const double d = mix(-1.97760, -1.27393), e = mix(-4.32054, -4.85967);
  return a / (1.0 + b * std::pow(x, c)) + d * x + e;
}
double spec_lambda_sheen(double cos_theta, double alpha_g) {
  return std::abs(cos_theta) < 0.5
             ? std::exp(spec_l(cos_theta, alpha_g))
             : std::exp(2.0 * spec_l(0.5, alpha_g) - spec_l(1.0 - cos_theta, alpha_g));
}
double spec_sheen_visibility(double n_dot_v, double n_dot_l, double alpha_g) {
  return 1.0 / ((1.0 + spec_lambda_sheen(n_dot_v, alpha_g) + spec_lambda_sheen(n_dot_l, alpha_g)) *
                (4.0 * n_dot_v * n_dot_l));
}

// The sheen lobe's directional albedo E(mu) = integral of D V cos_i d omega_i, by the midpoint
// rule on a uniform (cos_i, phi) grid (phi over [0, 2 pi]): another quadrature than the
// worker's table.
double spec_sheen_albedo(double mu, double alpha_g, int n = 400) {
  const double so = std::sqrt(1.0 - mu * mu);
  double sum = 0.0;
  for (int i = 0; i < n; ++i) {
    const double ci = (i + 0.5) / n, si = std::sqrt(1.0 - ci * ci);
    for (int j = 0; j < n; ++j) {
      const double phi = (j + 0.5) * 2.0 * M_PI / n;
      const double hx = so + si * std::cos(phi), hy = si * std::sin(phi), hz = mu + ci;
      const double n_dot_h = hz / std::sqrt(hx * hx + hy * hy + hz * hz);
      sum += spec_charlie_d(n_dot_h, alpha_g) * spec_sheen_visibility(mu, ci, alpha_g) * ci;
    }
  }
  return sum * (1.0 / n) * (2.0 * M_PI / n);
}

TEST(Clearcoat, FresnelIsTheExtensionsSchlickAtIor15) {
  for (double c = 0.0; c <= 1.0; c += 0.05) {
    EXPECT_NEAR(clearcoat_fresnel(float(c)), spec_clearcoat_fresnel(c), 1e-6) << c;
    EXPECT_NEAR(clearcoat_fresnel(float(-c)), spec_clearcoat_fresnel(c), 1e-6) << -c;
  }
  EXPECT_NEAR(clearcoat_fresnel(1.f), 0.04, 1e-7);
  EXPECT_NEAR(clearcoat_fresnel(0.f), 1.0, 1e-6);
}

TEST(Sheen, CharlieDistributionAndVisibilityAreTheExtensionsFormulas) {
  for (double roughness : {0.1, 0.3, 0.5, 0.8, 1.0}) {
    const double a = roughness * roughness;
    for (double c = 0.0; c < 1.0; c += 0.05)
      EXPECT_NEAR(sheen_charlie_d(float(c), float(a)), spec_charlie_d(c, a),
                  2e-5 * (1.0 + spec_charlie_d(c, a)))
          << "cos_h " << c << " alpha " << a;
    for (double co : {0.05, 0.3, 0.49, 0.51, 0.8, 1.0})
      for (double ci : {0.02, 0.4, 0.6, 0.95})
        EXPECT_NEAR(sheen_charlie_visibility(float(co), float(ci), float(a)),
                    spec_sheen_visibility(co, ci, a), 1e-4 * spec_sheen_visibility(co, ci, a))
            << co << " " << ci << " alpha " << a;
    // D is a normalized microfacet distribution: the integral of D cos_h over the hemisphere
    // is 1 (d omega = d cos_h d phi).
    double norm = 0.0;
    const int n = 20000;
    for (int i = 0; i < n; ++i) {
      const double c = (i + 0.5) / n;
      norm += spec_charlie_d(c, a) * c * 2.0 * M_PI / n;
    }
    EXPECT_NEAR(norm, 1.0, 1e-3) << a;
  }
}

TEST(Sheen, AlbedoTableMatchesAQuadratureOfTheLobe) {
  for (double roughness : {0.1, 0.25, 0.5, 0.75, 1.0})
    for (double mu : {0.05, 0.2, 0.5, 0.8, 0.98}) {
      const double a = roughness * roughness;
      const double want = spec_sheen_albedo(mu, a);
      EXPECT_NEAR(sheen_albedo(float(mu), float(a)), want, 5e-3 + 0.03 * want)
          << "mu " << mu << " roughness " << roughness;
    }
  // The spec's lobe gains energy at grazing angles when smooth (E > 1: corrected in the
  // BSDF, see WhiteFurnacePerLobe), and conserves it elsewhere.
  EXPECT_GT(spec_sheen_albedo(0.05, 0.01), 1.0);
  EXPECT_LT(spec_sheen_albedo(0.05, 0.25), 1.0);
}

// ---- The BSDF with its layers.

BsdfParams base(Vec3 color, float metallic, float roughness, float specular = 1.f) {
  BsdfParams p;
  p.base = color;
  p.metallic = metallic;
  p.alpha = std::max(kMinAlpha, roughness * roughness);
  p.specular = specular;
  return p;
}

BsdfParams coated(BsdfParams p, float coat, float roughness, Vec3 n = {0.f, 0.f, 1.f}) {
  p.clearcoat = coat;
  p.clearcoat_alpha = std::max(kMinAlpha, roughness * roughness);
  p.clearcoat_n = normalize(n);
  return p;
}

BsdfParams sheened(BsdfParams p, Vec3 color, float roughness) {
  p.sheen = color;
  p.sheen_alpha = std::max(kMinSheenAlpha, roughness * roughness);
  return p;
}

const Vec3 kBlack{0.f, 0.f, 0.f}, kWhite{1.f, 1.f, 1.f};

// The directional albedo by Monte Carlo over bsdf_sample: the mean of its weights (f cos / pdf,
// delta lobes included), with its standard error.
void sampled_albedo(const BsdfParams& p, Vec3 wo, int n, uint64_t seed, Vec3* mean,
                    Vec3* stderr_out) {
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<float> uni(0.f, 1.f);
  double s[3] = {0, 0, 0}, s2[3] = {0, 0, 0};
  for (int i = 0; i < n; ++i) {
    BsdfSample bs;
    if (!bsdf_sample(p, wo, {uni(rng), uni(rng)}, uni(rng), uni(rng), &bs)) continue;
    if (!bs.delta) {
      float pdf = 0.f;
      bsdf_eval_pdf(p, wo, bs.wi, &pdf);
      EXPECT_NEAR(bs.pdf, pdf, 1e-4f * (1.f + pdf));
    }
    for (int c = 0; c < 3; ++c) {
      s[c] += bs.weight[c];
      s2[c] += double(bs.weight[c]) * bs.weight[c];
    }
  }
  for (int c = 0; c < 3; ++c) {
    (*mean)[c] = float(s[c] / n);
    (*stderr_out)[c] = float(std::sqrt(std::max(0.0, s2[c] / n - (s[c] / n) * (s[c] / n)) / n));
  }
}

TEST(Layers, WhiteFurnacePerLobe) {
  const int n = 40000;
  uint64_t seed = 1;
  for (float roughness : {0.f, 0.3f, 0.6f, 1.f})
    for (double mu : {0.05, 0.3, 0.6, 0.95}) {
      const Vec3 wo = spherical(mu, 0.3);
      const double fc = spec_clearcoat_fresnel(mu);
      Vec3 m, e;
      // The coat alone (a black base without specular): at most F_c, the coat's weight.
      sampled_albedo(coated(base(kBlack, 0.f, 1.f, 0.f), 1.f, roughness), wo, n, seed++, &m, &e);
      EXPECT_LE(m.x, fc + 4 * e.x + 1e-3) << "coat, mu " << mu << " roughness " << roughness;
      EXPECT_GT(m.x, 0.f);
      // The sheen alone: its albedo is E(mu), the quadrature of the spec's lobe.
      const double a = std::max(double(kMinSheenAlpha), double(roughness) * roughness);
      sampled_albedo(sheened(base(kBlack, 0.f, 1.f, 0.f), kWhite, roughness), wo, n, seed++, &m,
                     &e);
      const double e_sheen = spec_sheen_albedo(mu, a, 200);
      EXPECT_LE(m.x, 1.0 + 4 * e.x + 1e-3) << "sheen, mu " << mu << " roughness " << roughness;
      // Where the spec's lobe conserves energy at every angle (roughness >= 0.3), it is the
      // spec's lobe: its albedo is E(mu).
      if (roughness >= 0.3f) {
        EXPECT_NEAR(m.x, e_sheen, 5 * e.x + 0.03 * e_sheen + 2e-3)
            << "sheen, mu " << mu << " roughness " << roughness;
      }
      // A white Lambertian base (albedo exactly 1) under the coat: 1 - F_c (1 - E_coat), in
      // [1 - F_c, 1].
      sampled_albedo(coated(base(kWhite, 0.f, 1.f, 0.f), 1.f, roughness), wo, n, seed++, &m, &e);
      EXPECT_LE(m.x, 1.0 + 4 * e.x + 1e-3) << "base + coat, mu " << mu << " r " << roughness;
      EXPECT_GE(m.x, 1.0 - fc - 4 * e.x - 1e-3) << "base + coat, mu " << mu;
      // The same base under a white sheen.
      sampled_albedo(sheened(base(kWhite, 0.f, 1.f, 0.f), kWhite, roughness), wo, n, seed++, &m,
                     &e);
      EXPECT_LE(m.x, 1.0 + 4 * e.x + 2e-3) << "base + sheen, mu " << mu << " r " << roughness;
      EXPECT_GT(m.x, 0.5f);
      // Everything: a white rough metal (energy-conserving base), sheen and coat.
      sampled_albedo(coated(sheened(base(kWhite, 1.f, 0.5f), kWhite, roughness), 1.f, roughness),
                     wo, n, seed++, &m, &e);
      EXPECT_LE(max_component(m), 1.0 + 4 * max_component(e) + 5e-3) << "all, mu " << mu;
      // Coated and sheened glass (its delta lobe weighted under the layers): the reflected
      // and transmitted energy is at most what arrives (the transmitted radiance is also
      // scaled by 1 / eta^2 entering the glass).
      BsdfParams glass = coated(sheened(base(kWhite, 0.f, 0.f), kWhite, 0.5f), 1.f, roughness);
      glass.transmission = 1.f;
      sampled_albedo(glass, wo, n, seed++, &m, &e);
      EXPECT_LE(max_component(m), 1.0 + 4 * max_component(e) + 2e-3) << "glass, mu " << mu;
      EXPECT_GT(m.x, 0.4f);
    }
}

TEST(Layers, EvaluationIsReciprocal) {
  // The sheen's albedo scaling is the extension's reciprocal min(..) form; the coat's Fresnel
  // is on N.V (the extension text), so the coated material is reciprocal where the view and
  // light make the same angle with the coat normal: f(wo, wi) = f(wi, wo) checked there, and
  // for the uncoated layers everywhere.
  const std::vector<BsdfParams> sheen_only = {
      sheened(base({0.8f, 0.3f, 0.2f}, 0.f, 0.5f), {0.9f, 0.7f, 0.5f}, 0.4f),
      sheened(base({0.4f, 0.4f, 0.9f}, 0.6f, 0.2f), kWhite, 1.f)};
  const std::vector<BsdfParams> all = {
      coated(sheen_only[0], 1.f, 0.1f), coated(sheen_only[1], 0.5f, 0.6f),
      coated(base({0.1f, 0.5f, 0.2f}, 0.f, 0.8f), 0.8f, 0.3f)};
  int compared = 0;
  for (double zo : {0.1, 0.4, 0.7, 0.95})
    for (double zi : {0.05, 0.3, 0.6, 0.9})
      for (double dphi : {0.3, 1.5, 2.9}) {
        const Vec3 wo = spherical(zo, 0.2), wi = spherical(zi, 0.2 + dphi);
        for (const BsdfParams& p : sheen_only) {
          const Vec3 a = bsdf_eval_cos(p, wo, wi) * (1.f / wi.z);
          const Vec3 b = bsdf_eval_cos(p, wi, wo) * (1.f / wo.z);
          for (int c = 0; c < 3; ++c) ASSERT_NEAR(a[c], b[c], 1e-4f * (1.f + a[c]));
          ++compared;
        }
        const Vec3 wj = spherical(zo, 0.2 + dphi);  // same angle with the normal as wo
        for (const BsdfParams& p : all) {
          const Vec3 a = bsdf_eval_cos(p, wo, wj) * (1.f / wj.z);
          const Vec3 b = bsdf_eval_cos(p, wj, wo) * (1.f / wo.z);
          for (int c = 0; c < 3; ++c) ASSERT_NEAR(a[c], b[c], 1e-4f * (1.f + a[c]));
          ++compared;
        }
      }
  EXPECT_EQ(compared, 48 * 5);
}

TEST(Layers, CoatedValueIsTheExtensionsFormula) {
  // (f_base) (1 - c F_c) + c F_c D G / (4 |V.Nc| |L.Nc|), with the spec's GGX D and Smith G of
  // Appendix B written out here (height-correlated: V = G / (4 |N.L| |N.V|)).
  const float c = 0.7f, roughness = 0.4f;
  const BsdfParams b = base({0.3f, 0.6f, 0.2f}, 0.2f, 0.6f);
  const BsdfParams p = coated(b, c, roughness);
  const double a = double(roughness) * roughness, a2 = a * a;
  for (double zo : {0.2, 0.6, 0.9})
    for (double zi : {0.1, 0.5, 0.99}) {
      const Vec3 wo = spherical(zo, 0.0), wi = spherical(zi, 2.0);
      const double hx = wo.x + wi.x, hy = wo.y + wi.y, hz = wo.z + wi.z;
      const double n_dot_h = hz / std::sqrt(hx * hx + hy * hy + hz * hz);
      const double d = a2 / (M_PI * std::pow(n_dot_h * n_dot_h * (a2 - 1.0) + 1.0, 2.0));
      const double vis = 0.5 / (zi * std::sqrt(zo * zo * (1 - a2) + a2) +
                                zo * std::sqrt(zi * zi * (1 - a2) + a2));
      const double fc = spec_clearcoat_fresnel(zo);
      const Vec3 fb = bsdf_eval_cos(b, wo, wi);
      const Vec3 f = bsdf_eval_cos(p, wo, wi);
      for (int k = 0; k < 3; ++k) {
        const double want = fb[k] * (1.0 - c * fc) + c * fc * d * vis * zi;
        EXPECT_NEAR(f[k], want, 2e-4 * (1.0 + want)) << zo << " " << zi;
      }
    }
}

TEST(Layers, SheenedValueIsTheExtensionsFormula) {
  const Vec3 color{0.9f, 0.5f, 0.3f};
  const float roughness = 0.5f;
  const BsdfParams b = base({0.3f, 0.6f, 0.2f}, 0.f, 0.6f);
  const BsdfParams p = sheened(b, color, roughness);
  const double a = double(roughness) * roughness;
  for (double zo : {0.2, 0.6, 0.9})
    for (double zi : {0.1, 0.5, 0.99}) {
      const Vec3 wo = spherical(zo, 0.0), wi = spherical(zi, 2.5);
      const double hx = wo.x + wi.x, hy = wo.y + wi.y, hz = wo.z + wi.z;
      const double n_dot_h = hz / std::sqrt(hx * hx + hy * hy + hz * hz);
      const double lobe = spec_charlie_d(n_dot_h, a) * spec_sheen_visibility(zo, zi, a);
      const double scale = std::min(1.0 - 0.9 * spec_sheen_albedo(zo, a, 300),
                                    1.0 - 0.9 * spec_sheen_albedo(zi, a, 300));
      const Vec3 fb = bsdf_eval_cos(b, wo, wi);
      const Vec3 f = bsdf_eval_cos(p, wo, wi);
      for (int k = 0; k < 3; ++k) {
        const double want = fb[k] * scale + color[k] * lobe * zi;
        EXPECT_NEAR(f[k], want, 3e-3 * (1.0 + want)) << zo << " " << zi;
      }
    }
}

std::vector<BsdfParams> layered_materials() {
  BsdfParams glass = coated(base(kWhite, 0.f, 0.3f), 1.f, 0.3f);
  glass.transmission = 0.6f;
  return {coated(base(kBlack, 0.f, 1.f, 0.f), 1.f, 0.3f),                   // coat alone
          coated(base({0.8f, 0.2f, 0.1f}, 0.f, 0.7f), 0.6f, 0.25f),          // glossy coat
          coated(base({0.5f, 0.5f, 0.5f}, 1.f, 0.5f), 1.f, 0.4f, {0.3f, -0.2f, 1.f}),  // tilted
          sheened(base(kBlack, 0.f, 1.f, 0.f), kWhite, 0.5f),                // sheen alone
          sheened(base({0.2f, 0.3f, 0.8f}, 0.f, 0.5f), {0.9f, 0.6f, 0.6f}, 0.2f),
          coated(sheened(base({0.6f, 0.6f, 0.2f}, 0.3f, 0.6f), kWhite, 0.8f), 0.7f, 0.2f),
          glass};
}

const Vec3 kOutgoing[] = {normalize(Vec3(0.3f, 0.1f, 0.9f)), normalize(Vec3(-0.8f, 0.2f, 0.4f)),
                          normalize(Vec3(0.9f, 0.f, 0.3f))};

TEST(Layers, SamplesFollowThePdf) {
  const int nz = 12, nphi = 24, sub = 16, n = 150000;
  std::mt19937_64 rng(7);
  std::uniform_real_distribution<float> uni(0.f, 1.f);
  for (const BsdfParams& p : layered_materials())
    for (Vec3 wo : kOutgoing) {
      ChiSquareTest chi2(nz, nphi);
      int ok = 0;
      for (int s = 0; s < n; ++s) {
        BsdfSample bs;
        if (!bsdf_sample(p, wo, {uni(rng), uni(rng)}, uni(rng), uni(rng), &bs) || bs.delta)
          continue;
        ++ok;
        const Vec3 f = bsdf_eval_cos(p, wo, bs.wi);
        for (int c = 0; c < 3; ++c)
          ASSERT_NEAR(bs.weight[c], f[c] / bs.pdf, 1e-3f * (1.f + f[c] / bs.pdf));
        double phi = std::atan2(bs.wi.y, bs.wi.x);
        if (phi < 0) phi += 2 * M_PI;
        chi2.add_sample(bs.wi.z, phi / (2 * M_PI));
      }
      double integral = 0.0;
      chi2.integrate(
          [&](double x, double y) {
            const double d = bsdf_pdf(p, wo, spherical(x, 2 * M_PI * y)) * 2 * M_PI;
            integral += d / (nz * nphi * sub * sub);
            return d;
          },
          sub, n);
      // The pdf integrates to the fraction of non-delta samples produced.
      const double frac = double(ok) / n;
      EXPECT_NEAR(integral, frac, 4 * std::sqrt(frac * (1 - frac) / n) + 0.01)
          << "coat " << p.clearcoat << " wo.z " << wo.z;
      const ChiSquareResult result = chi2.run();
      EXPECT_TRUE(result.passed) << result.message << ", coat " << p.clearcoat << " sheen "
                                 << p.sheen.x << " wo.z " << wo.z;
    }
}

TEST(Layers, JointEvaluationEqualsTheReference) {
  for (const BsdfParams& p : layered_materials())
    for (double zo : {0.05, 0.4, 0.9})
      for (double zi : {0.02, 0.3, 0.7, 1.0})
        for (double phi : {0.0, 1.2, 3.1}) {
          const Vec3 wo = spherical(zo, 0.4), wi = spherical(zi, 0.4 + phi);
          float pdf = -1.f;
          const Vec3 f = bsdf_eval_pdf(p, bsdf_lobes(p, wo), wo, wi, &pdf);
          const Vec3 f_ref = bsdf_eval_cos(p, wo, wi);
          const float pdf_ref = bsdf_pdf(p, wo, wi);
          ASSERT_NEAR(pdf, pdf_ref, 1e-3f * pdf_ref + 1e-6f);
          for (int c = 0; c < 3; ++c) ASSERT_NEAR(f[c], f_ref[c], 1e-3f * f_ref[c] + 1e-6f);
        }
}

uint32_t float_bits(float x) {
  uint32_t u;
  std::memcpy(&u, &x, sizeof u);
  return u;
}

TEST(Layers, BatchEvaluationEqualsTheScalarOneBitForBit) {
  std::mt19937 rng(424242);
  std::uniform_real_distribution<float> uni(0.f, 1.f);
  const auto direction = [&](float below) {
    const float z = uni(rng) < below ? -uni(rng) : uni(rng);
    const float phi = 6.2831853f * uni(rng);
    const float r = std::sqrt(std::max(0.f, 1.f - z * z));
    return normalize(Vec3(r * std::cos(phi), r * std::sin(phi), z));
  };
  const std::vector<BsdfParams> layered = layered_materials();
  BsdfEvalBatch batch;
  int compared = 0, layered_compared = 0;
  for (int round = 0; round < 200; ++round) {
    batch.clear();
    struct Queued {
      BsdfParams p;
      Vec3 wo, wi;
      int slot;
    };
    std::vector<Queued> queued;
    for (int lane = 0; lane < BsdfEvalBatch::kLanes; ++lane) {
      // Layered and plain vertices side by side.
      const bool is_layered = uni(rng) < 0.5f;
      const BsdfParams p = is_layered ? layered[size_t(lane) % layered.size()]
                                      : base({uni(rng), uni(rng), uni(rng)}, uni(rng), uni(rng));
      const Vec3 wo = direction(0.05f);
      batch.set_vertex(lane, p, bsdf_lobes(p, wo), wo, Frame(direction(0.f)));
      queued.push_back({p, wo, direction(0.2f), -1});
      queued.back().slot = batch.add_light(lane, queued.back().wi);
      queued.push_back({p, wo, direction(0.2f) * (0.5f + uni(rng)), -1});
      queued.back().slot = batch.add_sampled(lane, queued.back().wi);
    }
    batch.evaluate();
    for (const Queued& q : queued) {
      const Vec3 wi = q.slot >= BsdfEvalBatch::kLanes ? normalize(q.wi) : q.wi;
      float pdf = -1.f;
      const Vec3 f = bsdf_eval_pdf(q.p, bsdf_lobes(q.p, q.wo), q.wo, wi, &pdf);
      ASSERT_EQ(float_bits(batch.pdf(q.slot)), float_bits(pdf)) << round;
      for (int c = 0; c < 3; ++c) ASSERT_EQ(float_bits(batch.f(q.slot)[c]), float_bits(f[c]));
      ++compared;
      layered_compared += q.p.layered();
    }
  }
  EXPECT_GT(layered_compared, 1000);
  EXPECT_GT(compared - layered_compared, 1000);
}

// ---- The glTF loader and renders.

// A unit quad (z = 0, facing +z) with one material, seen head-on by a narrow camera.
std::string quad_scene(const std::string& material, const std::string& extra = "") {
  return R"({"asset": {"version": "2.0"}, )" + extra + R"(
  "scene": 0, "scenes": [{"nodes": [0]}],
  "nodes": [{"mesh": 0}],
  "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "NORMAL": 1, "TEXCOORD_0": 2},
                              "indices": 3, "material": 0}]}],
  "materials": [)" + material + R"(],
  )" + testing::quad_gltf_buffers_json() + "}";
}

SceneDescription load(const std::string& json, std::vector<std::string>* warnings) {
  return load_gltf_from_string(json, "", "quad.gltf", warnings);
}

TEST(Layers, LoaderReadsTheExtensions) {
  std::vector<std::string> warnings;
  const SceneDescription d = load(
      quad_scene(R"({"extensions": {
          "KHR_materials_clearcoat": {"clearcoatFactor": 0.8, "clearcoatRoughnessFactor": 0.3},
          "KHR_materials_sheen": {"sheenColorFactor": [0.5, 0.25, 1], "sheenRoughnessFactor": 0.4}}})",
                 R"("extensionsUsed": ["KHR_materials_clearcoat", "KHR_materials_sheen"],
                    "extensionsRequired": ["KHR_materials_clearcoat", "KHR_materials_sheen"],)"),
      &warnings);
  for (const auto& w : warnings) ADD_FAILURE() << "unexpected warning: " << w;
  const Material& m = d.materials[0];
  EXPECT_FLOAT_EQ(m.clearcoat, 0.8f);
  EXPECT_FLOAT_EQ(m.clearcoat_roughness, 0.3f);
  EXPECT_FLOAT_EQ(m.sheen_color.y, 0.25f);
  EXPECT_FLOAT_EQ(m.sheen_roughness, 0.4f);
  EXPECT_FALSE(m.unlit);
  // Unlit: a flag; the emission is not used.
  const SceneDescription u = load(
      quad_scene(R"({"emissiveFactor": [1, 1, 1], "extensions": {"KHR_materials_unlit": {}}})",
                 R"("extensionsUsed": ["KHR_materials_unlit"],)"),
      &warnings);
  EXPECT_TRUE(u.materials[0].unlit);
  EXPECT_TRUE(is_zero(u.materials[0].emission));
  // Out of range factors are refused with their path; an unsupported required extension
  // still is.
  try {
    load(quad_scene(R"({"extensions": {"KHR_materials_clearcoat": {"clearcoatFactor": 2}}})"),
         &warnings);
    ADD_FAILURE() << "clearcoatFactor 2 accepted";
  } catch (const SceneError& e) {
    EXPECT_EQ(e.path(), "materials[0].extensions.KHR_materials_clearcoat.clearcoatFactor");
  }
  try {
    load(quad_scene("{}", R"("extensionsUsed": ["ADOBE_materials_thin_transparency"],
                             "extensionsRequired": ["ADOBE_materials_thin_transparency"],)"),
         &warnings);
    ADD_FAILURE() << "an unsupported required extension was accepted";
  } catch (const SceneError& e) {
    EXPECT_EQ(e.path(), "extensionsRequired[0]");
  }
}

// Mean radiance of a 1 x 1 image.
Vec3 render_pixel(const Scene& scene, RenderSettings settings, uint32_t spp) {
  settings.width = settings.height = 1;
  TileBuffer tile;
  EXPECT_TRUE(render_rect(scene, settings, {0, 0, 1, 1}, 0, spp, &tile));
  return Vec3(float(tile.rgb_sum[0] / spp), float(tile.rgb_sum[1] / spp),
              float(tile.rgb_sum[2] / spp));
}

TEST(Layers, RenderClearcoatOnBlackShowsTheCoatsReflection) {
  // A black base without specular under a large emitter, seen at 45 degrees: black, and with a
  // smooth coat the emitter's reflection, L F_c(cos 45) (the near-mirror coat reflects all of
  // F_c: its GGX albedo at alpha 2e-3 is 1 to well below the tolerance).
  const float L = 5.f;
  SceneDescription desc =
      testing::plane_under_emitter(0.f, L, 4.f, 4.f, 1.f, {0.f, -0.8f, 0.8f}, 1e-3f);
  desc.camera = testing::look_at({0.f, -0.8f, 0.8f}, {0.f, 0.f, 0.f}, 1e-3f);
  RenderSettings settings;
  const Vec3 bare = render_pixel(Scene(desc), settings, 64);
  EXPECT_EQ(bare.x, 0.f);
  desc.materials[0].clearcoat = 1.f;
  desc.materials[0].clearcoat_roughness = 0.f;
  const Vec3 coat = render_pixel(Scene(desc), settings, 64);
  const double want = L * spec_clearcoat_fresnel(std::sqrt(0.5));
  for (int c = 0; c < 3; ++c) EXPECT_NEAR(coat[c], want, 0.02 * want) << c;
}

TEST(Layers, RenderEmissionUnderACoat) {
  // The emitter of plane_under_emitter coated: seen from below it shows L (1 - F_c), and the
  // white Lambertian floor under it receives its emission dimmed by 1 - F_c(cos) in every
  // direction (light samples and rays that hit the emitter alike): rho / pi times the integral
  // of L (1 - F_c(cos)) cos^2 / d^2 over the emitter, by quadrature here.
  const float L = 50.f, side = 0.4f, height = 1.f;
  SceneDescription desc = testing::plane_under_emitter(1.f, L, side, side, height,
                                                       {0.f, -0.01f, 0.02f}, 1e-3f);
  desc.materials[1].clearcoat = 1.f;
  desc.camera = testing::look_at({0.f, 0.f, 0.5f}, {0.f, 0.f, 2.f}, 1e-3f);
  RenderSettings settings;
  const Vec3 seen = render_pixel(Scene(SceneDescription(desc)), settings, 64);
  desc.camera = testing::look_at({0.f, -0.01f, 0.02f}, {0.f, 0.f, 0.f}, 1e-3f);
  settings.max_depth = 1;
  const Vec3 floor = render_pixel(Scene(std::move(desc)), settings, 1024);
  double irradiance = 0.0;
  const int n = 400;
  for (int i = 0; i < n; ++i)
    for (int j = 0; j < n; ++j) {
      const double x = side * ((i + 0.5) / n - 0.5), y = side * ((j + 0.5) / n - 0.5);
      const double d2 = x * x + y * y + height * height, cos = height / std::sqrt(d2);
      irradiance += L * (1.0 - spec_clearcoat_fresnel(cos)) * cos * cos / d2 * (side * side) /
                    (double(n) * n);
    }
  const double want = irradiance / M_PI;
  EXPECT_NEAR(floor.x, want, 0.02 * want);
  // From below: the emission through the coat, plus the coat's mirror image of the lit floor.
  EXPECT_NEAR(seen.x, L * (1.0 - 0.04) + 0.04 * want, 2e-4 * L);
}

TEST(Layers, RenderSheenInAWhiteFurnace) {
  // A black base with a white sheen in a uniform environment of radiance 1: the pixel is the
  // sheen's directional albedo E(mu) at the view angle (nothing else reflects).
  SceneDescription desc =
      testing::plane_under_emitter(0.f, 0.f, 0.1f, 0.1f, -50.f, {0.f, -1.f, 0.5f}, 1e-3f);
  desc.camera = testing::look_at({0.f, -2.f, 1.f}, {0.f, 0.f, 0.f}, 1e-3f);
  desc.materials[0].sheen_color = kWhite;
  desc.materials[0].sheen_roughness = 0.5f;
  RenderSettings settings;
  settings.environment = Environment::constant({1.f, 1.f, 1.f});
  const Vec3 got = render_pixel(Scene(desc), settings, 1024);
  const double mu = 1.0 / std::sqrt(5.0);
  const double want = spec_sheen_albedo(mu, 0.25);
  EXPECT_NEAR(got.x, want, 0.03 * want + 2e-3);
}

TEST(Layers, RenderUnlitShowsItsExactBaseColourAndLightsNeighbours) {
  std::vector<std::string> warnings;
  SceneDescription desc = load(
      quad_scene(R"({"pbrMetallicRoughness": {"baseColorFactor": [0.2, 0.5, 0.8, 1]},
                     "extensions": {"KHR_materials_unlit": {}}})",
                 R"("extensionsUsed": ["KHR_materials_unlit"],)"),
      &warnings);
  desc.camera = testing::look_at({0.f, 0.f, 2.f}, {0.f, 0.f, 0.f}, 1e-3f);
  {
    // Under a bright environment, which an unlit surface does not reflect.
    RenderSettings settings;
    settings.environment = Environment::constant({3.f, 3.f, 3.f});
    const Vec3 got = render_pixel(Scene(SceneDescription(desc)), settings, 16);
    EXPECT_FLOAT_EQ(got.x, 0.2f);
    EXPECT_FLOAT_EQ(got.y, 0.5f);
    EXPECT_FLOAT_EQ(got.z, 0.8f);
  }
  // A white Lambertian floor facing the unlit quad (the only source): lit by it.
  const uint32_t floor = uint32_t(desc.materials.size());
  desc.materials.push_back(Material{"floor", {1.f, 1.f, 1.f}, {0.f, 0.f, 0.f}});
  testing::add_quad(&desc, {-1.f, -1.f, 1.f}, {-1.f, 1.f, 1.f}, {1.f, 1.f, 1.f},
                    {1.f, -1.f, 1.f}, floor);
  desc.camera = testing::look_at({0.f, 0.f, 0.5f}, {0.f, 0.f, 1.f}, 1e-3f);
  RenderSettings settings;
  const Vec3 lit = render_pixel(Scene(std::move(desc)), settings, 256);
  EXPECT_GT(lit.z, lit.x);  // the quad's blue dominates
  EXPECT_GT(lit.x, 0.02f);
}

}  // namespace
}  // namespace rf
