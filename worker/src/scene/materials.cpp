#include "scene/materials.h"

#include <algorithm>
#include <cmath>

#include "math/simd.h"

namespace rf {

namespace {

// ---- Multiple-scattering energy compensation for the metal lobe (Kulla & Conty 2017,
// "Revisiting Physically Based Shading at Imageworks"): single-scattering GGX loses the energy
// of light bouncing between microfacets, 1 - E(mu, alpha). The lost energy is added back as
//   f_ms = F_ms (1 - E(mu_o)) (1 - E(mu_i)) / (pi (1 - E_avg)),
// a reciprocal lobe whose albedo is exactly 1 - E(mu_o) for F = 1 (white furnace).
// E is tabulated over (mu, alpha) by quadrature of the VNDF estimator (E = mean of G2/G1 over
// visible normals whose reflection stays above the horizon) and interpolated bilinearly.
class EnergyTable {
 public:
  static constexpr int kMu = 32, kAlpha = 32;
  EnergyTable() {
    const int n = 48;  // n x n stratified visible normals per entry
    for (int ia = 0; ia < kAlpha; ++ia) {
      const float alpha = alpha_at(ia);
      double avg = 0.0;
      for (int im = 0; im < kMu; ++im) {
        const float mu = mu_at(im);
        const Vec3 wo(std::sqrt(std::max(0.f, 1.f - mu * mu)), 0.f, mu);
        double sum = 0.0;
        for (int i = 0; i < n; ++i)
          for (int j = 0; j < n; ++j) {
            const Vec3 m = sample_ggx_vndf(wo, alpha, {(i + 0.5f) / n, (j + 0.5f) / n});
            const Vec3 wi = m * (2.f * dot(wo, m)) - wo;
            if (wi.z <= 0.f) continue;
            sum += double(ggx_g2(wo, wi, alpha) / ggx_g1(wo, alpha));
          }
        e_[ia][im] = float(std::min(1.0, sum / (n * n)));
        avg += 2.0 * double(e_[ia][im]) * double(mu) / kMu;  // E_avg = 2 int E(mu) mu dmu
      }
      e_avg_[ia] = float(std::min(avg, 0.9999));
    }
  }
  float e(float mu, float alpha) const {
    const float fa = std::min(float(kAlpha - 1), std::max(0.f, alpha_index(alpha)));
    const float fm = std::min(float(kMu - 1), std::max(0.f, mu * kMu - 0.5f));
    const int a0 = std::min(kAlpha - 2, int(fa)), m0 = std::min(kMu - 2, int(fm));
    const float ta = fa - float(a0), tm = fm - float(m0);
    const float lo = e_[a0][m0] * (1.f - tm) + e_[a0][m0 + 1] * tm;
    const float hi = e_[a0 + 1][m0] * (1.f - tm) + e_[a0 + 1][m0 + 1] * tm;
    return lo * (1.f - ta) + hi * ta;
  }
  float e_avg(float alpha) const {
    const float fa = std::min(float(kAlpha - 1), std::max(0.f, alpha_index(alpha)));
    const int a0 = std::min(kAlpha - 2, int(fa));
    const float ta = fa - float(a0);
    return e_avg_[a0] * (1.f - ta) + e_avg_[a0 + 1] * ta;
  }

 private:
  // mu at cell centers; alpha on a square-root grid (denser where E changes fastest).
  static float mu_at(int i) { return (float(i) + 0.5f) / kMu; }
  static float alpha_at(int i) {
    const float t = float(i) / float(kAlpha - 1);
    return std::max(kMinAlpha, t * t);
  }
  static float alpha_index(float alpha) { return std::sqrt(alpha) * float(kAlpha - 1); }
  float e_[kAlpha][kMu];
  float e_avg_[kAlpha];
};

const EnergyTable& energy_table() {
  static const EnergyTable table;
  return table;
}

inline float schlick_weight(float c) {
  const float m = std::min(1.f, std::max(0.f, 1.f - c));
  const float m2 = m * m;
  return m2 * m2 * m;
}

inline float dielectric_f0(const BsdfParams& p) {
  const float r = (p.ior - 1.f) / (p.ior + 1.f);
  return std::min(1.f, p.specular * r * r);
}


// Kulla & Conty's colored F_ms = F_avg^2 E_avg / (1 - F_avg (1 - E_avg)), with
// F_avg = f0 + (1 - f0) / 21 for Schlick and f0 = base.
Vec3 metal_ms_fresnel(const BsdfParams& p, float e_avg) {
  Vec3 f_ms;
  for (int c = 0; c < 3; ++c) {
    const float f_avg = p.base[c] + (1.f - p.base[c]) / 21.f;
    f_ms[c] = f_avg * f_avg * e_avg / (1.f - f_avg * (1.f - e_avg));
  }
  return f_ms;
}

// m * F_ms * (1 - E(mu_o)) (1 - E(mu_i)) / (pi (1 - E_avg)).
Vec3 metal_multiple_scattering(const BsdfParams& p, Vec3 wo, Vec3 wi) {
  if (p.metallic <= 0.f) return {0.f, 0.f, 0.f};
  const EnergyTable& t = energy_table();
  const float e_avg = t.e_avg(p.alpha);
  const float k = p.metallic * (1.f - t.e(wo.z, p.alpha)) * (1.f - t.e(wi.z, p.alpha)) /
                  (kPi * (1.f - e_avg));
  return metal_ms_fresnel(p, e_avg) * k;
}

}  // namespace

// A function of wo only, so that bsdf_pdf can recompute them.
BsdfLobes bsdf_lobes(const BsdfParams& p, Vec3 wo) {
  BsdfLobes l;
  l.glass = (1.f - p.metallic) * p.transmission;
  l.wd = (1.f - p.metallic) * (1.f - p.transmission);
  const float fw = schlick_weight(wo.z);
  l.f0d = dielectric_f0(p);
  const float fd = p.specular > 0.f ? l.f0d + (p.specular - l.f0d) * fw : 0.f;
  const float lum = luminance(p.base);
  const float fm = lum + (1.f - lum) * fw;
  const float ws = l.wd * fd + p.metallic * fm;
  // The cosine lobe also samples the metal's multiple-scattering term.
  float ms = 0.f;
  if (p.metallic > 0.f) {
    const EnergyTable& t = energy_table();
    const float e_o = t.e(wo.z, p.alpha);
    ms = p.metallic * (1.f - e_o);
    const float e_avg = t.e_avg(p.alpha);
    l.ms = metal_ms_fresnel(p, e_avg) * (ms / (kPi * (1.f - e_avg)));
  }
  const float wdiff = l.wd * (1.f - fd) * std::max(lum, 1e-3f) + ms;
  l.spec = ws + wdiff > 0.f ? ws / (ws + wdiff) : 1.f;
  const float c2 = wo.z * wo.z;
  l.root_o = std::sqrt(c2 + p.alpha * p.alpha * std::max(0.f, 1.f - c2));
  l.pdf_k = wo.z > 0.f ? 1.f / (2.f * (wo.z + l.root_o)) : 0.f;
  return l;
}

float metal_single_scattering_albedo(float mu, float alpha) {
  return energy_table().e(mu, alpha);
}

float fresnel_dielectric(float cos_i, float eta) {
  cos_i = std::min(1.f, std::max(0.f, cos_i));
  const float sin_t2 = (1.f - cos_i * cos_i) / (eta * eta);
  if (sin_t2 >= 1.f) return 1.f;  // total internal reflection
  const float cos_t = std::sqrt(1.f - sin_t2);
  const float r_parl = (eta * cos_i - cos_t) / (eta * cos_i + cos_t);
  const float r_perp = (cos_i - eta * cos_t) / (cos_i + eta * cos_t);
  return 0.5f * (r_parl * r_parl + r_perp * r_perp);
}

Vec3 bsdf_eval_cos(const BsdfParams& p, Vec3 wo, Vec3 wi) {
  if (wo.z <= 0.f || wi.z <= 0.f) return {0.f, 0.f, 0.f};
  const float wd = (1.f - p.metallic) * (1.f - p.transmission);
  const Vec3 h_raw = wo + wi;
  const float hl = length(h_raw);
  if (!(hl > 0.f)) return {0.f, 0.f, 0.f};
  const Vec3 h = h_raw / hl;
  const float c = std::max(0.f, dot(wo, h));
  const float fw = schlick_weight(c);
  // KHR_materials_specular: the dielectric Fresnel is scaled by specularFactor.
  const float f0d = dielectric_f0(p);
  const float fd = p.specular > 0.f ? f0d + (p.specular - f0d) * fw : 0.f;
  const Vec3 fm = p.base + (Vec3(1.f, 1.f, 1.f) - p.base) * fw;
  const float spec = ggx_d(h, p.alpha) * ggx_g2(wo, wi, p.alpha) / (4.f * wo.z * wi.z);
  const Vec3 diffuse = p.base * (wd * (1.f - fd) * kInvPi);
  const Vec3 specular = (Vec3(1.f, 1.f, 1.f) * (wd * fd) + fm * p.metallic) * spec;
  return (diffuse + specular + metal_multiple_scattering(p, wo, wi)) * wi.z;
}

float bsdf_pdf(const BsdfParams& p, Vec3 wo, Vec3 wi) {
  if (wo.z <= 0.f || wi.z <= 0.f) return 0.f;
  const BsdfLobes l = bsdf_lobes(p, wo);
  const Vec3 h_raw = wo + wi;
  const float hl = length(h_raw);
  float pdf_spec = 0.f;
  if (hl > 0.f && l.spec > 0.f) {
    const Vec3 h = h_raw / hl;
    const float c = dot(wo, h);
    // Reflection about m: dwi = dm * 4 |wo.m| (Walter et al. 2007, eq. 14).
    if (c > 0.f) pdf_spec = ggx_vndf_pdf(wo, h, p.alpha) / (4.f * c);
  }
  const float pdf_diffuse = wi.z * kInvPi;
  return (1.f - l.glass) * (l.spec * pdf_spec + (1.f - l.spec) * pdf_diffuse);
}

Vec3 bsdf_eval_pdf(const BsdfParams& p, Vec3 wo, Vec3 wi, float* pdf) {
  return bsdf_eval_pdf(p, bsdf_lobes(p, wo), wo, wi, pdf);
}

Vec3 bsdf_eval_pdf(const BsdfParams& p, const BsdfLobes& l, Vec3 wo, Vec3 wi, float* pdf) {
  *pdf = 0.f;
  if (wo.z <= 0.f || wi.z <= 0.f) return {0.f, 0.f, 0.f};
  // The same quantities as bsdf_eval_cos and bsdf_pdf, rearranged to need two square roots
  // and two divisions (the functions above are the readable reference the tests hold this
  // one to):
  //   h = (wo + wi) / |wo + wi| with |wo + wi|^2 = 4 c^2, c = wo.h;
  //   D = alpha^2 / (pi t^2), t = h_z^2 (alpha^2 - 1) + 1 = (s_z^2 (alpha^2 - 1) + 4 c^2) / 4c^2
  //   with s = wo + wi;
  //   1 + Lambda(wo) + Lambda(wi) = (root_o / cos_o + root_i / cos_i) / 2, so
  //   D G2 / (4 cos_o cos_i) = D / (2 (root_o cos_i + root_i cos_o));
  //   the VNDF pdf of wi, G1(wo) D (wo.h) / cos_o / (4 wo.h) = D pdf_k.
  const Vec3 sum = wo + wi;
  const float c2 = 0.25f * dot(sum, sum);  // not (1 + wo.wi) / 2: no cancellation when wi ~ -wo
  if (!(c2 > 0.f)) return {0.f, 0.f, 0.f};
  const float c = std::sqrt(c2);
  const float fw = schlick_weight(c);
  const float fd = p.specular > 0.f ? l.f0d + (p.specular - l.f0d) * fw : 0.f;
  const float a2 = p.alpha * p.alpha;
  const float sz = sum.z;
  const float four_c2 = 4.f * c2;
  const float den = sz * sz * (a2 - 1.f) + four_c2;
  const float d = a2 * four_c2 * four_c2 / (kPi * den * den);
  const float ci2 = wi.z * wi.z;
  const float root_i = std::sqrt(ci2 + a2 * std::max(0.f, 1.f - ci2));
  const float spec = d / (2.f * (l.root_o * wi.z + root_i * wo.z));
  const float spec_weight_d = l.wd * fd;
  Vec3 diffuse = p.base * (l.wd * (1.f - fd) * kInvPi);
  if (p.metallic > 0.f) diffuse += l.ms * (1.f - energy_table().e(wi.z, p.alpha));
  const Vec3 fm = p.base + (Vec3(1.f, 1.f, 1.f) - p.base) * fw;
  const Vec3 specular = (Vec3(spec_weight_d, spec_weight_d, spec_weight_d) + fm * p.metallic) * spec;
  *pdf = (1.f - l.glass) * (l.spec * d * l.pdf_k + (1.f - l.spec) * wi.z * kInvPi);
  return (diffuse + specular) * wi.z;
}

bool bsdf_sample(const BsdfParams& p, Vec3 wo, Point2 u, float u_lobe, float u_fresnel,
                 BsdfSample* out) {
  return bsdf_sample(p, bsdf_lobes(p, wo), wo, u, u_lobe, u_fresnel, out);
}

bool bsdf_sample(const BsdfParams& p, const BsdfLobes& l, Vec3 wo, Point2 u, float u_lobe,
                 float u_fresnel, BsdfSample* out) {
  switch (bsdf_sample_direction(p, l, wo, bsdf_disks(u), u_lobe, u_fresnel, out)) {
    case BsdfSampleStep::Failed:
      return false;
    case BsdfSampleStep::Done:
      return true;
    case BsdfSampleStep::NeedsEval:
      break;
  }
  out->wi = normalize(out->wi);
  float pdf = 0.f;
  const Vec3 f = bsdf_eval_pdf(p, l, wo, out->wi, &pdf);
  return bsdf_sample_finish(f, pdf, out);
}

BsdfSampleStep bsdf_sample_direction(const BsdfParams& p, const BsdfLobes& l, Vec3 wo,
                                     const BsdfDisks& disks, float u_lobe, float u_fresnel,
                                     BsdfSample* out) {
  if (wo.z <= 0.f) return BsdfSampleStep::Failed;
  if (u_lobe < l.glass) {
    // Smooth dielectric: reflect with probability F, otherwise refract. eta is the ratio of
    // the indices across the interface in the direction of travel of wi.
    const float eta = p.front ? p.ior : 1.f / p.ior;
    const float F = fresnel_dielectric(wo.z, eta);
    out->delta = true;
    out->pdf = 0.f;
    if (u_fresnel < F) {
      out->wi = Vec3(-wo.x, -wo.y, wo.z);
      out->weight = Vec3(1.f, 1.f, 1.f);
      out->transmitted = false;
      return BsdfSampleStep::Done;
    }
    const float sin_t2 = (1.f - wo.z * wo.z) / (eta * eta);
    const float cos_t = std::sqrt(std::max(0.f, 1.f - sin_t2));
    out->wi = normalize(Vec3(-wo.x / eta, -wo.y / eta, -cos_t));
    // Radiance is scaled by 1/eta^2 across the interface (pbrt-v4, TransportMode::Radiance);
    // the transmitted light is tinted by the base color (glTF transmission).
    out->weight = p.base * (1.f / (eta * eta));
    out->transmitted = true;
    return BsdfSampleStep::Done;
  }
  // Non-delta lobes: reuse u_lobe, rescaled, to choose GGX or diffuse.
  const float u_rest = l.glass < 1.f ? (u_lobe - l.glass) / (1.f - l.glass) : 0.f;
  Vec3 wi;
  if (u_rest < l.spec) {
    const Vec3 m = sample_ggx_vndf_from_disk(wo, p.alpha, disks.polar);
    wi = m * (2.f * dot(wo, m)) - wo;
  } else {
    wi = disks.cosine;
  }
  if (wi.z <= 0.f) return BsdfSampleStep::Failed;
  out->wi = wi;
  return BsdfSampleStep::NeedsEval;
}

bool bsdf_sample_finish(Vec3 f, float pdf, BsdfSample* out) {
  if (!(pdf > 0.f)) return false;
  out->pdf = pdf;
  out->delta = false;
  out->transmitted = false;
  out->weight = f * (1.f / pdf);
  return true;
}

float BsdfEvalBatch::metal_ms_factor(float cos_i, float alpha) {
  return 1.f - energy_table().e(cos_i, alpha);
}

void BsdfEvalBatch::add_lights_world(uint32_t lanes, const float (*w)[kLanes]) {
  for (int i = 0; i < kLanes; i += 4) {
    const uint32_t bits = (lanes >> i) & 0xfu;
    if (!bits) continue;
    const I32x4 mask = lane_mask4(bits);
    const F32x4 wx = load4(&w[0][i]), wy = load4(&w[1][i]), wz = load4(&w[2][i]);
    // Frame::to_local: (dot(w, s), dot(w, t), dot(w, n)).
    for (int a = 0; a < 3; ++a) {
      const F32x4 local = dot4(wx, wy, wz, load4(&frame_[a][0][i]), load4(&frame_[a][1][i]),
                               load4(&frame_[a][2][i]));
      store4(&wi_[a][i], select4(mask, local, load4(&wi_[a][i])));
    }
  }
  for (uint32_t m = lanes; m; m &= m - 1) {
    const int lane = __builtin_ctz(m);
    ms_factor_[lane] = 0.f;
    if (metallic_[lane] > 0.f && wo_[2][lane] > 0.f && wi_[2][lane] > 0.f)
      ms_factor_[lane] = metal_ms_factor(wi_[2][lane], alpha_[lane]);
  }
  used_ |= lanes;
}

void BsdfEvalBatch::evaluate() {
  // The blocks of four slots with any queued, visited through a mask (which blocks are in
  // use changes from packet to packet: a branch per block would mispredict).
  uint32_t blocks = 0;
  for (int b = 0; b < kSlots / 4; ++b) blocks |= uint32_t(((used_ >> (4 * b)) & 0xfu) != 0) << b;
  for (; blocks; blocks &= blocks - 1) evaluate_block(4 * __builtin_ctz(blocks));
}

// bsdf_eval_pdf's arithmetic on four slots at a time, every operation in the scalar function's
// order (see there for the derivation); its early returns become a selection of zeros.
void BsdfEvalBatch::evaluate_block(int i) {
  const int v = i % kLanes;  // the slots' vertices
  const F32x4 zero = splat4(0.f), one = splat4(1.f);
  F32x4 wi_x = load4(&wi_[0][i]), wi_y = load4(&wi_[1][i]), wi_z = load4(&wi_[2][i]);
  if (i >= kLanes) {
    // Sampled directions: normalized here, and turned into world space (Frame::to_world,
    // then normalize) for the next ray.
    normalize4(wi_x, wi_y, wi_z);
    F32x4 w[3];
    for (int c = 0; c < 3; ++c)
      w[c] = load4(&frame_[0][c][v]) * wi_x + load4(&frame_[1][c][v]) * wi_y +
             load4(&frame_[2][c][v]) * wi_z;
    normalize4(w[0], w[1], w[2]);
    for (int c = 0; c < 3; ++c) store4(&world_[c][i - kLanes], w[c]);
  }
  const F32x4 wo_z = load4(&wo_[2][v]);
  const F32x4 sx = load4(&wo_[0][v]) + wi_x;
  const F32x4 sy = load4(&wo_[1][v]) + wi_y;
  const F32x4 sz = wo_z + wi_z;
  const F32x4 c2 = 0.25f * (sx * sx + sy * sy + sz * sz);
  const I32x4 valid = (wo_z > zero) & (wi_z > zero) & (c2 > zero);
  const F32x4 c = sqrt4(c2);
  const F32x4 m = min4(one, max4(zero, one - c));
  const F32x4 m2 = m * m;
  const F32x4 fw = m2 * m2 * m;
  const F32x4 specular = load4(&specular_[v]), f0d = load4(&f0d_[v]);
  const F32x4 fd = select4(specular > zero, f0d + (specular - f0d) * fw, zero);
  const F32x4 alpha = load4(&alpha_[v]);
  const F32x4 a2 = alpha * alpha;
  const F32x4 four_c2 = 4.f * c2;
  const F32x4 den = sz * sz * (a2 - 1.f) + four_c2;
  const F32x4 d = a2 * four_c2 * four_c2 / (kPi * den * den);
  const F32x4 ci2 = wi_z * wi_z;
  const F32x4 root_i = sqrt4(ci2 + a2 * max4(zero, one - ci2));
  const F32x4 spec = d / (2.f * (load4(&root_o_[v]) * wi_z + root_i * wo_z));
  const F32x4 wd = load4(&wd_[v]);
  const F32x4 spec_weight_d = wd * fd;
  const F32x4 kd = wd * (1.f - fd) * kInvPi;
  const F32x4 metallic = load4(&metallic_[v]);
  const F32x4 ms_factor = load4(&ms_factor_[i]);
  for (int ch = 0; ch < 3; ++ch) {
    const F32x4 base = load4(&base_[ch][v]);
    // ms is 0 for non-metals, where bsdf_eval_pdf adds nothing: x + 0 = x.
    const F32x4 diffuse = base * kd + load4(&ms_[ch][v]) * ms_factor;
    const F32x4 fm = base + (1.f - base) * fw;
    const F32x4 specular_ch = (spec_weight_d + fm * metallic) * spec;
    store4(&f_[ch][i], select4(valid, (diffuse + specular_ch) * wi_z, zero));
  }
  const F32x4 lobe = load4(&spec_[v]);
  const F32x4 pdf = (1.f - load4(&glass_[v])) *
                    (lobe * d * load4(&pdf_k_[v]) + (1.f - lobe) * wi_z * kInvPi);
  store4(&pdf_[i], select4(valid, pdf, zero));
}

}  // namespace rf
