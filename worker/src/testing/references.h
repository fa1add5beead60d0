// What the render tests compare with (renderfarm_testing, not part of the worker): closed-form
// form factors, a plain material, and a rendered tile's per-pixel means with their errors.
#pragma once

#include <cstdint>
#include <vector>

#include "render/integrators.h"
#include "scene/scene.h"

namespace rf {
namespace testing {

// Form factor from a point to a parallel a x b rectangle at height c with the point under a
// corner (Howell's catalogue, configuration B-3 / the "corner formula").
double form_factor_corner(double a, double b, double c);
// Form factor from point (px, py) to a parallel rectangle [x0, x1] x [y0, y1] at height c, by
// the corner formula on the four signed corner rectangles.
double form_factor(double px, double py, double x0, double x1, double y0, double y1, double c);

// A material of grey base colour `base` with the given metallic, roughness, specular and
// transmission factors (a Lambert diffuser: 0, 1, 0, 0) and grey emission.
Material plain_material(const char* name, float base, float metallic, float roughness,
                        float specular, float transmission, float emission = 0.f);

// A pixel's mean over its samples and the standard error of that mean (the per-sample variance
// over N: valid for the independent sampler).
struct PixelStats {
  double mean = 0.0, standard_error = 0.0;
};
// Renders samples [0, spp) of the whole image (render_rect, every row) and returns each pixel's
// PixelStats of its radiance, which must be grey so that R equals the luminance whose M2 is
// reported; a failed render or a non-finite sample fails the calling test.
std::vector<PixelStats> pixel_stats(const Scene& scene, const RenderSettings& settings,
                                    uint32_t spp);

}  // namespace testing
}  // namespace rf
