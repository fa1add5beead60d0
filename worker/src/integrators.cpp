#include "integrators.h"

#include <cmath>
#include <limits>

#include "materials.h"
#include "sampling.h"

namespace rf {

bool parse_integrator_type(const std::string& name, IntegratorType* out) {
  if (name == "path") {
    *out = IntegratorType::Path;
    return true;
  }
  if (name == "ao") {
    *out = IntegratorType::AmbientOcclusion;
    return true;
  }
  return false;
}

const char* integrator_type_name(IntegratorType t) {
  return t == IntegratorType::Path ? "path" : "ao";
}

namespace {

constexpr float kInfinity = std::numeric_limits<float>::infinity();

// Offset for spawned rays: floating-point error of a hit position grows with its magnitude,
// so the offset along the geometric normal scales with it (with a floor near the origin).
inline float ray_epsilon(Vec3 p) { return 3e-5f * std::max(max_abs_component(p), 1e-2f); }

struct ShadingPoint {
  Vec3 ng;  // geometric normal on the side of wo
  Vec3 ns;  // shading normal on the same side as ng
  Vec3 origin;  // hit point offset along ng, for rays leaving on the wo side
};

ShadingPoint make_shading_point(const Hit& hit, Vec3 wo) {
  ShadingPoint sp;
  sp.ng = dot(hit.ng, wo) >= 0.f ? hit.ng : -hit.ng;
  sp.ns = dot(hit.ns, sp.ng) >= 0.f ? hit.ns : -hit.ns;
  sp.origin = hit.p + sp.ng * ray_epsilon(hit.p);
  return sp;
}

SampleResult trace_path(const Scene& scene, const RenderSettings& settings,
                        const SampleStream& s, Vec3 o, Vec3 d) {
  SampleResult result;
  Vec3 radiance(0.f, 0.f, 0.f);
  Vec3 beta(1.f, 1.f, 1.f);    // path throughput: product of f cos / pdf so far
  float prev_bsdf_pdf = 0.f;   // solid-angle pdf of the direction d (bounce > 0)
  const LightSet& lights = scene.lights();
  for (uint32_t bounce = 0;; ++bounce) {
    Hit hit;
    ++result.rays;
    if (!scene.intersect(o, d, kInfinity, &hit)) break;  // no environment yet: black
    const Material& mat = scene.material(hit.prim);
    const Vec3 wo = -d;
    if (bounce == 0) {
      result.albedo = mat.albedo;
      result.normal = hit.ns;
    }
    // Emission, one-sided: only the front (counter-clockwise) face emits.
    const float cos_emit = dot(hit.ng, wo);
    if (mat.is_emissive() && cos_emit > 0.f) {
      if (bounce == 0) {
        radiance += beta * mat.emission;  // seen directly: light sampling cannot produce it
      } else {
        // The same point could have come from light sampling at the previous vertex: convert
        // its area pdf to solid angle (pdf_A d^2 / |cos|) and weight by the power heuristic.
        const float pdf_light = lights.pdf_area(hit.prim) * hit.t * hit.t / cos_emit;
        radiance += beta * mat.emission * power_heuristic(prev_bsdf_pdf, pdf_light);
      }
    }
    if (bounce >= settings.max_depth) break;
    // Russian roulette after 3 bounces; dividing by the survival probability keeps the
    // estimator unbiased.
    if (bounce >= 3) {
      const float q = std::min(0.95f, max_component(beta));
      if (!(s.get(dim::bounce(bounce, dim::kRoulette)) < q)) break;
      beta = beta / q;
    }
    const ShadingPoint sp = make_shading_point(hit, wo);
    const Vec3 f = lambert_f(mat);
    if (is_zero(mat.albedo)) break;  // black surface: nothing further contributes

    // Next-event estimation: one point on one emissive triangle.
    if (!lights.empty()) {
      const LightSample ls =
          lights.sample(s.get(dim::bounce(bounce, dim::kLightSelect)),
                        s.get(dim::bounce(bounce, dim::kLightU)),
                        s.get(dim::bounce(bounce, dim::kLightV)));
      const Vec3 to_light = ls.p - sp.origin;
      const float dist2 = dot(to_light, to_light);
      const float dist = std::sqrt(dist2);
      const Vec3 wi = to_light / dist;
      const float cos_light = dot(ls.n, -wi);
      const float cos_surface = dot(sp.ns, wi);
      if (dist > 0.f && cos_light > 0.f && cos_surface > 0.f && dot(sp.ng, wi) > 0.f) {
        const float pdf_light = ls.pdf_area * dist2 / cos_light;
        // Stop short of the light's own surface so it does not occlude itself.
        const float tmax = dist * (1.f - 1e-4f) - ray_epsilon(ls.p);
        ++result.rays;
        if (tmax > 0.f && !scene.occluded(sp.origin, wi, tmax)) {
          const float w = power_heuristic(pdf_light, lambert_pdf(sp.ns, wi));
          radiance += beta * f * ls.emission * (cos_surface * w / pdf_light);
        }
      }
    }

    // BSDF sampling: cosine-weighted about the shading normal, so f cos / pdf = albedo.
    const Vec3 local = sample_cosine_hemisphere(
        {s.get(dim::bounce(bounce, dim::kBsdfU)), s.get(dim::bounce(bounce, dim::kBsdfV))});
    const float pdf = cosine_hemisphere_pdf(local);
    const Vec3 wi = normalize(Frame(sp.ns).to_world(local));
    // Directions below the geometric surface would leak through it: end the path there.
    if (!(pdf > 0.f) || dot(wi, sp.ng) <= 0.f) break;
    beta *= mat.albedo;
    prev_bsdf_pdf = pdf;
    o = sp.origin;
    d = wi;
  }
  result.radiance = radiance;
  return result;
}

SampleResult trace_ao(const Scene& scene, const SampleStream& s, Vec3 o, Vec3 d) {
  SampleResult result;
  Hit hit;
  ++result.rays;
  if (!scene.intersect(o, d, kInfinity, &hit)) return result;  // background = 0
  result.albedo = scene.material(hit.prim).albedo;
  result.normal = hit.ns;
  const ShadingPoint sp = make_shading_point(hit, -d);
  const Vec3 local = sample_cosine_hemisphere(
      {s.get(dim::bounce(0, dim::kBsdfU)), s.get(dim::bounce(0, dim::kBsdfV))});
  const Vec3 wi = normalize(Frame(sp.ns).to_world(local));
  if (dot(wi, sp.ng) <= 0.f) return result;  // below the surface: blocked by it
  const float radius = 0.1f * scene.diagonal();
  ++result.rays;
  const float v = scene.occluded(sp.origin, wi, radius) ? 0.f : 1.f;
  result.radiance = Vec3(v, v, v);
  return result;
}

}  // namespace

SampleResult trace_sample(const Scene& scene, const RenderSettings& settings,
                          const Sampler& sampler, uint32_t x, uint32_t y, uint32_t index) {
  const SampleStream s{&sampler, uint64_t(y) * settings.width + x, index};
  // Box filter: the sample position is uniform inside the pixel.
  const float px = float(x) + s.get(dim::kPixelX);
  const float py = float(y) + s.get(dim::kPixelY);
  const Camera& cam = scene.camera();
  const Vec3 d = cam.ray_direction(px, py, settings.width, settings.height);
  if (settings.integrator == IntegratorType::AmbientOcclusion)
    return trace_ao(scene, s, cam.position, d);
  return trace_path(scene, settings, s, cam.position, d);
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
  for (uint32_t ty = 0; ty < rect.height; ++ty) {
    if (cancel && cancel->load(std::memory_order_relaxed)) return false;
    for (uint32_t tx = 0; tx < rect.width; ++tx) {
      const size_t i = size_t(ty) * rect.width + tx;
      double sum[3] = {0.0, 0.0, 0.0};
      double mean_y = 0.0, m2_y = 0.0;
      float albedo[3] = {0.f, 0.f, 0.f}, normal[3] = {0.f, 0.f, 0.f};
      for (uint32_t k = 0; k < count; ++k) {
        const SampleResult r =
            trace_sample(scene, settings, sampler, rect.x0 + tx, rect.y0 + ty,
                         uint32_t(start + k));
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
        // Welford's update of the luminance mean and M2.
        const double y = 0.2126 * double(L.x) + 0.7152 * double(L.y) + 0.0722 * double(L.z);
        const double delta = y - mean_y;
        mean_y += delta / double(k + 1);
        m2_y += delta * (y - mean_y);
      }
      for (int c = 0; c < 3; ++c) {
        out->rgb_sum[3 * i + size_t(c)] = sum[c];
        out->albedo_sum[3 * i + size_t(c)] = albedo[c];
        out->normal_sum[3 * i + size_t(c)] = normal[c];
      }
      out->luminance_m2[i] = m2_y;
    }
  }
  return true;
}

}  // namespace rf
