#include "render/light_sampling.h"

#include <algorithm>
#include <cmath>

#include "math/simd.h"
#include "sampling/sampling.h"

namespace rf {

LightContext light_context(const Scene& scene, const RenderSettings& settings) {
  LightContext c;
  c.lights = &scene.lights();
  c.clusters = scene.lights().empty() ? 0 : scene.lights().cluster_count();
  const Environment* env = settings.environment.get();
  if (env && env->mean_luminance() > 0.f) {
    c.env = env;
    c.env_weight = kPi * env->mean_luminance();
  }
  c.any = c.entries() > 0;
  c.single = c.entries() == 1;
  return c;
}

namespace {

float cluster_weight(const LightContext& lc, uint32_t c, Vec3 o, Vec3 ng, bool two_sided) {
  const float w = lc.lights->importance(c, o, ng);
  return two_sided ? std::max(w, lc.lights->importance(c, o, -ng)) : w;
}

}  // namespace

float light_weights(const LightContext& lc, Vec3 o, Vec3 ng, float* w, bool two_sided) {
  if (lc.single) return 1.f;
  float total = 0.f;
  if (lc.clusters && !two_sided) {
    total = lc.lights->importances(o, ng, w);
  } else {
    for (uint32_t c = 0; c < lc.clusters; ++c) {
      w[c] = cluster_weight(lc, c, o, ng, true);
      total += w[c];
    }
  }
  if (lc.env) {
    w[lc.clusters] = lc.env_weight;
    total += lc.env_weight;
  }
  return total;
}

float light_entry_pmf(const LightContext& lc, uint32_t e, Vec3 o, Vec3 ng, float total,
                      bool two_sided) {
  if (lc.single) return 1.f;
  if (!(total > 0.f)) return 0.f;
  const float w = e < lc.clusters ? cluster_weight(lc, e, o, ng, two_sided) : lc.env_weight;
  return w / total;
}

float light_pdf_area(const LightContext& lc, Vec3 o, Vec3 ng, float total, uint32_t slot,
                     uint32_t prim, Vec3 d, bool two_sided) {
  if (!lc.clusters) return 0.f;
  uint32_t c = 0;
  const float pdf = lc.lights->pdf_area_in_cluster(slot, prim, &c);
  if (!(pdf > 0.f) || dot(ng, d) <= 0.f) return 0.f;
  return light_entry_pmf(lc, c, o, ng, total, two_sided) * pdf;
}

float light_env_pmf(const LightContext& lc, Vec3 o, Vec3 ng, float total, Vec3 d,
                    bool two_sided) {
  if (!lc.env || dot(d, ng) <= 0.f) return 0.f;
  return light_entry_pmf(lc, lc.clusters, o, ng, total, two_sided);
}

bool punctual_light_sample(const PunctualLight& light, float p_entry, const ShadingPoint& sp,
                           const Frame& frame, Vec3 wo_local, LightRay* out) {
  // A light behind the surface is reached only through a rough glass lobe or a diffuse BTDF;
  // its shadow ray then leaves below the surface.
  const bool through = has_through_lobe(sp.params);
  for (int side = 0; side < (through ? 2 : 1); ++side) {
    const Vec3 origin = side == 0 ? sp.above() : sp.below();
    Vec3 wi, Li;
    float tmax;
    if (light.type == PunctualType::Directional) {
      wi = -light.direction;
      Li = light.intensity;  // irradiance normal to the direction
      tmax = kInfinity;
    } else {
      const Vec3 to = light.position - origin;
      const float d2 = dot(to, to);
      if (!(d2 > 0.f)) return false;
      const float dist = std::sqrt(d2);
      wi = to / dist;
      Li = light.intensity * (light.spot_falloff(dot(-wi, light.direction)) / d2);
      tmax = dist;
    }
    const float cos_ng = dot(wi, sp.ng);
    if (side == 0 && !(cos_ng > 0.f)) continue;  // behind: the other side, if any
    if (side == 1 && !(cos_ng < 0.f)) return false;
    if (is_zero(Li)) return false;
    const Vec3 wl = frame.to_local(wi);
    Vec3 f = side == 0 ? bsdf_eval_cos(sp.params, wo_local, wl) : Vec3(0.f, 0.f, 0.f);
    // The sampled-only lobes where the shading frame agrees on the side.
    if (through && (wl.z > 0.f) == (side == 0)) f += through_eval_cos(sp.params, wo_local, wl);
    if (is_zero(f)) return false;
    out->origin = origin;
    out->wi = wi;
    out->tmax = tmax;
    out->contribution = f * Li * (1.f / p_entry);
    out->through = side == 1;
    return true;
  }
  return false;
}

bool choose_light(const LightContext& lc, const float* w, float total, float u_select,
                  uint32_t* entry, float* pmf, float* u_rest) {
  if (lc.single) {
    *entry = lc.clusters ? 0u : lc.clusters;
    *pmf = 1.f;
    *u_rest = u_select;
    return true;
  }
  if (!(total > 0.f)) return false;
  const uint32_t n = lc.entries();
  const float target = u_select * total;
  float below = 0.f;
  uint32_t last = n;
  for (uint32_t e = 0; e < n; ++e) {
    if (!(w[e] > 0.f)) continue;
    last = e;
    if (below + w[e] > target) break;
    below += w[e];
  }
  // Rounding may leave target past the sum: the last entry with weight takes it.
  if (last == n) return false;
  *entry = last;
  *pmf = w[last] / total;
  *u_rest = std::min(0.99999994f, std::max(0.f, (target - below) / w[last]));
  return true;
}

void LightBatch::finish_geometry(BsdfEvalBatch* batch) {
  const F32x4 zero = splat4(0.f);
  for (int i = 0; i < kLanes; i += 4) {
    const uint32_t bits = (area >> i) & 0xfu;
    if (!bits) continue;
    const I32x4 mask = lane_mask4(bits);
    F32x4 t[3];
    for (int c = 0; c < 3; ++c) t[c] = load4(&lp[c][i]) - load4(&o[c][i]);
    const F32x4 dist2 = dot4(t[0], t[1], t[2], t[0], t[1], t[2]);
    const F32x4 dist = sqrt4(dist2);
    const F32x4 inv = 1.f / dist;  // Vec3 / float multiplies by the reciprocal
    const F32x4 wx = t[0] * inv, wy = t[1] * inv, wz = t[2] * inv;
    const F32x4 cos_light =
        dot4(load4(&ln[0][i]), load4(&ln[1][i]), load4(&ln[2][i]), -wx, -wy, -wz);
    const F32x4 cos_vertex =
        dot4(load4(&ng[0][i]), load4(&ng[1][i]), load4(&ng[2][i]), wx, wy, wz);
    // Stop short of the light's own surface so it does not occlude itself.
    const F32x4 t_max = dist * (1.f - 1e-4f) - load4(&eps[i]);
    const I32x4 keep = (dist > zero) & ~(cos_light <= zero) & ~(cos_vertex <= zero) &
                       (t_max > zero);
    const F32x4 pdf = load4(&k[i]) * dist2 / cos_light;
    store4(&wi[0][i], select4(mask, wx, load4(&wi[0][i])));
    store4(&wi[1][i], select4(mask, wy, load4(&wi[1][i])));
    store4(&wi[2][i], select4(mask, wz, load4(&wi[2][i])));
    store4(&tmax[i], select4(mask, t_max, load4(&tmax[i])));
    store4(&pdf_light[i], select4(mask, pdf, load4(&pdf_light[i])));
    store4(&ok[i], mask ? keep : load4(&ok[i]));
  }
  batch->add_lights_world(area, wi);
}

void LightBatch::finish_contributions(const BsdfEvalBatch& batch) {
  const F32x4 zero = splat4(0.f), one = splat4(1.f), inf = splat4(kInfinity);
  for (int i = 0; i < kLanes; i += 4) {
    const uint32_t bits = (waiting >> i) & 0xfu;
    if (!bits) continue;
    const I32x4 mask = lane_mask4(bits);
    F32x4 f[3];
    for (int c = 0; c < 3; ++c) f[c] = load4(batch.light_f(c) + i);
    // power_heuristic(pdf_light, pdf_bsdf).
    const F32x4 pdf = load4(&pdf_light[i]);
    F32x4 pdf_bsdf = load4(batch.light_pdf() + i);
    if ((guided >> i) & 0xfu) {  // alpha p_guide + (1 - alpha) p_bsdf; alpha = 0 elsewhere
      const F32x4 frac = load4(&guide_frac[i]);
      pdf_bsdf = frac * load4(&guide_pdf[i]) + (one - frac) * pdf_bsdf;
    }
    const F32x4 a = pdf * pdf, b = pdf_bsdf * pdf_bsdf;
    const F32x4 w = select4(a == zero, zero, select4(a == inf, one, a / (a + b)));
    const F32x4 factor = w / pdf;
    for (int c = 0; c < 3; ++c)
      store4(&contribution[c][i], f[c] * load4(&radiance[c][i]) * factor);
    const I32x4 f_zero = (f[0] == zero) & (f[1] == zero) & (f[2] == zero);
    store4(&ok[i], mask ? (load4(&ok[i]) & ~f_zero) : load4(&ok[i]));
  }
}

LightSampleSource light_sample_source(const Scene& scene, const LightContext& lc,
                                      const BounceSamples& s, const float* w, float total) {
  uint32_t entry = 0;
  float p_entry = 0.f, u_sel = 0.f;
  const Point2 u_light = s.get2(dim::kLightU);  // sample_light's choice, made again
  if (!choose_light(lc, w, total, u_light.x, &entry, &p_entry, &u_sel)) return {};
  if (entry == lc.clusters) return {true, -1, 0, 0};
  const LightSample ls = scene.lights().sample_in(entry, u_sel, u_light.y);
  return {false, ls.punctual, ls.slot, ls.prim};
}

LightSampleKind sample_light(const Scene& scene, const LightContext& lc, const ShadingPoint& sp,
                             const Frame& frame, Vec3 wo_local, const BounceSamples& s,
                             const float* w, float total, BsdfEvalBatch* batch, LightBatch* lb,
                             int lane, LightRay* out) {
  uint32_t entry = 0;
  float p_entry = 0.f, u_sel = 0.f;
  // The light position's first coordinate also chooses the light (rescaled at each choice),
  // so that the pair's stratification reaches every light (LightSet::sample_in).
  const Point2 u_light = s.get2(dim::kLightU);
  if (!choose_light(lc, w, total, u_light.x, &entry, &p_entry, &u_sel))
    return LightSampleKind::None;
  const Point2 u{u_sel, u_light.y};
  const Vec3 origin = sp.above();
  const uint32_t bit = uint32_t(1) << lane;
  const auto set3 = [lane](float (*to)[LightBatch::kLanes], Vec3 v) {
    to[0][lane] = v.x;
    to[1][lane] = v.y;
    to[2][lane] = v.z;
  };
  if (entry == lc.clusters) {
    float pdf = 0.f;
    const Vec3 wi = lc.env->sample(u, &pdf);
    pdf *= p_entry;
    if (!(pdf > 0.f) || dot(wi, sp.ng) <= 0.f) return LightSampleKind::None;
    set3(lb->o, origin);
    set3(lb->wi, wi);
    lb->tmax[lane] = kInfinity;
    set3(lb->radiance, lc.env->eval(wi));
    lb->pdf_light[lane] = pdf;
    lb->ok[lane] = -1;
    lb->waiting |= bit;
    batch->add_light(lane, frame.to_local(wi));
    return LightSampleKind::Waiting;
  }
  const LightSet& lights = scene.lights();
  const LightSample ls = lights.sample_in(entry, u.x, u.y);
  if (ls.punctual >= 0) {
    // The selection probability only: a delta light.
    return punctual_light_sample(lights.punctual()[size_t(ls.punctual)], ls.pdf_area * p_entry,
                                 sp, frame, wo_local, out)
               ? LightSampleKind::Delta
               : LightSampleKind::None;
  }
  // An emissive triangle: the rest is LightBatch::finish_geometry's.
  set3(lb->o, origin);
  set3(lb->lp, ls.p);
  set3(lb->ln, facing_light_normal(scene, ls, origin));
  set3(lb->ng, sp.ng);
  lb->eps[lane] = ray_epsilon(ls.p);
  lb->k[lane] = p_entry * ls.pdf_area;
  // The cosine at the light towards the vertex, for an emitter under a clear coat only (the
  // batch computes it for the pdf later); its sign does not matter.
  float cos_view = 1.f;
  if (scene.material(ls.slot, ls.prim).clearcoat > 0.f) {
    const Vec3 to = origin - ls.p;
    const float d = length(to);
    if (d > 0.f) cos_view = dot(ls.n, to) / d;
  }
  set3(lb->radiance, scene.covered_emission(ls.slot, ls.prim, ls.b1, ls.b2, cos_view));
  lb->area |= bit;
  lb->waiting |= bit;
  return LightSampleKind::Waiting;
}

}  // namespace rf
