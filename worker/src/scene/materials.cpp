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

// ---- KHR_materials_sheen: the Charlie lobe (Conty Estevez and Kulla 2017, as the extension
// text writes it) and its directional albedo.

// The extension's fit of the Charlie lambda: L(x) = a / (1 + b x^c) + d x + e, its
// coefficients interpolated between those for alpha 0 and 1 by (1 - alpha)^2.
float charlie_l(float x, float alpha) {
  const float t = (1.f - alpha) * (1.f - alpha);
  const float a = 21.5473f + (25.3245f - 21.5473f) * t;
  const float b = 3.82987f + (3.32435f - 3.82987f) * t;
  const float c = 0.19823f + (0.16801f - 0.19823f) * t;
  const float d = -1.97760f + (-1.27393f + 1.97760f) * t;
  const float e = -4.32054f + (-4.85967f + 4.32054f) * t;
  return a / (1.f + b * std::pow(x, c)) + d * x + e;
}

float charlie_lambda(float cos_theta, float alpha) {
  const float c = std::abs(cos_theta);
  return c < 0.5f ? std::exp(charlie_l(c, alpha))
                  : std::exp(2.f * charlie_l(0.5f, alpha) - charlie_l(1.f - c, alpha));
}

// f_sheen cos_i for sheenColor 1: D V cos_i = D / ((1 + L(cos_o) + L(cos_i)) 4 cos_o), with
// cos_h = h.z for h = (wo + wi) / |wo + wi|.
float sheen_lobe_cos(Vec3 wo, Vec3 wi, float alpha) {
  const Vec3 s = wo + wi;
  const float sl = length(s);
  if (!(sl > 0.f)) return 0.f;
  const float d = sheen_charlie_d(s.z / sl, alpha);
  return d / ((1.f + charlie_lambda(wo.z, alpha) + charlie_lambda(wi.z, alpha)) * 4.f * wo.z);
}

// E(mu, alpha): the integral over wi of sheen_lobe_cos, by the midpoint rule over
// (t, phi) with cos_i = t^2 (denser towards the horizon, where the lobe's grazing peak is) and
// phi in [0, pi] (the lobe is symmetric about the plane of wo), on a grid of mu = s^2 (s at
// cell centres: dense at grazing angles, where E changes fastest) and sheen roughness
// sqrt(alpha) (kRough points from sqrt(kMinSheenAlpha) to 1). E is not clamped: the spec's
// lobe (its fitted visibility) reflects more than it receives at grazing angles for sheen
// roughness below about 0.3 (E(0.05) = 1.03 at roughness 0.1), which add_layers corrects.
class SheenTable {
 public:
  static constexpr int kMu = 32, kRough = 32;
  SheenTable() {
    const int nt = 96, nphi = 48;
    for (int ir = 0; ir < kRough; ++ir) {
      const float alpha = alpha_at(ir);
      for (int im = 0; im < kMu; ++im) {
        const float s = (float(im) + 0.5f) / kMu, mu = s * s;
        const Vec3 wo(std::sqrt(std::max(0.f, 1.f - mu * mu)), 0.f, mu);
        double sum = 0.0;
        for (int i = 0; i < nt; ++i) {
          const double t = (i + 0.5) / nt, ci = t * t;
          const double si = std::sqrt(std::max(0.0, 1.0 - ci * ci));
          double ring = 0.0;
          for (int j = 0; j < nphi; ++j) {
            const double phi = (j + 0.5) * kPi / nphi;
            const Vec3 wi(float(si * std::cos(phi)), float(si * std::sin(phi)), float(ci));
            ring += double(sheen_lobe_cos(wo, wi, alpha));
          }
          // d omega = d cos_i d phi = 2 t dt d phi; both halves of phi.
          sum += ring * 2.0 * t * (1.0 / nt) * (kPi / nphi) * 2.0;
        }
        e_[ir][im] = float(sum);
      }
    }
  }
  float e(float mu, float alpha) const {
    const float fr =
        std::min(float(kRough - 1),
                 std::max(0.f, (std::sqrt(alpha) - kMinRough) / (1.f - kMinRough) * (kRough - 1)));
    const float fm = std::min(float(kMu - 1), std::max(0.f, std::sqrt(std::max(0.f, mu)) * kMu - 0.5f));
    const int r0 = std::min(kRough - 2, int(fr)), m0 = std::min(kMu - 2, int(fm));
    const float tr = fr - float(r0), tm = fm - float(m0);
    const float lo = e_[r0][m0] * (1.f - tm) + e_[r0][m0 + 1] * tm;
    const float hi = e_[r0 + 1][m0] * (1.f - tm) + e_[r0 + 1][m0 + 1] * tm;
    return lo * (1.f - tr) + hi * tr;
  }

 private:
  static constexpr float kMinRough = 0.07f;  // sqrt(kMinSheenAlpha)
  static float alpha_at(int i) {
    const float r = kMinRough + (1.f - kMinRough) * float(i) / float(kRough - 1);
    return std::max(kMinSheenAlpha, r * r);
  }
  float e_[kRough][kMu];
};

const SheenTable& sheen_table() {
  static const SheenTable table;
  return table;
}

inline float max3(Vec3 v) { return std::max(v.x, std::max(v.y, v.z)); }

// ---- KHR_materials_clearcoat: the coat's directions in a frame around its normal (the
// shading frame itself when the coat has no normal map of its own).
struct CoatFrame {
  bool tilted;
  Frame frame;
  explicit CoatFrame(Vec3 n) : tilted(n.x != 0.f || n.y != 0.f), frame(n) {}
  Vec3 to_local(Vec3 v) const { return tilted ? frame.to_local(v) : v; }
  Vec3 to_world(Vec3 v) const { return tilted ? frame.to_world(v) : v; }
};

inline float schlick_weight(float c) {
  const float m = std::min(1.f, std::max(0.f, 1.f - c));
  const float m2 = m * m;
  return m2 * m2 * m;
}

// KHR_materials_specular: dielectric_f0 = min(((ior - 1)/(ior + 1))^2 specularColor, 1)
// specular, per channel (specular = specularFactor x specularTexture.a, specularColor =
// specularColorFactor x specularColorTexture.rgb).
inline Vec3 dielectric_f0(const BsdfParams& p) {
  const float r = (p.ior - 1.f) / (p.ior + 1.f);
  const float r2 = r * r;
  // Channel by channel, written out (a loop over Vec3's operator[] goes through memory).
  return {std::min(1.f, r2 * p.specular_color.x) * p.specular,
          std::min(1.f, r2 * p.specular_color.y) * p.specular,
          std::min(1.f, r2 * p.specular_color.z) * p.specular};
}

// The dielectric Fresnel of the extension's fresnel_mix, weight x (f0 + (1 - f0) fw) per
// channel, as f0d + (specular - f0d) fw with f0d = weight x f0 (dielectric_f0); 0 without a
// specular layer.
inline Vec3 dielectric_fresnel(const BsdfParams& p, const Vec3& f0d, float fw) {
  if (!(p.specular > 0.f)) return {0.f, 0.f, 0.f};
  return {f0d.x + (p.specular - f0d.x) * fw, f0d.y + (p.specular - f0d.y) * fw,
          f0d.z + (p.specular - f0d.z) * fw};
}


// Kulla & Conty's colored F_ms = F_avg^2 E_avg / (1 - F_avg (1 - E_avg)), with
// F_avg = f0 + (1 - f0) / 21 for Schlick and f0 = base.
Vec3 metal_ms_fresnel(const BsdfParams& p, float e_avg) {
  const auto channel = [e_avg](float base) {
    const float f_avg = base + (1.f - base) / 21.f;
    return f_avg * f_avg * e_avg / (1.f - f_avg * (1.f - e_avg));
  };
  return {channel(p.base.x), channel(p.base.y), channel(p.base.z)};
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

const Material::TextureSlot (&Material::texture_slots())[Material::kTextureSlots] {
  static const TextureSlot slots[kTextureSlots] = {
      {&Material::base_color_tex, "baseColorTexture", true, true},
      {&Material::metallic_roughness_tex, "metallicRoughnessTexture", false, true},
      {&Material::normal_tex, "normalTexture", false, true},
      {&Material::emissive_tex, "emissiveTexture", true, false},
      {&Material::transmission_tex, "transmissionTexture", false, true},
      {&Material::diffuse_transmission_tex, "diffuseTransmissionTexture", false, true},
      {&Material::diffuse_transmission_color_tex, "diffuseTransmissionColorTexture", true, true},
      {&Material::specular_tex, "specularTexture", false, true},
      {&Material::specular_color_tex, "specularColorTexture", true, true},
      {&Material::anisotropy_tex, "anisotropyTexture", false, true},
      {&Material::iridescence_tex, "iridescenceTexture", false, true},
      {&Material::iridescence_thickness_tex, "iridescenceThicknessTexture", false, true},
      {&Material::clearcoat_tex, "clearcoatTexture", false, true},
      {&Material::clearcoat_roughness_tex, "clearcoatRoughnessTexture", false, true},
      {&Material::clearcoat_normal_tex, "clearcoatNormalTexture", false, true},
      {&Material::sheen_color_tex, "sheenColorTexture", true, true},
      {&Material::sheen_roughness_tex, "sheenRoughnessTexture", false, true},
  };
  return slots;
}

float clearcoat_fresnel(float cos_v) {
  const float m = std::min(1.f, std::max(0.f, 1.f - std::abs(cos_v)));
  const float m2 = m * m;
  return 0.04f + 0.96f * (m2 * m2 * m);
}

float sheen_charlie_d(float cos_h, float alpha) {
  const float inv_r = 1.f / alpha;
  const float sin2h = std::max(0.f, 1.f - cos_h * cos_h);
  return (2.f + inv_r) * std::pow(sin2h, inv_r * 0.5f) / (2.f * kPi);
}

float sheen_charlie_visibility(float cos_o, float cos_i, float alpha) {
  return 1.f / ((1.f + charlie_lambda(cos_o, alpha) + charlie_lambda(cos_i, alpha)) *
                (4.f * cos_o * cos_i));
}

float sheen_albedo(float mu, float alpha) { return sheen_table().e(mu, alpha); }

namespace {

// The layers on a base value (f_base = the base's f cos at (wo, wi), pdf_base = the density
// of the base's own sampling): the layered f cos, and *pdf the mixture density (the formulas
// in materials.h).
// The layered functions are out of line: most materials have no layers, and the common path
// stays as small as it was.
__attribute__((noinline)) Vec3 add_layers(const BsdfParams& p, const BsdfLobes& l, Vec3 wo,
                                          Vec3 wi, Vec3 f_base, float pdf_base, float* pdf) {
  float density = l.base_pick * pdf_base;
  Vec3 f = f_base;
  if (!is_zero(p.sheen)) {
    // The spec's albedo scaling, with E clamped to 1; the lobe divided by max(1, E(mu_o),
    // E(mu_i)) (1 wherever the spec's lobe conserves energy), which keeps it reciprocal and its
    // albedo at most min(1, E(mu_o)).
    const float e_i = sheen_albedo(wi.z, p.sheen_alpha);
    const float s = max3(p.sheen);
    const float lobe = sheen_lobe_cos(wo, wi, p.sheen_alpha) / std::max(l.sheen_norm, e_i);
    f = f * std::min(1.f - l.sheen_e, 1.f - s * std::min(1.f, e_i)) + p.sheen * lobe;
    density += l.sheen * wi.z * kInvPi;
  }
  if (p.clearcoat > 0.f) {
    f = f * (1.f - l.coat_f);
    const CoatFrame cf(p.clearcoat_n);
    const Vec3 wo_c = cf.to_local(wo), wi_c = cf.to_local(wi);
    const Vec3 h_raw = wo_c + wi_c;
    const float hl = length(h_raw);
    if (wo_c.z > 0.f && wi_c.z > 0.f && hl > 0.f) {
      const Vec3 h = h_raw / hl;
      const float a = p.clearcoat_alpha;
      // D G2 / (4 cos_o cos_i) times cos_i, on the coat normal.
      const float spec = ggx_d(h, a) * ggx_g2(wo_c, wi_c, a) / (4.f * wo_c.z);
      f += Vec3(1.f, 1.f, 1.f) * (l.coat_f * spec);
      const float c = dot(wo_c, h);
      if (c > 0.f) density += l.coat * ggx_vndf_pdf(wo_c, h, a) / (4.f * c);
    }
  }
  *pdf = density;
  return f;
}

// bsdf_lobes' layered part: the lobe probabilities from estimates of each lobe's albedo at wo
// (the coat: c F_c; the sheen: S luminance(sheenColor) E(wo.z); the base: S (1 - sheen_e)
// times the base's estimate, base_albedo), S = 1 - c F_c.
__attribute__((noinline)) void layer_lobes(const BsdfParams& p, Vec3 wo, float base_albedo,
                                           BsdfLobes* l) {
  l->layered = true;
  float a_coat = 0.f, above = 1.f;
  if (p.clearcoat > 0.f) {
    const float cos_c = CoatFrame(p.clearcoat_n).to_local(wo).z;
    l->coat_f = p.clearcoat * clearcoat_fresnel(cos_c);
    a_coat = l->coat_f;
    above = 1.f - l->coat_f;
  }
  float a_sheen = 0.f;
  if (!is_zero(p.sheen)) {
    const float e_raw = sheen_albedo(wo.z, p.sheen_alpha);
    l->sheen_norm = std::max(1.f, e_raw);
    const float e_o = std::min(1.f, e_raw);
    l->sheen_e = max3(p.sheen) * e_o;
    a_sheen = above * std::max(luminance(p.sheen), 1e-3f) * e_o;
  }
  const float a_base = above * (1.f - l->sheen_e) * base_albedo;
  const float total = a_coat + a_sheen + a_base;
  if (total > 0.f) {
    l->coat = a_coat / total;
    l->sheen = a_sheen / total;
  }
  l->base_pick = std::max(0.f, 1.f - l->coat - l->sheen);
}

}  // namespace

// A function of wo only, so that bsdf_pdf can recompute them.
BsdfLobes bsdf_lobes(const BsdfParams& p, Vec3 wo) {
  BsdfLobes l;
  l.glass = (1.f - p.metallic) * p.transmission;
  l.wd = (1.f - p.metallic) * (1.f - p.transmission);
  const float fw = schlick_weight(wo.z);
  l.f0d = dielectric_f0(p);
  const float fd = max3(dielectric_fresnel(p, l.f0d, fw));
  const float lum = luminance(p.base);
  const float fm = lum + (1.f - lum) * fw;
  const float ws = l.wd * fd + p.metallic * fm;
  // The cosine lobe also samples the metal's multiple-scattering term.
  float ms = 0.f;
  if (p.metallic > 0.f) {
    const EnergyTable& t = energy_table();
    // An anisotropic lobe's compensation at the isotropic alpha of the same area.
    const float ms_alpha = p.anisotropic() ? std::sqrt(p.alpha_t * p.alpha) : p.alpha;
    const float e_o = t.e(wo.z, ms_alpha);
    ms = p.metallic * (1.f - e_o);
    const float e_avg = t.e_avg(ms_alpha);
    l.ms = metal_ms_fresnel(p, e_avg) * (ms / (kPi * (1.f - e_avg)));
  }
  // KHR_materials_diffuse_transmission: the diffuse base's share d goes to the BTDF, a
  // sampled-only lobe after the glass lobe.
  const float dt = has_diffuse_btdf(p) ? p.diffuse_transmission : 0.f;
  const float wdiff = l.wd * (1.f - fd) * (1.f - dt) * std::max(lum, 1e-3f) + ms;
  const float a_dt =
      l.wd * (1.f - fd) * dt * std::max(luminance(p.diffuse_transmission_color), 1e-3f);
  const float glass_w = l.glass;
  if (a_dt > 0.f) {
    l.diffuse_bt = (1.f - l.glass) * (a_dt / (ws + wdiff + a_dt));
    l.glass += l.diffuse_bt;
  }
  l.spec = ws + wdiff > 0.f ? ws / (ws + wdiff) : 1.f;
  const float c2 = wo.z * wo.z;
  l.root_o = std::sqrt(c2 + p.alpha * p.alpha * std::max(0.f, 1.f - c2));
  l.pdf_k = wo.z > 0.f ? 1.f / (2.f * (wo.z + l.root_o)) : 0.f;
  l.general = p.anisotropic() || p.iridescence > 0.f || dt > 0.f;
  if (p.layered()) layer_lobes(p, wo, glass_w + ws + wdiff + a_dt, &l);
  return l;
}

float metal_single_scattering_albedo(float mu, float alpha) {
  return energy_table().e(mu, alpha);
}

Vec3 iridescence_fresnel(float outside_ior, float film_ior, float cos1, float thickness_nm,
                         Vec3 base_f0) {
  // In double: the phase terms multiply ~1e6 by ~1e-6.
  const double pi = 3.14159265358979323846;
  const double outside = outside_ior, d = thickness_nm;
  // A film that thins to nothing becomes the outside medium (Khronos' sample viewer blends its
  // index so over the first 0.03 nm; the notes do not say).
  const double ts = std::min(1.0, std::max(0.0, d / 0.03));
  const double film = outside + (double(film_ior) - outside) * ts * ts * (3.0 - 2.0 * ts);
  const double c1 = std::min(1.0, std::max(0.0, double(cos1)));
  const double sin2_sq = (outside / film) * (outside / film) * (1.0 - c1 * c1);
  if (sin2_sq >= 1.0) return {1.f, 1.f, 1.f};  // total internal reflection in the film
  const double c2 = std::sqrt(1.0 - sin2_sq);
  auto schlick = [](double f0, double c) {
    const double m = 1.0 - c, m2 = m * m;
    return f0 + (1.0 - f0) * m2 * m2 * m;
  };
  auto ior_to_f0 = [](double transmitted, double incident) {
    const double r = (transmitted - incident) / (transmitted + incident);
    return r * r;
  };
  // First interface (outside / film).
  const double r12 = schlick(ior_to_f0(film, outside), c1);
  const double t121 = 1.0 - r12;
  const double phi12 = film < outside ? pi : 0.0;
  const double phi21 = pi - phi12;
  // The optical path difference in the film, 2 n d cos(theta2) (the paper's; the notes write
  // cos(theta1), docs/scenes.md).
  const double opd = 2.0 * film * d * c2;
  // evalSensitivity's Gaussian fits of the CIE XYZ functions in Fourier space, to Rec. 709.
  auto sensitivity = [&](double m_opd, const double shift[3], double out[3]) {
    const double phase = 2.0 * pi * m_opd * 1.0e-9;
    const double val[3] = {5.4856e-13, 4.4201e-13, 5.2481e-13};
    const double pos[3] = {1.6810e+06, 1.7953e+06, 2.2084e+06};
    const double var[3] = {4.3278e+09, 9.3046e+09, 6.6121e+09};
    double xyz[3];
    for (int k = 0; k < 3; ++k)
      xyz[k] = val[k] * std::sqrt(2.0 * pi * var[k]) * std::cos(pos[k] * phase + shift[k]) *
               std::exp(-phase * phase * var[k]);
    xyz[0] += 9.7470e-14 * std::sqrt(2.0 * pi * 4.5282e+09) *
              std::cos(2.2399e+06 * phase + shift[0]) * std::exp(-4.5282e+09 * phase * phase);
    for (double& v : xyz) v /= 1.0685e-7;
    out[0] = 3.2404542 * xyz[0] - 1.5371385 * xyz[1] - 0.4985314 * xyz[2];
    out[1] = -0.9692660 * xyz[0] + 1.8760108 * xyz[1] + 0.0415560 * xyz[2];
    out[2] = 0.0556434 * xyz[0] - 0.2040259 * xyz[1] + 1.0572252 * xyz[2];
  };
  double r23[3], phi[3];
  for (int k = 0; k < 3; ++k) {
    // Second interface (film / base), the base's index from its F0 (guarded against 1).
    const double f0 = std::min(0.9999, std::max(0.0, double(base_f0[k])));
    const double s = std::sqrt(f0);
    const double base_ior = (1.0 + s) / (1.0 - s);
    r23[k] = schlick(ior_to_f0(base_ior, film), c2);
    phi[k] = phi21 + (base_ior < film ? pi : 0.0);
  }
  Vec3 out;
  double cm[3], r123[3], intensity[3];
  for (int k = 0; k < 3; ++k) {
    const double r = std::min(0.9999, std::max(1e-5, r12 * r23[k]));
    r123[k] = std::sqrt(r);
    const double rs = t121 * t121 * r23[k] / (1.0 - r);
    intensity[k] = r12 + rs;  // m = 0
    cm[k] = rs - t121;
  }
  for (int m = 1; m <= 2; ++m) {
    const double shift[3] = {m * phi[0], m * phi[1], m * phi[2]};
    double sm[3];
    sensitivity(m * opd, shift, sm);
    for (int k = 0; k < 3; ++k) {
      cm[k] *= r123[k];
      intensity[k] += cm[k] * 2.0 * sm[k];
    }
  }
  for (int k = 0; k < 3; ++k) out[k] = float(std::max(0.0, intensity[k]));
  return out;
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

namespace {

// The dielectric layer's Fresnel at c = wo.h (weighted by specularFactor): Schlick's with
// KHR_materials_specular's F0, and KHR_materials_iridescence's film mixed in,
// F = mix(F_schlick, F_iridescence, iridescence), the film over the dielectric's F0 (before
// specularFactor weighs it).
Vec3 dielectric_layer_fresnel(const BsdfParams& p, const BsdfLobes& l, float c) {
  Vec3 fd = dielectric_fresnel(p, l.f0d, schlick_weight(c));
  if (p.iridescence > 0.f && p.specular > 0.f) {
    const float k = p.iridescence;
    const Vec3 f0 = l.f0d * (1.f / p.specular);
    const Vec3 fi = iridescence_fresnel(1.f, p.iridescence_ior, c, p.iridescence_thickness, f0);
    fd = (fd * (1.f / p.specular) * (1.f - k) + fi * k) * p.specular;
  }
  return fd;
}

// The diffuse BTDF's f |cos_i| for wi below the surface, without the layers over it:
// (1 - m)(1 - t) d C (1 - max3(F_d)) |cos_i| / pi, F_d at the half vector of wo and the
// mirror image of wi above the surface (materials.h).
Vec3 diffuse_btdf_cos(const BsdfParams& p, const BsdfLobes& l, Vec3 wo, Vec3 wi) {
  const Vec3 h_raw = wo + Vec3(wi.x, wi.y, -wi.z);
  const float hl = length(h_raw);
  if (!(hl > 0.f) || !(wi.z < 0.f)) return {0.f, 0.f, 0.f};
  const float c = std::max(0.f, dot(wo, h_raw / hl));
  const float fd = max3(dielectric_layer_fresnel(p, l, c));
  return p.diffuse_transmission_color *
         (l.wd * p.diffuse_transmission * (1.f - fd) * (-wi.z) * kInvPi);
}

// The base's f cos and pdf with an anisotropic GGX lobe (KHR_materials_anisotropy), a thin
// film (KHR_materials_iridescence) or a diffuse BTDF (KHR_materials_diffuse_transmission):
// the formulas of bsdf_eval_cos and bsdf_pdf with D and Lambda of the anisotropic distribution
// (alpha_t along x, alpha along y), the spec's BRDF_specularAnisotropicGGX: V = G2 / (4 cos_o
// cos_i) is its V_GGX_anisotropic, with the film's Fresnel mixed in, and the Lambert BRDF
// weighted by 1 - diffuseTransmission. The metal's multiple-scattering term keeps its
// isotropic table at alpha sqrt(alpha_t alpha) (the compensation only).
// The terms of the base at (wo, wi) that general_base and bsdf_eval_lobes (its parts by lobe
// category) share: false where the base is 0 (wo or wi below the surface, or no half vector).
struct BaseTerms {
  float c = 0.f;         // wo . h
  float d = 0.f;         // D(h)
  float lo = 0.f;        // Lambda(wo)
  float spec = 0.f;      // D G2 / (4 cos_o cos_i)
  float ms_alpha = 0.f;  // the isotropic alpha of the metal's compensation
  Vec3 fd, fm;           // the dielectric layer's and the metal's Fresnel
};
inline bool base_terms(const BsdfParams& p, const BsdfLobes& l, Vec3 wo, Vec3 wi,
                       BaseTerms* t) {
  if (wo.z <= 0.f || wi.z <= 0.f) return false;
  const Vec3 h_raw = wo + wi;
  const float hl = length(h_raw);
  if (!(hl > 0.f)) return false;
  const Vec3 h = h_raw / hl;
  t->c = std::max(0.f, dot(wo, h));
  const float fw = schlick_weight(t->c);
  const float ax = p.anisotropic() ? p.alpha_t : p.alpha, ay = p.alpha;
  t->fd = dielectric_layer_fresnel(p, l, t->c);
  t->fm = p.base + (Vec3(1.f, 1.f, 1.f) - p.base) * fw;
  if (p.iridescence > 0.f && p.metallic > 0.f) {
    // KHR_materials_iridescence over the metal's base colour.
    const float k = p.iridescence;
    t->fm = t->fm * (1.f - k) +
            iridescence_fresnel(1.f, p.iridescence_ior, t->c, p.iridescence_thickness, p.base) *
                k;
  }
  t->d = ggx_d_aniso(h, ax, ay);
  t->lo = ggx_lambda_aniso(wo, ax, ay);
  const float li = ggx_lambda_aniso(wi, ax, ay);
  t->spec = t->d / ((1.f + t->lo + li) * 4.f * wo.z * wi.z);
  t->ms_alpha = p.anisotropic() ? std::sqrt(ax * ay) : ay;
  return true;
}

__attribute__((noinline)) Vec3 general_base(const BsdfParams& p, const BsdfLobes& l, Vec3 wo,
                                            Vec3 wi, float* pdf) {
  *pdf = 0.f;
  BaseTerms t;
  if (!base_terms(p, l, wo, wi, &t)) return {0.f, 0.f, 0.f};
  const Vec3 fd = t.fd, fm = t.fm;
  const float c = t.c, d = t.d, lo = t.lo, spec = t.spec;
  const float dt = has_diffuse_btdf(p) ? p.diffuse_transmission : 0.f;
  Vec3 diffuse = p.base * (l.wd * (1.f - dt) * (1.f - max3(fd)) * kInvPi);
  if (p.metallic > 0.f) diffuse += l.ms * (1.f - energy_table().e(wi.z, t.ms_alpha));
  Vec3 specular;
  for (int ch = 0; ch < 3; ++ch) specular[ch] = (l.wd * fd[ch] + fm[ch] * p.metallic) * spec;
  // The GGX sample's density: visible normals, G1(wo) (wo.h) D / cos_o, over 4 (wo.h).
  const float pdf_spec = c > 0.f ? d / ((1.f + lo) * 4.f * wo.z) : 0.f;
  *pdf = (1.f - l.glass) * (l.spec * pdf_spec + (1.f - l.spec) * wi.z * kInvPi);
  return (diffuse + specular) * wi.z;
}

}  // namespace

Vec3 bsdf_eval_cos(const BsdfParams& p, Vec3 wo, Vec3 wi) {
  if (p.anisotropic() || p.iridescence > 0.f || has_diffuse_btdf(p)) {
    float pdf = 0.f;
    return bsdf_eval_pdf(p, bsdf_lobes(p, wo), wo, wi, &pdf);
  }
  if (wo.z <= 0.f || wi.z <= 0.f) return {0.f, 0.f, 0.f};
  const float wd = (1.f - p.metallic) * (1.f - p.transmission);
  const Vec3 h_raw = wo + wi;
  const float hl = length(h_raw);
  if (!(hl > 0.f)) return {0.f, 0.f, 0.f};
  const Vec3 h = h_raw / hl;
  const float c = std::max(0.f, dot(wo, h));
  const float fw = schlick_weight(c);
  // KHR_materials_specular's fresnel_mix: the specular layer weighted by the coloured
  // Fresnel F, the diffuse base by 1 - max(F).
  const Vec3 fd = dielectric_fresnel(p, dielectric_f0(p), fw);
  const Vec3 fm = p.base + (Vec3(1.f, 1.f, 1.f) - p.base) * fw;
  const float spec = ggx_d(h, p.alpha) * ggx_g2(wo, wi, p.alpha) / (4.f * wo.z * wi.z);
  const Vec3 diffuse = p.base * (wd * (1.f - max3(fd)) * kInvPi);
  const Vec3 specular = (fd * wd + fm * p.metallic) * spec;
  const Vec3 f = (diffuse + specular + metal_multiple_scattering(p, wo, wi)) * wi.z;
  if (!p.layered()) return f;
  float pdf = 0.f;
  return add_layers(p, bsdf_lobes(p, wo), wo, wi, f, 0.f, &pdf);
}

float bsdf_pdf(const BsdfParams& p, Vec3 wo, Vec3 wi) {
  if (wo.z <= 0.f || wi.z <= 0.f) return 0.f;
  const BsdfLobes l = bsdf_lobes(p, wo);
  if (l.general) {
    float pdf = 0.f;
    bsdf_eval_pdf(p, l, wo, wi, &pdf);
    return pdf;
  }
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
  const float pdf_base = (1.f - l.glass) * (l.spec * pdf_spec + (1.f - l.spec) * pdf_diffuse);
  if (!l.layered) return pdf_base;
  float pdf = 0.f;
  add_layers(p, l, wo, wi, Vec3(0.f, 0.f, 0.f), pdf_base, &pdf);
  return pdf;
}

Vec3 bsdf_eval_pdf(const BsdfParams& p, Vec3 wo, Vec3 wi, float* pdf) {
  return bsdf_eval_pdf(p, bsdf_lobes(p, wo), wo, wi, pdf);
}

Vec3 bsdf_eval_pdf(const BsdfParams& p, const BsdfLobes& l, Vec3 wo, Vec3 wi, float* pdf) {
  *pdf = 0.f;
  if (wo.z <= 0.f || wi.z <= 0.f) return {0.f, 0.f, 0.f};
  if (l.general) {
    const Vec3 f = general_base(p, l, wo, wi, pdf);
    if (!l.layered) return f;
    return add_layers(p, l, wo, wi, f, *pdf, pdf);
  }
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
  const Vec3 fd = dielectric_fresnel(p, l.f0d, fw);
  const float a2 = p.alpha * p.alpha;
  const float sz = sum.z;
  const float four_c2 = 4.f * c2;
  const float den = sz * sz * (a2 - 1.f) + four_c2;
  const float d = a2 * four_c2 * four_c2 / (kPi * den * den);
  const float ci2 = wi.z * wi.z;
  const float root_i = std::sqrt(ci2 + a2 * std::max(0.f, 1.f - ci2));
  const float spec = d / (2.f * (l.root_o * wi.z + root_i * wo.z));
  const float fdm = std::max(fd.x, std::max(fd.y, fd.z));
  Vec3 diffuse = p.base * (l.wd * (1.f - fdm) * kInvPi);
  if (p.metallic > 0.f) diffuse += l.ms * (1.f - energy_table().e(wi.z, p.alpha));
  const Vec3 fm = p.base + (Vec3(1.f, 1.f, 1.f) - p.base) * fw;
  Vec3 specular;
  for (int ch = 0; ch < 3; ++ch) specular[ch] = (l.wd * fd[ch] + fm[ch] * p.metallic) * spec;
  *pdf = (1.f - l.glass) * (l.spec * d * l.pdf_k + (1.f - l.spec) * wi.z * kInvPi);
  if (!l.layered) return (diffuse + specular) * wi.z;
  return add_layers(p, l, wo, wi, (diffuse + specular) * wi.z, *pdf, pdf);
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

namespace {

// bsdf_sample_direction's layers: the coat (its VNDF on its own normal) with probability
// l.coat, the sheen (cosine-weighted) with l.sheen, and false with *step the result
// (NeedsEval with out->wi set, or Failed); otherwise true, the base: *u_lobe rescaled to the
// base's share and *glass_scale the glass lobe's weight under the layers over the base's
// probability.
__attribute__((noinline)) bool sample_layers(const BsdfParams& p, const BsdfLobes& l, Vec3 wo,
                                             const BsdfDisks& disks, float* u_lobe,
                                             float* glass_scale, BsdfSampleStep* step,
                                             BsdfSample* out) {
  *step = BsdfSampleStep::Failed;
  if (*u_lobe < l.coat) {
    const CoatFrame cf(p.clearcoat_n);
    const Vec3 wo_c = cf.to_local(wo);
    if (wo_c.z <= 0.f) return false;
    const Vec3 m = sample_ggx_vndf_from_disk(wo_c, p.clearcoat_alpha, disks.polar);
    const Vec3 wi_c = m * (2.f * dot(wo_c, m)) - wo_c;
    if (wi_c.z <= 0.f) return false;
    const Vec3 wi = cf.to_world(wi_c);
    if (wi.z <= 0.f) return false;
    out->wi = wi;
    *step = BsdfSampleStep::NeedsEval;
    return false;
  }
  if (*u_lobe < l.coat + l.sheen) {
    if (disks.cosine.z <= 0.f) return false;
    out->wi = disks.cosine;
    *step = BsdfSampleStep::NeedsEval;
    return false;
  }
  if (!(l.base_pick > 0.f)) return false;
  *u_lobe = std::min(0.99999994f, (*u_lobe - l.coat - l.sheen) / l.base_pick);
  *glass_scale = (1.f - l.coat_f) * (1.f - l.sheen_e) / l.base_pick;
  return true;
}

}  // namespace

namespace {

// The rough glass lobe (KHR_materials_transmission with roughness): a visible normal m of
// GGX(alpha) (Heitz 2018), then reflection about m with probability F(wo.m), the exact
// dielectric Fresnel, else refraction through m (Walter et al. 2007). With these choices the
// weight f |cos_i| / pdf of the reflection f = F D G2 / (4 |cos_o cos_i|) and of the
// transmission f = (1 - F) D G2 |wi.m| |wo.m| / (|cos_o cos_i| (wo.m + eta wi.m)^2) (Walter's
// BTDF with radiance scaled by 1/eta^2) is G2(wo, wi) / G1(wo): the lobe is sampled, never
// evaluated, like the smooth glass it becomes at alpha -> 0 (materials.h).
BsdfSampleStep sample_rough_glass(const BsdfParams& p, Vec3 wo, const BsdfDisks& disks,
                                  float u_fresnel, float eta, float scale, BsdfSample* out) {
  const Vec3 m = sample_ggx_vndf_from_disk(wo, p.alpha, disks.polar);
  const float c = dot(wo, m);
  if (!(c > 0.f)) return BsdfSampleStep::Failed;
  const float F = fresnel_dielectric(c, eta);
  Vec3 wi;
  if (u_fresnel < F) {
    wi = m * (2.f * c) - wo;
    if (wi.z <= 0.f) return BsdfSampleStep::Failed;  // reflected below the surface
    out->transmitted = false;
  } else {
    // Snell through m (F < 1 here, so no total internal reflection): wi = -wo / eta +
    // (c / eta - cos_t) m.
    const float cos_t = std::sqrt(std::max(0.f, 1.f - (1.f - c * c) / (eta * eta)));
    wi = normalize(m * (c / eta - cos_t) - wo / eta);
    if (wi.z >= 0.f) return BsdfSampleStep::Failed;  // refracted above the surface
    out->transmitted = true;
  }
  const float g = ggx_g2(wo, wi, p.alpha) / ggx_g1(wo, p.alpha);
  out->wi = wi;
  out->delta = true;
  out->pdf = 0.f;
  if (out->transmitted) out->eta2 = eta * eta;
  out->weight = out->transmitted ? p.base * (scale * g / (eta * eta))
                                 : Vec3(1.f, 1.f, 1.f) * (scale * g);
  return BsdfSampleStep::Done;
}

}  // namespace

BsdfSampleStep bsdf_sample_direction(const BsdfParams& p, const BsdfLobes& l, Vec3 wo,
                                     const BsdfDisks& disks, float u_lobe, float u_fresnel,
                                     BsdfSample* out) {
  out->eta2 = 1.f;
  if (wo.z <= 0.f) return BsdfSampleStep::Failed;
  out->lobe = SampledLobe::Evaluated;
  float glass_scale = 1.f;
  if (l.layered) {
    // The layers first, then the base with u_lobe rescaled to its share.
    BsdfSampleStep step;
    if (!sample_layers(p, l, wo, disks, &u_lobe, &glass_scale, &step, out)) return step;
  }
  if (u_lobe < l.glass) {
    if (u_lobe >= l.glass - l.diffuse_bt) {
      // The diffuse BTDF: cosine-weighted below the surface, weight f |cos_i| / pdf with
      // pdf = diffuse_bt |cos_i| / pi (times the base's share under the layers).
      const Vec3 c = disks.cosine;
      if (c.z <= 0.f) return BsdfSampleStep::Failed;
      out->wi = Vec3(c.x, c.y, -c.z);
      out->weight =
          diffuse_btdf_cos(p, l, wo, out->wi) * (glass_scale * kPi / (l.diffuse_bt * c.z));
      out->delta = true;
      out->pdf = 0.f;
      out->transmitted = true;
      out->lobe = SampledLobe::DiffuseBtdf;
      return BsdfSampleStep::Done;
    }
    out->lobe = SampledLobe::Glass;
    // Smooth dielectric: reflect with probability F, otherwise refract. eta is the ratio of
    // the indices across the interface in the direction of travel of wi.
    const float eta = p.front ? p.ior : 1.f / p.ior;
    if (p.alpha > kMinAlpha)
      return sample_rough_glass(p, wo, disks, u_fresnel, eta, glass_scale, out);
    const float F = fresnel_dielectric(wo.z, eta);
    out->delta = true;
    out->pdf = 0.f;
    if (u_fresnel < F) {
      out->wi = Vec3(-wo.x, -wo.y, wo.z);
      out->weight = Vec3(glass_scale, glass_scale, glass_scale);
      out->transmitted = false;
      return BsdfSampleStep::Done;
    }
    const float sin_t2 = (1.f - wo.z * wo.z) / (eta * eta);
    const float cos_t = std::sqrt(std::max(0.f, 1.f - sin_t2));
    out->wi = normalize(Vec3(-wo.x / eta, -wo.y / eta, -cos_t));
    // Radiance is scaled by 1/eta^2 across the interface (pbrt-v4, TransportMode::Radiance);
    // the transmitted light is tinted by the base color (glTF transmission).
    out->weight = p.base * (glass_scale / (eta * eta));
    out->eta2 = eta * eta;
    out->transmitted = true;
    return BsdfSampleStep::Done;
  }
  // Non-delta lobes: reuse u_lobe, rescaled, to choose GGX or diffuse.
  const float u_rest = l.glass < 1.f ? (u_lobe - l.glass) / (1.f - l.glass) : 0.f;
  Vec3 wi;
  if (u_rest < l.spec) {
    const Vec3 m = p.anisotropic()
                       ? sample_ggx_vndf_aniso_from_disk(wo, p.alpha_t, p.alpha, disks.polar)
                       : sample_ggx_vndf_from_disk(wo, p.alpha, disks.polar);
    wi = m * (2.f * dot(wo, m)) - wo;
  } else {
    wi = disks.cosine;
  }
  if (wi.z <= 0.f) return BsdfSampleStep::Failed;
  out->wi = wi;
  return BsdfSampleStep::NeedsEval;
}

namespace {

// The rough glass lobe's f |cos_i| with its weight (1 - metallic) transmission.
Vec3 rough_glass_cos(const BsdfParams& p, Vec3 wo, Vec3 wi) {
  const float eta = p.front ? p.ior : 1.f / p.ior;  // n(wi's side) / n(wo's) if transmitted
  const bool reflect = wi.z > 0.f;
  Vec3 h = reflect ? wo + wi : -(wo + wi * eta);
  const float hl = length(h);
  if (!(hl > 0.f)) return {0.f, 0.f, 0.f};
  h = h / hl;
  if (h.z < 0.f) h = -h;
  const float oh = dot(wo, h), ih = dot(wi, h);
  if (!(oh > 0.f) || (reflect ? !(ih > 0.f) : !(ih < 0.f))) return {0.f, 0.f, 0.f};
  const float F = fresnel_dielectric(oh, eta);
  const float dg = ggx_d(h, p.alpha) * ggx_g2(wo, wi, p.alpha);
  const float weight = (1.f - p.metallic) * p.transmission;
  if (reflect) return Vec3(1.f, 1.f, 1.f) * (weight * F * dg / (4.f * wo.z));
  // (1 - F) D G2 |wi.h| (wo.h) / (cos_o (wo.h + eta wi.h)^2): Walter's BTDF times |cos_i|,
  // over eta^2 (radiance).
  const float den = oh + eta * ih;
  return p.base * (weight * (1.f - F) * dg * (-ih) * oh / (wo.z * den * den));
}

}  // namespace

Vec3 through_eval_cos(const BsdfParams& p, Vec3 wo, Vec3 wi) {
  if (wo.z <= 0.f || wi.z == 0.f) return {0.f, 0.f, 0.f};
  const bool rough = has_rough_glass(p), diffuse = has_diffuse_btdf(p) && wi.z < 0.f;
  if (!rough && !diffuse) return {0.f, 0.f, 0.f};
  // The layers' weight over the base.
  float layers = 1.f;
  BsdfLobes l;
  if (p.layered() || diffuse) {
    l = bsdf_lobes(p, wo);
    if (p.layered()) layers = (1.f - l.coat_f) * (1.f - l.sheen_e);
  }
  Vec3 f = diffuse ? diffuse_btdf_cos(p, l, wo, wi) * layers : Vec3(0.f, 0.f, 0.f);
  if (rough) f += rough_glass_cos(p, wo, wi) * layers;
  return f;
}

void through_eval_lobes(const BsdfParams& p, Vec3 wo, Vec3 wi, Vec3 out[kLobeCategories]) {
  // through_eval_cos's terms, each to its category.
  if (wo.z <= 0.f || wi.z == 0.f) return;
  const bool rough = has_rough_glass(p), diffuse = has_diffuse_btdf(p) && wi.z < 0.f;
  if (!rough && !diffuse) return;
  float layers = 1.f;
  BsdfLobes l;
  if (p.layered() || diffuse) {
    l = bsdf_lobes(p, wo);
    if (p.layered()) layers = (1.f - l.coat_f) * (1.f - l.sheen_e);
  }
  if (diffuse) out[kDiffuseLobes] += diffuse_btdf_cos(p, l, wo, wi) * layers;
  if (rough)
    out[wi.z > 0.f ? kGlossyLobes : kTransmissionLobes] += rough_glass_cos(p, wo, wi) * layers;
}

void bsdf_eval_lobes(const BsdfParams& p, const BsdfLobes& l, Vec3 wo, Vec3 wi,
                     Vec3 out[kLobeCategories]) {
  for (int k = 0; k < kLobeCategories; ++k) out[k] = Vec3(0.f, 0.f, 0.f);
  // The base (general_base's terms; for an isotropic lobe without a film they are
  // bsdf_eval_cos's): the Lambert lobe is diffuse, the GGX lobes and the metal's multiple
  // scattering glossy.
  BaseTerms t;
  if (!base_terms(p, l, wo, wi, &t)) return;
  const Vec3 fd = t.fd, fm = t.fm;
  const float spec = t.spec;
  const float dt = has_diffuse_btdf(p) ? p.diffuse_transmission : 0.f;
  Vec3 diffuse = p.base * (l.wd * (1.f - dt) * (1.f - max3(fd)) * kInvPi * wi.z);
  Vec3 glossy = (fd * l.wd + fm * p.metallic) * (spec * wi.z);
  if (p.metallic > 0.f)  // the metal's multiple scattering
    glossy += l.ms * ((1.f - energy_table().e(wi.z, t.ms_alpha)) * wi.z);
  // The layers (add_layers): the sheen scales the base and adds its own diffuse lobe, the coat
  // scales everything under it and adds its glossy lobe.
  if (!is_zero(p.sheen)) {
    const float e_i = sheen_albedo(wi.z, p.sheen_alpha);
    const float scale = std::min(1.f - l.sheen_e, 1.f - max3(p.sheen) * std::min(1.f, e_i));
    diffuse = diffuse * scale +
              p.sheen * (sheen_lobe_cos(wo, wi, p.sheen_alpha) / std::max(l.sheen_norm, e_i));
    glossy = glossy * scale;
  }
  if (p.clearcoat > 0.f) {
    diffuse = diffuse * (1.f - l.coat_f);
    glossy = glossy * (1.f - l.coat_f);
    const CoatFrame cf(p.clearcoat_n);
    const Vec3 wo_c = cf.to_local(wo), wi_c = cf.to_local(wi);
    const Vec3 hc_raw = wo_c + wi_c;
    const float hcl = length(hc_raw);
    if (wo_c.z > 0.f && wi_c.z > 0.f && hcl > 0.f) {
      const float a = p.clearcoat_alpha;
      const float coat = ggx_d(hc_raw / hcl, a) * ggx_g2(wo_c, wi_c, a) / (4.f * wo_c.z);
      glossy += Vec3(1.f, 1.f, 1.f) * (l.coat_f * coat);
    }
  }
  out[kDiffuseLobes] = diffuse;
  out[kGlossyLobes] = glossy;
}

bool bsdf_sample_finish(Vec3 f, float pdf, BsdfSample* out) {
  if (!(pdf > 0.f)) return false;
  out->pdf = pdf;
  out->delta = false;
  out->transmitted = false;
  out->eta2 = 1.f;
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
  // Layered vertices: bsdf_eval_pdf itself, on the direction the blocks normalized.
  for (uint32_t m = used_ & (layered_ | (layered_ << kLanes)); m; m &= m - 1) {
    const int slot = __builtin_ctz(m);
    const LayeredVertex& v = layered_vertex(slot % kLanes);
    Vec3 wi(wi_[0][slot], wi_[1][slot], wi_[2][slot]);
    if (slot >= kLanes) wi = normalize(wi);
    float pdf = 0.f;
    const Vec3 f = bsdf_eval_pdf(v.p, v.lobes, v.wo, wi, &pdf);
    for (int c = 0; c < 3; ++c) f_[c][slot] = f[c];
    pdf_[slot] = pdf;
  }
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
  const F32x4 specular = load4(&specular_[v]);
  const I32x4 has_specular = specular > zero;
  F32x4 fd[3];
  for (int ch = 0; ch < 3; ++ch) {
    const F32x4 f0d = load4(&f0d_[ch][v]);
    fd[ch] = select4(has_specular, f0d + (specular - f0d) * fw, zero);
  }
  const F32x4 fdm = max4(fd[0], max4(fd[1], fd[2]));
  const F32x4 alpha = load4(&alpha_[v]);
  const F32x4 a2 = alpha * alpha;
  const F32x4 four_c2 = 4.f * c2;
  const F32x4 den = sz * sz * (a2 - 1.f) + four_c2;
  const F32x4 d = a2 * four_c2 * four_c2 / (kPi * den * den);
  const F32x4 ci2 = wi_z * wi_z;
  const F32x4 root_i = sqrt4(ci2 + a2 * max4(zero, one - ci2));
  const F32x4 spec = d / (2.f * (load4(&root_o_[v]) * wi_z + root_i * wo_z));
  const F32x4 wd = load4(&wd_[v]);
  const F32x4 kd = wd * (1.f - fdm) * kInvPi;
  const F32x4 metallic = load4(&metallic_[v]);
  const F32x4 ms_factor = load4(&ms_factor_[i]);
  for (int ch = 0; ch < 3; ++ch) {
    const F32x4 base = load4(&base_[ch][v]);
    // ms is 0 for non-metals, where bsdf_eval_pdf adds nothing: x + 0 = x.
    const F32x4 diffuse = base * kd + load4(&ms_[ch][v]) * ms_factor;
    const F32x4 fm = base + (1.f - base) * fw;
    const F32x4 specular_ch = (wd * fd[ch] + fm * metallic) * spec;
    store4(&f_[ch][i], select4(valid, (diffuse + specular_ch) * wi_z, zero));
  }
  const F32x4 lobe = load4(&spec_[v]);
  const F32x4 pdf = (1.f - load4(&glass_[v])) *
                    (lobe * d * load4(&pdf_k_[v]) + (1.f - lobe) * wi_z * kInvPi);
  store4(&pdf_[i], select4(valid, pdf, zero));
}

}  // namespace rf
