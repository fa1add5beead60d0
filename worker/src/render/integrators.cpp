#include "render/integrators.h"

#include <algorithm>
#include <cmath>
#include <limits>

#include "math/estimators.h"
#include "scene/materials.h"
#include "sampling/sampling.h"
#include "math/simd.h"

namespace rf {

bool parse_integrator_type(const std::string& name, IntegratorType* out) {
  if (name == "path") {
    *out = IntegratorType::Path;
    return true;
  }
  if (name == "direct") {
    *out = IntegratorType::Direct;
    return true;
  }
  if (name == "ao") {
    *out = IntegratorType::AmbientOcclusion;
    return true;
  }
  return false;
}

const char* integrator_type_name(IntegratorType t) {
  switch (t) {
    case IntegratorType::Path:
      return "path";
    case IntegratorType::Direct:
      return "direct";
    case IntegratorType::AmbientOcclusion:
      return "ao";
  }
  return "?";
}

namespace {

constexpr float kInfinity = std::numeric_limits<float>::infinity();

// Offset for spawned rays: floating-point error of a hit position grows with its magnitude,
// so the offset along the geometric normal scales with it (with a floor near the origin).
inline float ray_epsilon(Vec3 p) { return 3e-5f * std::max(max_abs_component(p), 1e-2f); }

// Light selection between the scene's lights and the environment, by power (the scene's own
// alias table does the rest): P_env = pi^2 R^2 mean luminance, the power an environment of
// that mean radiance sends through a disk of the scene's bounding radius R.
struct LightContext {
  const Environment* env = nullptr;
  float p_env = 0.f;  // probability of choosing the environment
  bool any = false;
};

LightContext light_context(const Scene& scene, const RenderSettings& settings) {
  LightContext c;
  c.env = settings.environment.get();
  const double scene_power = scene.lights().empty() ? 0.0 : scene.lights().total_power();
  double env_power = 0.0;
  if (c.env) {
    const double r = 0.5 * double(scene.diagonal());
    env_power = double(kPi) * double(kPi) * r * r * double(c.env->mean_luminance());
  }
  if (scene_power + env_power > 0.0) {
    c.any = true;
    c.p_env = float(env_power / (scene_power + env_power));
    if (scene_power == 0.0) c.p_env = 1.f;
    if (env_power == 0.0) c.p_env = 0.f;
  }
  return c;
}

// A surface point ready for shading: material parameters after textures, normals oriented
// towards wo, and the ray origins for leaving on either side.
struct ShadingPoint {
  BsdfParams params;
  Vec3 albedo;  // base color, the albedo AOV
  Vec3 ng;      // geometric normal on the side of wo
  Vec3 ns;      // shading normal (normal-mapped) on the same side as ng
  Vec3 p;
  float eps = 0.f;
  Vec3 above() const { return p + ng * eps; }
  Vec3 below() const { return p - ng * eps; }
};

// The texture coordinates of a texture slot at the hit: TEXCOORD_0 and _1 come with the hit,
// other sets are interpolated when asked for.
Point2 texcoord(const Scene& scene, const Hit& hit, const TextureRef& ref) {
  return ref.apply(ref.texcoord < 2 ? hit.uv[ref.texcoord] : scene.texcoord(hit, ref.texcoord));
}

ShadingPoint make_shading_point(const Scene& scene, const Hit& hit, Vec3 wo) {
  const Material& mat = scene.materials()[hit.material];
  const TextureSet& tex = scene.textures();
  ShadingPoint sp;
  BsdfParams& bp = sp.params;
  bp.base = mat.albedo;
  float metallic = mat.metallic, roughness = mat.roughness;
  float c[4];
  if (mat.base_color_tex.valid() &&
      tex.lookup(mat.base_color_tex.texture, texcoord(scene, hit, mat.base_color_tex), 3, c))
    bp.base = bp.base * Vec3(c[0], c[1], c[2]);  // linear: decoded from sRGB before filtering
  // glTF 2.0, 3.9.2: COLOR_0 multiplies the base colour.
  Vec3 vertex_rgb;
  if (scene.vertex_color(hit, &vertex_rgb)) bp.base = bp.base * vertex_rgb;
  if (mat.metallic_roughness_tex.valid() &&
      tex.lookup(mat.metallic_roughness_tex.texture,
                 texcoord(scene, hit, mat.metallic_roughness_tex), 3, c)) {
    // glTF: roughness in G, metallic in B, both linear.
    roughness *= c[1];
    metallic *= c[2];
  }
  bp.metallic = std::min(1.f, std::max(0.f, metallic));
  const float r = std::min(1.f, std::max(0.f, roughness));
  bp.alpha = std::max(kMinAlpha, r * r);
  bp.specular = mat.specular;
  bp.ior = mat.ior;
  bp.transmission = mat.transmission;
  sp.albedo = bp.base;

  Vec3 ns = hit.ns;
  if (mat.normal_tex.valid() && length(hit.dpdu) > 0.f &&
      tex.lookup(mat.normal_tex.texture, texcoord(scene, hit, mat.normal_tex), 3, c)) {
    // Tangent-space normal map (glTF 3.9.3): n = normalize((2c - 1) * (scale, scale, 1)) in
    // the frame (T, B, N) with T the uv tangent made orthogonal to N.
    const Vec3 tn((2.f * c[0] - 1.f) * mat.normal_scale, (2.f * c[1] - 1.f) * mat.normal_scale,
                  2.f * c[2] - 1.f);
    Vec3 t = hit.dpdu - ns * dot(ns, hit.dpdu);
    const float tl = length(t);
    if (tl > 0.f && std::isfinite(tl)) {
      t = t / tl;
      const Vec3 b = cross(ns, t) * hit.tangent_sign;
      const Vec3 n = t * tn.x + b * tn.y + ns * tn.z;
      const float nl = length(n);
      if (nl > 0.f && std::isfinite(nl)) ns = n / nl;
    }
  }
  bp.front = dot(hit.ng, wo) >= 0.f;
  sp.ng = bp.front ? hit.ng : -hit.ng;
  sp.ns = dot(ns, sp.ng) >= 0.f ? ns : -ns;
  // A shading normal that puts wo below its hemisphere cannot be used (the BSDF would see
  // wo.z <= 0 and the path would end black): fall back to the geometric normal.
  if (dot(sp.ns, wo) <= 1e-4f) sp.ns = sp.ng;
  sp.p = hit.p;
  sp.eps = ray_epsilon(hit.p);
  return sp;
}

// The normal of an area light's sample point on the side facing `origin`: its front normal, or
// the back face's for a double-sided emitter seen from behind (both faces emit).
inline Vec3 facing_light_normal(const Scene& scene, const LightSample& ls, Vec3 origin) {
  if (dot(ls.n, origin - ls.p) >= 0.f || !scene.material(ls.slot, ls.prim).double_sided)
    return ls.n;
  return -ls.n;
}

// The cosine between a hit's geometric normal and wo on the emitting side (<= 0: the hit
// face does not emit towards wo).
inline float emitting_cosine(const Material& m, Vec3 ng, Vec3 wo) {
  const float c = dot(ng, wo);
  return m.double_sided ? std::abs(c) : c;
}

// A light sample waiting for its shadow ray: it contributes `contribution` if nothing blocks
// origin + t wi for t in (0, tmax). In the packet tracer only delta lights' samples are held
// so (the others wait in a LightBatch); the scalar reference holds every light's.
struct LightRay {
  Vec3 origin, wi;
  float tmax = 0.f;
  Vec3 contribution;
};

// The light samples of a packet's vertices that wait for their BSDF values (lights with a pdf:
// emissive triangles and the environment). Area-light samples finish their geometry here
// (direction, distance, pdf, the tests that drop them), and every waiting sample its MIS
// weight and contribution, four lanes at a time: the lanes' chains of square roots and
// divisions run side by side instead of one after another. Each lane computes exactly what
// the scalar code would, in its order of operations.
struct LightBatch {
  static constexpr int kLanes = kPacketSize;
  uint32_t area = 0;     // lanes with an area-light sample to finish
  uint32_t waiting = 0;  // lanes with a sample waiting for its BSDF value (area or environment)
  // Shadow ray origin; point, unit normal and ray_epsilon of the light; geometric normal of the
  // vertex; p_scene * pdf_area (area lights).
  alignas(16) float o[3][kLanes] = {}, lp[3][kLanes] = {}, ln[3][kLanes] = {};
  alignas(16) float ng[3][kLanes] = {}, eps[kLanes] = {}, k[kLanes] = {};
  // Radiance arriving along wi; solid-angle pdf of wi; the shadow ray (set for the environment,
  // computed for area lights) and whether the sample is kept.
  alignas(16) float radiance[3][kLanes] = {}, pdf_light[kLanes] = {};
  alignas(16) float wi[3][kLanes] = {}, tmax[kLanes] = {};
  alignas(16) int32_t ok[kLanes] = {};
  alignas(16) float contribution[3][kLanes] = {};

  void clear() { area = waiting = 0; }
  // The area-light lanes' shadow rays, pdfs and tests, and their directions queued in *batch.
  void finish_geometry(BsdfEvalBatch* batch);
  // After batch->evaluate(): the waiting lanes' contributions, and ok cleared where f = 0.
  void finish_contributions(const BsdfEvalBatch& batch);
};

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
    const F32x4 pdf = load4(&pdf_light[i]), pdf_bsdf = load4(batch.light_pdf() + i);
    const F32x4 a = pdf * pdf, b = pdf_bsdf * pdf_bsdf;
    const F32x4 w = select4(a == zero, zero, select4(a == inf, one, a / (a + b)));
    const F32x4 factor = w / pdf;
    for (int c = 0; c < 3; ++c)
      store4(&contribution[c][i], f[c] * load4(&radiance[c][i]) * factor);
    const I32x4 f_zero = (f[0] == zero) & (f[1] == zero) & (f[2] == zero);
    store4(&ok[i], mask ? (load4(&ok[i]) & ~f_zero) : load4(&ok[i]));
  }
}

// The BSDF samples' disk warps (bsdf_disks) of a packet's lanes, four lanes at a time: they
// depend on the sample values alone, so they are computed for every live lane before the
// vertices are shaded, both of them (a lane uses one, known only once its material is).
struct DiskBatch {
  static constexpr int kLanes = kPacketSize;
  alignas(16) float cosine[3][kLanes] = {}, polar[2][kLanes] = {};

  // Lanes `lanes` of the pairs (ux[i], uy[i]); the other lanes of a block of four are computed
  // too (from whatever values they hold) and never read.
  void compute(const float* ux, const float* uy, uint32_t lanes) {
    for (int i = 0; i < kLanes; i += 4) {
      if (!((lanes >> i) & 0xfu)) continue;
      const F32x4 x = load4(ux + i), y = load4(uy + i);
      F32x4 cx, cy, cz, px, py;
      sample_cosine_hemisphere4(x, y, &cx, &cy, &cz);
      sample_polar_disk4(x, y, &px, &py);
      store4(&cosine[0][i], cx);
      store4(&cosine[1][i], cy);
      store4(&cosine[2][i], cz);
      store4(&polar[0][i], px);
      store4(&polar[1][i], py);
    }
  }
  BsdfDisks get(int lane) const {
    return {Vec3(cosine[0][lane], cosine[1][lane], cosine[2][lane]),
            Point2{polar[0][lane], polar[1][lane]}};
  }
};

// What sample_light produced.
enum class LightSampleKind {
  None,     // contributes nothing whatever the visibility: no shadow ray
  Delta,    // a punctual light: *out holds the shadow ray and the unoccluded contribution
  Waiting,  // a light with a pdf: in the LightBatch, waiting for its BSDF value
};

// Next-event estimation: one light (or the environment) chosen by power, its contribution
// f cos L / pdf, MIS-weighted against BSDF sampling with the power heuristic unless the light
// is a delta light.
LightSampleKind sample_light(const Scene& scene, const LightContext& lc, const ShadingPoint& sp,
                             const Frame& frame, Vec3 wo_local, const BounceSamples& s,
                             BsdfEvalBatch* batch, LightBatch* lb, int lane, LightRay* out) {
  float u_sel = s.get(dim::kLightSelect);
  const Point2 u = s.get2(dim::kLightU);
  const Vec3 origin = sp.above();
  const uint32_t bit = uint32_t(1) << lane;
  const auto set3 = [lane](float (*to)[LightBatch::kLanes], Vec3 v) {
    to[0][lane] = v.x;
    to[1][lane] = v.y;
    to[2][lane] = v.z;
  };
  if (lc.env && u_sel < lc.p_env) {
    float pdf = 0.f;
    const Vec3 wi = lc.env->sample(u, &pdf);
    pdf *= lc.p_env;
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
  if (lights.empty()) return LightSampleKind::None;
  // Reuse the selection variate: rescale the part above p_env to [0, 1).
  const float p_scene = 1.f - lc.p_env;
  u_sel = std::min(0.99999994f, (u_sel - lc.p_env) / p_scene);
  const LightSample ls = lights.sample(u_sel, u.x, u.y);
  if (ls.punctual >= 0) {
    const PunctualLight& light = lights.punctual()[size_t(ls.punctual)];
    const float pdf = ls.pdf_area * p_scene;  // selection probability only: a delta light
    Vec3 wi, Li;
    float tmax;
    if (light.type == PunctualType::Directional) {
      wi = -light.direction;
      Li = light.intensity;  // irradiance normal to the direction
      tmax = kInfinity;
    } else {
      const Vec3 to = light.position - origin;
      const float d2 = dot(to, to);
      if (!(d2 > 0.f)) return LightSampleKind::None;
      const float dist = std::sqrt(d2);
      wi = to / dist;
      Li = light.intensity * (light.spot_falloff(dot(-wi, light.direction)) / d2);
      tmax = dist;
    }
    if (is_zero(Li) || dot(wi, sp.ng) <= 0.f) return LightSampleKind::None;
    const Vec3 f = bsdf_eval_cos(sp.params, wo_local, frame.to_local(wi));
    if (is_zero(f)) return LightSampleKind::None;
    out->origin = origin;
    out->wi = wi;
    out->tmax = tmax;
    out->contribution = f * Li * (1.f / pdf);
    return LightSampleKind::Delta;
  }
  // An emissive triangle: the rest is LightBatch::finish_geometry's.
  set3(lb->o, origin);
  set3(lb->lp, ls.p);
  set3(lb->ln, facing_light_normal(scene, ls, origin));
  set3(lb->ng, sp.ng);
  lb->eps[lane] = ray_epsilon(ls.p);
  lb->k[lane] = p_scene * ls.pdf_area;
  set3(lb->radiance, scene.covered_emission(ls.slot, ls.prim, ls.b1, ls.b2));
  lb->area |= bit;
  lb->waiting |= bit;
  return LightSampleKind::Waiting;
}

// One sample's path while it is traced in a packet: its state between bounces.
struct PathState {
  SampleStream s{nullptr, 0};
  SampleResult result;  // radiance accumulates here
  Vec3 o, d;            // the ray of the next bounce
  float tmin = 0.f, tmax = kInfinity;  // the camera ray's range (its clipping planes)
  Vec3 beta{1.f, 1.f, 1.f};   // path throughput: product of f cos / pdf so far
  float prev_bsdf_pdf = 0.f;  // solid-angle pdf of the direction d (bounce > 0)
  bool prev_delta = true;     // camera rays and delta bounces: no light sampling could
                              // have produced this direction, so emission gets weight 1
  bool alive = false;
  BounceSamples u;  // this bounce's sample values
  Vec3 nee;         // this bounce's light sample, added if its shadow ray is not blocked
  // Between the halves of a vertex's shading (shade_vertex_begin, then shade_vertex_end_light
  // and shade_vertex_end_bsdf):
  LightSampleKind light_kind = LightSampleKind::None;
  LightRay light;          // light_kind Delta
  int bsdf_slot = -2;      // BsdfEvalBatch slot of the sampled direction's f and pdf; -1: the
                           // sample (glass) is complete; -2: the path ends at this vertex
  BsdfSample bs;
  Vec3 next_o, next_d;     // the next ray if the path goes on (next_d from the batch if pending)
  Vec3 ng;                 // the vertex's geometric normal on the side of wo
  // KHR_materials_volume: the absorption coefficient of the medium the ray travels in (0:
  // none), and the one the next ray will (a transmission into or out of a volume changes it).
  Vec3 medium, next_medium;
};

// exp(-sigma t) per channel: what a medium of absorption sigma lets through over a length t
// (t may be infinite: a ray that leaves through an open mesh is absorbed entirely).
inline Vec3 transmittance(Vec3 sigma, float t) {
  Vec3 out{1.f, 1.f, 1.f};
  for (int k = 0; k < 3; ++k)
    if (sigma[k] > 0.f) out[k] = std::exp(-sigma[k] * t);
  return out;
}

// The medium after a transmission at a vertex of material m seen from the front (entering the
// mesh) or not (leaving it); media are not nested: leaving a volume returns to none.
inline Vec3 medium_after(const Material& m, bool front, Vec3 medium) {
  if (!m.has_volume()) return medium;
  return front ? m.absorption : Vec3{0.f, 0.f, 0.f};
}


// Directions on the wrong side of the geometric surface (possible with shading normals)
// would leak light through it: the path ends there.
inline bool wrong_side(Vec3 wi, Vec3 ng, bool transmitted) {
  const float side = dot(wi, ng);
  return transmitted ? side >= 0.f : side <= 0.f;
}

// The first half of what a path does at the vertex its ray found (hit null: the ray escaped):
// emission, Russian roulette, the light sample and the BSDF sample's direction. The BSDF values
// both samples need are queued in *batch (one evaluation for a packet's lanes together);
// shade_vertex_end_light and shade_vertex_end_bsdf finish the vertex once the batch has been
// evaluated.
void shade_vertex_begin(const Scene& scene, const LightContext& lc, PathState& p,
                        const Hit* hit, uint32_t bounce, uint32_t max_depth,
                        const DiskBatch& disks, BsdfEvalBatch* batch, LightBatch* lb,
                        int lane) {
  const Vec3 d = p.d;
  SampleResult& result = p.result;
  p.alive = false;
  p.light_kind = LightSampleKind::None;
  p.bsdf_slot = -2;
  p.next_medium = p.medium;
  const bool in_medium = !is_zero(p.medium);
  if (!hit) {
    if (lc.env) {
      const Vec3 L = lc.env->eval(d);
      const float w =
          p.prev_delta ? 1.f : power_heuristic(p.prev_bsdf_pdf, lc.p_env * lc.env->pdf(d));
      result.radiance +=
          (in_medium ? p.beta * transmittance(p.medium, kInfinity) : p.beta) * L * w;
    }
    return;
  }
  if (in_medium) p.beta *= transmittance(p.medium, hit->t);
  const Vec3 wo = -d;
  const ShadingPoint sp = make_shading_point(scene, *hit, wo);
  if (bounce == 0) {
    result.albedo = sp.albedo;
    result.normal = sp.ns;
    result.depth = hit->t;
  }
  // Emission: the front (counter-clockwise) face emits, and the back of a double-sided one.
  const Material& hit_material = scene.materials()[hit->material];
  const float cos_emit = emitting_cosine(hit_material, hit->ng, wo);
  if (cos_emit > 0.f && hit_material.is_emissive()) {
    const Vec3 Le = scene.emission(hit->slot, hit->prim, hit->b1, hit->b2);
    if (p.prev_delta) {
      result.radiance += p.beta * Le;
    } else {
      // The same point could have come from light sampling at the previous vertex: convert
      // its area pdf to solid angle (pdf_A d^2 / |cos|) and weight by the power heuristic.
      const float pdf_light = (1.f - lc.p_env) * scene.lights().pdf_area(hit->slot, hit->prim) *
                              hit->t * hit->t / cos_emit;
      result.radiance += p.beta * Le * power_heuristic(p.prev_bsdf_pdf, pdf_light);
    }
  }
  if (bounce >= max_depth) return;
  const BounceSamples& u = p.u;
  // Russian roulette after 3 bounces; dividing by the survival probability keeps the
  // estimator unbiased.
  if (bounce >= 3) {
    const float q = std::min(0.95f, max_component(p.beta));
    if (!(u.get(dim::kRoulette) < q)) return;
    p.beta = p.beta / q;
  }
  const Frame frame(sp.ns);
  const Vec3 wo_local = frame.to_local(wo);
  const BsdfLobes lobes = bsdf_lobes(sp.params, wo_local);
  batch->set_vertex(lane, sp.params, lobes, wo_local, frame);
  if (lc.any && bsdf_has_smooth_part(sp.params))
    p.light_kind = sample_light(scene, lc, sp, frame, wo_local, u, batch, lb, lane, &p.light);

  BsdfSample& bs = p.bs;
  const BsdfSampleStep step =
      bsdf_sample_direction(sp.params, lobes, wo_local, disks.get(lane), u.get(dim::kLobe),
                            // Read only by the glass lobe: skipped (any value would do) without
                            // one.
                            lobes.glass > 0.f ? u.get(dim::kFresnel) : 0.f, &bs);
  if (step == BsdfSampleStep::Failed) return;
  p.ng = sp.ng;
  if (step == BsdfSampleStep::NeedsEval) {
    // The batch normalizes the direction and turns it into world space.
    p.next_o = sp.above();
    p.bsdf_slot = batch->add_sampled(lane, bs.wi);
    return;
  }
  const Vec3 wi = normalize(frame.to_world(bs.wi));
  if (wrong_side(wi, sp.ng, bs.transmitted)) return;
  p.next_o = bs.transmitted ? sp.below() : sp.above();
  p.next_d = wi;
  p.bsdf_slot = -1;
  // Only the glass lobe transmits: the one place the medium changes.
  if (bs.transmitted)
    p.next_medium = medium_after(scene.materials()[hit->material], sp.params.front, p.medium);
}

// The second half, in two parts for the lanes that need them. The light sample's shadow ray
// goes into lane `lane` of *shadow (a light sample was taken)...
void shade_vertex_end_light(PathState& p, const LightBatch& lb, RayPacket* shadow, int lane) {
  if (p.light_kind == LightSampleKind::Delta) {
    shadow->set(lane, p.light.origin, p.light.wi, p.light.tmax);
    p.nee = p.beta * p.light.contribution;
    // The shadow ray leaves on the side of wo: in the medium the path arrived through.
    if (!is_zero(p.medium)) p.nee *= transmittance(p.medium, p.light.tmax);
    ++p.result.rays;
    return;
  }
  if (!lb.ok[lane]) return;
  shadow->set(lane, Vec3(lb.o[0][lane], lb.o[1][lane], lb.o[2][lane]),
              Vec3(lb.wi[0][lane], lb.wi[1][lane], lb.wi[2][lane]), lb.tmax[lane]);
  p.nee = p.beta * Vec3(lb.contribution[0][lane], lb.contribution[1][lane],
                        lb.contribution[2][lane]);
  if (!is_zero(p.medium)) p.nee *= transmittance(p.medium, lb.tmax[lane]);
  ++p.result.rays;
}

// ... then, if p.bsdf_slot != -2, the BSDF sample gives the next ray (p.alive) unless the path
// ends here. It runs after the light part, whose throughput is the one before this vertex's
// BSDF.
void shade_vertex_end_bsdf(PathState& p, const BsdfEvalBatch& batch) {
  BsdfSample& bs = p.bs;
  if (p.bsdf_slot >= 0) {
    p.next_d = batch.world(p.bsdf_slot);
    if (wrong_side(p.next_d, p.ng, false) ||
        !bsdf_sample_finish(batch.f(p.bsdf_slot), batch.pdf(p.bsdf_slot), &bs))
      return;
  }
  if (is_zero(bs.weight)) return;
  p.beta *= bs.weight;
  p.prev_bsdf_pdf = bs.pdf;
  p.prev_delta = bs.delta;
  p.o = p.next_o;
  p.d = p.next_d;
  p.medium = p.next_medium;
  p.alive = true;
}

// Traces the live paths of paths[0, kPacketSize) together, bounce by bounce: the rays of a
// bounce go to Embree as one packet query and their shadow rays as another, and the BSDF
// evaluations of the bounce's vertices are computed together. Each path computes exactly what
// it would alone (the same sample values, the same sums in the same order); the packets only
// let Embree share traversal between similar rays (a pixel's camera rays, shadow rays towards
// the same light) and let the shading of independent paths overlap.
void trace_paths(const Scene& scene, const LightContext& lc, PathState* paths,
                 uint32_t max_depth) {
  constexpr int kFewLanes = 3;
  static_assert(BsdfEvalBatch::kLanes == kPacketSize, "a batch lane per packet lane");
  static_assert(PixelSampler::kLanes16 == kPacketSize, "a sampler lane per packet lane");
  RayPacket rays, shadow;
  Hit hits[kPacketSize];
  bool found[kPacketSize], blocked[kPacketSize];
  BsdfEvalBatch batch;
  LightBatch lights;
  DiskBatch disks;
  // A lane's rays carry its sample index (for the transparency test).
  for (int i = 0; i < kPacketSize; ++i) rays.id[i] = shadow.id[i] = paths[i].s.index;
  // Lanes are visited through bit masks of the live ones: whether a path is still alive is
  // data the branch predictor cannot learn, and a branch per lane per loop mispredicts often.
  for (uint32_t bounce = 0;; ++bounce) {
    uint32_t live = 0;
    for (int i = 0; i < kPacketSize; ++i) {
      rays.active[i] = paths[i].alive;
      shadow.active[i] = false;
      live |= uint32_t(paths[i].alive) << i;
    }
    if (!live) return;
    // This vertex's sample values, for every lane at once: the lanes are samples of one pixel
    // (one PixelSampler) with different sample indices, which the sobol sampler scrambles
    // side by side in SIMD lanes.
    uint32_t index[kPacketSize];
    for (int i = 0; i < kPacketSize; ++i) index[i] = paths[i].s.index;
    // A packet with few live lanes (after Russian roulette, from bounce 4 on, most carry one
    // or two) gets its values lane by lane: the 16-lane kernel costs the same for one lane as
    // for sixteen, about four of value8's single-sample calls (the values are the same).
    float values[8][PixelSampler::kLanes16];
    const bool batched = __builtin_popcount(live) > kFewLanes &&
                         paths[__builtin_ctz(live)].s.sampler->value8_lanes(
                             index, dim::bounce(bounce, 0), values);
    if (!batched) {  // the disk pairs are filled lane by lane below; dead lanes get zeros
      std::fill(values[dim::kBsdfU], values[dim::kBsdfU] + kPacketSize, 0.f);
      std::fill(values[dim::kBsdfV], values[dim::kBsdfV] + kPacketSize, 0.f);
    }
    for (uint32_t m = live; m; m &= m - 1) {
      const int i = __builtin_ctz(m);
      PathState& p = paths[i];
      if (batched) {
        p.u.assign(p.s, bounce, values, i);
      } else {
        p.u.reset(p.s, bounce);
        const Point2 u = p.u.get2(dim::kBsdfU);
        values[dim::kBsdfU][i] = u.x;
        values[dim::kBsdfV][i] = u.y;
      }
      rays.set(i, p.o, p.d, kInfinity);
      ++p.result.rays;
    }
    // The camera rays see what lies between the camera's clipping planes; later rays the
    // whole of (0, infinity).
    if (bounce == 0)
      for (int i = 0; i < kPacketSize; ++i) {
        rays.tnear[i] = paths[i].tmin;
        rays.tfar[i] = paths[i].tmax;
      }
    disks.compute(values[dim::kBsdfU], values[dim::kBsdfV], live);
    // The lanes are samples of one pixel: one transparency key per query for all of them.
    const PixelSampler& pixel = *paths[__builtin_ctz(live)].s.sampler;
    const uint64_t path_query =
        scene.has_transparency()
            ? ray_query(pixel.seed(), pixel.pixel(), bounce, RayKind::Path)
            : 0;
    // The camera rays of a pixel's samples are alike: Embree's coherent traversal (about 3%
    // more samples/s on the Cornell box). Later bounces scatter, where it would be far slower.
    scene.intersect(rays, hits, found, bounce == 0, path_query);
    if (bounce == 0) std::fill(rays.tnear, rays.tnear + kPacketSize, 0.f);
    batch.clear();
    lights.clear();
    for (uint32_t m = live; m; m &= m - 1) {
      const int i = __builtin_ctz(m);
      shade_vertex_begin(scene, lc, paths[i], found[i] ? &hits[i] : nullptr, bounce, max_depth,
                         disks, &batch, &lights, i);
    }
    lights.finish_geometry(&batch);
    batch.evaluate();
    lights.finish_contributions(batch);
    uint32_t with_light = 0, going_on = 0;
    for (int i = 0; i < kPacketSize; ++i) {
      with_light |= uint32_t(paths[i].light_kind != LightSampleKind::None) << i;
      going_on |= uint32_t(paths[i].bsdf_slot != -2) << i;
    }
    for (uint32_t m = with_light & live; m; m &= m - 1) {
      const int i = __builtin_ctz(m);
      shade_vertex_end_light(paths[i], lights, &shadow, i);
    }
    for (uint32_t m = going_on & live; m; m &= m - 1)
      shade_vertex_end_bsdf(paths[__builtin_ctz(m)], batch);
    uint32_t shadowed = 0;
    for (int i = 0; i < kPacketSize; ++i) shadowed |= uint32_t(shadow.active[i]) << i;
    if (!shadowed) continue;
    scene.occluded(shadow, blocked,
                   scene.has_transparency()
                       ? ray_query(pixel.seed(), pixel.pixel(), bounce, RayKind::Shadow)
                       : 0);
    for (; shadowed; shadowed &= shadowed - 1) {
      PathState& p = paths[__builtin_ctz(shadowed)];
      if (!blocked[__builtin_ctz(shadowed)]) p.result.radiance += p.nee;
    }
  }
}

SampleResult trace_ao(const Scene& scene, const SampleStream& s, Vec3 o, Vec3 d, float tmin,
                      float tmax) {
  SampleResult result;
  Hit hit;
  ++result.rays;
  const uint64_t seed = s.sampler->seed(), pixel = s.sampler->pixel();
  if (!scene.intersect(o, d, tmax, &hit, ray_query(seed, pixel, 0, RayKind::Path), s.index,
                       tmin))
    return result;  // background = 0
  const ShadingPoint sp = make_shading_point(scene, hit, -d);
  result.albedo = sp.albedo;
  result.normal = sp.ns;
  result.depth = hit.t;
  const Vec3 local = sample_cosine_hemisphere(s.get2(dim::bounce(0, dim::kBsdfU)));
  const Vec3 wi = normalize(Frame(sp.ns).to_world(local));
  if (dot(wi, sp.ng) <= 0.f) return result;  // below the surface: blocked by it
  const float radius = 0.1f * scene.diagonal();
  ++result.rays;
  const float v =
      scene.occluded(sp.above(), wi, radius, ray_query(seed, pixel, 0, RayKind::Shadow), s.index)
          ? 0.f
          : 1.f;
  result.radiance = Vec3(v, v, v);
  return result;
}

// What every sample of a render shares: computed once per render_rect.
struct TraceContext {
  LightContext lights;
  Camera::Raster raster;
  TraceContext(const Scene& scene, const RenderSettings& settings)
      : lights(light_context(scene, settings)),
        raster(scene.camera().raster(settings.width, settings.height)) {}
};

// Sample `index` of pixel (x, y) up to its camera ray: a path ready for its first bounce.
// camera_dims: the sample's values of dimensions kPixelX .. kLensV if already computed, or null.
PathState start_path(const TraceContext& ctx, const Scene& scene, const RenderSettings& settings,
                     const PixelSampler& sampler, uint32_t x, uint32_t y, uint32_t index,
                     const float* camera_dims = nullptr) {
  PathState p;
  p.s = SampleStream{&sampler, index};
  // Box filter: the sample position is uniform inside the pixel.
  const Point2 jitter = camera_dims ? Point2{camera_dims[dim::kPixelX], camera_dims[dim::kPixelY]}
                                    : p.s.get2(dim::kPixelX);
  const float px = float(x) + jitter.x;
  const float py = float(y) + jitter.y;
  const Camera& cam = scene.camera();
  p.o = ctx.raster.origin(px, py);
  float per_axial;
  p.d = ctx.raster.direction(px, py, &per_axial);
  if (settings.aperture_radius > 0.f) {
    // Thin lens: the pinhole ray through the pixel meets the plane of focus (at
    // focus_distance along the viewing axis) at p_focus; the lens ray starts at a uniform
    // point of the aperture disk and aims at p_focus.
    const Point2 lens = sample_concentric_disk(
        camera_dims ? Point2{camera_dims[dim::kLensU], camera_dims[dim::kLensV]}
                    : p.s.get2(dim::kLensU));
    const Vec3 p_focus = p.o + p.d * (settings.focus_distance / dot(p.d, cam.forward));
    p.o = p.o + (cam.right * lens.x + cam.up * lens.y) * settings.aperture_radius;
    p.d = normalize(p_focus - p.o);
    per_axial = 1.f / dot(p.d, cam.forward);
  }
  // The clipping planes are distances along the viewing axis.
  p.tmin = cam.znear * per_axial;
  p.tmax = cam.zfar * per_axial;
  p.alive = true;
  return p;
}

uint32_t path_max_depth(const RenderSettings& settings) {
  return settings.integrator == IntegratorType::Direct ? std::min<uint32_t>(settings.max_depth, 1u)
                                                       : settings.max_depth;
}

// Samples [first, first + n) of pixel (x, y), n <= kPacketSize, into out[0, n).
void trace_samples(const TraceContext& ctx, const Scene& scene, const RenderSettings& settings,
                   const PixelSampler& sampler, uint32_t x, uint32_t y, uint32_t first,
                   uint32_t n, SampleResult* out) {
  if (settings.integrator == IntegratorType::AmbientOcclusion) {
    for (uint32_t k = 0; k < n; ++k) {
      const PathState p = start_path(ctx, scene, settings, sampler, x, y, first + k);
      out[k] = trace_ao(scene, p.s, p.o, p.d, p.tmin, p.tmax);
    }
    return;
  }
  // The camera dimensions of all lanes at once where the sampler can (sobol).
  uint32_t index[kPacketSize];
  for (uint32_t k = 0; k < uint32_t(kPacketSize); ++k) index[k] = first + k;
  float values[8][PixelSampler::kLanes16];
  const bool batched = sampler.value8_lanes(index, dim::kPixelX, values);
  PathState paths[kPacketSize];
  for (uint32_t k = 0; k < n; ++k) {
    float camera_dims[4];
    for (uint32_t d = 0; d < 4; ++d) camera_dims[d] = values[dim::kPixelX + d][k];
    paths[k] = start_path(ctx, scene, settings, sampler, x, y, first + k,
                          batched ? camera_dims : nullptr);
  }
  trace_paths(scene, ctx.lights, paths, path_max_depth(settings));
  for (uint32_t k = 0; k < n; ++k) out[k] = paths[k].result;
}

// ---- The reference: one path at a time, with the scalar BSDF and light code.

// sample_light with the BSDF evaluated on the spot: false if the sample contributes nothing
// whatever the visibility, otherwise *out holds the shadow ray and the unoccluded
// contribution.
bool reference_light_sample(const Scene& scene, const LightContext& lc, const ShadingPoint& sp,
                            const BsdfLobes& lobes, const Frame& frame, Vec3 wo_local,
                            const BounceSamples& s, LightRay* out) {
  float u_sel = s.get(dim::kLightSelect);
  const Point2 u = s.get2(dim::kLightU);
  const Vec3 origin = sp.above();
  out->origin = origin;
  if (lc.env && u_sel < lc.p_env) {
    float pdf = 0.f;
    const Vec3 wi = lc.env->sample(u, &pdf);
    pdf *= lc.p_env;
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
  if (lights.empty()) return false;
  const float p_scene = 1.f - lc.p_env;
  u_sel = std::min(0.99999994f, (u_sel - lc.p_env) / p_scene);
  const LightSample ls = lights.sample(u_sel, u.x, u.y);
  if (ls.punctual >= 0) {
    const PunctualLight& light = lights.punctual()[size_t(ls.punctual)];
    const float pdf = ls.pdf_area * p_scene;
    Vec3 wi, Li;
    float tmax;
    if (light.type == PunctualType::Directional) {
      wi = -light.direction;
      Li = light.intensity;
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
    if (is_zero(Li) || dot(wi, sp.ng) <= 0.f) return false;
    const Vec3 f = bsdf_eval_cos(sp.params, wo_local, frame.to_local(wi));
    if (is_zero(f)) return false;
    out->wi = wi;
    out->tmax = tmax;
    out->contribution = f * Li * (1.f / pdf);
    return true;
  }
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
  const float pdf_light = p_scene * ls.pdf_area * dist2 / cos_light;
  const float tmax = dist * (1.f - 1e-4f) - ray_epsilon(ls.p);
  if (!(tmax > 0.f)) return false;
  const float w = power_heuristic(pdf_light, bsdf_pdf_wi);
  const Vec3 Le = scene.covered_emission(ls.slot, ls.prim, ls.b1, ls.b2);
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
    return trace_ao(scene, p.s, p.o, p.d, p.tmin, p.tmax);
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
    ++result.rays;
    scene.intersect(ray, hits, found, false, ray_query(seed, pixel, bounce, RayKind::Path));
    const Vec3 wo = -p.d;
    if (!found[0]) {
      if (lc.env) {
        const float w =
            p.prev_delta ? 1.f : power_heuristic(p.prev_bsdf_pdf, lc.p_env * lc.env->pdf(p.d));
        const Vec3 beta =
            is_zero(p.medium) ? p.beta : p.beta * transmittance(p.medium, kInfinity);
        result.radiance += beta * lc.env->eval(p.d) * w;
      }
      return result;
    }
    const Hit& hit = hits[0];
    if (!is_zero(p.medium)) p.beta *= transmittance(p.medium, hit.t);
    const ShadingPoint sp = make_shading_point(scene, hit, wo);
    if (bounce == 0) {
      result.albedo = sp.albedo;
      result.normal = sp.ns;
      result.depth = hit.t;
    }
    const Material& hit_material = scene.materials()[hit.material];
    const float cos_emit = emitting_cosine(hit_material, hit.ng, wo);
    if (cos_emit > 0.f && hit_material.is_emissive()) {
      const Vec3 Le = scene.emission(hit.slot, hit.prim, hit.b1, hit.b2);
      if (p.prev_delta) {
        result.radiance += p.beta * Le;
      } else {
        const float pdf_light = (1.f - lc.p_env) * scene.lights().pdf_area(hit.slot, hit.prim) *
                                hit.t * hit.t / cos_emit;
        result.radiance += p.beta * Le * power_heuristic(p.prev_bsdf_pdf, pdf_light);
      }
    }
    if (bounce >= max_depth) return result;
    if (bounce >= 3) {
      const float q = std::min(0.95f, max_component(p.beta));
      if (!(u.get(dim::kRoulette) < q)) return result;
      p.beta = p.beta / q;
    }
    const Frame frame(sp.ns);
    const Vec3 wo_local = frame.to_local(wo);
    const BsdfLobes lobes = bsdf_lobes(sp.params, wo_local);
    LightRay light;
    if (lc.any && bsdf_has_smooth_part(sp.params) &&
        reference_light_sample(scene, lc, sp, lobes, frame, wo_local, u, &light)) {
      Vec3 nee = p.beta * light.contribution;
      if (!is_zero(p.medium)) nee *= transmittance(p.medium, light.tmax);
      shadow.set(0, light.origin, light.wi, light.tmax);
      ++result.rays;
      scene.occluded(shadow, blocked, ray_query(seed, pixel, bounce, RayKind::Shadow));
      if (!blocked[0]) result.radiance += nee;
    }
    BsdfSample bs;
    if (!bsdf_sample(sp.params, lobes, wo_local, u.get2(dim::kBsdfU), u.get(dim::kLobe),
                     lobes.glass > 0.f ? u.get(dim::kFresnel) : 0.f, &bs))
      return result;
    const Vec3 wi = normalize(frame.to_world(bs.wi));
    if (wrong_side(wi, sp.ng, bs.transmitted)) return result;
    if (is_zero(bs.weight)) return result;
    p.beta *= bs.weight;
    p.prev_bsdf_pdf = bs.pdf;
    p.prev_delta = bs.delta;
    p.o = bs.transmitted ? sp.below() : sp.above();
    p.d = wi;
    if (bs.transmitted)
      p.medium = medium_after(scene.materials()[hit.material], sp.params.front, p.medium);
  }
}

SampleResult trace_sample(const Scene& scene, const RenderSettings& settings,
                          const Sampler& sampler, uint32_t x, uint32_t y, uint32_t index) {
  const PixelSampler pixel_sampler(sampler, uint64_t(y) * settings.width + x);
  return trace_sample(scene, settings, pixel_sampler, x, y, index);
}

SampleResult trace_sample(const Scene& scene, const RenderSettings& settings,
                          const PixelSampler& sampler, uint32_t x, uint32_t y, uint32_t index) {
  SampleResult result;
  trace_samples(TraceContext(scene, settings), scene, settings, sampler, x, y, index, 1, &result);
  return result;
}

std::string validate_render_request(const RenderSettings& settings, PixelRect rect,
                                    uint64_t start, uint64_t count) {
  if (settings.width == 0 || settings.height == 0) return "image width and height must be > 0";
  if (uint64_t(settings.width) * settings.height > (uint64_t(1) << 32))
    return "image has more than 2^32 pixels";
  if (rect.width == 0 || rect.height == 0) return "tile rect is empty";
  if (uint64_t(rect.x0) + rect.width > settings.width ||
      uint64_t(rect.y0) + rect.height > settings.height)
    return "tile rect lies outside the " + std::to_string(settings.width) + "x" +
           std::to_string(settings.height) + " image";
  if (!(settings.aperture_radius >= 0.f) || !std::isfinite(settings.aperture_radius))
    return "aperture_radius must be finite and >= 0";
  if (settings.aperture_radius > 0.f &&
      !(settings.focus_distance > 0.f && std::isfinite(settings.focus_distance)))
    return "focus_distance must be finite and > 0 when aperture_radius > 0";
  if (count == 0) return "sample count must be > 0";
  if (count > kMaxSamplesPerPixel || start > kMaxSamplesPerPixel ||
      start + count > kMaxSamplesPerPixel)
    return "sample indices beyond 2^31 are not supported";
  return {};
}

bool render_rect(const Scene& scene, const RenderSettings& settings, PixelRect rect,
                 uint64_t start, uint32_t count, TileBuffer* out,
                 const std::atomic<bool>* cancel) {
  out->reset(rect, start, count);
  const Sampler sampler(settings.sampler, settings.seed);
  const TraceContext ctx(scene, settings);
  for (uint32_t ty = 0; ty < rect.height; ++ty) {
    for (uint32_t tx = 0; tx < rect.width; ++tx) {
      // Checked every pixel, so that a cancel (or the worker's time budget) stops even a
      // render whose pixels are very costly within a second.
      if (cancel && cancel->load(std::memory_order_relaxed)) return false;
      const size_t i = size_t(ty) * rect.width + tx;
      double sum[3] = {0.0, 0.0, 0.0};
      RunningStats luminance_stats;
      float albedo[3] = {0.f, 0.f, 0.f}, normal[3] = {0.f, 0.f, 0.f};
      float depth = 0.f;
      const PixelSampler pixel_sampler(sampler, uint64_t(rect.y0 + ty) * settings.width +
                                                    (rect.x0 + tx));
      SampleResult results[kPacketSize];
      for (uint32_t k = 0; k < count; ++k) {
        // The pixel's samples go through the path tracer kPacketSize at a time.
        const uint32_t lane = k % kPacketSize;
        if (lane == 0)
          trace_samples(ctx, scene, settings, pixel_sampler, rect.x0 + tx, rect.y0 + ty,
                        uint32_t(start + k), std::min<uint32_t>(kPacketSize, count - k), results);
        const SampleResult& r = results[lane];
        out->rays += r.rays;
        Vec3 L = r.radiance;
        if (!is_finite(L)) {
          L = Vec3(0.f, 0.f, 0.f);  // counted, recorded as zero radiance
          ++out->nonfinite_samples;
        }
        for (int c = 0; c < 3; ++c) {
          sum[c] += double(L[c]);
          albedo[c] += r.albedo[c];
          normal[c] += r.normal[c];
        }
        depth += r.depth;
        // Welford's update of the luminance mean and M2.
        luminance_stats.add(0.2126 * double(L.x) + 0.7152 * double(L.y) + 0.0722 * double(L.z));
      }
      for (int c = 0; c < 3; ++c) {
        out->rgb_sum[3 * i + size_t(c)] = sum[c];
        out->albedo_sum[3 * i + size_t(c)] = albedo[c];
        out->normal_sum[3 * i + size_t(c)] = normal[c];
      }
      out->luminance_m2[i] = luminance_stats.m2;
      out->depth_sum[i] = depth;
    }
  }
  return true;
}

}  // namespace rf
