// The Depth and Position rows of the channel table (a window of one sample): the first hit's
// planar depth along the camera's viewing axis and its world position, the values of Blender's
// Depth and Position passes. Expected values come from the geometry of the scenes (planes seen
// through cameras whose rays follow from the field of view and each pixel's corners).
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <vector>

#include "render/channels.h"
#include "render/integrators.h"
#include "render/reference.h"
#include "testing/test_scenes.h"

namespace rf {
namespace {

constexpr uint32_t kWidth = 16, kHeight = 12;
constexpr float kYfov = 0.8f;
// Float rounding of a hit distance or position, relative to the scene's scale.
constexpr float kRel = 1e-5f;
// Blender's depth where the camera ray hit nothing.
constexpr float kBackground = 1e10f;
// The plane's coordinate along the viewing axis and the camera's distance from it: the camera
// stands at z = kPlaneZ + kDistance looking down -z (look_at: right +x, up +y).
constexpr float kPlaneZ = 0.75f, kDistance = 4.f;

constexpr channels::Set kFirstHitRows =
    channels::bit(channels::Id::Depth) | channels::bit(channels::Id::Position);

// The plane z = kPlaneZ + y tan(tilt) (tilted about the horizontal axis, nearer the camera
// above the axis for tilt > 0), for x in [-20, x_max] and y in [-5, 5], facing the camera.
SceneDescription plane(float x_max, float tilt = 0.f) {
  SceneDescription desc;
  desc.source = "plane";
  desc.materials.push_back(Material{"grey", {0.5f, 0.5f, 0.5f}, {0, 0, 0}});
  const float s = std::tan(tilt);
  testing::add_quad(&desc, {-20.f, -5.f, kPlaneZ - 5.f * s}, {x_max, -5.f, kPlaneZ - 5.f * s},
                    {x_max, 5.f, kPlaneZ + 5.f * s}, {-20.f, 5.f, kPlaneZ + 5.f * s}, 0);
  desc.camera = testing::look_at({0.f, 0.f, kPlaneZ + kDistance}, {0.f, 0.f, kPlaneZ}, kYfov);
  return desc;
}

// Where the pinhole camera's rays through pixel column x (row y) cross the image plane at unit
// distance along the viewing axis: [lo, hi] of the horizontal (vertical) coordinate.
struct Span {
  float lo, hi;
};
Span column_span(uint32_t x) {
  const float half_width = float(kWidth) / float(kHeight) * std::tan(0.5f * kYfov);
  return {(2.f * float(x) / kWidth - 1.f) * half_width,
          (2.f * float(x + 1) / kWidth - 1.f) * half_width};
}
Span row_span(uint32_t y) {
  const float half_height = std::tan(0.5f * kYfov);
  return {(1.f - 2.f * float(y + 1) / kHeight) * half_height,
          (1.f - 2.f * float(y) / kHeight) * half_height};
}

RenderSettings settings_for(IntegratorType integrator) {
  RenderSettings settings;
  settings.width = kWidth;
  settings.height = kHeight;
  settings.seed = 9;
  settings.integrator = integrator;
  return settings;
}

// The Depth and Position rows of the whole image over the one-sample batch at sample 0 (the
// only batch a server asks them of).
struct FirstHit {
  std::vector<float> depth, position;
  std::vector<float> ray_length;  // the first hit's distance along the ray (0 on a miss)
};
FirstHit render_first_hit(const Scene& scene, const RenderSettings& settings) {
  TileBuffer tile;
  EXPECT_TRUE(
      render_rect(scene, settings, {0, 0, kWidth, kHeight}, 0, 1, &tile, nullptr, kFirstHitRows));
  EXPECT_TRUE(tile.sum(channels::Id::Albedo).empty()) << "a row not asked for";
  FirstHit out{tile.sum(channels::Id::Depth), tile.sum(channels::Id::Position), tile.depth_sum};
  EXPECT_EQ(out.depth.size(), size_t(kWidth) * kHeight);
  EXPECT_EQ(out.position.size(), 3 * size_t(kWidth) * kHeight);
  for (float v : out.depth) EXPECT_TRUE(std::isfinite(v));
  for (float v : out.position) EXPECT_TRUE(std::isfinite(v));
  return out;
}

const IntegratorType kIntegrators[] = {IntegratorType::Path, IntegratorType::AmbientOcclusion};

// A pixel whose camera ray missed: Blender's background depth and the origin.
void expect_miss(const FirstHit& f, size_t i) {
  EXPECT_EQ(f.depth[i], kBackground) << "pixel " << i;
  for (int c = 0; c < 3; ++c) EXPECT_EQ(f.position[3 * i + c], 0.f) << "pixel " << i;
}

// A plane perpendicular to the viewing axis at distance d: every pixel's depth is d, though
// its rays' lengths differ (d / cos of their angle to the axis); the hit lies on the plane,
// inside the pixel's footprint there (its corners' rays at distance d). Columns past the
// plane's edge (it ends at the middle of column 12) see nothing.
TEST(FirstHitRows, PerpendicularPlaneHasItsDistanceAsDepthInEveryPixel) {
  const float edge = 0.5f * (column_span(12).lo + column_span(12).hi) * kDistance;
  const Scene scene(plane(edge));
  for (IntegratorType integrator : kIntegrators) {
    SCOPED_TRACE(integrator_type_name(integrator));
    const FirstHit f = render_first_hit(scene, settings_for(integrator));
    const float slack = kRel * kDistance;
    float longest = 0.f;
    for (uint32_t y = 0; y < kHeight; ++y)
      for (uint32_t x = 0; x < kWidth; ++x) {
        const size_t i = size_t(y) * kWidth + x;
        if (x > 12) {
          expect_miss(f, i);
          continue;
        }
        if (x == 12 && f.depth[i] == kBackground) continue;  // the edge's column: either
        EXPECT_NEAR(f.depth[i], kDistance, slack) << x << ", " << y;
        EXPECT_NEAR(f.position[3 * i + 2], kPlaneZ, slack) << x << ", " << y;
        const Span sx = column_span(x), sy = row_span(y);
        EXPECT_GE(f.position[3 * i], sx.lo * kDistance - slack) << x << ", " << y;
        EXPECT_LE(f.position[3 * i], sx.hi * kDistance + slack) << x << ", " << y;
        EXPECT_GE(f.position[3 * i + 1], sy.lo * kDistance - slack) << x << ", " << y;
        EXPECT_LE(f.position[3 * i + 1], sy.hi * kDistance + slack) << x << ", " << y;
        longest = std::max(longest, f.ray_length[i]);
      }
    // The corner pixels' rays are about 1.1 times the depth: the depth is not the ray length.
    EXPECT_GT(longest, 1.08f * kDistance);
  }
}

// A thin lens focused nearer than the plane: the rays start across the aperture and cross the
// plane up to r |1 - d / f| off the pinhole's footprint, at the same planar depth d. An
// orthographic camera's rays all run along the axis from the camera's plane: depth d, the
// hit inside the pixel's box of [-xmag, xmag] x [-ymag, ymag].
TEST(FirstHitRows, ThinLensAndOrthographicCamerasHaveThePlanarDistanceAsDepth) {
  const Scene scene(plane(20.f));
  const float slack = kRel * kDistance;
  for (IntegratorType integrator : kIntegrators) {
    SCOPED_TRACE(integrator_type_name(integrator));
    RenderSettings settings = settings_for(integrator);
    settings.aperture_radius = 0.3f;
    settings.focus_distance = 2.5f;
    const float blur = settings.aperture_radius * std::fabs(1.f - kDistance / 2.5f);
    const FirstHit f = render_first_hit(scene, settings);
    for (uint32_t y = 0; y < kHeight; ++y)
      for (uint32_t x = 0; x < kWidth; ++x) {
        const size_t i = size_t(y) * kWidth + x;
        EXPECT_NEAR(f.depth[i], kDistance, slack) << x << ", " << y;
        EXPECT_NEAR(f.position[3 * i + 2], kPlaneZ, slack) << x << ", " << y;
        const Span sx = column_span(x), sy = row_span(y);
        EXPECT_GE(f.position[3 * i], sx.lo * kDistance - blur - slack) << x << ", " << y;
        EXPECT_LE(f.position[3 * i], sx.hi * kDistance + blur + slack) << x << ", " << y;
        EXPECT_GE(f.position[3 * i + 1], sy.lo * kDistance - blur - slack) << x << ", " << y;
        EXPECT_LE(f.position[3 * i + 1], sy.hi * kDistance + blur + slack) << x << ", " << y;
      }
  }
  SceneDescription desc = plane(20.f);
  desc.camera->orthographic = true;
  desc.camera->xmag = 2.f;
  desc.camera->ymag = 1.25f;
  const Scene ortho(std::move(desc));
  for (IntegratorType integrator : kIntegrators) {
    SCOPED_TRACE(integrator_type_name(integrator));
    const FirstHit f = render_first_hit(ortho, settings_for(integrator));
    for (uint32_t y = 0; y < kHeight; ++y)
      for (uint32_t x = 0; x < kWidth; ++x) {
        const size_t i = size_t(y) * kWidth + x;
        EXPECT_NEAR(f.depth[i], kDistance, slack) << x << ", " << y;
        EXPECT_NEAR(f.position[3 * i + 2], kPlaneZ, slack) << x << ", " << y;
        const float x0 = (2.f * float(x) / kWidth - 1.f) * 2.f;
        const float x1 = (2.f * float(x + 1) / kWidth - 1.f) * 2.f;
        const float y0 = (1.f - 2.f * float(y + 1) / kHeight) * 1.25f;
        const float y1 = (1.f - 2.f * float(y) / kHeight) * 1.25f;
        EXPECT_GE(f.position[3 * i], x0 - slack) << x << ", " << y;
        EXPECT_LE(f.position[3 * i], x1 + slack) << x << ", " << y;
        EXPECT_GE(f.position[3 * i + 1], y0 - slack) << x << ", " << y;
        EXPECT_LE(f.position[3 * i + 1], y1 + slack) << x << ", " << y;
      }
  }
}

// A plane tilted by 0.5 rad about the horizontal axis: the ray through image-plane height v
// (at unit distance along the axis) meets z = kPlaneZ + y tan(tilt) at planar depth
// d / (1 + v tan(tilt)), which falls as v rises. A pixel's depth lies between those of its
// bottom and top edges, and its hit on the plane at that depth.
TEST(FirstHitRows, TiltedPlaneDepthLiesBetweenThoseOfThePixelsEdges) {
  const float tilt = 0.5f, slope = std::tan(tilt);
  const Scene scene(plane(20.f, tilt));
  const auto depth_at = [&](float v) { return kDistance / (1.f + v * slope); };
  for (IntegratorType integrator : kIntegrators) {
    SCOPED_TRACE(integrator_type_name(integrator));
    const FirstHit f = render_first_hit(scene, settings_for(integrator));
    float shallowest = kBackground, deepest = 0.f;
    for (uint32_t y = 0; y < kHeight; ++y)
      for (uint32_t x = 0; x < kWidth; ++x) {
        const size_t i = size_t(y) * kWidth + x;
        const Span sy = row_span(y), sx = column_span(x);
        const float z = f.depth[i], slack = kRel * depth_at(sy.lo);
        EXPECT_GE(z, depth_at(sy.hi) - slack) << x << ", " << y;
        EXPECT_LE(z, depth_at(sy.lo) + slack) << x << ", " << y;
        const float px = f.position[3 * i], py = f.position[3 * i + 1];
        const float pz = f.position[3 * i + 2];
        // On the plane, at the planar depth the row gives, inside the pixel's ray cone.
        EXPECT_NEAR(pz, kPlaneZ + py * slope, slack) << x << ", " << y;
        EXPECT_NEAR(kPlaneZ + kDistance - pz, z, slack) << x << ", " << y;
        EXPECT_GE(px, sx.lo * z - slack) << x << ", " << y;
        EXPECT_LE(px, sx.hi * z + slack) << x << ", " << y;
        EXPECT_GE(py, sy.lo * z - slack) << x << ", " << y;
        EXPECT_LE(py, sy.hi * z + slack) << x << ", " << y;
        shallowest = std::min(shallowest, z);
        deepest = std::max(deepest, z);
      }
    EXPECT_LT(shallowest, 0.85f * kDistance);  // the rows' depths do differ
    EXPECT_GT(deepest, 1.2f * kDistance);
  }
}

// The packet tracer (trace_sample), the scalar reference and the ao integrator record the
// same first hit for the same sample: the camera ray is the sample's whatever the integrator.
// With a pinhole and a thin lens, over a tilted plane that ends mid-image (hits and misses).
TEST(FirstHitRows, IntegratorsRecordTheSameFirstHit) {
  const Scene scene(plane(0.3f, 0.4f));
  for (float aperture : {0.f, 0.2f}) {
    RenderSettings path = settings_for(IntegratorType::Path);
    path.aperture_radius = aperture;
    path.focus_distance = 3.f;
    RenderSettings ao = path;
    ao.integrator = IntegratorType::AmbientOcclusion;
    const Sampler sampler(path.sampler, path.seed);
    int hits = 0, misses = 0;
    for (uint32_t y = 0; y < kHeight; ++y)
      for (uint32_t x = 0; x < kWidth; ++x) {
        const PixelSampler pixel(sampler, uint64_t(y) * kWidth + x);
        for (uint32_t index : {0u, 1u, 5u}) {
          const SampleResult results[] = {
              trace_sample(scene, path, pixel, x, y, index),
              trace_sample_reference(scene, path, pixel, x, y, index),
              trace_sample(scene, ao, pixel, x, y, index),
              trace_sample_reference(scene, ao, pixel, x, y, index)};
          const SampleResult& first = results[0];
          (first.depth > 0.f ? hits : misses) += 1;
          for (const SampleResult& r : results) {
            ASSERT_EQ(r.depth > 0.f, first.depth > 0.f) << x << ", " << y << " #" << index;
            const float scale = kRel * (std::fabs(first.z) + 1.f);
            EXPECT_NEAR(r.z, first.z, scale) << x << ", " << y << " #" << index;
            for (int c = 0; c < 3; ++c)
              EXPECT_NEAR(r.position[c], first.position[c], scale)
                  << x << ", " << y << " #" << index;
          }
        }
      }
    EXPECT_GT(hits, 100);
    EXPECT_GT(misses, 100);
  }
}

// render_rect asked for the Depth and Position rows over the one-sample batch at sample 0
// gives that sample's values exactly: its planar depth (1e10 on a miss) and position (0 on a
// miss), whatever else the pixel's later samples would see.
TEST(FirstHitRows, TheFirstSampleBatchCarriesTheFirstSamplesValues) {
  const Scene scene(plane(0.3f, 0.4f));
  for (IntegratorType integrator : kIntegrators) {
    SCOPED_TRACE(integrator_type_name(integrator));
    RenderSettings settings = settings_for(integrator);
    settings.aperture_radius = 0.1f;
    settings.focus_distance = 3.f;
    const FirstHit f = render_first_hit(scene, settings);
    const Sampler sampler(settings.sampler, settings.seed);
    int misses = 0;
    for (uint32_t y = 0; y < kHeight; ++y)
      for (uint32_t x = 0; x < kWidth; ++x) {
        const size_t i = size_t(y) * kWidth + x;
        const SampleResult r = trace_sample(scene, settings, sampler, x, y, 0);
        if (!(r.depth > 0.f)) {
          expect_miss(f, i);
          ++misses;
          continue;
        }
        EXPECT_EQ(f.depth[i], r.z) << x << ", " << y;
        for (int c = 0; c < 3; ++c) EXPECT_EQ(f.position[3 * i + c], r.position[c]);
      }
    EXPECT_GT(misses, 0);
  }
}

}  // namespace
}  // namespace rf
