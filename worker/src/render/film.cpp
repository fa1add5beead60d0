#include "render/film.h"

#include <OpenImageIO/imageio.h>

#include <cmath>
#include <cstring>
#include <memory>
#include <stdexcept>

namespace rf {

void TileBuffer::reset(PixelRect r, uint64_t start, uint32_t count, uint32_t which,
                       uint32_t light_groups) {
  rect = r;
  sample_start = start;
  sample_count = count;
  rows = which;
  groups = light_groups;
  const size_t n = r.pixel_count();
  rgb_sum.assign(3 * n, 0.0);
  luminance_m2.assign(n, 0.0);
  for (const channels::Spec& s : channels::kSpecs) {
    std::vector<float>& plane = sums[size_t(s.id)];
    std::vector<uint32_t>& pairs = ranks[size_t(s.id)];
    const bool wanted = (which >> uint32_t(s.id)) & 1u;
    if (wanted && !s.ranked && s.id != channels::Id::Rgb && s.id != channels::Id::Luminance)
      plane.assign((s.per_group ? s.components * light_groups : s.components) * n, 0.f);
    else
      plane.clear();
    if (wanted && s.ranked)
      pairs.assign(s.components * n, 0u);
    else
      pairs.clear();
  }
  depth_sum.assign(n, 0.f);
  nonfinite_samples = 0;
  rays = 0;
}

namespace {

template <typename Float, typename Bits>
std::string pack_le(const std::vector<Float>& values) {
  static_assert(sizeof(Float) == sizeof(Bits), "size mismatch");
  std::string out(values.size() * sizeof(Bits), '\0');
  for (size_t i = 0; i < values.size(); ++i) {
    Bits b;
    std::memcpy(&b, &values[i], sizeof(b));
    for (size_t k = 0; k < sizeof(Bits); ++k)
      out[i * sizeof(Bits) + k] = char((b >> (8 * k)) & 0xff);
  }
  return out;
}

template <typename Float, typename Bits>
std::vector<Float> unpack_le(const std::string& bytes) {
  if (bytes.size() % sizeof(Bits) != 0) throw std::runtime_error("packed array has odd size");
  std::vector<Float> out(bytes.size() / sizeof(Bits));
  for (size_t i = 0; i < out.size(); ++i) {
    Bits b = 0;
    for (size_t k = 0; k < sizeof(Bits); ++k)
      b |= Bits(static_cast<unsigned char>(bytes[i * sizeof(Bits) + k])) << (8 * k);
    std::memcpy(&out[i], &b, sizeof(b));
  }
  return out;
}

}  // namespace

std::string pack_f64_le(const std::vector<double>& v) { return pack_le<double, uint64_t>(v); }
std::string pack_f32_le(const std::vector<float>& v) { return pack_le<float, uint32_t>(v); }
std::string pack_f64_as_f32_le(const std::vector<double>& v) {
  return pack_le<float, uint32_t>(std::vector<float>(v.begin(), v.end()));
}
std::string pack_u32_le(const std::vector<uint32_t>& v) { return pack_le<uint32_t, uint32_t>(v); }
std::string pack_f32_as_u32_le(const std::vector<float>& sums) {
  std::vector<uint32_t> ids(sums.size());
  for (size_t i = 0; i < sums.size(); ++i)
    ids[i] = sums[i] >= 0.f && sums[i] < 4294967296.f ? uint32_t(std::nearbyint(sums[i])) : 0u;
  return pack_u32_le(ids);
}
std::vector<double> unpack_f64_le(const std::string& b) { return unpack_le<double, uint64_t>(b); }
std::vector<float> unpack_f32_le(const std::string& b) { return unpack_le<float, uint32_t>(b); }
std::vector<uint32_t> unpack_u32_le(const std::string& b) {
  return unpack_le<uint32_t, uint32_t>(b);
}

Image::Image(uint32_t w, uint32_t h)
    : width(w),
      height(h),
      rgb(3 * size_t(w) * h, 0.f),
      albedo(3 * size_t(w) * h, 0.f),
      normal(3 * size_t(w) * h, 0.f),
      depth(size_t(w) * h, 0.f),
      alpha(size_t(w) * h, 0.f) {}

void Image::set_from_tile(const TileBuffer& tile) {
  const double inv = tile.sample_count ? 1.0 / double(tile.sample_count) : 0.0;
  for (uint32_t y = 0; y < tile.rect.height; ++y)
    for (uint32_t x = 0; x < tile.rect.width; ++x) {
      const size_t src = size_t(y) * tile.rect.width + x;
      const size_t dst = size_t(tile.rect.y0 + y) * width + (tile.rect.x0 + x);
      const std::vector<float>& albedo_sum = tile.sum(channels::Id::Albedo);
      const std::vector<float>& normal_sum = tile.sum(channels::Id::Normal);
      for (int c = 0; c < 3; ++c) {
        rgb[3 * dst + size_t(c)] = float(tile.rgb_sum[3 * src + size_t(c)] * inv);
        albedo[3 * dst + size_t(c)] = float(albedo_sum[3 * src + size_t(c)] * inv);
        normal[3 * dst + size_t(c)] = float(normal_sum[3 * src + size_t(c)] * inv);
      }
      depth[dst] = float(double(tile.depth_sum[src]) * inv);
      alpha[dst] = float(double(tile.sum(channels::Id::Coverage)[src]) * inv);
    }
}

void write_exr(const std::string& path, const Image& image) {
  constexpr size_t kChannels = 11;
  OIIO::ImageSpec spec(int(image.width), int(image.height), int(kChannels),
                       OIIO::TypeDesc::FLOAT);
  spec.channelnames = {"R",        "G",        "B",        "A",        "albedo.R", "albedo.G",
                       "albedo.B", "normal.X", "normal.Y", "normal.Z", "depth"};
  spec.alpha_channel = 3;
  spec.attribute("compression", "zip");
  std::vector<float> interleaved(size_t(image.width) * image.height * kChannels);
  for (size_t i = 0; i < size_t(image.width) * image.height; ++i) {
    for (size_t c = 0; c < 3; ++c) {
      interleaved[kChannels * i + c] = image.rgb[3 * i + c];
      interleaved[kChannels * i + 4 + c] = image.albedo[3 * i + c];
      interleaved[kChannels * i + 7 + c] = image.normal[3 * i + c];
    }
    interleaved[kChannels * i + 3] = image.alpha[i];
    interleaved[kChannels * i + 10] = image.depth[i];
  }
  auto out = OIIO::ImageOutput::create(path);
  if (!out) throw std::runtime_error(path + ": cannot create EXR writer: " + OIIO::geterror());
  if (!out->open(path, spec))
    throw std::runtime_error(path + ": cannot open for writing: " + out->geterror());
  if (!out->write_image(OIIO::TypeDesc::FLOAT, interleaved.data()))
    throw std::runtime_error(path + ": write failed: " + out->geterror());
  if (!out->close()) throw std::runtime_error(path + ": close failed: " + out->geterror());
}

}  // namespace rf
