// BSDF tests: sampling matches the pdf (chi-square), the pdf integrates to the non-delta
// probability, weights equal f cos / pdf, energy bounds and reciprocity, Fresnel values.
#include "scene/materials.h"

#include <gtest/gtest.h>

#include "testing/chi_square.h"

#include <cstring>
#include <random>
#include <vector>

namespace rf {
namespace {

using testing::ChiSquareResult;
using testing::ChiSquareTest;

Vec3 spherical(double z, double phi) {
  const double r = std::sqrt(std::max(0.0, 1.0 - z * z));
  return Vec3(float(r * std::cos(phi)), float(r * std::sin(phi)), float(z));
}

BsdfParams params(Vec3 base, float metallic, float roughness, float specular = 1.f,
                  float transmission = 0.f) {
  BsdfParams p;
  p.base = base;
  p.metallic = metallic;
  p.alpha = std::max(kMinAlpha, roughness * roughness);
  p.specular = specular;
  p.transmission = transmission;
  return p;
}

// KHR_materials_specular with a colour: F0 per channel, one of them clamped to 1 (0.04 x 30).
BsdfParams coloured_specular() {
  BsdfParams p = params({0.6f, 0.4f, 0.3f}, 0.f, 0.35f, 0.7f);
  p.specular_color = Vec3(0.2f, 2.5f, 30.f);
  return p;
}

// KHR_materials_anisotropy: alpha_t = mix(alpha, 1, strength^2) along the local x axis.
BsdfParams anisotropic(float metallic, float roughness, float strength) {
  BsdfParams p = params({0.8f, 0.6f, 0.4f}, metallic, roughness);
  p.alpha_t = p.alpha * (1.f - strength * strength) + strength * strength;
  return p;
}

// KHR_materials_iridescence: a thin film (ior 1.3, 400 nm) mixed in with weight k.
BsdfParams iridescent(float metallic, float k) {
  BsdfParams p = params({0.7f, 0.5f, 0.3f}, metallic, 0.4f);
  p.iridescence = k;
  p.iridescence_ior = 1.3f;
  p.iridescence_thickness = 400.f;
  return p;
}

// KHR_materials_diffuse_transmission: share d of the diffuse base transmitted, colour c.
BsdfParams translucent(Vec3 base, float roughness, float d, Vec3 c, float transmission = 0.f) {
  BsdfParams p = params(base, 0.f, roughness, 1.f, transmission);
  p.diffuse_transmission = d;
  p.diffuse_transmission_color = c;
  return p;
}

std::vector<BsdfParams> test_materials() {
  return {params({0.8f, 0.5f, 0.2f}, 0.f, 0.5f),        // plastic
          params({0.9f, 0.6f, 0.3f}, 1.f, 0.3f),        // rough gold-ish metal
          params({1.f, 1.f, 1.f}, 1.f, 0.8f),           // very rough white metal
          params({0.5f, 0.5f, 0.5f}, 0.3f, 0.6f, 0.5f),  // mixture
          params({0.7f, 0.7f, 0.7f}, 0.f, 0.4f, 1.f, 0.5f),  // half glass
          coloured_specular(), anisotropic(0.f, 0.3f, 0.7f), anisotropic(1.f, 0.2f, 0.9f),
          iridescent(0.f, 1.f), iridescent(1.f, 0.7f),
          translucent({0.3f, 0.6f, 0.2f}, 0.5f, 0.6f, {0.5f, 0.9f, 0.1f}),
          translucent({0.8f, 0.8f, 0.8f}, 0.3f, 1.f, {1.f, 0.7f, 0.5f}, 0.4f)};
}

const Vec3 kOutgoing[] = {normalize(Vec3(0.3f, 0.1f, 0.9f)), normalize(Vec3(-0.8f, 0.2f, 0.4f))};

// Integral of the pdf over the hemisphere in (z, phi) coordinates (dω = dz dφ).
double integrate_pdf(const BsdfParams& p, Vec3 wo, int n = 600) {
  double sum = 0.0;
  for (int i = 0; i < n; ++i)
    for (int j = 0; j < n; ++j) {
      const double z = (i + 0.5) / n, phi = (j + 0.5) * 2 * M_PI / n;
      sum += bsdf_pdf(p, wo, spherical(z, phi)) * (1.0 / n) * (2 * M_PI / n);
    }
  return sum;
}

// The pdf over the upper hemisphere integrates to the probability that bsdf_sample returns
// a non-delta direction: 1 - P(glass lobe) - P(GGX reflection fell below the horizon).
TEST(Bsdf, PdfIntegratesToTheNonDeltaSuccessProbability) {
  std::mt19937_64 rng(3);
  std::uniform_real_distribution<float> uni(0.f, 1.f);
  for (const BsdfParams& p : test_materials())
    for (Vec3 wo : kOutgoing) {
      const int n = 100000;
      int ok = 0;
      for (int s = 0; s < n; ++s) {
        BsdfSample bs;
        ok += bsdf_sample(p, wo, {uni(rng), uni(rng)}, uni(rng), uni(rng), &bs) && !bs.delta;
      }
      const double frac = double(ok) / n;
      const double upper = 1.0 - (1.0 - p.metallic) * p.transmission;
      const double integral = integrate_pdf(p, wo);
      EXPECT_NEAR(integral, frac, 4.0 * std::sqrt(frac * (1 - frac) / n) + 3e-3)
          << "metallic " << p.metallic;
      EXPECT_LE(integral, upper + 3e-3);
    }
}

TEST(Bsdf, SamplesFollowThePdfAndWeightsAreFCosOverPdf) {
  // Fine midpoint integration of the expected counts: the anisotropic metal's lobe is narrow
  // across its direction (alpha 0.04).
  const int nz = 12, nphi = 24, sub = 32, n = 150000;
  std::mt19937_64 rng(99);
  std::uniform_real_distribution<float> uni(0.f, 1.f);
  for (const BsdfParams& p : test_materials())
    for (Vec3 wo : kOutgoing) {
      // The test's unit square: x = z, y = phi / (2 pi), d(omega) = dz dphi = 2 pi dx dy.
      ChiSquareTest chi2(nz, nphi);
      for (int s = 0; s < n; ++s) {
        BsdfSample bs;
        if (!bsdf_sample(p, wo, {uni(rng), uni(rng)}, uni(rng), uni(rng), &bs) || bs.delta)
          continue;
        const Vec3 f = bsdf_eval_cos(p, wo, bs.wi);
        float joint_pdf = 0.f;
        const Vec3 joint_f = bsdf_eval_pdf(p, wo, bs.wi, &joint_pdf);
        ASSERT_NEAR(joint_pdf, bsdf_pdf(p, wo, bs.wi), 1e-4f * (1.f + joint_pdf));
        ASSERT_NEAR(joint_f.y, f.y, 1e-4f * (1.f + f.y));
        for (int c = 0; c < 3; ++c)
          ASSERT_NEAR(bs.weight[c], f[c] / bs.pdf, 1e-3f * (1.f + f[c] / bs.pdf));
        double phi = std::atan2(bs.wi.y, bs.wi.x);
        if (phi < 0) phi += 2 * M_PI;
        chi2.add_sample(bs.wi.z, phi / (2 * M_PI));
      }
      chi2.integrate(
          [&](double x, double y) {
            return bsdf_pdf(p, wo, spherical(x, 2 * M_PI * y)) * 2 * M_PI;
          },
          sub, n);
      const ChiSquareResult result = chi2.run();
      EXPECT_TRUE(result.passed) << result.message << ", metallic " << p.metallic << " alpha "
                                 << p.alpha << " wo.z " << wo.z;
    }
}

// bsdf_eval_pdf (the path tracer's evaluation: wo terms precomputed per vertex, the GGX terms
// rearranged) equals the reference formulas of bsdf_eval_cos and bsdf_pdf in every channel,
// over a grid of directions including grazing ones and for roughness down to kMinAlpha.
TEST(Bsdf, JointEvaluationEqualsTheReferenceFormulas) {
  std::vector<BsdfParams> materials = test_materials();
  materials.push_back(params({0.9f, 0.9f, 0.9f}, 1.f, 0.f));        // mirror-like metal
  materials.push_back(params({0.2f, 0.6f, 0.9f}, 0.f, 0.05f, 1.f));  // glossy plastic
  materials.push_back(params({0.6f, 0.6f, 0.6f}, 0.f, 1.f, 0.f));    // pure Lambert
  int compared = 0;
  for (const BsdfParams& p : materials)
    for (double zo : {0.02, 0.3, 0.7, 0.999})
      for (double zi : {0.01, 0.2, 0.5, 0.9, 1.0})
        for (double phi : {0.0, 1.0, 2.5, 3.14159}) {
          const Vec3 wo = spherical(zo, 0.4), wi = spherical(zi, 0.4 + phi);
          float pdf = -1.f;
          const Vec3 f = bsdf_eval_pdf(p, bsdf_lobes(p, wo), wo, wi, &pdf);
          const Vec3 f_ref = bsdf_eval_cos(p, wo, wi);
          const float pdf_ref = bsdf_pdf(p, wo, wi);
          ASSERT_NEAR(pdf, pdf_ref, 1e-3f * pdf_ref + 1e-6f) << zo << " " << zi << " " << phi;
          for (int c = 0; c < 3; ++c)
            ASSERT_NEAR(f[c], f_ref[c], 1e-3f * f_ref[c] + 1e-6f) << zo << " " << zi << " " << phi;
          ++compared;
        }
  EXPECT_EQ(compared, int(materials.size()) * 4 * 5 * 4);
  // Below either hemisphere: zero, with zero pdf.
  const BsdfParams p = test_materials()[0];
  float pdf = 1.f;
  EXPECT_TRUE(is_zero(bsdf_eval_pdf(p, bsdf_lobes(p, kOutgoing[0]), kOutgoing[0],
                                    Vec3(0.f, 0.6f, -0.8f), &pdf)));
  EXPECT_EQ(pdf, 0.f);
}

uint32_t float_bits(float x) {
  uint32_t u;
  std::memcpy(&u, &x, sizeof u);
  return u;
}

// BsdfEvalBatch (the path tracer's packet-wide evaluation) gives bsdf_eval_pdf's results, and
// for sampled directions normalize(frame.to_world(normalize(wi))), bit for bit: random
// materials (metals, glass, the specular factor on and off), random directions including ones
// below the surface, lanes left out, both directions of a vertex, and batches reused without
// resetting the slots left over from earlier rounds.
TEST(Bsdf, BatchEvaluationEqualsTheScalarOneBitForBit) {
  std::mt19937 rng(20261123);
  std::uniform_real_distribution<float> uni(0.f, 1.f);
  const auto direction = [&](float below) {
    const float z = uni(rng) < below ? -uni(rng) : uni(rng);
    const float phi = 6.2831853f * uni(rng);
    const float r = std::sqrt(std::max(0.f, 1.f - z * z));
    return normalize(Vec3(r * std::cos(phi), r * std::sin(phi), z));
  };
  BsdfEvalBatch batch;
  int compared = 0, sampled_compared = 0, nonzero = 0;
  for (int round = 0; round < 300; ++round) {
    batch.clear();
    struct Queued {
      BsdfParams p;
      Vec3 wo, wi;
      Frame frame;
      int slot;
    };
    std::vector<Queued> queued;
    for (int lane = 0; lane < BsdfEvalBatch::kLanes; ++lane) {
      if (uni(rng) < 0.25f) continue;  // a dead path
      BsdfParams p = params({uni(rng), uni(rng), uni(rng)}, uni(rng) < 0.3f ? 0.f : uni(rng),
                            uni(rng), uni(rng) < 0.2f ? 0.f : uni(rng),
                            uni(rng) < 0.7f ? 0.f : uni(rng));
      p.ior = 1.f + uni(rng);
      if (uni(rng) < 0.2f) p.diffuse_transmission = uni(rng);
      const Vec3 wo = direction(0.1f);
      const BsdfLobes lobes = bsdf_lobes(p, wo);
      const Frame frame(direction(0.f));
      batch.set_vertex(lane, p, lobes, wo, frame);
      // A light sample's direction (unit), then a sampled one (any length, normalized by the
      // batch, which also returns it in world space).
      if (uni(rng) < 0.7f) {
        const Vec3 wi = direction(0.2f);
        queued.push_back({p, wo, wi, frame, batch.add_light(lane, wi)});
      }
      if (uni(rng) < 0.7f) {
        const Vec3 wi = direction(0.2f) * (0.2f + 3.f * uni(rng));
        queued.push_back({p, wo, wi, frame, batch.add_sampled(lane, wi)});
      }
    }
    batch.evaluate();
    for (const Queued& q : queued) {
      const bool sampled = q.slot >= BsdfEvalBatch::kLanes;
      const Vec3 wi = sampled ? normalize(q.wi) : q.wi;
      float pdf = -1.f;
      const Vec3 f = bsdf_eval_pdf(q.p, bsdf_lobes(q.p, q.wo), q.wo, wi, &pdf);
      ASSERT_EQ(float_bits(batch.pdf(q.slot)), float_bits(pdf)) << "round " << round;
      for (int c = 0; c < 3; ++c)
        ASSERT_EQ(float_bits(batch.f(q.slot)[c]), float_bits(f[c])) << "round " << round;
      if (sampled) {
        const Vec3 world = normalize(q.frame.to_world(wi));
        for (int c = 0; c < 3; ++c)
          ASSERT_EQ(float_bits(batch.world(q.slot)[c]), float_bits(world[c])) << round;
        ++sampled_compared;
      }
      ++compared;
      nonzero += pdf > 0.f;
    }
  }
  EXPECT_GT(compared, 5000);
  EXPECT_GT(sampled_compared, 2000);
  EXPECT_GT(nonzero, compared / 2);  // most pairs are above the surface
  EXPECT_LT(nonzero, compared);      // and some are not
}

// Directional albedo integral of f cos over the hemisphere, by quadrature.
Vec3 albedo(const BsdfParams& p, Vec3 wo, int n = 500) {
  Vec3 sum;
  for (int i = 0; i < n; ++i)
    for (int j = 0; j < n; ++j) {
      const double z = (i + 0.5) / n, phi = (j + 0.5) * 2 * M_PI / n;
      sum += bsdf_eval_cos(p, wo, spherical(z, phi)) * float((1.0 / n) * (2 * M_PI / n));
    }
  return sum;
}

TEST(Bsdf, EnergyBoundsReciprocityAndLambertLimit) {
  // specular = 0, metallic = 0: exactly Lambert, albedo = base.
  const BsdfParams lambert = params({0.6f, 0.6f, 0.6f}, 0.f, 1.f, 0.f);
  for (Vec3 wo : kOutgoing) EXPECT_NEAR(albedo(lambert, wo).x, 0.6f, 2e-3f);
  for (const BsdfParams& p : test_materials()) {
    for (Vec3 wo : kOutgoing) {
      const Vec3 a = albedo(p, wo);
      EXPECT_LE(max_component(a), 1.0f + 5e-3f);  // no energy gain
      EXPECT_GT(max_component(a), 0.f);
      // Reciprocity f(wo, wi) = f(wi, wo): compare f cos / cos both ways.
      const Vec3 wi = normalize(Vec3(0.2f, -0.5f, 0.6f));
      const Vec3 a1 = bsdf_eval_cos(p, wo, wi) * (1.f / wi.z);
      const Vec3 a2 = bsdf_eval_cos(p, wi, wo) * (1.f / wo.z);
      for (int c = 0; c < 3; ++c) EXPECT_NEAR(a1[c], a2[c], 1e-4f * (1.f + a1[c]));
    }
  }
  // White metal conserves energy at every roughness and angle (multiple-scattering
  // compensation), up to the energy table's accuracy.
  for (float roughness : {0.2f, 0.5f, 0.8f, 1.f})
    for (Vec3 wo : kOutgoing) {
      const BsdfParams white = params({1.f, 1.f, 1.f}, 1.f, roughness);
      EXPECT_NEAR(albedo(white, wo).x, 1.f, 4e-3f) << "roughness " << roughness;
    }
  // Nothing below the surface.
  EXPECT_TRUE(is_zero(bsdf_eval_cos(test_materials()[0], kOutgoing[0], {0.f, 0.6f, -0.8f})));
}

TEST(Bsdf, FresnelAndGlass) {
  EXPECT_NEAR(fresnel_dielectric(1.f, 1.5f), 0.04f, 1e-6f);
  EXPECT_EQ(fresnel_dielectric(0.1f, 1.f / 1.5f), 1.f);  // total internal reflection
  EXPECT_NEAR(fresnel_dielectric(0.f, 1.5f), 1.f, 1e-6f);
  // Smooth glass: reflection with probability F, refraction obeys Snell's law and scales
  // radiance by 1/eta^2.
  BsdfParams glass = params({1.f, 1.f, 1.f}, 0.f, 0.f, 1.f, 1.f);
  EXPECT_FALSE(bsdf_has_smooth_part(glass));
  const Vec3 wo = normalize(Vec3(0.5f, 0.f, 0.8f));
  const float F = fresnel_dielectric(wo.z, 1.5f);
  BsdfSample r, t;
  ASSERT_TRUE(bsdf_sample(glass, wo, {0.5f, 0.5f}, 0.f, F * 0.5f, &r));
  EXPECT_TRUE(r.delta);
  EXPECT_FALSE(r.transmitted);
  EXPECT_NEAR(r.wi.x, -wo.x, 1e-6f);
  ASSERT_TRUE(bsdf_sample(glass, wo, {0.5f, 0.5f}, 0.f, 0.5f + 0.5f * F, &t));
  EXPECT_TRUE(t.transmitted);
  const float sin_o = std::sqrt(1.f - wo.z * wo.z), sin_t = std::sqrt(1.f - t.wi.z * t.wi.z);
  EXPECT_NEAR(sin_o, 1.5f * sin_t, 1e-5f);
  EXPECT_LT(t.wi.z, 0.f);
  EXPECT_NEAR(t.weight.x, 1.f / (1.5f * 1.5f), 1e-6f);
  // The scaling is reported beside the weight (Russian roulette undoes it), and only for a
  // refraction.
  EXPECT_NEAR(t.eta2, 1.5f * 1.5f, 1e-6f);
  EXPECT_EQ(r.eta2, 1.f);
  glass.front = false;  // leaving the glass: radiance grows by eta^2 (unless TIR)
  const Vec3 wo2 = normalize(Vec3(0.2f, 0.f, 0.9f));
  ASSERT_TRUE(bsdf_sample(glass, wo2, {0.5f, 0.5f}, 0.f, 0.999f, &t));
  EXPECT_TRUE(t.transmitted);
  EXPECT_NEAR(t.weight.x, 1.5f * 1.5f, 1e-4f);
  EXPECT_NEAR(t.eta2, 1.f / (1.5f * 1.5f), 1e-6f);
  // A sample completed from its evaluated value (what a guided direction is, in the sample a
  // path keeps from vertex to vertex) is never a refraction, whatever the last one was.
  ASSERT_TRUE(bsdf_sample_finish(Vec3(0.2f, 0.2f, 0.2f), 0.5f, &t));
  EXPECT_FALSE(t.transmitted);
  EXPECT_EQ(t.eta2, 1.f);
}

// ---- Diffuse transmission (KHR_materials_diffuse_transmission): the extension's
// mix(diffuse_brdf(baseColor), diffuse_btdf(C), d) under the dielectric's Fresnel weight.

Vec3 mirrored(Vec3 w) { return Vec3(w.x, w.y, -w.z); }

// What the BTDF transmits is what the diffuse BRDF no longer reflects: with C = baseColor,
// f(d = 0) - f(d) at wi equals the BTDF at wi mirrored below the surface (the Fresnel angle of
// the mirrored direction, materials.h); the BTDF is the closed form d C (1 - m)(1 - t)
// (1 - s max(F)) / pi written here, zero above the surface, and reciprocal. With t > 0 the
// rough glass lobe is in through_eval_cos too: the BTDF is what d adds to it.
TEST(DiffuseTransmission, TransmitsWhatTheDiffuseReflectionGivesUp) {
  int compared = 0;
  for (float d : {0.25f, 1.f})
    for (float t : {0.f, 0.5f})
      for (double zo : {0.05, 0.4, 0.95})
        for (double zi : {0.1, 0.6, 1.0})
          for (double phi : {0.0, 1.3, 3.0}) {
            const Vec3 base(0.7f, 0.4f, 0.2f);
            BsdfParams opaque = params(base, 0.f, 0.45f, 0.8f, t);
            opaque.ior = 1.45f;
            BsdfParams p = opaque;
            p.diffuse_transmission = d;
            p.diffuse_transmission_color = base;
            const auto btdf = [&](Vec3 a, Vec3 b) {
              return through_eval_cos(p, a, b) - through_eval_cos(opaque, a, b);
            };
            const Vec3 wo = spherical(zo, 0.3), wi = spherical(zi, 0.3 + phi);
            const Vec3 given_up = bsdf_eval_cos(opaque, wo, wi) - bsdf_eval_cos(p, wo, wi);
            const Vec3 through = btdf(wo, mirrored(wi));
            // The closed form: F = s (F0 + (1 - F0)(1 - |V.H|)^5), F0 = ((ior-1)/(ior+1))^2,
            // H = normalize(V + L mirrored), times |cos_i|.
            const Vec3 h = normalize(wo + wi);
            const double f0 = std::pow((1.45 - 1.0) / (1.45 + 1.0), 2.0);
            const double F = 0.8 * (f0 + (1.0 - f0) * std::pow(1.0 - dot(wo, h), 5.0));
            for (int c = 0; c < 3; ++c) {
              const double want = d * base[c] * (1.0 - t) * (1.0 - F) / M_PI * zi;
              ASSERT_NEAR(through[c], want, 1e-5 + 1e-4 * want) << zo << " " << zi << " " << phi;
              ASSERT_NEAR(given_up[c], want, 1e-5 + 1e-4 * want) << zo << " " << zi << " " << phi;
            }
            EXPECT_TRUE(is_zero(btdf(wo, wi)));  // nothing above
            // Reciprocity: f(wo, wi) = f(-wi, -wo), the same pair seen from the other side.
            const Vec3 wl = mirrored(wi);
            const Vec3 a1 = through * float(1.0 / zi);
            const Vec3 a2 = btdf(-wl, -wo) * float(1.0 / zo);
            for (int c = 0; c < 3; ++c) ASSERT_NEAR(a1[c], a2[c], 1e-5f + 1e-4f * a1[c]);
            ++compared;
          }
  EXPECT_EQ(compared, 2 * 2 * 3 * 3 * 3);
}

// The BTDF's samples: with u_lobe in its share [glass - diffuse_bt, glass) of the sampled-only
// lobes, every direction lies below the surface with density |cos_i| / pi (chi-square over
// the lower hemisphere), and its weight times that share is f |cos_i| / (|cos_i| / pi) = d C
// (1 - t)(1 - s max(F)) with F at the mirrored half vector, the closed form written here.
TEST(DiffuseTransmission, BtdfSamplesFollowTheCosineDensityWithTheClosedFormWeight) {
  std::mt19937_64 rng(23);
  std::uniform_real_distribution<float> uni(0.f, 1.f);
  const int nz = 12, nphi = 24, n = 100000;
  for (float t : {0.f, 0.4f})
    for (Vec3 wo : kOutgoing) {
      const Vec3 base(0.6f, 0.5f, 0.4f), colour(0.9f, 0.3f, 0.6f);
      BsdfParams p = translucent(base, 0.5f, 0.7f, colour, t);
      p.ior = 1.5f;
      const BsdfLobes l = bsdf_lobes(p, wo);
      ASSERT_GT(l.diffuse_bt, 0.f);
      ChiSquareTest chi2(nz, nphi);
      const double f0 = 0.04;
      for (int s = 0; s < n; ++s) {
        BsdfSample bs;
        const float u_lobe = l.glass - l.diffuse_bt * (1.f - uni(rng)) * 0.9999f;
        ASSERT_TRUE(bsdf_sample(p, wo, {uni(rng), uni(rng)}, u_lobe, uni(rng), &bs));
        ASSERT_TRUE(bs.transmitted);
        ASSERT_TRUE(bs.delta);
        ASSERT_LT(bs.wi.z, 0.f);
        const Vec3 h = normalize(wo + mirrored(bs.wi));
        const double F = p.specular * (f0 + (1.0 - f0) * std::pow(1.0 - dot(wo, h), 5.0));
        for (int c = 0; c < 3; ++c) {
          const double want = 0.7 * colour[c] * (1.0 - t) * (1.0 - F);
          ASSERT_NEAR(bs.weight[c] * l.diffuse_bt, want, 1e-4 + 1e-4 * want);
        }
        double phi = std::atan2(bs.wi.y, bs.wi.x);
        if (phi < 0) phi += 2 * M_PI;
        chi2.add_sample(-bs.wi.z, phi / (2 * M_PI));
      }
      // Density over (x = |cos_i|, y = phi / 2pi): |cos| / pi x dz dphi = x / pi x 2 pi.
      chi2.integrate([](double x, double) { return 2.0 * x; }, 8, n);
      const ChiSquareResult result = chi2.run();
      EXPECT_TRUE(result.passed) << result.message << ", t " << t << " wo.z " << wo.z;
    }
}

// The samples' mean weight (BTDF samples marked as transmitted, sampled-only lobes) estimates
// the material's albedo, reflection and transmission integrated by quadrature; a white,
// fully translucent Lambert without a specular layer transmits everything (white furnace).
TEST(DiffuseTransmission, SamplesEstimateTheAlbedoAndAWhiteLambertTransmitsAll) {
  std::mt19937_64 rng(11);
  std::uniform_real_distribution<float> uni(0.f, 1.f);
  BsdfParams white = translucent({1.f, 1.f, 1.f}, 1.f, 1.f, {1.f, 1.f, 1.f});
  white.specular = 0.f;
  std::vector<BsdfParams> materials = {
      white, translucent({0.3f, 0.6f, 0.2f}, 0.5f, 0.6f, {0.5f, 0.9f, 0.1f}),
      translucent({0.8f, 0.8f, 0.8f}, 0.3f, 1.f, {1.f, 0.7f, 0.5f}, 0.4f)};
  materials[1].clearcoat = 0.7f;  // under a coat
  materials[1].clearcoat_alpha = 0.1f;
  for (size_t k = 0; k < materials.size(); ++k)
    for (Vec3 wo : kOutgoing) {
      const BsdfParams& p = materials[k];
      // Quadrature: reflection over the upper hemisphere, the BTDF over the lower one.
      const int nq = 400;
      Vec3 want = albedo(p, wo, nq);
      BsdfParams clear = p;  // the same material without the BTDF (its rough glass lobe)
      clear.diffuse_transmission = 0.f;
      for (int i = 0; i < nq; ++i)
        for (int j = 0; j < nq; ++j) {
          const double z = (i + 0.5) / nq, phi = (j + 0.5) * 2 * M_PI / nq;
          const Vec3 wl = mirrored(spherical(z, phi));
          want += (through_eval_cos(p, wo, wl) - through_eval_cos(clear, wo, wl)) *
                  float((1.0 / nq) * (2 * M_PI / nq));
        }
      // The glass lobe (t = 0.4 in material 2, chosen for u_lobe < t) is left to the glass
      // tests: u_lobe is drawn from [t, 1), and the mean weight times 1 - t estimates what the
      // other lobes contribute.
      const float g = p.transmission;
      const int n = 200000;
      Vec3 sum, sum2;
      int transmitted = 0;
      for (int s = 0; s < n; ++s) {
        BsdfSample bs;
        const float u_lobe = std::min(0.99999994f, g + (1.f - g) * uni(rng));
        if (!bsdf_sample(p, wo, {uni(rng), uni(rng)}, u_lobe, uni(rng), &bs)) continue;
        bs.weight = bs.weight * (1.f - g);
        if (bs.transmitted) {
          ASSERT_TRUE(bs.delta);
          ASSERT_LT(bs.wi.z, 0.f);
          ++transmitted;
        }
        sum += bs.weight;
        sum2 += bs.weight * bs.weight;
      }
      EXPECT_GT(transmitted, n / 10);
      for (int c = 0; c < 3; ++c) {
        const double mean = sum[c] / n, se = std::sqrt((sum2[c] / n - mean * mean) / n);
        EXPECT_NEAR(mean, want[c], 4.0 * se + 3e-3) << "material " << k << " wo.z " << wo.z;
      }
      if (k == 0) {
        EXPECT_NEAR(want.x, 1.f, 2e-3f);
      }
    }
}

// ---- Rough glass (KHR_materials_transmission with roughness): Walter et al. 2007's microfacet
// BSDF, its formulas written here in double from the paper, independently of materials.cpp.
// eta = n_i / n_o: the index on wi's side over wo's (the material's ior entering it).
struct WalterGlass {
  double alpha, eta;
  static double dot3(const double* a, const double* b) {
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
  }
  double d(const double* h) const {  // GGX (Trowbridge-Reitz), h.z > 0
    const double a2 = alpha * alpha, c2 = h[2] * h[2];
    const double t = c2 * (a2 - 1.0) + 1.0;
    return a2 / (M_PI * t * t);
  }
  double lambda(const double* w) const {
    const double c2 = w[2] * w[2];
    return 0.5 * (-1.0 + std::sqrt(1.0 + alpha * alpha * (1.0 - c2) / c2));
  }
  double g1(const double* w) const { return 1.0 / (1.0 + lambda(w)); }
  double g2(const double* wo, const double* wi) const {
    return 1.0 / (1.0 + lambda(wo) + lambda(wi));
  }
  double fresnel(double c) const {  // exact, unpolarized; c = cos at the interface, wo's side
    const double s2 = (1.0 - c * c) / (eta * eta);
    if (s2 >= 1.0) return 1.0;
    const double ct = std::sqrt(1.0 - s2);
    const double rs = (c - eta * ct) / (c + eta * ct), rp = (eta * c - ct) / (eta * c + ct);
    return 0.5 * (rs * rs + rp * rp);
  }
  // The half vector of (wo, wi), towards +z: reflection wo + wi, refraction -(wo + eta wi).
  bool half(const double* wo, const double* wi, double* h) const {
    const bool refl = wi[2] > 0.0;
    for (int k = 0; k < 3; ++k) h[k] = refl ? wo[k] + wi[k] : -(wo[k] + eta * wi[k]);
    const double l = std::sqrt(dot3(h, h));
    if (!(l > 0.0)) return false;
    for (int k = 0; k < 3; ++k) h[k] /= l;
    if (h[2] < 0.0)
      for (int k = 0; k < 3; ++k) h[k] = -h[k];
    // Both directions on the sides of h that the configuration needs.
    return dot3(wo, h) > 0.0 && (refl ? dot3(wi, h) > 0.0 : dot3(wi, h) < 0.0);
  }
  // f |cos_i| in importance form (no 1/eta^2 radiance scaling) and the density with which
  // the sampling strategy (visible normal, then F(wo.h) reflect / refract) gives wi.
  void eval(const double* wo, const double* wi, double* f_cos, double* pdf) const {
    *f_cos = *pdf = 0.0;
    double h[3];
    if (!half(wo, wi, h)) return;
    const double oh = dot3(wo, h), ih = dot3(wi, h);
    const double F = fresnel(oh), D = d(h), G = g2(wo, wi);
    const double vndf = g1(wo) * oh * D / wo[2];
    if (wi[2] > 0.0) {
      *f_cos = F * D * G / (4.0 * wo[2]);
      *pdf = F * vndf / (4.0 * oh);
    } else {
      const double den = oh + eta * ih;
      *f_cos = (1.0 - F) * D * G * std::fabs(ih) * oh * eta * eta / (wo[2] * den * den);
      *pdf = (1.0 - F) * vndf * eta * eta * std::fabs(ih) / (den * den);
    }
  }
};

BsdfParams rough_glass(float roughness, bool front) {
  BsdfParams p = params({1.f, 1.f, 1.f}, 0.f, roughness, 1.f, 1.f);
  p.front = front;
  return p;
}

// Every sample's direction follows the strategy's density (chi-square over the whole sphere),
// its weight is f |cos_i| / pdf of the model (over eta^2 for a refraction: radiance), and it
// is marked as the sampled-only glass lobe (delta, pdf 0: light sampling leaves it out).
TEST(RoughGlass, SamplesFollowWaltersDensityWithWeightFCosOverPdf) {
  // Fine midpoint integration of the expected counts: the lobes at roughness 0.3 are narrow.
  const int nz = 16, nphi = 24, sub = 32, n = 200000;
  std::mt19937_64 rng(17);
  std::uniform_real_distribution<float> uni(0.f, 1.f);
  for (float roughness : {0.3f, 0.7f})
    for (bool front : {true, false})
      for (Vec3 wo : kOutgoing) {
        const BsdfParams p = rough_glass(roughness, front);
        const WalterGlass w{double(p.alpha), front ? 1.5 : 1.0 / 1.5};
        const double wod[3] = {wo.x, wo.y, wo.z};
        ChiSquareTest chi2(nz, nphi);
        int refracted = 0;
        for (int s = 0; s < n; ++s) {
          BsdfSample bs;
          if (!bsdf_sample(p, wo, {uni(rng), uni(rng)}, uni(rng), uni(rng), &bs)) continue;
          ASSERT_TRUE(bs.delta);
          ASSERT_EQ(bs.pdf, 0.f);
          ASSERT_EQ(bs.transmitted, bs.wi.z < 0.f);
          refracted += bs.transmitted;
          const double wid[3] = {bs.wi.x, bs.wi.y, bs.wi.z};
          double f_cos, pdf;
          w.eval(wod, wid, &f_cos, &pdf);
          ASSERT_GT(pdf, 0.0) << "a sample where the model has no density";
          const double want = f_cos / pdf / (bs.transmitted ? w.eta * w.eta : 1.0);
          ASSERT_NEAR(bs.eta2, bs.transmitted ? w.eta * w.eta : 1.0, 1e-5);
          ASSERT_NEAR(bs.weight.x, want, 2e-3 * (1.0 + want))
              << "roughness " << roughness << " front " << front << " wi.z " << bs.wi.z;
          double phi = std::atan2(bs.wi.y, bs.wi.x);
          if (phi < 0) phi += 2 * M_PI;
          chi2.add_sample(0.5 * (bs.wi.z + 1.0), phi / (2 * M_PI));
        }
        // Entering, most light refracts; leaving at grazing angles, most is totally reflected.
        EXPECT_GT(refracted, front ? n / 2 : n / 100);
        chi2.integrate(
            [&](double x, double y) {
              const Vec3 v = spherical(2.0 * x - 1.0, 2 * M_PI * y);
              const double vd[3] = {v.x, v.y, v.z};
              double f_cos, pdf;
              w.eval(wod, vd, &f_cos, &pdf);
              return pdf * 4 * M_PI;  // d(omega) = dz dphi = 2 dx 2 pi dy
            },
            sub, n);
        const ChiSquareResult result = chi2.run();
        EXPECT_TRUE(result.passed) << result.message << ", roughness " << roughness
                                   << " front " << front << " wo.z " << wo.z;
      }
}

// White furnace of the lobe: its albedo (importance form), integrated over the sphere from
// the model's f, is at most 1 (single scattering loses the energy of light that meets a second
// microfacet) and is what the samples' mean weight estimates; at low roughness it nears 1.
TEST(RoughGlass, WhiteFurnaceAlbedoAtMostOneAndEstimatedByTheSamples) {
  std::mt19937_64 rng(5);
  std::uniform_real_distribution<float> uni(0.f, 1.f);
  for (float roughness : {0.2f, 0.5f, 0.9f})
    for (bool front : {true, false})
      for (Vec3 wo : kOutgoing) {
        const BsdfParams p = rough_glass(roughness, front);
        const WalterGlass w{double(p.alpha), front ? 1.5 : 1.0 / 1.5};
        const double wod[3] = {wo.x, wo.y, wo.z};
        // Quadrature over the sphere, dense in z near the poles where the lobes peak.
        const int nzq = 1200, nphiq = 600;
        double albedo = 0.0;
        for (int i = 0; i < nzq; ++i)
          for (int j = 0; j < nphiq; ++j) {
            const double z = -1.0 + 2.0 * (i + 0.5) / nzq, phi = 2 * M_PI * (j + 0.5) / nphiq;
            const Vec3 v = spherical(z, phi);
            const double vd[3] = {v.x, v.y, v.z};
            double f_cos, pdf;
            w.eval(wod, vd, &f_cos, &pdf);
            albedo += f_cos * (2.0 / nzq) * (2 * M_PI / nphiq);
          }
        EXPECT_LE(albedo, 1.0 + 2e-3) << "roughness " << roughness << " front " << front;
        if (roughness <= 0.2f) {
          EXPECT_GT(albedo, 0.95);
        }
        const int n = 200000;
        double sum = 0.0, sum2 = 0.0;
        for (int s = 0; s < n; ++s) {
          BsdfSample bs;
          double x = 0.0;
          if (bsdf_sample(p, wo, {uni(rng), uni(rng)}, uni(rng), uni(rng), &bs))
            x = bs.weight.x * (bs.transmitted ? w.eta * w.eta : 1.0);
          sum += x;
          sum2 += x * x;
        }
        const double mean = sum / n, se = std::sqrt((sum2 / n - mean * mean) / n);
        EXPECT_NEAR(mean, albedo, 4.0 * se + 3e-3)
            << "roughness " << roughness << " front " << front << " wo.z " << wo.z;
      }
}

}  // namespace
}  // namespace rf
