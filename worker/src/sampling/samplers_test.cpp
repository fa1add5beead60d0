#include "sampling/samplers.h"

#include <gtest/gtest.h>

#include "testing/chi_square.h"

#include <algorithm>
#include <random>
#include <string>
#include <utility>
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
  for (SamplerType type : {SamplerType::Sobol, SamplerType::Independent,
                           SamplerType::Stratified, SamplerType::Halton}) {
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
    // The per-pixel cached path (render_rect's) gives the same values, in any order.
    for (size_t i : order) {
      const PixelSampler ps(sampler, keys[i].pixel);
      ASSERT_EQ(ps.value(keys[i].index, keys[i].dim), fraction_to_float(reference[i]));
    }
    for (uint64_t pixel : {0ull, 511ull}) {
      const PixelSampler ps(sampler, pixel);
      for (uint32_t dim = 140; dim-- > 0;)
        for (uint32_t index : {69u, 3u, 0u})
          ASSERT_EQ(ps.value(index, dim), sampler.value(pixel, index, dim));
      // Pairs evaluated together (value2, sharing sobol's shuffled index) equal the values
      // one at a time, on a fresh sampler (seeds filled by value2) and on a filled one.
      const PixelSampler fresh(sampler, pixel);
      for (uint32_t dim = 0; dim < 140; dim += 2)
        for (uint32_t index : {0u, 5u, 1000u}) {
          const Point2 a = fresh.value2(index, dim), b = ps.value2(index, dim);
          ASSERT_EQ(a.x, sampler.value(pixel, index, dim));
          ASSERT_EQ(a.y, sampler.value(pixel, index, dim + 1));
          ASSERT_EQ(b.x, a.x);
          ASSERT_EQ(b.y, a.y);
        }
    }
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

using testing::chi2_critical;

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
  EXPECT_TRUE(parse_sampler_type("halton", &t));
  EXPECT_EQ(t, SamplerType::Halton);
  EXPECT_TRUE(parse_sampler_type("stratified", &t));
  EXPECT_EQ(t, SamplerType::Stratified);
  EXPECT_FALSE(parse_sampler_type("sobol2", &t));
  for (SamplerType u : {SamplerType::Sobol, SamplerType::Independent, SamplerType::Stratified,
                        SamplerType::Halton}) {
    ASSERT_TRUE(parse_sampler_type(sampler_type_name(u), &t));
    EXPECT_EQ(t, u);
  }
}

// The schedule of server/renderfarm/domain/tiling.py, written out from its specification: sizes
// 1, 1, 2, 4, 8, 16, 32, 64, 64, 64, ...; batch b starts at the sum of the earlier sizes.
TEST(BatchSchedule, MatchesTheFarmSchedule) {
  const uint64_t starts[] = {0, 1, 2, 4, 8, 16, 32, 64, 128, 192, 256, 320};
  const uint32_t sizes[] = {1, 1, 2, 4, 8, 16, 32, 64, 64, 64, 64, 64};
  for (uint32_t b = 0; b < 12; ++b) {
    EXPECT_EQ(batch_range(b).start, starts[b]) << b;
    EXPECT_EQ(batch_range(b).size, sizes[b]) << b;
    EXPECT_EQ(batch_range(b).index, b);
  }
  // Every index lies in exactly one batch; batches are powers of two aligned to their size.
  uint32_t expected_batch = 0;
  for (uint64_t i = 0; i < 5000; ++i) {
    if (i == batch_range(expected_batch).start + batch_range(expected_batch).size)
      ++expected_batch;
    const BatchRange r = batch_containing(i);
    ASSERT_EQ(r.index, expected_batch) << i;
    ASSERT_LE(r.start, i);
    ASSERT_LT(i, r.start + r.size);
    ASSERT_EQ(r.size & (r.size - 1), 0u);
    ASSERT_EQ(r.start % r.size, 0u);
  }
  EXPECT_EQ(batch_containing(63).index, 6u);
  EXPECT_EQ(batch_containing(64).index, 7u);
  EXPECT_EQ(batch_containing(191).index, 8u);
  EXPECT_EQ(batch_containing((uint64_t(1) << 31) - 1).start % 64, 0u);
}

TEST(Samplers, StratifiedBatchIsAJitteredGridPaddedWithLatinHypercubes) {
  const Sampler s(SamplerType::Stratified, 9);
  for (uint64_t pixel : {0ull, 77ull}) {
    for (uint32_t b = 0; b < 10; ++b) {
      const BatchRange r = batch_range(b);
      uint32_t k = 0;
      while ((1u << k) < r.size) ++k;
      const uint32_t nx = 1u << ((k + 1) / 2), ny = 1u << (k / 2);
      std::vector<int> cells(r.size, 0);
      std::vector<std::vector<int>> strata(6, std::vector<int>(r.size, 0));
      for (uint32_t j = 0; j < r.size; ++j) {
        const uint32_t i = uint32_t(r.start + j);
        const uint32_t cx = uint32_t(s.value(pixel, i, 0) * float(nx));
        const uint32_t cy = uint32_t(s.value(pixel, i, 1) * float(ny));
        ++cells[cy * nx + cx];
        for (uint32_t d = 2; d < 8; ++d) ++strata[d - 2][uint32_t(s.value(pixel, i, d) * float(r.size))];
      }
      for (int c : cells) EXPECT_EQ(c, 1) << "batch " << b;
      for (const auto& st : strata)
        for (int c : st) EXPECT_EQ(c, 1) << "batch " << b;
    }
  }
  // Different batches use different Latin hypercube permutations: batch 8 and 9 differ.
  int same = 0;
  for (uint32_t j = 0; j < 64; ++j)
    same += uint32_t(s.value(0, 128 + j, 4) * 64.f) == uint32_t(s.value(0, 192 + j, 4) * 64.f);
  EXPECT_LT(same, 16);
}

TEST(Samplers, HaltonFirstBToTheMPointsFillEveryElementaryInterval) {
  // Digit permutations keep the radical inverse's defining property: indices 0 .. b^m - 1
  // hit each interval [k b^-m, (k + 1) b^-m) exactly once.
  const Sampler s(SamplerType::Halton, 4);
  for (uint32_t dim : {0u, 1u, 2u, 5u, 40u}) {
    const uint32_t b = halton_base(dim);
    uint32_t n = b;
    while (n * b <= 256) n *= b;
    std::vector<int> hits(n, 0);
    for (uint32_t i = 0; i < n; ++i) ++hits[uint32_t(double(s.value(12, i, dim)) * n)];
    for (int h : hits) EXPECT_EQ(h, 1) << "dim " << dim << " base " << b;
  }
  EXPECT_EQ(halton_base(0), 2u);
  EXPECT_EQ(halton_base(1), 3u);
  EXPECT_EQ(halton_base(5), 13u);
  EXPECT_EQ(halton_base(255), 1619u);
}

TEST(Samplers, SobolFastPathEqualsTheDefinition) {
  // sobol_bits works in the bit-reversed domain; it must equal the nested definition.
  for (uint32_t i : {0u, 1u, 2u, 7u, 100u, 65535u, 123456789u, 0xffffffffu})
    for (uint32_t dim : {0u, 1u, 6u, 9u})
      for (uint32_t s1 : {0u, 0x9e3779b9u})
        for (uint32_t s2 : {0u, 0x7f4a7c15u})
          ASSERT_EQ(Sampler::sobol_bits(i, dim, s1, s2),
                    nested_uniform_scramble(sobol32(nested_uniform_scramble(i, s1), dim % 2), s2));
}

TEST(Samplers, BatchedBounceValuesEqualTheValuesOneAtATime) {
  // value8 computes a bounce's eight sobol dimensions together (vector lanes, Sobol dimension
  // 1 without tables); every value must equal the scalar definition, on fresh and filled
  // samplers and for any first dimension it accepts.
  const Sampler sobol(SamplerType::Sobol, 7);
  for (uint64_t pixel : {0ull, 12345ull, 4000000000ull}) {
    const PixelSampler ps(sobol, pixel);
    for (uint32_t first = 0; first + 8 <= PixelSampler::kCachedDimensions; first += 4)
      for (uint32_t index : {0u, 1u, 2u, 63u, 64u, 1000u, 123456789u, 0x7fffffffu}) {
        float v[8];
        ASSERT_TRUE(ps.value8(index, first, v));
        for (uint32_t k = 0; k < 8; ++k)
          ASSERT_EQ(v[k], sobol.value(pixel, index, first + k)) << first << " " << index;
      }
    float v[8] = {};
    EXPECT_FALSE(ps.value8(0, 2, v));  // not a multiple of 4
    EXPECT_FALSE(ps.value8(0, PixelSampler::kCachedDimensions - 4, v));
  }
  // The other samplers answer one value at a time.
  for (SamplerType type : {SamplerType::Independent, SamplerType::Stratified, SamplerType::Halton}) {
    const Sampler sampler(type, 7);
    const PixelSampler ps(sampler, 3);
    float v[8];
    EXPECT_FALSE(ps.value8(0, 4, v));
    // BounceSamples gives the same values through either path.
    const SampleStream s{&ps, 9};
    const BounceSamples b(s, 2);
    for (uint32_t k = 0; k < 8; ++k) ASSERT_EQ(b.get(k), sampler.value(3, 9, dim::bounce(2, k)));
  }
  const PixelSampler ps(sobol, 5);
  const SampleStream s{&ps, 77};
  for (uint32_t bounce : {0u, 1u, 14u, 15u, 40u}) {
    const BounceSamples b(s, bounce);
    for (uint32_t k = 0; k < 8; k += 2) {
      const Point2 p = b.get2(k);
      ASSERT_EQ(p.x, sobol.value(5, 77, dim::bounce(bounce, k)));
      ASSERT_EQ(p.y, sobol.value(5, 77, dim::bounce(bounce, k + 1)));
    }
  }
}

TEST(Samplers, LaneBatchedBounceValuesEqualTheValuesOneAtATime) {
  // value8_lanes computes a bounce's eight sobol dimensions for sixteen sample indices at once,
  // with the widest kernel this CPU runs; every kernel this CPU can run (SSE always, AVX2 and
  // AVX-512 where present) must give the scalar definition's values for every lane.
  const std::vector<std::pair<std::string, Sobol8LanesKernel>> kernels = sobol8_lanes_kernels();
  ASSERT_GE(kernels.size(), 1u);
  EXPECT_EQ(kernels[0].first, "sse");
  std::mt19937 rng(11);
  const Sampler sobol(SamplerType::Sobol, 7);
  int compared = 0;
  for (uint64_t pixel : {0ull, 12345ull, 4000000000ull}) {
    const PixelSampler ps(sobol, pixel);
    for (uint32_t first = 0; first + 8 <= PixelSampler::kCachedDimensions; first += 4) {
      uint32_t index[PixelSampler::kLanes16];
      for (int l = 0; l < PixelSampler::kLanes16; ++l)
        index[l] = l < 8 ? uint32_t(first * 3 + l) : uint32_t(rng());
      float out[8][PixelSampler::kLanes16];
      ASSERT_TRUE(ps.value8_lanes(index, first, out));
      // The kernels themselves, on the seeds value8_lanes filled.
      uint32_t shuffle[4], scramble[8];
      const uint64_t key = sobol.sobol_pixel_key(pixel);
      for (uint32_t k = 0; k < 8; ++k) scramble[k] = Sampler::sobol_scramble_seed(key, first + k);
      for (uint32_t p = 0; p < 4; ++p)
        shuffle[p] = Sampler::sobol_shuffle_seed(key, first + 2 * p);
      for (const auto& [name, kernel] : kernels) {
        float direct[8][PixelSampler::kLanes16];
        kernel(index, shuffle, scramble, &direct[0][0]);
        for (uint32_t k = 0; k < 8; ++k)
          for (int l = 0; l < PixelSampler::kLanes16; ++l) {
            const float expected = sobol.value(pixel, index[l], first + k);
            ASSERT_EQ(direct[k][l], expected) << name << " " << first << " lane " << l;
            ASSERT_EQ(out[k][l], expected) << first << " lane " << l;
            ++compared;
          }
      }
    }
  }
  EXPECT_GE(compared, 3 * 31 * 8 * 16);
  // The other samplers decline.
  for (SamplerType type :
       {SamplerType::Independent, SamplerType::Stratified, SamplerType::Halton}) {
    const Sampler sampler(type, 7);
    const PixelSampler ps(sampler, 3);
    uint32_t index[PixelSampler::kLanes16] = {};
    float out[8][PixelSampler::kLanes16];
    EXPECT_FALSE(ps.value8_lanes(index, 4, out));
  }
}

TEST(Samplers, PermuteIndexIsAPermutation) {
  for (uint32_t n : {1u, 2u, 3u, 5u, 64u, 97u, 1619u})
    for (uint64_t seed : {0ull, 1ull, 0xdeadbeefull}) {
      std::vector<int> seen(n, 0);
      for (uint32_t i = 0; i < n; ++i) ++seen[permute_index(i, n, seed)];
      for (int c : seen) ASSERT_EQ(c, 1) << n;
    }
}

// Randomized samplers are unbiased only if every single value is uniform over the
// randomization: check the marginal distribution of one (index, dimension) over pixels.
TEST(Samplers, StratifiedAndHaltonValuesAreUniformOverTheRandomization) {
  for (SamplerType type : {SamplerType::Stratified, SamplerType::Halton}) {
    const Sampler s(type, 11);
    for (uint32_t index : {0u, 5u, 100u})
      for (uint32_t dim : {0u, 1u, 3u, 6u, 300u}) {
        const int bins = 64, n = 40000;
        std::vector<double> count(bins, 0.0);
        for (int p = 0; p < n; ++p) count[size_t(s.value(uint64_t(p), index, dim) * bins)] += 1.0;
        double stat = 0.0;
        const double e = double(n) / bins;
        for (double c : count) stat += (c - e) * (c - e) / e;
        EXPECT_LT(stat, chi2_critical(bins - 1))
            << sampler_type_name(type) << " index " << index << " dim " << dim;
      }
  }
}

// The sobol sampler's per-pixel seeds (hashes of the pixel's key with the dimension) must make
// a pixel's dimensions independent of each other and of its neighbours': over many pixels, the
// pairs (value of dimension a, value of dimension b) at one sample index, and (dimension a at
// pixel p, dimension a at pixel p + 1), fill the unit square uniformly.
TEST(Samplers, SobolSeedsDecorrelateDimensionsAndPixels) {
  const Sampler s(SamplerType::Sobol, 5);
  const int side = 16, n = 40000;
  auto chi2 = [&](auto&& point) {
    std::vector<double> count(side * side, 0.0);
    for (int p = 0; p < n; ++p) {
      const auto [u, v] = point(uint64_t(p) * 7919u);
      count[size_t(int(u * side) * side + int(v * side))] += 1.0;
    }
    const double e = double(n) / (side * side);
    double stat = 0.0;
    for (double c : count) stat += (c - e) * (c - e) / e;
    return stat;
  };
  for (uint32_t index : {0u, 3u, 64u}) {
    for (auto [a, b] : {std::pair{0u, 1u}, {0u, 4u}, {4u, 12u}, {5u, 6u}, {2u, 100u},
                        {8u, 9u}}) {
      const double stat = chi2([&](uint64_t pixel) {
        return std::pair{s.value(pixel, index, a), s.value(pixel, index, b)};
      });
      EXPECT_LT(stat, chi2_critical(side * side - 1))
          << "index " << index << " dimensions " << a << ", " << b;
    }
    for (uint32_t d : {0u, 7u, 40u}) {
      const double stat = chi2([&](uint64_t pixel) {
        return std::pair{s.value(pixel, index, d), s.value(pixel + 1, index, d)};
      });
      EXPECT_LT(stat, chi2_critical(side * side - 1))
          << "index " << index << " dimension " << d << " of neighbouring pixels";
    }
  }
}

}  // namespace
}  // namespace rf
