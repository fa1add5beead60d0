// Sample generators. Contract (the server relies on it): every value is a pure function
//   value(seed, pixel, sample_index, dimension) in [0, 1)
// with pixel = y * width + x over the full image and sample_index the global per-pixel index,
// so an image does not depend on which worker, thread or batch rendered which samples.
//
// Dimension layout used by the integrators (never depends on what happened on the path):
//   0, 1   pixel jitter (box filter: sample position (x + u0, y + u1))
//   2, 3   lens (reserved)
//   4 + 8 b + k   for bounce b: k = 0-1 light position, 2-3 BSDF direction, 4 light
//                 selection, 5 Russian roulette, 6-7 spare.
// 2D quantities sit on an even dimension and the next one: the sobol sampler pads pairs
// (2p, 2p + 1), each pair a scrambled (0, m, 2)-net.
#pragma once

#include <cstdint>
#include <string>

namespace rf {

enum class SamplerType { Sobol, Independent };

// Parses "sobol" / "independent"; false for anything else.
bool parse_sampler_type(const std::string& name, SamplerType* out);
const char* sampler_type_name(SamplerType t);

// Largest supported samples per pixel: sample indices must fit 32 bits, and we keep one bit
// of headroom so that sample_start + sample_count never wraps.
constexpr uint64_t kMaxSamplesPerPixel = uint64_t(1) << 31;

namespace dim {
constexpr uint32_t kPixelX = 0, kPixelY = 1, kLensU = 2, kLensV = 3;
constexpr uint32_t kFirstBounce = 4, kPerBounce = 8;
constexpr uint32_t kLightU = 0, kLightV = 1, kBsdfU = 2, kBsdfV = 3, kLightSelect = 4,
                   kRoulette = 5;
inline uint32_t bounce(uint32_t b, uint32_t k) { return kFirstBounce + kPerBounce * b + k; }
}  // namespace dim

// ---- Building blocks, exposed for the tests.
uint64_t mix64(uint64_t x);  // splitmix64 finalizer: a bijection with full avalanche
// Chained strong hash of four words (order matters).
uint64_t hash4(uint64_t a, uint64_t b, uint64_t c, uint64_t d);
uint32_t reverse_bits32(uint32_t x);
uint32_t laine_karras_permutation(uint32_t x, uint32_t seed);
// Owen scrambling by hashing (Burley 2020): output bit j depends only on input bits above j.
uint32_t nested_uniform_scramble(uint32_t x, uint32_t seed);
// Unscrambled Sobol point: 32-bit fraction of dimension d in 0..3 for index i (the sampler
// uses dimensions 0 and 1 only; 2 and 3 are kept for tests of why).
uint32_t sobol32(uint32_t index, uint32_t d);
// 32-bit fraction -> float in [0, 1) from the top 24 bits (exactly representable).
inline float fraction_to_float(uint32_t v) { return float(v >> 8) * (1.f / 16777216.f); }

// ---- The sampler: stateless, cheap to copy, safe to share between threads.
class Sampler {
 public:
  Sampler(SamplerType type, uint64_t seed) : type_(type), seed_(seed) {}
  SamplerType type() const { return type_; }
  uint64_t seed() const { return seed_; }
  // The 32-bit fraction behind value(); value = fraction_to_float(bits(...)).
  uint32_t bits(uint64_t pixel, uint32_t sample_index, uint32_t dimension) const;
  float value(uint64_t pixel, uint32_t sample_index, uint32_t dimension) const {
    return fraction_to_float(bits(pixel, sample_index, dimension));
  }

 private:
  SamplerType type_;
  uint64_t seed_;
};

// Convenience view for one (pixel, sample) pair.
struct SampleStream {
  const Sampler* sampler;
  uint64_t pixel;
  uint32_t index;
  float get(uint32_t dimension) const { return sampler->value(pixel, index, dimension); }
};

}  // namespace rf
