// Next-event estimation (internal to src/render): the choice between the scene's lights and
// the environment, the packet tracer's light samples (sample_light, finished four lanes at a
// time by a LightBatch once the BSDF values are known) and the shadow ray they wait for.
#pragma once

#include <cstdint>

#include "render/integrators.h"
#include "render/shading.h"
#include "sampling/samplers.h"
#include "scene/materials.h"
#include "scene/scene.h"

namespace rf {

// Light selection per shading point between the scene's light clusters (LightSet::importance:
// an estimate of the irradiance each sends to the point, 0 only where it cannot contribute)
// and the environment, whose importance is pi * its mean luminance (the irradiance an
// environment of that mean radiance gives an unoccluded surface). Entries 0 .. clusters - 1
// are the scene's clusters, entry `clusters` the environment. With a single entry (one
// cluster and no environment, or the environment alone) it is chosen with probability 1 and
// no weights are computed.
struct LightContext {
  const Environment* env = nullptr;
  const LightSet* lights = nullptr;
  uint32_t clusters = 0;   // the scene's light clusters
  float env_weight = 0.f;  // the environment's importance (0: none)
  bool single = false;     // one entry only
  bool any = false;
  uint32_t entries() const { return clusters + (env ? 1u : 0u); }
};
constexpr uint32_t kMaxLightEntries = LightSet::kMaxClusters + 1;

LightContext light_context(const Scene& scene, const RenderSettings& settings);

// The entries' weights at a light-sampling origin o with geometric normal ng into
// w[0, lc.entries()) (not computed when lc.single); their sum (1 when lc.single). two_sided
// (a vertex with a through lobe, has_through_lobe, which punctual lights behind the surface
// reach): a cluster weighs the larger of its importances on either side of ng's plane.
float light_weights(const LightContext& lc, Vec3 o, Vec3 ng, float* w, bool two_sided = false);
// The probability with which light sampling at (o, ng), whose weights summed to total, chose
// entry e (a cluster, or lc.clusters for the environment): what MIS needs when a BSDF-sampled
// ray finds that light.
float light_entry_pmf(const LightContext& lc, uint32_t e, Vec3 o, Vec3 ng, float total,
                      bool two_sided = false);
// The area density with which light sampling at (o, ng) (weights summing to total) samples a
// point on triangle prim of slot, seen along direction d from o (0 if light sampling cannot
// produce it: not a light, or d below ng's plane, where light samples are dropped).
float light_pdf_area(const LightContext& lc, Vec3 o, Vec3 ng, float total, uint32_t slot,
                     uint32_t prim, Vec3 d, bool two_sided = false);
// The probability of choosing the environment at (o, ng) for direction d likewise.
float light_env_pmf(const LightContext& lc, Vec3 o, Vec3 ng, float total, Vec3 d,
                    bool two_sided = false);

// A light sample waiting for its shadow ray: it contributes `contribution` if nothing blocks
// origin + t wi for t in (0, tmax). In the packet tracer only delta lights' samples are held
// so (the others wait in a LightBatch); the scalar reference holds every light's.
struct LightRay {
  Vec3 origin, wi;
  float tmax = 0.f;
  Vec3 contribution;
  // Through the surface (a punctual light behind a rough glass lobe or a diffuse BTDF): the
  // shadow ray leaves below it, in the medium a transmission enters.
  bool through = false;
};

// The sample of punctual light `light` chosen with probability p_entry at sp (the caller's
// frame and wo in it): false if it contributes nothing whatever the visibility, otherwise
// *out holds the shadow ray and the unoccluded contribution f cos Li / p_entry, with f the
// BSDF's value above the surface and the through lobes' (through_eval_cos) on either side.
bool punctual_light_sample(const PunctualLight& light, float p_entry, const ShadingPoint& sp,
                           const Frame& frame, Vec3 wo_local, LightRay* out);

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
  // vertex; the selection probability times pdf_area (area lights).
  alignas(16) float o[3][kLanes] = {}, lp[3][kLanes] = {}, ln[3][kLanes] = {};
  alignas(16) float ng[3][kLanes] = {}, eps[kLanes] = {}, k[kLanes] = {};
  // Radiance arriving along wi; solid-angle pdf of wi; the shadow ray (set for the environment,
  // computed for area lights) and whether the sample is kept.
  alignas(16) float radiance[3][kLanes] = {}, pdf_light[kLanes] = {};
  alignas(16) float wi[3][kLanes] = {}, tmax[kLanes] = {};
  alignas(16) int32_t ok[kLanes] = {};
  alignas(16) float contribution[3][kLanes] = {};
  // Path guiding: the lanes whose vertex is guided, with the guide's share alpha and its
  // density of wi: their MIS weight uses the density alpha p_guide + (1 - alpha) p_bsdf with
  // which the vertex samples directions (render/guiding.h).
  uint32_t guided = 0;
  alignas(16) float guide_frac[kLanes] = {}, guide_pdf[kLanes] = {};

  void clear() { area = waiting = guided = 0; }
  // The area-light lanes' shadow rays, pdfs and tests, and their directions queued in *batch.
  void finish_geometry(BsdfEvalBatch* batch);
  // After batch->evaluate(): the waiting lanes' contributions, and ok cleared where f = 0.
  void finish_contributions(const BsdfEvalBatch& batch);
};

// What sample_light produced.
enum class LightSampleKind {
  None,     // contributes nothing whatever the visibility: no shadow ray
  Delta,    // a punctual light: *out holds the shadow ray and the unoccluded contribution
  Waiting,  // a light with a pdf: in the LightBatch, waiting for its BSDF value
};

// A light (or the environment) chosen with u_select from the weights w (summing to total):
// its entry, its probability, and u_select rescaled to [0, 1) within the entry. False if no
// entry has weight.
bool choose_light(const LightContext& lc, const float* w, float total, float u_select,
                  uint32_t* entry, float* pmf, float* u_rest);

// Which light a light sample is of, for the light groups (render/light_groups.h): the
// environment, punctual light `punctual` of the scene's LightSet, or else the emissive
// triangle prim of geometry slot `slot`.
struct LightSampleSource {
  bool environment = false;
  int punctual = -1;
  uint32_t slot = 0, prim = 0;
};

// Next-event estimation: one light (or the environment) chosen by the weights w at sp.above()
// (light_weights, summing to total), its contribution f cos L / pdf, MIS-weighted against
// BSDF sampling with the power heuristic unless the light is a delta light.
LightSampleKind sample_light(const Scene& scene, const LightContext& lc, const ShadingPoint& sp,
                             const Frame& frame, Vec3 wo_local, const BounceSamples& s,
                             const float* w, float total, BsdfEvalBatch* batch, LightBatch* lb,
                             int lane, LightRay* out);
// Which light sample_light chose with the same s, w and total (valid where it did not return
// None): its choice made again, for the light groups only. Apart from sample_light so that
// the tracer without light groups keeps it as it was (reporting the choice from inside made
// the link-time optimiser stop inlining it: 2% of the Cornell box's samples per second).
LightSampleSource light_sample_source(const Scene& scene, const LightContext& lc,
                                      const BounceSamples& s, const float* w, float total);

}  // namespace rf
