// Integrators: estimate the radiance arriving through one pixel sample. All randomness comes
// from the Sampler with the fixed dimension layout in samplers.h, so a sample's value is a
// pure function of (scene, settings, pixel, sample index).
#pragma once

#include <atomic>
#include <cstdint>
#include <memory>
#include <string>

#include "scene/environment.h"
#include "render/film.h"
#include "sampling/samplers.h"
#include "scene/scene.h"

namespace rf {

struct LightGroups;  // render/light_groups.h
class GuideField;    // render/guiding.h

// path: unidirectional path tracing, NEE + MIS (power heuristic), Russian roulette from
//       bounce 3 (roulette_survival, render/packet_tracer.h), at most max_depth bounces.
// direct: the same estimator stopped after one bounce (emission seen directly, plus light
//       sampled and BSDF sampled direct illumination combined by MIS).
// ao: ambient occlusion within 10% of the scene diagonal, cosine weighted.
enum class IntegratorType { Path, Direct, AmbientOcclusion };

// Parses "path" / "direct" / "ao"; false for anything else.
bool parse_integrator_type(const std::string& name, IntegratorType* out);
const char* integrator_type_name(IntegratorType t);

struct RenderSettings {
  uint32_t width = 512, height = 512;  // full image, defines pixel indices and aspect
  uint64_t seed = 0;
  SamplerType sampler = SamplerType::Sobol;
  IntegratorType integrator = IntegratorType::Path;
  uint32_t max_depth = 8;  // maximum number of bounces; 1 = direct lighting only
  // Thin lens (pbrt's model): radius of the aperture disk in scene units, 0 = pinhole; points
  // at focus_distance along the viewing axis are in focus (required > 0 if aperture > 0).
  float aperture_radius = 0.f;
  float focus_distance = 0.f;
  // Environment light (intensity and rotation are applied by the Environment itself); null =
  // black background.
  std::shared_ptr<const Environment> environment;
  // The task's light groups (settings.light_groups, render/light_groups.h), which the
  // LightGroups row splits the radiance by; null: none (that row is then not rendered).
  std::shared_ptr<const LightGroups> light_groups;
  // Path guiding (settings.guiding, render/guiding.h): whether the render asks for it, and
  // the field train_guide learned for it, which the tracer samples beside the BSDF; null: no
  // guiding (render_image trains it when guiding is set; the farm worker once per job's frame).
  bool guiding = false;
  std::shared_ptr<const GuideField> guide;
};

// One sample's radiance and what its camera ray hit first (every integrator sets the first-hit
// fields through record_first_hit, packet_tracer.h).
struct SampleResult {
  Vec3 radiance;  // may be non-finite; the caller records that as 0
  Vec3 albedo;    // first-hit base color, 0 on a miss
  Vec3 normal;    // first-hit shading normal (world space, unit), 0 on a miss
  // First-hit position in world space (glTF axes), 0 on a miss: the Position row.
  Vec3 position;
  // Distance from the camera (lens point) to the first hit along the camera ray, 0 on a miss:
  // whether the camera ray hit anything (depth > 0), and the standalone EXR's depth.
  float depth = 0.f;
  // Planar depth of the first hit: its distance from the camera along the viewing axis (not
  // along the ray; t dot(d, forward) for the camera ray o + t d), as Blender's Depth pass has
  // it; 0 on a miss (the Depth row writes channels::kBackgroundDepth there).
  float z = 0.f;
  // The Instance and Material rows: the first hit's glTF node (Scene::node) and glTF material
  // (Material::gltf_index), each plus one; 0 on a miss and where the scene has none.
  uint32_t instance_id = 0;
  uint32_t material_id = 0;
  uint32_t rays = 0;
  // The first hit's surface point (Hit::slot, prim, b1, b2; meaningful where depth > 0): the
  // Motion row finds it in the scene posed at the previous and the next frame's times.
  uint32_t slot = 0, prim = 0;
  float b1 = 0.f, b2 = 0.f;
};

// The `lobes` rows of one sample (channels::kLobes, render/channels.h), in the channel table's
// order: diffuse, glossy and transmission, each direct then indirect, then emission and
// background. Per sample they sum to its radiance (up to float rounding), each an unbiased
// estimate of its own part of the pixel's integral (render/packet_tracer.h, PathLobes). Not
// part of SampleResult: render_rect asks for them only when the task names a lobe row.
constexpr uint32_t kLobeRows = 8;
struct LobeValues {
  Vec3 row[kLobeRows];
};

// The Motion row's context (render/motion.h): the poses of the frame before and after.
struct MotionPoses;

// One sample of pixel (x, y) with global sample index `index`.
SampleResult trace_sample(const Scene& scene, const RenderSettings& settings,
                          const Sampler& sampler, uint32_t x, uint32_t y, uint32_t index);
// The same, with the sampler already bound to the pixel (render_rect's fast path).
SampleResult trace_sample(const Scene& scene, const RenderSettings& settings,
                          const PixelSampler& sampler, uint32_t x, uint32_t y, uint32_t index);

// Empty string if rendering samples [start, start + count) of rect is valid for settings,
// otherwise a message naming the problem.
std::string validate_render_request(const RenderSettings& settings, PixelRect rect,
                                    uint64_t start, uint64_t count);

// Renders samples [start, start + count) of every pixel of rect into *out (reset first), for
// the rows of the channel table in `rows` (a channels::Set; every row by default). Per pixel,
// samples are accumulated in sample-index order (radiance sums in double, Welford M2 of
// luminance, the other rows' values in float32; the first-sample rows depth, position,
// motion, instance and material too, which over the one-sample batch at sample 0 are that
// sample's values; the ranked rows' labels counted, channels::RankedCounts; the lobe rows
// traced only when one of them is asked for, and the LightGroups row only when it is and
// settings.light_groups is set: without groups it is not rendered). Checks *cancel
// (if given) between rows and returns false as soon as it is set; *out is then incomplete.
// The request must pass validate_render_request, and with the LightGroups row
// check_light_groups (render/light_groups.h). motion: the Motion row's other poses
// (render/motion.h); null: a still, whose Motion row is 0. active: per-pixel adaptive
// sampling's mask (workers.proto, Task.active_pixels), one bit per pixel of rect in row-major
// order, least significant bit first, ceil(pixels / 8) bytes; a pixel whose bit is 0 is not
// rendered and all its values stay 0. Null: every pixel.
bool render_rect(const Scene& scene, const RenderSettings& settings, PixelRect rect,
                 uint64_t start, uint32_t count, TileBuffer* out,
                 const std::atomic<bool>* cancel = nullptr,
                 uint32_t rows = (uint32_t(1) << channels::kCount) - 1,
                 const MotionPoses* motion = nullptr, const uint8_t* active = nullptr);

}  // namespace rf
