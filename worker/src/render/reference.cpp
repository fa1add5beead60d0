#include "render/reference.h"

#include <algorithm>
#include <cmath>

#include "render/packet_tracer.h"

namespace rf {

namespace {

// ---- The reference: one path at a time, with the scalar BSDF and light code.

// sample_light with the BSDF evaluated on the spot: false if the sample contributes nothing
// whatever the visibility, otherwise *out holds the shadow ray and the unoccluded
// contribution.
bool reference_light_sample(const Scene& scene, const LightContext& lc, const ShadingPoint& sp,
                            const BsdfLobes& lobes, const Frame& frame, Vec3 wo_local,
                            const BounceSamples& s, const float* weights, float total,
                            LightRay* out) {
  uint32_t entry = 0;
  float p_entry = 0.f, u_sel = 0.f;
  const Point2 u_light = s.get2(dim::kLightU);
  if (!choose_light(lc, weights, total, u_light.x, &entry, &p_entry, &u_sel)) return false;
  const Point2 u{u_sel, u_light.y};
  const Vec3 origin = sp.above();
  out->origin = origin;
  if (entry == lc.clusters) {
    float pdf = 0.f;
    const Vec3 wi = lc.env->sample(u, &pdf);
    pdf *= p_entry;
    if (!(pdf > 0.f) || dot(wi, sp.ng) <= 0.f) return false;
    float bsdf_pdf_wi = 0.f;
    const Vec3 f = bsdf_eval_pdf(sp.params, lobes, wo_local, frame.to_local(wi), &bsdf_pdf_wi);
    if (is_zero(f)) return false;
    const float w = power_heuristic(pdf, bsdf_pdf_wi);
    out->wi = wi;
    out->tmax = kInfinity;
    out->contribution = f * lc.env->eval(wi) * (w / pdf);
    return true;
  }
  const LightSet& lights = scene.lights();
  const LightSample ls = lights.sample_in(entry, u.x, u.y);
  if (ls.punctual >= 0)
    return punctual_light_sample(lights.punctual()[size_t(ls.punctual)], ls.pdf_area * p_entry,
                                 sp, frame, wo_local, out);
  const Vec3 to_light = ls.p - origin;
  const float dist2 = dot(to_light, to_light);
  const float dist = std::sqrt(dist2);
  if (!(dist > 0.f)) return false;
  const Vec3 wi = to_light / dist;
  const float cos_light = dot(facing_light_normal(scene, ls, origin), -wi);
  if (cos_light <= 0.f || dot(sp.ng, wi) <= 0.f) return false;
  float bsdf_pdf_wi = 0.f;
  const Vec3 f = bsdf_eval_pdf(sp.params, lobes, wo_local, frame.to_local(wi), &bsdf_pdf_wi);
  if (is_zero(f)) return false;
  const float pdf_light = p_entry * ls.pdf_area * dist2 / cos_light;
  const float tmax = dist * (1.f - 1e-4f) - ray_epsilon(ls.p);
  if (!(tmax > 0.f)) return false;
  const float w = power_heuristic(pdf_light, bsdf_pdf_wi);
  const Vec3 Le = scene.covered_emission(ls.slot, ls.prim, ls.b1, ls.b2, cos_light);
  out->wi = wi;
  out->tmax = tmax;
  out->contribution = f * Le * (w / pdf_light);
  return true;
}

}  // namespace

SampleResult trace_sample_reference(const Scene& scene, const RenderSettings& settings,
                                    const PixelSampler& sampler, uint32_t x, uint32_t y,
                                    uint32_t index) {
  const TraceContext ctx(scene, settings);
  PathState p = start_path(ctx, scene, settings, sampler, x, y, index);
  if (settings.integrator == IntegratorType::AmbientOcclusion)
    return trace_ao(scene, p);
  const LightContext& lc = ctx.lights;
  const uint32_t max_depth = path_max_depth(settings);
  SampleResult& result = p.result;
  // Rays go through the packet interface with one lane active: the same queries as the packet
  // tracer's (a single-ray query may round the hit differently in the last bits; the coherent
  // traversal of its camera rays finds the same hits, which Scene/PacketQueries checks).
  RayPacket ray, shadow;
  Hit hits[kPacketSize];
  bool found[kPacketSize], blocked[kPacketSize];
  const uint64_t seed = sampler.seed(), pixel = sampler.pixel();
  for (uint32_t bounce = 0;; ++bounce) {
    const BounceSamples u(p.s, bounce);
    ray.set(0, p.o, p.d, bounce == 0 ? p.tmax : kInfinity);
    ray.tnear[0] = bounce == 0 ? p.tmin : 0.f;
    ray.id[0] = shadow.id[0] = index;
    ray.time[0] = shadow.time[0] = p.time;
    ++result.rays;
    scene.intersect(ray, hits, found, false, ray_query(seed, pixel, bounce, RayKind::Path));
    const Vec3 wo = -p.d;
    if (!found[0]) {
      if (lc.env) {
        const float w =
            p.prev_delta ? 1.f
                         : power_heuristic(p.prev_bsdf_pdf,
                                           light_env_pmf(lc, p.sel_o, p.sel_ng, p.sel_total, p.d,
                                                         p.sel_two_sided) *
                                               lc.env->pdf(p.d));
        const Vec3 beta =
            is_zero(p.medium) ? p.beta : p.beta * transmittance(p.medium, kInfinity);
        add_radiance(p, nullptr, beta * lc.env->eval(p.d) * w, bounce,
                     RadianceSource::Environment);
      }
      return result;
    }
    const Hit& hit = hits[0];
    if (!is_zero(p.medium)) p.beta *= transmittance(p.medium, hit.t);
    ShadingPoint sp = make_shading_point(scene, hit, wo);
    if (bounce == 0) record_first_hit(scene, sp, hit, p.per_axial, &result);
    const Material& hit_material = scene.materials()[hit.material];
    const float cos_emit = emitting_cosine(hit_material, hit.ng, wo);
    if (hit_material.unlit) {  // as in the packet tracer
      if (cos_emit > 0.f) {
        add_radiance(p, nullptr, p.beta * sp.albedo, bounce, RadianceSource::Surface);
        if (hit_material.unlit_adds_emission)
          add_radiance(p, nullptr,
                       p.beta * scene.emission(hit.slot, hit.prim, hit.b1, hit.b2, cos_emit),
                       bounce, RadianceSource::Surface);
      }
      return result;
    }
    if (cos_emit > 0.f && hit_material.is_emissive()) {
      const Vec3 Le = scene.emission(hit.slot, hit.prim, hit.b1, hit.b2, cos_emit);
      if (p.prev_delta) {
        add_radiance(p, nullptr, p.beta * Le, bounce, RadianceSource::Surface);
      } else {
        const float pdf_light =
            light_pdf_area(lc, p.sel_o, p.sel_ng, p.sel_total, hit.slot, hit.prim, p.d,
                           p.sel_two_sided) *
            hit.t * hit.t / cos_emit;
        add_radiance(p, nullptr, p.beta * Le * power_heuristic(p.prev_bsdf_pdf, pdf_light),
                     bounce, RadianceSource::Surface);
      }
    }
    if (bounce >= max_depth) return result;
    if (bounce >= 3) {
      const float q = roulette_survival(p.beta, p.eta_scale);
      if (!(u.get(dim::kRoulette) < q)) return result;
      p.beta = p.beta / q;
    }
    disperse(p, u, &sp.params);
    const Frame frame = sp.frame();
    const Vec3 wo_local = frame.to_local(wo);
    const BsdfLobes lobes = bsdf_lobes(sp.params, wo_local);
    LightRay light;
    float weights[kMaxLightEntries];
    if (lc.any && bsdf_has_smooth_part(sp.params)) {
      p.sel_o = sp.above();
      p.sel_ng = sp.ng;
      p.sel_two_sided = has_through_lobe(sp.params);
      p.sel_total = light_weights(lc, p.sel_o, p.sel_ng, weights, p.sel_two_sided);
    }
    if (lc.any && bsdf_has_smooth_part(sp.params) &&
        reference_light_sample(scene, lc, sp, lobes, frame, wo_local, u, weights, p.sel_total,
                               &light)) {
      Vec3 nee = p.beta * light.contribution;
      // The shadow ray travels in the medium on its side: through the surface, the one a
      // transmission enters.
      const Vec3 medium =
          light.through ? medium_after(hit_material, sp.params.front, p.medium) : p.medium;
      if (!is_zero(medium)) nee *= transmittance(medium, light.tmax);
      shadow.set(0, light.origin, light.wi, light.tmax);
      ++result.rays;
      scene.occluded(shadow, blocked, ray_query(seed, pixel, bounce, RayKind::Shadow));
      if (!blocked[0]) add_radiance(p, nullptr, nee, bounce, RadianceSource::LightSample);
    }
    BsdfSample bs;
    if (!bsdf_sample(sp.params, lobes, wo_local, u.get2(dim::kBsdfU), u.get(dim::kLobe),
                     lobes.glass > 0.f ? u.get(dim::kFresnel) : 0.f, &bs))
      return result;
    const Vec3 wi = normalize(frame.to_world(bs.wi));
    if (wrong_side(wi, sp.ng, bs.transmitted)) return result;
    if (is_zero(bs.weight)) return result;
    p.beta *= bs.weight;
    p.eta_scale *= bs.eta2;
    p.prev_bsdf_pdf = bs.pdf;
    p.prev_delta = bs.delta;
    p.o = bs.transmitted ? sp.below() : sp.above();
    p.d = wi;
    if (bs.transmitted)
      p.medium = medium_after(scene.materials()[hit.material], sp.params.front, p.medium);
  }
}

}  // namespace rf
