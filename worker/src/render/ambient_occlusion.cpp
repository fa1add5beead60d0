// The ao integrator: ambient occlusion within 10% of the scene diagonal, cosine weighted.
#include "render/packet_tracer.h"

#include "sampling/sampling.h"

namespace rf {

SampleResult trace_ao(const Scene& scene, const PathState& camera) {
  const SampleStream& s = camera.s;
  const float time = camera.time;
  SampleResult result;
  Hit hit;
  ++result.rays;
  const uint64_t seed = s.sampler->seed(), pixel = s.sampler->pixel();
  if (!scene.intersect(camera.o, camera.d, camera.tmax, &hit,
                       ray_query(seed, pixel, 0, RayKind::Path), s.index, camera.tmin, time))
    return result;  // background = 0
  const ShadingPoint sp = make_shading_point(scene, hit, -camera.d);
  record_first_hit(scene, sp, hit, camera.per_axial, &result);
  const Vec3 local = sample_cosine_hemisphere(s.get2(dim::bounce(0, dim::kBsdfU)));
  const Vec3 wi = normalize(sp.frame().to_world(local));
  if (dot(wi, sp.ng) <= 0.f) return result;  // below the surface: blocked by it
  const float radius = 0.1f * scene.diagonal();
  ++result.rays;
  const float v =
      scene.occluded(sp.above(), wi, radius, ray_query(seed, pixel, 0, RayKind::Shadow), s.index,
                     time)
          ? 0.f
          : 1.f;
  result.radiance = Vec3(v, v, v);
  return result;
}

}  // namespace rf
