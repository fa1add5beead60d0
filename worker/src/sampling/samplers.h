// Sample generators. Contract (the server relies on it): every value is a pure function
//   value(seed, pixel, sample_index, dimension) in [0, 1)
// with pixel = y * width + x over the full image and sample_index the global per-pixel index,
// so an image does not depend on which worker, thread or batch rendered which samples.
//
// Dimension layout used by the integrators (never depends on what happened on the path):
//   0, 1   pixel jitter (box filter: sample position (x + u0, y + u1))
//   2, 3   thin lens position (concentric disk)
//   4 + 8 b + k   for bounce b: k = 0-1 light selection and position (the first coordinate
//                 chooses the light, then, rescaled, places the point with the second), 2-3
//                 BSDF direction, 4 unused (light selection had its own dimension until
//                 2026-12), 5 Russian roulette, 6 BSDF lobe selection, 7 glass
//                 reflect/refract choice.
// 2D quantities sit on an even dimension and the next one: the sobol sampler pads pairs
// (2p, 2p + 1), each pair a scrambled (0, m, 2)-net; the stratified sampler stratifies the
// pixel pair on a jittered grid and every other dimension by a Latin hypercube.
//
// Samplers:
//   independent  hashed values, no correlation between samples.
//   stratified   each batch of the farm's fixed schedule (batch_containing) is stratified on
//                its own: for a batch of S = 2^k samples, sample j of the batch falls in cell
//                j of a 2^ceil(k/2) x 2^floor(k/2) jittered grid on the pixel pair, and every
//                other dimension d gets a Latin hypercube: stratum pi_d(j) of S with
//                pi_d a random permutation that is a pure function of (seed, pixel, batch,
//                d); the pairs (2p, 2p + 1) with p >= 1 are therefore N-rooks patterns. The
//                stratification uses the unclipped batch size, so a batch clipped at
//                max_spp is a subset of a stratified batch (still unbiased: every sample is
//                marginally uniform).
//   halton       radical inverse in the d-th prime base b with random digit permutations
//                (Matousek's random digit scrambling, with permutations from the affine
//                family): digit position i of dimension d is mapped by
//                digit -> (a_i digit + c_i) mod b, a_i in [1, b - 1], c_i in [0, b - 1], drawn
//                as a pure function of (seed, pixel, d, i) (for b = 2 this is every
//                permutation: an xor per digit). Each pixel therefore gets an independently
//                randomized Halton sequence (a per-pixel digit scramble; no index offset and
//                no Cranley-Patterson rotation). Digits are permuted down to 2^-34, including
//                the zero digits above the index, so every value is exactly uniform over the
//                randomization. Dimensions >= kHaltonDimensions (bounce 31 and deeper) fall
//                back to independent values.
//   sobol        Owen-scrambled Sobol (0, m, 2)-nets on padded pairs (see samplers.cpp).
#pragma once

#include <cstdint>
#include <vector>
#include <utility>
#include <string>

#include "sampling/sampling.h"

namespace rf {

enum class SamplerType { Sobol, Independent, Stratified, Halton };

// Parses "sobol" / "independent" / "stratified" / "halton"; false for anything else.
bool parse_sampler_type(const std::string& name, SamplerType* out);
const char* sampler_type_name(SamplerType t);

// Largest supported samples per pixel: sample indices must fit 32 bits, and we keep one bit
// of headroom so that sample_start + sample_count never wraps.
constexpr uint64_t kMaxSamplesPerPixel = uint64_t(1) << 31;

namespace dim {
constexpr uint32_t kPixelX = 0, kPixelY = 1, kLensU = 2, kLensV = 3;
constexpr uint32_t kFirstBounce = 4, kPerBounce = 8;
constexpr uint32_t kLightU = 0, kLightV = 1, kBsdfU = 2, kBsdfV = 3,
                   kWavelength = 4,  // read once per path, at its first dispersive vertex
                   kRoulette = 5, kLobe = 6, kFresnel = 7;
inline uint32_t bounce(uint32_t b, uint32_t k) { return kFirstBounce + kPerBounce * b + k; }
// Motion blur: the sample's time within the shutter, on the first dimension after those of
// the deepest bounce a path of max_depth bounces can use (scenes without motion never read it,
// so their images do not depend on it).
inline uint32_t shutter_time(uint32_t max_depth) { return bounce(max_depth + 1, 0); }
}  // namespace dim

// ---- The farm's fixed batch schedule (server/renderfarm/domain/tiling.py): sizes 1, 1, 2, 4,
// 8, 16, 32, then 64 forever; batch b starts at the sum of the earlier sizes, so every batch is a
// power of two aligned to its size. Sizes here are unclipped (max_spp clips only the last batch).
struct BatchRange {
  uint32_t index = 0;  // b
  uint64_t start = 0;  // first global sample index of the batch
  uint32_t size = 0;   // S_b, a power of two
};
constexpr uint32_t kBatchCap = 64;
BatchRange batch_range(uint32_t batch_index);
// The batch whose [start, start + size) contains sample_index.
BatchRange batch_containing(uint64_t sample_index);

// Number of Halton dimensions (one prime base each); higher dimensions are independent.
constexpr uint32_t kHaltonDimensions = 256;
// The d-th prime (d < kHaltonDimensions): 2, 3, 5, 7, ...
uint32_t halton_base(uint32_t d);
// A random permutation of [0, n) evaluated at i (cycle-walking a hashed bijection on the next
// power of two, followed by a hashed rotation so that every output is exactly equally likely
// over seeds up to hash quality). n >= 1, i < n. The stratified sampler's cell and
// Latin hypercube permutations.
uint32_t permute_index(uint32_t i, uint32_t n, uint64_t seed);

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
  // The sobol sampler's two per-(pixel, dimension) seeds (index shuffle of the dimension's
  // pair, value scramble of the dimension) and its value given them. The seeds hash the
  // pixel's key (a hash of seed and pixel) with the dimension, so that a pixel's many
  // dimensions hash the (seed, pixel) pair once.
  uint64_t sobol_pixel_key(uint64_t pixel) const;
  static uint32_t sobol_shuffle_seed(uint64_t key, uint32_t dimension);
  static uint32_t sobol_scramble_seed(uint64_t key, uint32_t dimension);
  static uint32_t sobol_bits(uint32_t sample_index, uint32_t dimension, uint32_t shuffle_seed,
                             uint32_t scramble_seed);
  // The halton sampler's per-(pixel, dimension) random bits (digit shifts, digit multipliers)
  // and its value given them (dimension < kHaltonDimensions).
  uint64_t halton_shift_seed(uint64_t pixel, uint32_t dimension) const;
  uint64_t halton_mult_seed(uint64_t pixel, uint32_t dimension) const;
  static uint32_t halton_value_bits(uint32_t sample_index, uint32_t dimension,
                                    uint64_t shift_seed, uint64_t mult_seed);

 private:
  SamplerType type_;
  uint64_t seed_;
};

// The sampler bound to one pixel: the same values as Sampler::value(pixel, ...), with the
// per-(pixel, dimension) scrambling seeds of the sobol sampler computed once per pixel and
// dimension instead of once per sample (they do not depend on the sample index). Not
// thread-safe (the cache is filled lazily): one per thread.
class PixelSampler {
 public:
  PixelSampler(const Sampler& sampler, uint64_t pixel)
      : sampler_(&sampler),
        pixel_(pixel),
        key_(sampler.type() == SamplerType::Sobol ? sampler.sobol_pixel_key(pixel) : 0) {}
  uint64_t pixel() const { return pixel_; }
  uint64_t seed() const { return sampler_->seed(); }
  float value(uint32_t sample_index, uint32_t dimension) const;
  // The pair (value(i, d), value(i, d + 1)) for an even d. For sobol the two share the pair's
  // shuffled index, which is then computed once.
  Point2 value2(uint32_t sample_index, uint32_t dimension) const;
  // The eight values value(i, first + k), k = 0..7, for first a multiple of 4 below
  // kCachedDimensions - 7 (one bounce's dimensions), computed together. For sobol the four
  // pairs go through the scrambles side by side in 4-lane vectors, with Sobol dimension 1
  // computed arithmetically instead of by tables; returns false (and leaves out alone) for
  // the other samplers, whose values the caller should ask for one at a time when needed.
  bool value8(uint32_t sample_index, uint32_t first, float out[8]) const;
  // value8 for kLanes16 sample indices at once: out[k][lane] = value(index[lane], first + k).
  // For sobol the lanes go through the scrambles side by side in vectors as wide as the CPU
  // has (AVX-512, AVX2 or SSE, chosen at run time; integer arithmetic, so every width gives
  // the same bits); returns false (and leaves out alone) where value8 would.
  static constexpr int kLanes16 = 16;
  bool value8_lanes(const uint32_t index[kLanes16], uint32_t first,
                    float out[8][kLanes16]) const;
  static constexpr uint32_t kCachedDimensions = 128;

 private:
  void fill_sobol_seeds(uint32_t dimension) const;
  // value8's and value8_lanes' common part: false where they decline (not sobol, or first
  // not one bounce's dimensions within the cache), otherwise true with the seeds of
  // dimensions first .. first + 7 filled.
  bool prepare8(uint32_t first) const;
  const Sampler* sampler_;
  uint64_t pixel_;
  uint64_t key_;  // Sampler::sobol_pixel_key(pixel_) (sobol only)
  mutable uint32_t shuffle_[kCachedDimensions / 2] = {};
  mutable uint32_t scramble_[kCachedDimensions] = {};
  mutable uint64_t halton_[kCachedDimensions][2] = {};
  mutable uint64_t valid_[kCachedDimensions / 64] = {};
  mutable uint32_t valid8_ = 0;  // bit first / 4: value8's seeds for first.. first + 7 filled
};

// The kernels behind PixelSampler::value8_lanes that this CPU can run, by name ("sse" (4-lane
// vectors: NEON on ARM), then on x86-64 "avx2" and "avx512" where present), for the tests: kernel(index[16], shuffle seeds of the four pairs, scramble seeds
// of the eight dimensions, out[8][16]).
using Sobol8LanesKernel = void (*)(const uint32_t*, const uint32_t*, const uint32_t*, float*);
std::vector<std::pair<std::string, Sobol8LanesKernel>> sobol8_lanes_kernels();

// Convenience view for one (pixel, sample) pair.
struct SampleStream {
  const PixelSampler* sampler;
  uint32_t index;
  float get(uint32_t dimension) const { return sampler->value(index, dimension); }
  // Dimensions (d, d + 1), d even: a 2D quantity's pair.
  Point2 get2(uint32_t dimension) const { return sampler->value2(index, dimension); }
};

// The dimensions of one bounce (dim::bounce(b, 0..7)) of one sample. For sobol all eight are
// computed at once on construction (cheaper together than the five to eight a bounce reads,
// one at a time); for the other samplers each is computed when read, so that dimensions a
// path does not use (roulette before bounce 3, the glass choice without glass) cost nothing.
class BounceSamples {
 public:
  // No values: a placeholder to be assigned before use.
  BounceSamples() : stream_{nullptr, 0}, first_(0) {}
  BounceSamples(const SampleStream& s, uint32_t bounce) { reset(s, bounce); }
  // Becomes BounceSamples(s, bounce) in place: the path tracer refills one per bounce, and
  // building a temporary and copying it makes the copy's loads wait for value8's stores.
  void reset(const SampleStream& s, uint32_t bounce) {
    stream_ = s;
    first_ = dim::bounce(bounce, 0);
    // value8 declines dimensions beyond its cache (bounce 15 and deeper) and other samplers.
    batched_ = s.sampler->value8(s.index, first_, values_);
  }
  // Becomes BounceSamples(s, bounce) with the eight values given (out[k][lane] of
  // PixelSampler::value8_lanes for s.index).
  void assign(const SampleStream& s, uint32_t bounce,
              const float (*values)[PixelSampler::kLanes16], int lane) {
    stream_ = s;
    first_ = dim::bounce(bounce, 0);
    batched_ = true;
    for (int k = 0; k < 8; ++k) values_[k] = values[k][lane];
  }
  float get(uint32_t k) const { return batched_ ? values_[k] : stream_.get(first_ + k); }
  // k even: the pair (k, k + 1).
  Point2 get2(uint32_t k) const {
    return batched_ ? Point2{values_[k], values_[k + 1]} : stream_.get2(first_ + k);
  }

 private:
  SampleStream stream_;
  uint32_t first_;
  bool batched_ = false;
  float values_[8];
};

}  // namespace rf
