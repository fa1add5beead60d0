// The packet path tracer (internal to src/render): a pixel's samples traced sixteen at a time,
// bounce by bounce, each path computing exactly what it would alone. What it shares with the
// reference (src/render/reference.cpp) and the tile loop (tile_accumulator.cpp): the state of a
// path between bounces, the per-render context, the camera ray of a sample.
#pragma once

#include <cstdint>

#include "render/integrators.h"
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

// Samples [first, first + n) of pixel (x, y), n <= kPacketSize, into out[0, n).
void trace_samples(const TraceContext& ctx, const Scene& scene, const RenderSettings& settings,
                   const PixelSampler& sampler, uint32_t x, uint32_t y, uint32_t first,
                   uint32_t n, SampleResult* out);

}  // namespace rf
