// Standalone rendering of a whole image: 32x32 tiles handed to a pool of threads, each tile
// rendered by render_rect (the same code path as a farm task).
#pragma once

#include <cstdint>
#include <functional>

#include "render/film.h"
#include "render/guiding.h"
#include "render/integrators.h"

namespace rf {

constexpr uint32_t kTileSize = 32;

struct RenderStats {
  double seconds = 0.0;
  uint64_t rays = 0;
  uint64_t samples = 0;  // pixel samples
  uint64_t nonfinite_samples = 0;
  GuideStats guide;  // path guiding's training (settings.guiding), counted in seconds
};

// Renders samples [0, spp) of every pixel with `threads` threads (>= 1). progress(done,
// total) is called (serialized) after each finished tile. The result does not depend on the
// thread count: each pixel is accumulated by one thread in sample-index order. With
// settings.guiding and no settings.guide, the guide is trained first (train_guide).
Image render_image(const Scene& scene, const RenderSettings& settings, uint32_t spp,
                   uint32_t threads, RenderStats* stats,
                   const std::function<void(size_t, size_t)>& progress = {});

}  // namespace rf
