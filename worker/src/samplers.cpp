#include "samplers.h"

#include <array>

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
  return false;
}

const char* sampler_type_name(SamplerType t) {
  return t == SamplerType::Sobol ? "sobol" : "independent";
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
  x = ((x >> 1) & 0x55555555u) | ((x & 0x55555555u) << 1);
  x = ((x >> 2) & 0x33333333u) | ((x & 0x33333333u) << 2);
  x = ((x >> 4) & 0x0f0f0f0fu) | ((x & 0x0f0f0f0fu) << 4);
  x = ((x >> 8) & 0x00ff00ffu) | ((x & 0x00ff00ffu) << 8);
  return (x >> 16) | (x << 16);
}

uint32_t laine_karras_permutation(uint32_t x, uint32_t seed) {
  // Burley 2020, improved constants: every step only propagates information from lower to
  // higher bits, so (after the bit reversals around it) it is a nested uniform scramble.
  x += seed;
  x ^= x * 0x6c50b47cu;
  x ^= x * 0xb82f1e52u;
  x ^= x * 0xc7afe638u;
  x ^= x * 0x8d22f6e6u;
  return x;
}

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
  }
};

const SobolMatrices& sobol_matrices() {
  static const SobolMatrices matrices;
  return matrices;
}

// Domain tags keep the index-shuffle and value-scramble hashes independent.
constexpr uint64_t kShuffleTag = 0x53485546464c4531ull;  // "SHUFFLE1"
constexpr uint64_t kScrambleTag = 0x534352414d424c31ull;  // "SCRAMBL1"
constexpr uint64_t kIndependentTag = 0x494e444550454e44ull;  // "INDEPEND"

}  // namespace

uint32_t sobol32(uint32_t index, uint32_t d) {
  const auto& v = sobol_matrices().v[d & 3u];
  uint32_t x = 0;
  for (int k = 0; index != 0; ++k, index >>= 1)
    if (index & 1u) x ^= v[k];
  return x;
}

uint32_t Sampler::bits(uint64_t pixel, uint32_t sample_index, uint32_t dimension) const {
  if (type_ == SamplerType::Independent) {
    const uint64_t h = hash4(seed_ ^ kIndependentTag, pixel, sample_index, dimension);
    return uint32_t(h >> 32);
  }
  // Padded 2D Sobol (Burley 2020's scheme with pairs instead of quadruples): dimensions come in
  // pairs (pixel x/y, lens u/v, light u/v, ...); each pair takes Sobol dimensions 0 and 1, whose
  // first 2^m points are a (0, m, 2)-net, after shuffling the sample index with its own
  // per-pixel seed (which decorrelates the pairs), then scrambles each coordinate with a
  // per-pixel, per-dimension seed. Pairs of higher Sobol dimensions are not (0, m, 2)-nets
  // (dimensions 2 and 3 share their first direction numbers), which is why pairs, not groups of
  // four, are padded.
  const uint32_t pair = dimension / 2u;
  const uint32_t shuffle_seed = uint32_t(hash4(seed_, pixel, kShuffleTag, pair) >> 32);
  const uint32_t scramble_seed = uint32_t(hash4(seed_, pixel, kScrambleTag, dimension) >> 32);
  const uint32_t shuffled = nested_uniform_scramble(sample_index, shuffle_seed);
  return nested_uniform_scramble(sobol32(shuffled, dimension % 2u), scramble_seed);
}

}  // namespace rf
