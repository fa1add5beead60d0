// The scalar reference path tracer: part of the tests' library (renderfarm_testing), not of
// the worker.
#pragma once

#include <cstdint>

#include "render/integrators.h"

namespace rf {

// The same path tracer written for one path at a time with the scalar BSDF and light code:
// the readable reference the tests hold trace_sample and render_rect to, bit for bit (those
// trace a pixel's samples sixteen at a time, with the BSDF values, light-sample geometry and
// MIS weights of a bounce computed four lanes at a time).
SampleResult trace_sample_reference(const Scene& scene, const RenderSettings& settings,
                                    const PixelSampler& sampler, uint32_t x, uint32_t y,
                                    uint32_t index);

}  // namespace rf
