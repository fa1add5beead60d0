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

// Light selection between the scene's lights and the environment, by power (the scene's own
// alias table does the rest): P_env = pi^2 R^2 mean luminance, the power an environment of
// that mean radiance sends through a disk of the scene's bounding radius R.
struct LightContext {
  const Environment* env = nullptr;
  float p_env = 0.f;  // probability of choosing the environment
  bool any = false;
};

LightContext light_context(const Scene& scene, const RenderSettings& settings);

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
                             BsdfEvalBatch* batch, LightBatch* lb, int lane, LightRay* out);

}  // namespace rf
