// Per-pixel accumulation for a rectangle of the image (TileBuffer, the payload of the farm's
// TileResult), the standalone image it is resolved into, and OpenEXR output.
#pragma once

#include <array>
#include <cstdint>
#include <string>
#include <vector>

#include "render/channel_table.h"

namespace rf {

// Rectangle of the image in pixels, x right and y down from the top-left corner.
struct PixelRect {
  uint32_t x0 = 0, y0 = 0, width = 0, height = 0;
  size_t pixel_count() const { return size_t(width) * size_t(height); }
};

// Sums over samples [sample_start, sample_start + sample_count) of every pixel of rect, for the
// rows of the channel table (channel_table.h) asked for (`rows`, a channels::Set).
// Arrays are row-major over the rect: index = y * rect.width + x, relative to the rect.
struct TileBuffer {
  PixelRect rect;
  uint64_t sample_start = 0;
  uint32_t sample_count = 0;
  uint32_t rows = 0;                 // channels::Set of the rows accumulated
  uint32_t groups = 0;               // light groups of the per-group row (Spec::per_group)
  std::vector<double> rgb_sum;       // 3 per pixel, radiance summed in sample-index order
  std::vector<double> luminance_m2;  // 1 per pixel, Welford M2 of Y over the batch
  // The other rows but the ranked ones, by channels::Id, summed in float32
  // (channels::sample_values), their components per pixel (empty when not asked for): albedo
  // (first-hit base colour, 0 on a miss), normal (first-hit shading normal), coverage
  // (samples whose camera ray hit geometry: an integer count, exact in float32; the alpha),
  // depth (first-hit planar depth along the viewing axis, channels::kBackgroundDepth on a
  // miss) and position (first-hit world position, 0 on a miss), instance and material (the
  // first hit's glTF node and material plus one, 0 on a miss or where there is none:
  // integers, the row's type U32, exact in float32 below 2^24), and the eight lobe rows (3
  // each: the radiance split by the first hit's lobes, render/packet_tracer.h, PathLobes; over
  // every sample, summing to rgb_sum up to float rounding). The first-hit rows depth to
  // material have a window of one sample: asked for over the one-sample batch at sample 0,
  // their sum is the first sample's value. The per-group row (light_groups) has its
  // components per light group, `groups` blocks of 3 a pixel in the groups' order (each
  // group's radiance, render/light_groups.h; together summing to rgb_sum up to float
  // rounding).
  std::array<std::vector<float>, channels::kCount> sums;
  // The ranked rows (Spec::ranked: crypto_object, crypto_material), by channels::Id, their
  // components per pixel (empty when not asked for, and for every other row): each pixel's
  // (label, count) pairs of the task's samples, largest count first (channels::RankedCounts).
  std::array<std::vector<uint32_t>, channels::kCount> ranks;
  std::vector<float> depth_sum;      // 1 per pixel, first-hit distance along the camera ray
                                     // (0 on miss); not the Depth row, and not part of the
                                     // farm's TileResult (standalone EXR only)
  uint64_t nonfinite_samples = 0;    // samples whose radiance was NaN/Inf, recorded as 0
  uint64_t rays = 0;                 // closest-hit plus shadow rays

  // groups: the light groups of the per-group row (0: it stays empty).
  void reset(PixelRect r, uint64_t start, uint32_t count, uint32_t rows, uint32_t groups = 0);
  std::vector<float>& sum(channels::Id id) { return sums[size_t(id)]; }
  const std::vector<float>& sum(channels::Id id) const { return sums[size_t(id)]; }
  std::vector<uint32_t>& ranked(channels::Id id) { return ranks[size_t(id)]; }
  const std::vector<uint32_t>& ranked(channels::Id id) const { return ranks[size_t(id)]; }
};

// Little-endian IEEE packing, as the protocol's bytes fields require.
std::string pack_f64_le(const std::vector<double>& values);
std::string pack_f32_le(const std::vector<float>& values);
// Doubles rounded to the nearest float, packed as float32.
std::string pack_f64_as_f32_le(const std::vector<double>& values);
std::string pack_u32_le(const std::vector<uint32_t>& values);
// The float32 sums of a row of type U32 (channels::Type::U32: over the one-sample batch at 0,
// the sample's id, an integer exact in float32 below 2^24) as the integers they hold, packed
// as uint32: each rounded to the nearest integer, 0 for anything not in [0, 2^32).
std::string pack_f32_as_u32_le(const std::vector<float>& sums);
std::vector<uint32_t> unpack_u32_le(const std::string& bytes);
std::vector<double> unpack_f64_le(const std::string& bytes);
std::vector<float> unpack_f32_le(const std::string& bytes);

// A full image of per-pixel means: radiance, albedo and normal (3 floats each per pixel),
// depth (1 float per pixel: mean first-hit distance, misses counting as 0) and alpha (the
// share of samples whose camera ray hit geometry).
struct Image {
  uint32_t width = 0, height = 0;
  std::vector<float> rgb, albedo, normal, depth, alpha;
  Image(uint32_t w, uint32_t h);
  // Stores the tile's means (sums / sample_count) at its rect.
  void set_from_tile(const TileBuffer& tile);
};

// Writes R, G, B, A, albedo.{R,G,B}, normal.{X,Y,Z}, depth as 32-bit float channels. Throws
// std::runtime_error naming the file on failure.
void write_exr(const std::string& path, const Image& image);

}  // namespace rf
