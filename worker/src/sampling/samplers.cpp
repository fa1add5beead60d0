#include "sampling/samplers.h"

#include <string>
#include <utility>
#include <vector>

#include <array>

#include "util/isa.h"

namespace rf {

bool parse_sampler_type(const std::string& name, SamplerType* out) {
  if (name == "sobol") {
    *out = SamplerType::Sobol;
    return true;
  }
  if (name == "independent") {
    *out = SamplerType::Independent;
    return true;
  }
  if (name == "stratified") {
    *out = SamplerType::Stratified;
    return true;
  }
  if (name == "halton") {
    *out = SamplerType::Halton;
    return true;
  }
  return false;
}

const char* sampler_type_name(SamplerType t) {
  switch (t) {
    case SamplerType::Sobol:
      return "sobol";
    case SamplerType::Independent:
      return "independent";
    case SamplerType::Stratified:
      return "stratified";
    case SamplerType::Halton:
      return "halton";
  }
  return "?";
}

BatchRange batch_range(uint32_t b) {
  // Ramp 1, 1, 2, 4, 8, 16, 32 (batches 0..6), then kBatchCap = 64 from batch 7 on.
  BatchRange r;
  r.index = b;
  if (b == 0) {
    r.start = 0;
    r.size = 1;
  } else if (b < 7) {
    r.start = uint64_t(1) << (b - 1);
    r.size = uint32_t(1) << (b - 1);
  } else {
    r.start = 64 + uint64_t(b - 7) * kBatchCap;
    r.size = kBatchCap;
  }
  return r;
}

BatchRange batch_containing(uint64_t i) {
  if (i == 0) return batch_range(0);
  if (i < 64) {
    uint32_t log2 = 0;
    while ((uint64_t(2) << log2) <= i) ++log2;  // floor(log2 i)
    return batch_range(log2 + 1);
  }
  return batch_range(uint32_t(7 + (i - 64) / kBatchCap));
}

uint64_t mix64(uint64_t x) {
  x += 0x9e3779b97f4a7c15ull;
  x = (x ^ (x >> 30)) * 0xbf58476d1ce4e5b9ull;
  x = (x ^ (x >> 27)) * 0x94d049bb133111ebull;
  return x ^ (x >> 31);
}

uint64_t hash4(uint64_t a, uint64_t b, uint64_t c, uint64_t d) {
  // Each step mixes the running state with the next word; since mix64 is a bijection with
  // full avalanche, distinct tuples collide only by 64-bit chance.
  uint64_t h = mix64(a ^ 0x243f6a8885a308d3ull);
  h = mix64(h ^ b);
  h = mix64(h + c * 0xd6e8feb86659fd93ull);
  h = mix64(h ^ (d + 0x13198a2e03707344ull));
  return h;
}

uint32_t reverse_bits32(uint32_t x) {
  // Byte swap (one instruction), then reverse the bits inside each byte.
  x = __builtin_bswap32(x);
  x = ((x >> 1) & 0x55555555u) | ((x & 0x55555555u) << 1);
  x = ((x >> 2) & 0x33333333u) | ((x & 0x33333333u) << 2);
  return ((x >> 4) & 0x0f0f0f0fu) | ((x & 0x0f0f0f0fu) << 4);
}

namespace {
// Burley 2020, improved constants: every step only propagates information from lower to
// higher bits, so (after the bit reversals around it) it is a nested uniform scramble. T is
// uint32_t or a vector of them (value8's lanes).
template <typename T>
inline T laine_karras_steps(T x, T seed) {
  x += seed;
  x ^= x * 0x6c50b47cu;
  x ^= x * 0xb82f1e52u;
  x ^= x * 0xc7afe638u;
  x ^= x * 0x8d22f6e6u;
  return x;
}
}  // namespace

uint32_t laine_karras_permutation(uint32_t x, uint32_t seed) { return laine_karras_steps(x, seed); }

uint32_t nested_uniform_scramble(uint32_t x, uint32_t seed) {
  return reverse_bits32(laine_karras_permutation(reverse_bits32(x), seed));
}

namespace {

// Direction numbers v[d][k] (k = 0..31, the column for index bit k) of the first four Sobol
// dimensions, as 32-bit fractions.
struct SobolMatrices {
  std::array<std::array<uint32_t, 32>, 4> v{};

  SobolMatrices() {
    // Dimension 0: identity matrix = van der Corput radical inverse in base 2.
    for (int k = 0; k < 32; ++k) v[0][k] = 1u << (31 - k);
    // Joe & Kuo primitive polynomials (degree s, coefficient bits a) and initial m values.
    struct Poly {
      int s;
      uint32_t a;
      std::array<uint32_t, 3> m;
    };
    const Poly polys[3] = {{1, 0, {1, 0, 0}}, {2, 1, {1, 3, 0}}, {3, 1, {1, 3, 1}}};
    for (int d = 1; d < 4; ++d) {
      const Poly& p = polys[d - 1];
      // m_k as integers (odd, m_k < 2^k), 1-based k as in Bratley & Fox / Joe & Kuo.
      std::array<uint32_t, 33> m{};
      for (int k = 1; k <= p.s; ++k) m[k] = p.m[k - 1];
      // Recurrence: m_k = 2 a_1 m_{k-1} ^ 4 a_2 m_{k-2} ^ ... ^ 2^{s-1} a_{s-1} m_{k-s+1}
      //                   ^ 2^s m_{k-s} ^ m_{k-s}, with a = (a_1 ... a_{s-1}) in binary.
      for (int k = p.s + 1; k <= 32; ++k) {
        uint32_t mk = m[k - p.s] ^ (m[k - p.s] << p.s);
        for (int j = 1; j < p.s; ++j) {
          const uint32_t a_j = (p.a >> (p.s - 1 - j)) & 1u;
          if (a_j) mk ^= m[k - j] << j;
        }
        m[k] = mk;
      }
      // v_k = m_k / 2^k as a 32-bit fraction.
      for (int k = 1; k <= 32; ++k) v[d][k - 1] = m[k] << (32 - k);
    }
    // Byte tables: bytes[d][b][x] = XOR of the columns selected by byte b of the index
    // having value x, so a point costs four lookups instead of a loop over 32 bits.
    for (int d = 0; d < 4; ++d)
      for (int b = 0; b < 4; ++b)
        for (uint32_t x = 0; x < 256; ++x) {
          uint32_t acc = 0;
          for (int k = 0; k < 8; ++k)
            if (x & (1u << k)) acc ^= v[size_t(d)][size_t(8 * b + k)];
          bytes[size_t(d)][size_t(b)][x] = acc;
          // Bit-reversed domain: reversed[d](y) = reverse(sobol32(reverse(y))), the XOR of
          // reverse(v[31 - j]) over the set bits j of y (reversal is linear over XOR).
          uint32_t acc_r = 0;
          for (int k = 0; k < 8; ++k)
            if (x & (1u << k)) acc_r ^= reverse_bits32(v[size_t(d)][size_t(31 - (8 * b + k))]);
          reversed[size_t(d)][size_t(b)][x] = acc_r;
        }
  }
  std::array<std::array<std::array<uint32_t, 256>, 4>, 4> bytes{};
  std::array<std::array<std::array<uint32_t, 256>, 4>, 4> reversed{};
};

const SobolMatrices& sobol_matrices() {
  static const SobolMatrices matrices;
  return matrices;
}

// The rest of a sobol value once the shuffled index is known in the bit-reversed domain
// (y = LK(reverse(i), s1)): z = reverse(sobol32(reverse(y))) by the reversed tables of Sobol
// dimension d (0 or 1), then reverse(LK(z, s2)).
inline uint32_t sobol_finish(uint32_t y, uint32_t d, uint32_t scramble_seed) {
  static const SobolMatrices& m = sobol_matrices();
  const auto& t = m.reversed[d];
  const uint32_t z = t[0][y & 0xffu] ^ t[1][(y >> 8) & 0xffu] ^ t[2][(y >> 16) & 0xffu] ^
                     t[3][y >> 24];
  return reverse_bits32(laine_karras_permutation(z, scramble_seed));
}

// Domain tags keep the index-shuffle and value-scramble hashes independent.
constexpr uint64_t kShuffleTag = 0x53485546464c4531ull;  // "SHUFFLE1"
constexpr uint64_t kScrambleTag = 0x534352414d424c31ull;  // "SCRAMBL1"
constexpr uint64_t kSobolKeyTag = 0x534f424f4c4b4559ull;  // "SOBOLKEY"
constexpr uint64_t kIndependentTag = 0x494e444550454e44ull;  // "INDEPEND"
constexpr uint64_t kJitterTag = 0x4a49545445523031ull;       // "JITTER01"
constexpr uint64_t kLatinTag = 0x4c4154494e485950ull;        // "LATINHYP"
constexpr uint64_t kHaltonTag = 0x48414c544f4e3031ull;       // "HALTON01"

struct Primes {
  std::array<uint32_t, kHaltonDimensions> p{};
  Primes() {
    uint32_t n = 0;
    for (uint32_t c = 2; n < kHaltonDimensions; ++c) {
      bool prime = true;
      for (uint32_t k = 0; k < n && p[k] * p[k] <= c; ++k)
        if (c % p[k] == 0) {
          prime = false;
          break;
        }
      if (prime) p[n++] = c;
    }
  }
};

const Primes& primes() {
  static const Primes table;
  return table;
}

uint32_t independent_bits(uint64_t seed, uint64_t pixel, uint32_t index, uint32_t dimension) {
  return uint32_t(hash4(seed ^ kIndependentTag, pixel, index, dimension) >> 32);
}

uint32_t permute_index_impl(uint32_t i, uint32_t n, uint64_t seed);

// Random permutation of the k-bit integers. (The nested uniform scramble restricted to k
// bits is one too, but for a fixed k its family has only 2^k members of the form
// P(j + seed), so two dimensions' permutations would be shifts of one another: correlated.)
uint32_t permute_bits(uint32_t j, uint32_t k, uint64_t seed) {
  if (k == 0) return 0;
  return permute_index_impl(j, 1u << k, seed);
}

uint32_t stratified_bits(uint64_t seed, uint64_t pixel, uint32_t index, uint32_t dimension) {
  const BatchRange batch = batch_containing(index);
  const uint32_t j = uint32_t(index - batch.start);
  uint32_t k = 0;
  while ((1u << k) < batch.size) ++k;
  const uint32_t jitter = uint32_t(hash4(seed ^ kJitterTag, pixel, index, dimension) >> 32);
  if (dimension < 2) {
    // Jittered grid on the pixel: 2^kx columns by 2^ky rows. Sample j takes cell pi(j) =
    // row * 2^kx + column, pi a random permutation per (seed, pixel, batch): the whole batch
    // covers every cell once, and each sample alone is uniform over the pixel, so a batch
    // clipped at max_spp stays unbiased.
    const uint32_t kx = (k + 1) / 2, ky = k / 2;
    const uint32_t kd = dimension == 0 ? kx : ky;
    const uint64_t grid_seed = hash4(seed ^ kLatinTag, pixel, batch.index, 0);
    const uint32_t c = permute_bits(j, k, grid_seed);
    const uint32_t cell = dimension == 0 ? (c & ((1u << kx) - 1u)) : (c >> kx);
    if (kd == 0) return jitter;
    return (cell << (32 - kd)) | (jitter >> kd);
  }
  // Latin hypercube: sample j takes stratum pi_d(j) of S in this dimension.
  if (k == 0) return jitter;
  const uint64_t perm_seed = hash4(seed ^ kLatinTag, pixel, batch.index, dimension);
  const uint32_t stratum = permute_bits(j, k, perm_seed);
  return (stratum << (32 - k)) | (jitter >> k);
}

// Radical inverse of index in base b with digit i replaced by (a_i d + c_i) mod b: a random
// affine permutation of the digits per position (a_i in [1, b - 1], c_i in [0, b - 1]; b is
// prime, so d -> a d + c is a bijection). The c_i come from the base-b digits of h_shift, the
// a_i from the base-(b - 1) digits of h_mult (64 random bits each cover the ~34 bits of
// digits a value needs). Digits are permuted down to 2^-34, including the zero digits above
// the index, so that with uniform c_i every digit, hence the value, is exactly uniform.
uint32_t halton_scrambled(uint32_t index, uint32_t base, uint64_t h_shift, uint64_t h_mult) {
  if (base == 2) {
    // Base 2: the only permutations of {0, 1} are identity and swap, i.e. an xor per digit.
    return reverse_bits32(index) ^ uint32_t(h_shift >> 32);
  }
  double value = 0.0;
  const double inv_base = 1.0 / double(base);
  double weight = inv_base;
  uint32_t rest = index;
  for (; weight > 0x1p-34; weight *= inv_base) {
    const uint32_t digit = rest % base;
    rest /= base;
    const uint32_t c = uint32_t(h_shift % base);
    h_shift /= base;
    const uint32_t a = 1 + uint32_t(h_mult % (base - 1));
    h_mult /= (base - 1);
    value += double((uint64_t(a) * digit + c) % base) * weight;
  }
  const double scaled = value * 4294967296.0;
  return scaled >= 4294967295.0 ? 0xffffffffu : uint32_t(scaled);
}

}  // namespace

uint32_t halton_base(uint32_t d) { return primes().p[d % kHaltonDimensions]; }

uint32_t permute_index(uint32_t i, uint32_t n, uint64_t seed) {
  return permute_index_impl(i, n, seed);
}

namespace {
uint32_t permute_index_impl(uint32_t i, uint32_t n, uint64_t seed) {
  if (n <= 1) return 0;
  uint32_t mask = n - 1;
  mask |= mask >> 1;
  mask |= mask >> 2;
  mask |= mask >> 4;
  mask |= mask >> 8;
  mask |= mask >> 16;
  const uint32_t s0 = uint32_t(seed), s1 = uint32_t(seed >> 32);
  // Every step is a bijection of [0, mask]: xor with a constant, multiplication by an odd
  // number, xor-shift right, addition modulo mask + 1. Cycle-walking until the value lands in
  // [0, n) turns a permutation of [0, mask] into one of [0, n).
  const uint32_t s2 = uint32_t(mix64(seed ^ 0x5851f42d4c957f2dull));
  const uint32_t s3 = uint32_t(mix64(seed ^ 0x14057b7ef767814full) >> 32);
  // Kensler's (2013) shape of round, with seed-dependent multipliers and offsets: an
  // xor-shift right of half the width spreads high bits down, the odd multipliers spread low
  // bits up.
  uint32_t half = 1;
  while ((mask >> half) > (1u << half)) ++half;
  do {
    i ^= s0 & mask;
    i = (i * (s1 | 1u)) & mask;
    i ^= i >> half;
    i = (i + s2) & mask;
    i = (i * (s3 | 1u)) & mask;
    i ^= i >> half;
    i ^= (s0 >> 16) & mask;
    i = (i * ((s2 >> 8) | 1u)) & mask;
    i ^= (i >> (half > 1 ? half - 1 : 1));
    i = (i * ((s1 >> 7) | 1u)) & mask;
    i ^= i >> half;
  } while (i >= n);
  // A final rotation by a seeded offset makes each output exactly equally likely.
  return uint32_t((uint64_t(i) + (mix64(seed) % n)) % n);
}
}  // namespace

uint32_t sobol32(uint32_t index, uint32_t d) {
  static const SobolMatrices& m = sobol_matrices();
  const auto& t = m.bytes[d & 3u];
  return t[0][index & 0xffu] ^ t[1][(index >> 8) & 0xffu] ^ t[2][(index >> 16) & 0xffu] ^
         t[3][index >> 24];
}

uint32_t Sampler::bits(uint64_t pixel, uint32_t sample_index, uint32_t dimension) const {
  switch (type_) {
    case SamplerType::Independent:
      return independent_bits(seed_, pixel, sample_index, dimension);
    case SamplerType::Stratified:
      return stratified_bits(seed_, pixel, sample_index, dimension);
    case SamplerType::Halton:
      if (dimension >= kHaltonDimensions)
        return independent_bits(seed_, pixel, sample_index, dimension);
      return halton_scrambled(sample_index, primes().p[dimension],
                              halton_shift_seed(pixel, dimension),
                              halton_mult_seed(pixel, dimension));
    case SamplerType::Sobol:
      break;
  }
  // Padded 2D Sobol (Burley 2020's scheme with pairs instead of quadruples): dimensions come in
  // pairs (pixel x/y, lens u/v, light u/v, ...); each pair takes Sobol dimensions 0 and 1, whose
  // first 2^m points are a (0, m, 2)-net, after shuffling the sample index with its own
  // per-pixel seed (which decorrelates the pairs), then scrambles each coordinate with a
  // per-pixel, per-dimension seed. Pairs of higher Sobol dimensions are not (0, m, 2)-nets
  // (dimensions 2 and 3 share their first direction numbers), which is why pairs, not groups of
  // four, are padded.
  const uint64_t key = sobol_pixel_key(pixel);
  return sobol_bits(sample_index, dimension, sobol_shuffle_seed(key, dimension),
                    sobol_scramble_seed(key, dimension));
}

uint64_t Sampler::halton_shift_seed(uint64_t pixel, uint32_t dimension) const {
  return hash4(seed_ ^ kHaltonTag, pixel, dimension, 1);
}

uint64_t Sampler::halton_mult_seed(uint64_t pixel, uint32_t dimension) const {
  return hash4(seed_ ^ kHaltonTag, pixel, dimension, 2);
}

uint32_t Sampler::halton_value_bits(uint32_t sample_index, uint32_t dimension, uint64_t shift_seed,
                                    uint64_t mult_seed) {
  return halton_scrambled(sample_index, primes().p[dimension % kHaltonDimensions], shift_seed,
                          mult_seed);
}

uint64_t Sampler::sobol_pixel_key(uint64_t pixel) const {
  return mix64(mix64(seed_ ^ kSobolKeyTag) ^ pixel);
}

// The pixel's seeds are outputs of a splitmix64 stream started at its key: mix64 adds the
// golden-ratio increment itself, so seed (tag, n) is output number tag + n of that stream. The
// shuffle and scramble tags are about 2^50 outputs apart (no dimension reaches the other's),
// and different pixels' streams overlap only if their random 64-bit keys nearly coincide, so
// every seed is an independent-looking hash for one mix64 (hash4 of (seed, pixel, tag,
// dimension) took four).
uint32_t Sampler::sobol_shuffle_seed(uint64_t key, uint32_t dimension) {
  return uint32_t(mix64(key + (kShuffleTag + dimension / 2u) * 0x9e3779b97f4a7c15ull) >> 32);
}

uint32_t Sampler::sobol_scramble_seed(uint64_t key, uint32_t dimension) {
  return uint32_t(mix64(key + (kScrambleTag + dimension) * 0x9e3779b97f4a7c15ull) >> 32);
}

uint32_t Sampler::sobol_bits(uint32_t sample_index, uint32_t dimension, uint32_t shuffle_seed,
                             uint32_t scramble_seed) {
  // nested_uniform_scramble(sobol32(nested_uniform_scramble(i, s1)), s2), computed in the
  // bit-reversed domain to save two of the four bit reversals:
  //   y = LK(reverse(i), s1)  (so the shuffled index is reverse(y)),
  //   z = reverse(sobol32(reverse(y))) by the reversed tables,  result = reverse(LK(z, s2)).
  const uint32_t y = laine_karras_permutation(reverse_bits32(sample_index), shuffle_seed);
  return sobol_finish(y, dimension % 2u, scramble_seed);
}

void PixelSampler::fill_sobol_seeds(uint32_t dimension) const {
  const uint64_t bit = uint64_t(1) << (dimension % 64);
  uint64_t& valid = valid_[dimension / 64];
  if (valid & bit) return;
  if (dimension % 2u == 0 || !(valid & (bit >> 1)))
    shuffle_[dimension / 2] = Sampler::sobol_shuffle_seed(key_, dimension);
  scramble_[dimension] = Sampler::sobol_scramble_seed(key_, dimension);
  valid |= bit;
}

Point2 PixelSampler::value2(uint32_t sample_index, uint32_t dimension) const {
  if (sampler_->type() != SamplerType::Sobol || dimension % 2u != 0 ||
      dimension + 1 >= kCachedDimensions)
    return {value(sample_index, dimension), value(sample_index, dimension + 1)};
  fill_sobol_seeds(dimension);
  fill_sobol_seeds(dimension + 1);
  const uint32_t y = laine_karras_permutation(reverse_bits32(sample_index), shuffle_[dimension / 2]);
  return {fraction_to_float(sobol_finish(y, 0, scramble_[dimension])),
          fraction_to_float(sobol_finish(y, 1, scramble_[dimension + 1]))};
}

namespace {

// 4-lane unsigned 32-bit vectors (GCC/Clang vector extensions: SSE4.1 on x86-64-v2, NEON on
// ARM), for value8's four pairs side by side.
typedef uint32_t U32x4 __attribute__((vector_size(16)));
typedef uint8_t U8x16 __attribute__((vector_size(16)));
typedef int32_t I32x4 __attribute__((vector_size(16)));
typedef float F32x4 __attribute__((vector_size(16)));

inline U32x4 laine_karras4(U32x4 x, U32x4 seed) { return laine_karras_steps(x, seed); }

inline U32x4 reverse_bits4(U32x4 x) {
  const U8x16 bytes = reinterpret_cast<U8x16>(x);
  x = reinterpret_cast<U32x4>(
      __builtin_shuffle(bytes, U8x16{3, 2, 1, 0, 7, 6, 5, 4, 11, 10, 9, 8, 15, 14, 13, 12}));
  x = ((x >> 1) & 0x55555555u) | ((x & 0x55555555u) << 1);
  x = ((x >> 2) & 0x33333333u) | ((x & 0x33333333u) << 2);
  return ((x >> 4) & 0x0f0f0f0fu) | ((x & 0x0f0f0f0fu) << 4);
}

// Sobol dimension 1 in the bit-reversed domain, without tables. Its generator matrix is
// Pascal's triangle mod 2 (primitive polynomial x + 1, m_1 = 1: m_k = m_(k-1) xor 2 m_(k-1)):
// output digit j is the xor of the index bits k whose binary expansion contains j's (Lucas).
// With w = reverse(y) the index and z = reverse(sobol32(w)), bit j of z is that xor over the
// bits k of w with k a superset of j: the subset-sum transform over GF(2), five xor-shifts.
inline U32x4 sobol1_reversed4(U32x4 w) {
  w ^= (w >> 1) & 0x55555555u;
  w ^= (w >> 2) & 0x33333333u;
  w ^= (w >> 4) & 0x0f0f0f0fu;
  w ^= (w >> 8) & 0x00ff00ffu;
  w ^= (w >> 16) & 0x0000ffffu;
  return w;
}

inline F32x4 fraction_to_float4(U32x4 v) {
  return __builtin_convertvector(reinterpret_cast<I32x4>(v >> 8), F32x4) * (1.f / 16777216.f);
}

}  // namespace

bool PixelSampler::prepare8(uint32_t first) const {
  if (sampler_->type() != SamplerType::Sobol || first % 4u != 0 ||
      first + 8 > kCachedDimensions)
    return false;
  const uint32_t group = uint32_t(1) << (first / 4);
  if (!(valid8_ & group)) {
    for (uint32_t d = first; d < first + 8; ++d) fill_sobol_seeds(d);
    valid8_ |= group;
  }
  return true;
}

bool PixelSampler::value8(uint32_t sample_index, uint32_t first, float out[8]) const {
  if (!prepare8(first)) return false;
  // As sobol_bits, for the pairs (first + 2p, first + 2p + 1) in lanes p = 0..3: the shuffled
  // index w = reverse(y) with y = LK(reverse(i), shuffle_p); then z = reverse(sobol32(w)),
  // which is w itself for Sobol dimension 0 (van der Corput: sobol32 = reverse) and
  // sobol1_reversed4(w) for dimension 1; the value is reverse(LK(z, scramble)).
  U32x4 shuffle, lo, hi;
  __builtin_memcpy(&shuffle, &shuffle_[first / 2], sizeof shuffle);
  __builtin_memcpy(&lo, &scramble_[first], sizeof lo);
  __builtin_memcpy(&hi, &scramble_[first + 4], sizeof hi);
  const U32x4 even_seed = __builtin_shuffle(lo, hi, U32x4{0, 2, 4, 6});
  const U32x4 odd_seed = __builtin_shuffle(lo, hi, U32x4{1, 3, 5, 7});
  const U32x4 y = laine_karras4(U32x4{} + reverse_bits32(sample_index), shuffle);
  const U32x4 w = reverse_bits4(y);
  const F32x4 even = fraction_to_float4(reverse_bits4(laine_karras4(w, even_seed)));
  const F32x4 odd = fraction_to_float4(reverse_bits4(laine_karras4(sobol1_reversed4(w),
                                                                   odd_seed)));
  const F32x4 out_lo = __builtin_shuffle(even, odd, I32x4{0, 4, 1, 5});
  const F32x4 out_hi = __builtin_shuffle(even, odd, I32x4{2, 6, 3, 7});
  __builtin_memcpy(out, &out_lo, sizeof out_lo);
  __builtin_memcpy(out + 4, &out_hi, sizeof out_hi);
  return true;
}

namespace {

// Vector types of N lanes. GCC ignores vector_size on a type that depends on a template
// parameter, so each width is one specialization, stamped out by this macro.
template <int N>
struct LaneTypes;
#define RF_LANE_TYPES(N)                                      \
  template <>                                                 \
  struct LaneTypes<N> {                                       \
    typedef uint32_t U __attribute__((vector_size(4 * N)));   \
    typedef int32_t I __attribute__((vector_size(4 * N)));    \
    typedef float F __attribute__((vector_size(4 * N)));      \
    typedef uint8_t B __attribute__((vector_size(4 * N)));    \
  };
RF_LANE_TYPES(4)
RF_LANE_TYPES(8)
RF_LANE_TYPES(16)
#undef RF_LANE_TYPES

// value8's arithmetic for a vector of sample indices (one lane each) and the four pairs of
// seeds, written once for any vector width N: out[k * stride + lane]. Everything is inlined
// into the kernels below, each compiled for its instruction set (the helpers work in place,
// so that no vector is passed by value to a function compiled for a narrower one).
#define RF_INLINE inline __attribute__((always_inline))
template <int N>
struct SobolLanes {
  using U = typename LaneTypes<N>::U;
  using I = typename LaneTypes<N>::I;
  using F = typename LaneTypes<N>::F;
  using B = typename LaneTypes<N>::B;

  static RF_INLINE void reverse_bits(U& x) {
    B order;
    for (int i = 0; i < 4 * N; ++i) order[i] = uint8_t((i & ~3) + 3 - (i & 3));
    x = reinterpret_cast<U>(__builtin_shuffle(reinterpret_cast<B>(x), order));
    x = ((x >> 1) & 0x55555555u) | ((x & 0x55555555u) << 1);
    x = ((x >> 2) & 0x33333333u) | ((x & 0x33333333u) << 2);
    x = ((x >> 4) & 0x0f0f0f0fu) | ((x & 0x0f0f0f0fu) << 4);
  }
  static RF_INLINE void laine_karras(U& x, uint32_t seed) {
    x += seed;
    x ^= x * 0x6c50b47cu;
    x ^= x * 0xb82f1e52u;
    x ^= x * 0xc7afe638u;
    x ^= x * 0x8d22f6e6u;
  }
  static RF_INLINE void sobol1_reversed(U& w) {
    w ^= (w >> 1) & 0x55555555u;
    w ^= (w >> 2) & 0x33333333u;
    w ^= (w >> 4) & 0x0f0f0f0fu;
    w ^= (w >> 8) & 0x00ff00ffu;
    w ^= (w >> 16) & 0x0000ffffu;
  }
  static RF_INLINE void store_float(const U& v, float* out) {
    const F f = __builtin_convertvector(reinterpret_cast<I>(v >> 8), F) * (1.f / 16777216.f);
    __builtin_memcpy(out, &f, sizeof f);
  }
  // N lanes of indices (index[0..N)), seeds of the four pairs, out rows of stride `stride`.
  static RF_INLINE void run(const uint32_t* index, const uint32_t* shuffle,
                            const uint32_t* scramble, float* out, int stride) {
    U r;
    __builtin_memcpy(&r, index, sizeof r);
    reverse_bits(r);
    for (int p = 0; p < 4; ++p) {
      U w = r;
      laine_karras(w, shuffle[p]);
      reverse_bits(w);  // the shuffled index
      U even = w, odd = w;
      laine_karras(even, scramble[2 * p]);
      reverse_bits(even);
      store_float(even, out + (2 * p) * stride);
      sobol1_reversed(odd);
      laine_karras(odd, scramble[2 * p + 1]);
      reverse_bits(odd);
      store_float(odd, out + (2 * p + 1) * stride);
    }
  }
};
#undef RF_INLINE

constexpr int kLanes16 = PixelSampler::kLanes16;
using Sobol8LanesFn = void (*)(const uint32_t*, const uint32_t*, const uint32_t*, float*);

void sobol8_lanes_sse(const uint32_t* index, const uint32_t* shuffle, const uint32_t* scramble,
                      float* out) {
  for (int l = 0; l < kLanes16; l += 4)
    SobolLanes<4>::run(index + l, shuffle, scramble, out + l, kLanes16);
}

#if defined(__x86_64__)
#define RF_LANE_KERNELS_X86 1
__attribute__((target("avx2"))) void sobol8_lanes_avx2(const uint32_t* index,
                                                       const uint32_t* shuffle,
                                                       const uint32_t* scramble, float* out) {
  for (int l = 0; l < kLanes16; l += 8)
    SobolLanes<8>::run(index + l, shuffle, scramble, out + l, kLanes16);
}
__attribute__((target("avx512f,avx512bw"))) void sobol8_lanes_avx512(const uint32_t* index,
                                                                     const uint32_t* shuffle,
                                                                     const uint32_t* scramble,
                                                                     float* out) {
  SobolLanes<16>::run(index, shuffle, scramble, out, kLanes16);
}
bool has_avx512() {
  __builtin_cpu_init();
  return __builtin_cpu_supports("avx512f") && __builtin_cpu_supports("avx512bw");
}
bool has_avx2() {
  __builtin_cpu_init();
  return __builtin_cpu_supports("avx2");
}
#endif

// The widest kernel this CPU runs (chosen once).
Sobol8LanesFn choose_sobol8_lanes() {
#ifdef RF_LANE_KERNELS_X86
  // Within the worker's instruction set cap (util/isa.h), like Embree's kernels: the same
  // values at every width, but a capped worker runs what a CPU without the wider set would.
  if (has_avx512() && isa_allows(isa_cap(), IsaCap::Avx512)) return sobol8_lanes_avx512;
  if (has_avx2() && isa_allows(isa_cap(), IsaCap::Avx2)) return sobol8_lanes_avx2;
#endif
  return sobol8_lanes_sse;
}

}  // namespace

std::vector<std::pair<std::string, Sobol8LanesKernel>> sobol8_lanes_kernels() {
  std::vector<std::pair<std::string, Sobol8LanesKernel>> kernels = {{"sse", sobol8_lanes_sse}};
#ifdef RF_LANE_KERNELS_X86
  if (has_avx2()) kernels.emplace_back("avx2", sobol8_lanes_avx2);
  if (has_avx512()) kernels.emplace_back("avx512", sobol8_lanes_avx512);
#endif
  return kernels;
}

bool PixelSampler::value8_lanes(const uint32_t index[kLanes16], uint32_t first,
                                float out[8][kLanes16]) const {
  if (!prepare8(first)) return false;
  static const Sobol8LanesFn kernel = choose_sobol8_lanes();
  kernel(index, &shuffle_[first / 2], &scramble_[first], &out[0][0]);
  return true;
}

float PixelSampler::value(uint32_t sample_index, uint32_t dimension) const {
  const SamplerType type = sampler_->type();
  if ((type != SamplerType::Sobol && type != SamplerType::Halton) ||
      dimension >= kCachedDimensions)
    return sampler_->value(pixel_, sample_index, dimension);
  const uint64_t bit = uint64_t(1) << (dimension % 64);
  uint64_t& valid = valid_[dimension / 64];
  if (type == SamplerType::Halton) {
    if (!(valid & bit)) {
      halton_[dimension][0] = sampler_->halton_shift_seed(pixel_, dimension);
      halton_[dimension][1] = sampler_->halton_mult_seed(pixel_, dimension);
      valid |= bit;
    }
    return fraction_to_float(Sampler::halton_value_bits(sample_index, dimension,
                                                        halton_[dimension][0],
                                                        halton_[dimension][1]));
  }
  fill_sobol_seeds(dimension);
  return fraction_to_float(
      Sampler::sobol_bits(sample_index, dimension, shuffle_[dimension / 2], scramble_[dimension]));
}

}  // namespace rf
