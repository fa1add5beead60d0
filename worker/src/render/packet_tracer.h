// The packet path tracer (internal to src/render): a pixel's samples traced sixteen at a time,
// bounce by bounce, each path computing exactly what it would alone. What it shares with the
// reference (src/render/reference.cpp) and the tile loop (tile_accumulator.cpp): the state of a
// path between bounces, the per-render context, the camera ray of a sample.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

#include "render/guiding.h"
#include "render/integrators.h"
#include "render/light_groups.h"
#include "render/light_sampling.h"
#include "render/shading.h"
#include "sampling/samplers.h"
#include "sampling/spectrum.h"
#include "scene/materials.h"
#include "scene/scene.h"

namespace rf {

// One sample's path while it is traced in a packet: its state between bounces.
struct PathState {
  SampleStream s{nullptr, 0};
  SampleResult result;  // radiance accumulates here
  Vec3 o, d;            // the ray of the next bounce
  float tmin = 0.f, tmax = kInfinity;  // the camera ray's range (its clipping planes)
  // The camera ray's distance per unit distance along the camera's viewing axis
  // (1 / dot(d, forward); 1 for an orthographic camera): the first hit's planar depth is its
  // distance divided by this.
  float per_axial = 1.f;
  float time = 0.f;  // motion blur: where in the shutter every ray of the path is, in [0, 1]
  Vec3 beta{1.f, 1.f, 1.f};   // path throughput: product of f cos / pdf so far
  // The product of the eta^2 of the refractions so far (BsdfSample::eta2): beta times it is
  // the throughput without the radiance scaling at the interfaces, what Russian roulette
  // weighs (roulette_survival).
  float eta_scale = 1.f;
  float wavelength = 0.f;     // nm, from the first dispersive vertex on (0: none yet)
  float prev_bsdf_pdf = 0.f;  // solid-angle pdf of the direction d (bounce > 0)
  bool prev_delta = true;     // camera rays and delta bounces: no light sampling could
                              // have produced this direction, so emission gets weight 1
  bool alive = false;
  // Where the previous vertex's light sampling looked from (its origin, geometric normal and
  // the sum of its light weights): the light pdf of the MIS weight when d finds a light.
  Vec3 sel_o, sel_ng;
  float sel_total = 0.f;
  bool sel_two_sided = false;  // its weights were two-sided (has_through_lobe)
  BounceSamples u;  // this bounce's sample values
  Vec3 nee;         // this bounce's light sample, added if its shadow ray is not blocked
  // Between the halves of a vertex's shading (shade_vertex_begin, then shade_vertex_end_light
  // and shade_vertex_end_bsdf):
  LightSampleKind light_kind = LightSampleKind::None;
  LightRay light;          // light_kind Delta
  Vec3 light_medium;       // the medium its shadow ray travels in
  int bsdf_slot = -2;      // BsdfEvalBatch slot of the sampled direction's f and pdf; -1: the
                           // sample (glass) is complete; -2: the path ends at this vertex
  BsdfSample bs;
  Vec3 next_o, next_d;     // the next ray if the path goes on (next_d from the batch if pending)
  Vec3 ng;                 // the vertex's geometric normal on the side of wo
  // KHR_materials_volume: the absorption coefficient of the medium the ray travels in (0:
  // none), and the one the next ray will (a transmission into or out of a volume changes it).
  Vec3 medium, next_medium;
};

// Russian roulette's probability that a path with throughput beta goes on, its refractions
// having scaled its radiance by 1 / eta_scale (PathState::eta_scale):
// min(0.95, sqrt(max(beta) eta_scale)).
// - eta_scale: inside glass a path carries radiance scaled by 1 / eta^2 (0.44 at ior 1.5),
//   which its way out undoes; on beta alone the roulette would end the paths inside glass
//   more than twice as often as those outside (pbrt-v4's etaScale, Mitsuba 3's eta^2).
// - the square root (Cycles' rule): a path of low throughput goes on more often than in
//   proportion to it, so that where what follows is bright (a caustic met after a rough
//   bounce) the survivors' weights 1 / q stay small.
// Each measured on the realistic suite: docs/parity.md, "Russian roulette against Cycles'".
inline float roulette_survival(Vec3 beta, float eta_scale) {
  return std::min(0.95f, std::sqrt(max_component(beta) * eta_scale));
}

// Path guiding (render/guiding.h) at a path's current vertex, kept beside its PathState only
// when the render is guided (so that an unguided path's state keeps its size): the
// probability alpha with which its direction came from the guide (0: not guided), the guide's
// distribution there, and the guide's density of the sampled direction if the guide sampled
// it (-1: the BSDF did; its guide density is looked up once the direction is known).
struct PathGuide {
  float frac = 0.f;
  uint32_t dist = 0;
  float pdf = -1.f;
  float bsdf_pdf = 0.f;  // the BSDF's own density of the sampled direction (for training)
};

// Path guiding's training (train_guide, render/guiding.h): the vertices of a path being traced
// that left a surface in a direction sampled with a density (not a delta lobe), with what the
// path had gathered by then, so that once the path ends each vertex's incident radiance is
// what it gathered after, divided by the throughput after the vertex.
struct PathRecorder {
  static constexpr int kMaxVertices = 16;  // deeper vertices are not recorded
  struct Vertex {
    Vec3 p, d;
    Vec3 beta;      // throughput after the vertex's BSDF sample
    Vec3 gathered;  // the path's radiance when the vertex's own light sample was in
    float pdf = 0.f, bsdf_pdf = 0.f;  // GuideRecord's
    float cos = 0.f;  // |cos| of d to the vertex's geometric normal
  };
  Vertex v[kMaxVertices];
  int n = 0;
  // Appends the records of the finished path whose radiance is `radiance` to *out.
  void finish(Vec3 radiance, std::vector<GuideRecord>* out) const;
};

// Where a contribution to a sample's radiance comes from: the environment a ray escaped to,
// what the surface a ray hit emits (emission, or an unlit surface's colour), or the light
// sample (next-event estimate) of the vertex a ray left. Every contribution goes through
// add_radiance with it, which is where an output attributing the radiance to its sources
// (the `lobes` rows, the light groups) learns of it.
enum class RadianceSource : uint8_t { Environment, Surface, LightSample };

// The `lobes` rows of a path being traced (LobeValues, integrators.h), kept beside its
// PathState only when a lobe row is asked for. A contribution is attributed by the path's
// first scattering vertex (its camera ray's hit, bounce 0):
// - found by the camera ray itself: the environment to `background`, the hit's emission (or
//   unlit colour) to `emission`;
// - otherwise it is shared among the first vertex's diffuse, glossy and transmission lobes
//   (LobeCategory, scene/materials.h), to their `direct` rows if it is light reached in one
//   bounce from the first vertex (its light sample, or found by the ray leaving it, bounce 1),
//   to their `indirect` rows otherwise (light samples of later vertices, anything found from
//   bounce 2 on).
// The shares make each row an unbiased estimate of its own integral: the first vertex's light
// sample f(wl) L / pdf is shared by f_k(wl) / f(wl), the parts of f by category at its
// direction (bsdf_eval_lobes, and through_eval_lobes for a punctual light); a path whose
// first BSDF sample came from a sampled-only lobe (the glass lobe: reflected glossy,
// transmitted transmission; the diffuse BTDF: diffuse) gives everything it brings later to that
// category; one from the evaluated lobes is shared by f_k(wi) / f(wi) at the sampled wi, so
// that the expected share of category k is the integral of f_k L. The shares of a channel sum
// to 1 (up to rounding), so the rows sum to the radiance.
struct PathLobes {
  LobeValues values;
  // The shares (per channel, by LobeCategory) of what the path brings after its first vertex,
  // and of that vertex's light sample.
  Vec3 path_share[kLobeCategories];
  Vec3 light_share[kLobeCategories];
  // The first vertex, for its shares: its BSDF (after dispersion), lobes, wo and frame.
  BsdfParams params;
  BsdfLobes lobes;
  Vec3 wo;
  Frame frame{Vec3(0.f, 0.f, 1.f)};

  void add(Vec3 c, uint32_t bounce, RadianceSource source) {
    if (bounce == 0 && source != RadianceSource::LightSample) {
      values.row[source == RadianceSource::Environment ? kBackgroundRow : kEmissionRow] += c;
      return;
    }
    const bool light_sample = source == RadianceSource::LightSample;
    const bool direct = light_sample ? bounce == 0 : bounce == 1;
    const Vec3* share = light_sample && bounce == 0 ? light_share : path_share;
    for (int k = 0; k < kLobeCategories; ++k)
      values.row[2 * k + (direct ? 0 : 1)] += c * share[k];
  }
  // The first vertex's shares of the category parts f[k] (out: share[k] = f[k] / their sum,
  // per channel). Where a channel's parts sum to 0 (or are not finite) the sums over channels
  // share it, and failing those the diffuse lobes take it all: the shares always sum to 1.
  static void shares(const Vec3 f[kLobeCategories], Vec3 share[kLobeCategories]);

 private:
  // Rows by their place in LobeValues: category k's direct row is 2k, its indirect 2k + 1.
  static constexpr int kEmissionRow = 6, kBackgroundRow = 7;
};

// The light groups of a path being traced (render/light_groups.h), kept beside its PathState
// only when the LightGroups row is asked for: its radiance by group, and the group of the
// light its current vertex sampled (LightGroupMap::light), which the light sample's
// contribution goes to once its shadow ray is known to be clear.
struct PathGroups {
  const LightGroupMap* map = nullptr;
  Vec3* values = nullptr;  // map->count() of them
  uint32_t light_group = 0;
};

// Adds contribution c to the path's radiance (its only way there), and with the lobe rows on
// (lobes not null) to them; bounce: the vertex whose ray found it, or whose light sample it is.
// With the light groups on (groups not null), c goes to group `group` (the group of its
// source, which the caller finds only then).
inline void add_radiance(PathState& p, PathLobes* lobes, Vec3 c, uint32_t bounce,
                         RadianceSource source, PathGroups* groups = nullptr,
                         uint32_t group = 0) {
  p.result.radiance += c;
  if (lobes) lobes->add(c, bounce, source);
  if (groups) groups->values[group] += c;
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
                     const float* camera_dims = nullptr);

// KHR_materials_dispersion: at the path's first dispersive vertex, the wavelength it carries
// from then on (this bounce's dimension kWavelength) and its channel weights multiplied into
// the throughput (sampling/spectrum.h: their mean is 1); at every dispersive vertex, the
// material's index of refraction at that wavelength. Called after emission and Russian
// roulette, before the vertex's lobes.
inline void disperse(PathState& p, const BounceSamples& u, BsdfParams* params) {
  if (!(params->dispersion > 0.f)) return;
  if (p.wavelength == 0.f) {
    p.wavelength = sample_visible_wavelength(u.get(dim::kWavelength));
    p.beta *= wavelength_weight(p.wavelength);
  }
  params->ior = dispersion_ior(params->ior, params->dispersion, p.wavelength);
}

// The first hit of a sample (its camera ray's, bounce 0) into *r, for every integrator alike:
// the albedo and normal, the hit distance, the planar depth and world position of the Depth
// and Position rows, the glTF node and material of the Instance and Material rows (plus
// one; kNoNode + 1 and -1 + 1 are 0), and the surface point the Motion row follows.
// per_axial: PathState::per_axial of the camera ray. The ids are looked up here, once a
// sample, rather than by every ray query's hit record.
inline void record_first_hit(const Scene& scene, const ShadingPoint& sp, const Hit& hit,
                             float per_axial, SampleResult* r) {
  static_assert(kNoNode + 1 == 0, "a hit without a node is the Instance row's 0");
  r->albedo = sp.albedo;
  r->normal = sp.ns;
  r->depth = hit.t;
  r->z = hit.t / per_axial;
  r->position = hit.p;
  r->instance_id = scene.node(hit.slot, hit.prim) + 1;
  r->material_id = uint32_t(scene.materials()[hit.material].gltf_index + 1);
  r->slot = hit.slot;
  r->prim = hit.prim;
  r->b1 = hit.b1;
  r->b2 = hit.b2;
}

// The number of bounces of a path: max_depth, or at most 1 for the direct integrator.
uint32_t path_max_depth(const RenderSettings& settings);

// Ambient occlusion of one sample whose path start_path made: its camera ray o + t d, t in
// (tmin, tmax), at its time in the shutter (src/render/ambient_occlusion.cpp).
SampleResult trace_ao(const Scene& scene, const PathState& camera);

// Samples [first, first + n) of pixel (x, y), n <= kPacketSize, into out[0, n), their lobe
// rows into lobes[0, n) unless lobes is null, and their radiance by light group into
// group_values[k * groups->count() + g] (sample first + k, group g) unless groups is null (the
// rows are off; the radiance and everything else is the same bit for bit either way). The ao
// integrator's lobe rows and light groups are 0. Path guiding's training records of the samples
// are appended to *guide_records unless it is null (render/guiding.h). With settings.guide set,
// the paths are guided by it.
void trace_samples(const TraceContext& ctx, const Scene& scene, const RenderSettings& settings,
                   const PixelSampler& sampler, uint32_t x, uint32_t y, uint32_t first,
                   uint32_t n, SampleResult* out, LobeValues* lobes = nullptr,
                   const LightGroupMap* groups = nullptr, Vec3* group_values = nullptr,
                   std::vector<GuideRecord>* guide_records = nullptr);

}  // namespace rf
