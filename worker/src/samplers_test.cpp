#include "samplers.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <random>
#include <thread>
#include <vector>

namespace rf {
namespace {

struct Key {
  uint64_t pixel;
  uint32_t index, dim;
};

std::vector<Key> all_keys() {
  std::vector<Key> keys;
  for (uint64_t pixel : {0ull, 1ull, 511ull, 262143ull, 4000000000ull})
    for (uint32_t index = 0; index < 70; ++index)
      for (uint32_t dim = 0; dim < 24; ++dim) keys.push_back({pixel, index, dim});
  return keys;
}

// pbrt's Sampler.ConsistentValues, adapted: the same (seed, pixel, index, dim) gives the same
// value whatever order, thread or batch asks for it.
TEST(Samplers, ConsistentValues) {
  for (SamplerType type : {SamplerType::Sobol, SamplerType::Independent}) {
    const Sampler sampler(type, 42);
    const std::vector<Key> keys = all_keys();
    std::vector<uint32_t> reference(keys.size());
    for (size_t i = 0; i < keys.size(); ++i)
      reference[i] = sampler.bits(keys[i].pixel, keys[i].index, keys[i].dim);
    // Shuffled order, with a fresh sampler object.
    std::vector<size_t> order(keys.size());
    for (size_t i = 0; i < order.size(); ++i) order[i] = i;
    std::shuffle(order.begin(), order.end(), std::mt19937(3));
    const Sampler again(type, 42);
    for (size_t i : order)
      ASSERT_EQ(again.bits(keys[i].pixel, keys[i].index, keys[i].dim), reference[i]);
    // Two threads, interleaved halves.
    std::vector<uint32_t> threaded(keys.size());
    auto work = [&](size_t first) {
      for (size_t i = first; i < keys.size(); i += 2)
        threaded[i] = sampler.bits(keys[i].pixel, keys[i].index, keys[i].dim);
    };
    std::thread t0(work, 0), t1(work, 1);
    t0.join();
    t1.join();
    EXPECT_EQ(threaded, reference);
    // A different seed gives different values.
    const Sampler other(type, 43);
    size_t same = 0;
    for (size_t i = 0; i < keys.size(); ++i)
      same += other.bits(keys[i].pixel, keys[i].index, keys[i].dim) == reference[i];
    EXPECT_LT(same, keys.size() / 100);
  }
}

TEST(Samplers, ValuesInUnitInterval) {
  const Sampler sampler(SamplerType::Sobol, 9);
  for (const Key& k : all_keys()) {
    const float v = sampler.value(k.pixel, k.index, k.dim);
    ASSERT_GE(v, 0.f);
    ASSERT_LT(v, 1.f);
  }
  EXPECT_LT(fraction_to_float(0xffffffffu), 1.f);
}

TEST(Samplers, SobolFirstDimensionIsVanDerCorput) {
  for (uint32_t i : {0u, 1u, 2u, 3u, 1000u, 123456789u}) EXPECT_EQ(sobol32(i, 0), reverse_bits32(i));
  // Second dimension (Joe-Kuo s=1, m=[1]): 1/2, 3/4, 1/4, 5/8 for indices 1..4 (Bratley-Fox
  // order without Gray code).
  EXPECT_EQ(sobol32(1, 1), 0x80000000u);
  EXPECT_EQ(sobol32(2, 1), 0xc0000000u);
  EXPECT_EQ(sobol32(3, 1), 0x40000000u);
  EXPECT_EQ(sobol32(4, 1), 0xa0000000u);
}

TEST(Samplers, NestedUniformScrambleIsABijectionPreservingAlignedBlocks) {
  // Output bit j depends only on input bits above j (in the reversed sense used here): inputs
  // sharing their top bits map to outputs sharing their top bits... checked as block mapping:
  // the image of an aligned block of 2^m indices is an aligned block.
  for (uint32_t seed : {0u, 1u, 0xdeadbeefu}) {
    for (uint32_t m : {0u, 3u, 8u}) {
      for (uint32_t k : {0u, 5u, 77u}) {
        std::vector<uint32_t> out;
        for (uint32_t i = 0; i < (1u << m); ++i)
          out.push_back(nested_uniform_scramble((k << m) + i, seed));
        std::sort(out.begin(), out.end());
        EXPECT_EQ(std::unique(out.begin(), out.end()), out.end());
        EXPECT_EQ(out.front() >> m, out.back() >> m);
        EXPECT_EQ(out.front() & ((1u << m) - 1u), 0u);
      }
    }
  }
}

// Checks that points [first, first + 2^m) of dimensions (dx, dy) form a (t, m, 2)-net: every
// elementary interval of area 2^(t-m), of every shape 2^-a x 2^-(m-t-a), holds exactly 2^t
// points (for m < t: the trivial requirement that there are 2^m points).
bool is_net(const Sampler& s, uint64_t pixel, uint32_t first, uint32_t t, uint32_t m,
            uint32_t dx, uint32_t dy) {
  const uint32_t n = 1u << m;
  if (m <= t) return true;
  std::vector<uint32_t> xs(n), ys(n);
  for (uint32_t i = 0; i < n; ++i) {
    xs[i] = s.bits(pixel, first + i, dx);
    ys[i] = s.bits(pixel, first + i, dy);
  }
  const uint32_t k = m - t;  // log2 of the number of intervals
  for (uint32_t a = 0; a <= k; ++a) {
    std::vector<uint32_t> count(size_t(1) << k, 0);
    for (uint32_t i = 0; i < n; ++i) {
      const uint32_t cx = a ? xs[i] >> (32 - a) : 0;
      const uint32_t cy = (k - a) ? ys[i] >> (32 - (k - a)) : 0;
      if (++count[(cx << (k - a)) | cy] > (1u << t)) return false;
    }
  }
  return true;
}
bool is_02_net(const Sampler& s, uint64_t pixel, uint32_t first, uint32_t m, uint32_t dx,
               uint32_t dy) {
  return is_net(s, pixel, first, 0, m, dx, dy);
}

TEST(Samplers, SobolPairsAreZeroMTwoNets) {
  for (uint64_t seed : {0ull, 17ull}) {
    const Sampler s(SamplerType::Sobol, seed);
    for (uint64_t pixel : {0ull, 12345ull}) {
      for (uint32_t m = 0; m <= 10; ++m) {
        // Whole prefixes and aligned blocks (the batches of the farm's schedule).
        for (uint32_t block : {0u, 1u, 3u, 6u}) {
          const uint32_t first = block << m;
          // Every consecutive pair is a padded copy of Sobol dimensions 0 and 1.
          for (uint32_t d = 0; d < 12; d += 2) {
            EXPECT_TRUE(is_02_net(s, pixel, first, m, d, d + 1))
                << "dims " << d << "," << d + 1 << " m=" << m << " block " << block;
          }
        }
      }
    }
  }
}

TEST(Samplers, RawSobolDims23AreNotAZeroNet) {
  // Why pairs are padded rather than quadruples: with Joe-Kuo's direction numbers, Sobol
  // dimensions 2 and 3 share m_1 = 1 and m_2 = 3, so their first 4 points coincide (on the
  // diagonal), which is not a (0, 2, 2)-net.
  for (uint32_t i = 0; i < 4; ++i) EXPECT_EQ(sobol32(i, 2), sobol32(i, 3));
}

TEST(Samplers, IndependentIsNotANet) {
  // Control for the net test: random points almost surely leave some interval empty.
  const Sampler s(SamplerType::Independent, 0);
  EXPECT_FALSE(is_02_net(s, 0, 0, 8, 0, 1));
}

double chi2_critical(int dof) {  // significance 1e-3, Wilson-Hilferty
  const double k = dof, z = 3.09;
  const double t = 1.0 - 2.0 / (9.0 * k) + z * std::sqrt(2.0 / (9.0 * k));
  return k * t * t * t;
}

TEST(Samplers, IndependentIsUniform) {
  const Sampler s(SamplerType::Independent, 5);
  // 1D, per dimension, over many pixels and indices.
  for (uint32_t dim : {0u, 1u, 7u, 30u}) {
    const int bins = 100, n = 100000;
    std::vector<double> count(bins, 0.0);
    for (int i = 0; i < n; ++i)
      count[size_t(s.value(uint64_t(i % 997), uint32_t(i / 997), dim) * bins)] += 1.0;
    double stat = 0.0;
    const double e = double(n) / bins;
    for (double c : count) stat += (c - e) * (c - e) / e;
    EXPECT_LT(stat, chi2_critical(bins - 1)) << "dim " << dim;
  }
  // 2D joint uniformity of a dimension pair within one pixel.
  const int side = 16, n = 100000;
  std::vector<double> count(side * side, 0.0);
  for (int i = 0; i < n; ++i) {
    const int x = int(s.value(3, uint32_t(i), 3) * side), y = int(s.value(3, uint32_t(i), 4) * side);
    count[size_t(y * side + x)] += 1.0;
  }
  double stat = 0.0;
  const double e = double(n) / (side * side);
  for (double c : count) stat += (c - e) * (c - e) / e;
  EXPECT_LT(stat, chi2_critical(side * side - 1));
}

TEST(Samplers, ParseNames) {
  SamplerType t;
  EXPECT_TRUE(parse_sampler_type("sobol", &t));
  EXPECT_EQ(t, SamplerType::Sobol);
  EXPECT_TRUE(parse_sampler_type("independent", &t));
  EXPECT_EQ(t, SamplerType::Independent);
  EXPECT_FALSE(parse_sampler_type("halton", &t));
}

}  // namespace
}  // namespace rf
