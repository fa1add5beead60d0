// The ranked rows of the channel table (Cryptomatte: crypto_object, crypto_material): per
// pixel the 6 labels the most of a task's samples had at their camera ray's first hit, with
// their counts. Expected labels come from the construction of testing::ids_gltf_json (its
// cells, each a quad of a known node and material or nothing, seen by an orthographic camera
// spanning x in [-4, 4] and y in [-3, 3]), never from the renderer.
#include <gtest/gtest.h>

#include <map>
#include <memory>
#include <set>
#include <string>
#include <utility>
#include <vector>

#include "render/channels.h"
#include "render/integrators.h"
#include "testing/test_scenes.h"

namespace rf {
namespace {

using channels::Id;

constexpr uint32_t kWidth = 16, kHeight = 12;
constexpr uint32_t kPairs = 6;
constexpr uint32_t kDefaultMaterial = 0xFFFFFFFFu;  // the server's "default material" label

constexpr channels::Set kCryptoRows = channels::bit(Id::CryptoObject) |
                                      channels::bit(Id::CryptoMaterial) |
                                      channels::bit(Id::Coverage);

std::unique_ptr<Scene> load_ids_scene() {
  LoadOptions options;
  options.image_height = kHeight;  // the lines one pixel wide
  return std::make_unique<Scene>(
      load_gltf_from_string(testing::ids_gltf_json(), ".", "ids.gltf", nullptr, options));
}

RenderSettings settings_for(IntegratorType integrator, uint32_t width = kWidth) {
  RenderSettings settings;
  settings.width = width;
  settings.height = kHeight;
  settings.seed = 11;
  settings.max_depth = 2;
  settings.integrator = integrator;
  return settings;
}

// The cell of ids_gltf_json's grid at column c (x in [2c - 4, 2c - 2]), row r (y in
// [2 - 2r - 1, 2 - 2r + 1]).
const testing::IdCell& cell_at(uint32_t c, uint32_t r) {
  for (const testing::IdCell& cell : testing::ids_gltf_cells())
    if (cell.x0 == 4 * c && cell.y0 == 4 * r) return cell;
  ADD_FAILURE() << "no cell " << c << ", " << r;
  return testing::ids_gltf_cells().at(0);
}

// A cell's label in the crypto_material row: its glTF material plus one, or the default
// material's label for a primitive without a material; 0 for a cell without geometry.
uint32_t material_label(const testing::IdCell& cell) {
  if (cell.instance == 0) return 0;
  return cell.material ? cell.material : kDefaultMaterial;
}

using Pairs = std::vector<std::pair<uint32_t, uint32_t>>;  // (label, count), empty slots left out

// Pixel i's pairs of a ranked row, checked to be well formed: the used slots first, by count
// descending then label ascending, distinct labels, then (0, 0).
Pairs pairs_at(const std::vector<uint32_t>& row, size_t i) {
  Pairs out;
  bool ended = false;
  for (uint32_t k = 0; k < kPairs; ++k) {
    const uint32_t label = row.at(2 * kPairs * i + 2 * k);
    const uint32_t count = row.at(2 * kPairs * i + 2 * k + 1);
    EXPECT_EQ(label == 0, count == 0) << "pixel " << i << " slot " << k;
    if (label == 0) {
      ended = true;
      continue;
    }
    EXPECT_FALSE(ended) << "pixel " << i << ": a pair after an empty slot";
    if (!out.empty()) {
      const auto& [last_label, last_count] = out.back();
      EXPECT_TRUE(count < last_count || (count == last_count && label > last_label))
          << "pixel " << i << " slot " << k << ": out of order";
    }
    out.push_back({label, count});
  }
  return out;
}

uint32_t total(const Pairs& pairs) {
  uint32_t n = 0;
  for (const auto& p : pairs) n += p.second;
  return n;
}

std::set<uint32_t> labels(const Pairs& pairs) {
  std::set<uint32_t> out;
  for (const auto& p : pairs) out.insert(p.first);
  return out;
}

struct Crypto {
  std::vector<uint32_t> object, material;
  std::vector<float> coverage;
};

Crypto render_crypto(const Scene& scene, const RenderSettings& settings, uint64_t start,
                     uint32_t count) {
  TileBuffer tile;
  EXPECT_TRUE(render_rect(scene, settings, {0, 0, settings.width, settings.height}, start,
                          count, &tile, nullptr, kCryptoRows));
  const size_t pixels = size_t(settings.width) * settings.height;
  EXPECT_EQ(tile.ranked(Id::CryptoObject).size(), 2 * kPairs * pixels);
  EXPECT_EQ(tile.ranked(Id::CryptoMaterial).size(), 2 * kPairs * pixels);
  EXPECT_TRUE(tile.sum(Id::CryptoObject).empty()) << "ranked rows are not summed";
  EXPECT_TRUE(tile.ranked(Id::Instance).empty()) << "a row not asked for";
  return {tile.ranked(Id::CryptoObject), tile.ranked(Id::CryptoMaterial),
          tile.sum(Id::Coverage)};
}

// In the 2 x 2 inner pixels of every cell, a task of N samples gives one pair: the cell's node
// plus one and N, its material plus one (the default material's 0xFFFFFFFF for the primitive
// without one) and N; the cells of nothing give no pair at all. Every pixel's counts add up to
// its coverage (the samples that hit anything: every hit of this scene has a node and a
// label), and a pixel on a cell's edge has only labels of its cell and the cells around it.
// The same for a task at sample 0 and one at sample 5, with the path and the ao integrators.
TEST(CryptoRows, EachCellsInnerPixelsHaveItsNodeAndMaterialForEverySample) {
  const std::unique_ptr<Scene> scene = load_ids_scene();
  for (IntegratorType integrator : {IntegratorType::Path, IntegratorType::AmbientOcclusion})
    for (const auto& [start, n] : {std::pair<uint64_t, uint32_t>{0, 8}, {5, 7}}) {
      SCOPED_TRACE(std::string(integrator_type_name(integrator)) + " from sample " +
                   std::to_string(start));
      const Crypto crypto = render_crypto(*scene, settings_for(integrator), start, n);
      int inner = 0, empty = 0;
      for (const testing::IdCell& cell : testing::ids_gltf_cells())
        for (uint32_t y = cell.y0 + 1; y <= cell.y0 + 2; ++y)
          for (uint32_t x = cell.x0 + 1; x <= cell.x0 + 2; ++x) {
            const size_t i = size_t(y) * kWidth + x;
            const Pairs object = pairs_at(crypto.object, i);
            const Pairs material = pairs_at(crypto.material, i);
            ++inner;
            if (cell.instance == 0) {
              ++empty;
              EXPECT_TRUE(object.empty()) << x << ", " << y << ": " << cell.what;
              EXPECT_TRUE(material.empty()) << x << ", " << y << ": " << cell.what;
              EXPECT_EQ(crypto.coverage[i], 0.f) << x << ", " << y << ": " << cell.what;
              continue;
            }
            EXPECT_EQ(object, (Pairs{{cell.instance, n}}))
                << x << ", " << y << ": " << cell.what;
            EXPECT_EQ(material, (Pairs{{material_label(cell), n}}))
                << x << ", " << y << ": " << cell.what;
          }
      EXPECT_EQ(inner, 48);
      EXPECT_EQ(empty, 8);  // the cells of nothing and of the hole
      int partial = 0;
      for (uint32_t y = 0; y < kHeight; ++y)
        for (uint32_t x = 0; x < kWidth; ++x) {
          const size_t i = size_t(y) * kWidth + x;
          const Pairs object = pairs_at(crypto.object, i);
          const Pairs material = pairs_at(crypto.material, i);
          EXPECT_EQ(float(total(object)), crypto.coverage[i]) << x << ", " << y;
          EXPECT_EQ(float(total(material)), crypto.coverage[i]) << x << ", " << y;
          if (crypto.coverage[i] > 0.f && crypto.coverage[i] < float(n)) ++partial;
          // The labels of the pixel's cell and of the 8 around it.
          std::set<uint32_t> objects, materials;
          const int cx = int(x / 4), cy = int(y / 4);
          for (int r = cy - 1; r <= cy + 1; ++r)
            for (int c = cx - 1; c <= cx + 1; ++c) {
              if (r < 0 || r >= 3 || c < 0 || c >= 4) continue;
              const testing::IdCell& near = cell_at(uint32_t(c), uint32_t(r));
              if (near.instance == 0) continue;
              objects.insert(near.instance);
              materials.insert(material_label(near));
            }
          for (uint32_t l : labels(object))
            EXPECT_TRUE(objects.count(l)) << x << ", " << y << ": node label " << l;
          for (uint32_t l : labels(material))
            EXPECT_TRUE(materials.count(l)) << x << ", " << y << ": material label " << l;
        }
      // The lines' ribbons cover some pixels in part.
      EXPECT_GT(partial, 0);
    }
}

// At a width of 13 pixels the image still spans x in [-4, 4], so the cells' edges (x = -2, 0,
// 2) fall inside pixels 3, 6 and 9 (at 3.25, 6.5 and 9.75 pixels): those pixels see two cells
// and count the samples of both. In the inner rows of the top two cell rows (where the cells
// are whole quads or nothing), each pixel has exactly the labels of the cells its footprint
// overlaps, its counts add up to its coverage, which is every sample where all of those cells
// have geometry and none where none has. Pixel 6 of row 1 sees two nodes of one material
// (shared-1 and shared-2, green): one material pair of every sample; pixel 9 sees green and the
// primitive without a material.
TEST(CryptoRows, PixelsAcrossTwoCellsCountTheSamplesOfBoth) {
  constexpr uint32_t kNarrow = 13, kSamples = 16;
  const std::unique_ptr<Scene> scene = load_ids_scene();
  const Crypto crypto =
      render_crypto(*scene, settings_for(IntegratorType::Path, kNarrow), 0, kSamples);
  int two_cells = 0;
  for (uint32_t r = 0; r < 2; ++r)
    for (uint32_t y = 4 * r + 1; y <= 4 * r + 2; ++y)
      for (uint32_t x = 0; x < kNarrow; ++x) {
        SCOPED_TRACE("pixel " + std::to_string(x) + ", " + std::to_string(y));
        const size_t i = size_t(y) * kNarrow + x;
        // The pixel's footprint in x, and the cells it overlaps.
        const double x0 = -4.0 + 8.0 * x / kNarrow, x1 = -4.0 + 8.0 * (x + 1) / kNarrow;
        std::set<uint32_t> objects, materials;
        uint32_t cells = 0, with_geometry = 0;
        for (uint32_t c = 0; c < 4; ++c) {
          if (!(x0 < 2.0 * c - 2.0 && x1 > 2.0 * c - 4.0)) continue;
          ++cells;
          const testing::IdCell& cell = cell_at(c, r);
          if (cell.instance == 0) continue;
          ++with_geometry;
          objects.insert(cell.instance);
          materials.insert(material_label(cell));
        }
        if (cells == 2) ++two_cells;
        const Pairs object = pairs_at(crypto.object, i);
        const Pairs material = pairs_at(crypto.material, i);
        EXPECT_EQ(labels(object), objects);
        EXPECT_EQ(labels(material), materials);
        EXPECT_EQ(float(total(object)), crypto.coverage[i]);
        EXPECT_EQ(float(total(material)), crypto.coverage[i]);
        if (with_geometry == cells) {
          EXPECT_EQ(crypto.coverage[i], float(kSamples));
        } else if (with_geometry == 0) {
          EXPECT_EQ(crypto.coverage[i], 0.f);
        } else {
          EXPECT_GT(crypto.coverage[i], 0.f);
          EXPECT_LT(crypto.coverage[i], float(kSamples));
        }
      }
  EXPECT_EQ(two_cells, 12);  // pixels 3, 6 and 9 of 4 rows
  for (uint32_t y : {1u, 2u}) {
    const size_t at6 = size_t(y) * kNarrow + 6, at9 = size_t(y) * kNarrow + 9;
    EXPECT_EQ(labels(pairs_at(crypto.object, at6)), (std::set<uint32_t>{6, 3}));
    EXPECT_EQ(pairs_at(crypto.material, at6), (Pairs{{2, kSamples}}));
    EXPECT_EQ(labels(pairs_at(crypto.material, at9)),
              (std::set<uint32_t>{2, kDefaultMaterial}));
  }
}

// A task's pairs are the same bytes every time, whether its pixels are rendered in one rect or
// in four; asking for the ranked rows changes none of the other rows, and a task that does
// not ask for them gets none.
TEST(CryptoRows, TheSameTaskGivesTheSameBytes) {
  const std::unique_ptr<Scene> scene = load_ids_scene();
  const RenderSettings settings = settings_for(IntegratorType::Path);
  const channels::Set rows = kCryptoRows | channels::bit(Id::Rgb) |
                             channels::bit(Id::Luminance) | channels::bit(Id::Albedo);
  TileBuffer whole, again, plain;
  ASSERT_TRUE(render_rect(*scene, settings, {0, 0, kWidth, kHeight}, 3, 9, &whole, nullptr,
                          rows));
  ASSERT_TRUE(render_rect(*scene, settings, {0, 0, kWidth, kHeight}, 3, 9, &again, nullptr,
                          rows));
  EXPECT_EQ(whole.ranked(Id::CryptoObject), again.ranked(Id::CryptoObject));
  EXPECT_EQ(whole.ranked(Id::CryptoMaterial), again.ranked(Id::CryptoMaterial));
  for (uint32_t y0 : {0u, 6u})
    for (uint32_t x0 : {0u, 8u}) {
      TileBuffer part;
      ASSERT_TRUE(render_rect(*scene, settings, {x0, y0, 8, 6}, 3, 9, &part, nullptr, rows));
      for (uint32_t y = 0; y < 6; ++y)
        for (uint32_t x = 0; x < 8; ++x) {
          const size_t i = size_t(y) * 8 + x, w = size_t(y0 + y) * kWidth + (x0 + x);
          for (Id id : {Id::CryptoObject, Id::CryptoMaterial})
            for (uint32_t k = 0; k < 2 * kPairs; ++k)
              EXPECT_EQ(part.ranked(id)[2 * kPairs * i + k],
                        whole.ranked(id)[2 * kPairs * w + k])
                  << x0 + x << ", " << y0 + y;
        }
    }
  ASSERT_TRUE(render_rect(*scene, settings, {0, 0, kWidth, kHeight}, 3, 9, &plain, nullptr,
                          rows & ~channels::kRanked));
  EXPECT_TRUE(plain.ranked(Id::CryptoObject).empty());
  EXPECT_TRUE(plain.ranked(Id::CryptoMaterial).empty());
  EXPECT_EQ(plain.rgb_sum, whole.rgb_sum);
  EXPECT_EQ(plain.luminance_m2, whole.luminance_m2);
  EXPECT_EQ(plain.sum(Id::Albedo), whole.sum(Id::Albedo));
  EXPECT_EQ(plain.sum(Id::Coverage), whole.sum(Id::Coverage));
}

// Per-pixel adaptive sampling's mask (Task.active_pixels): the pixels it names get exactly the
// values of an unmasked render (a pixel's samples do not depend on its neighbours), every
// other pixel is 0 in every row, the ranked ones included.
TEST(CryptoRows, AMaskRendersOnlyItsPixels) {
  const std::unique_ptr<Scene> scene = load_ids_scene();
  const RenderSettings settings = settings_for(IntegratorType::Path);
  const channels::Set rows = kCryptoRows | channels::bit(Id::Rgb) |
                             channels::bit(Id::Luminance) | channels::bit(Id::Albedo) |
                             channels::bit(Id::Coverage);
  const size_t n = size_t(kWidth) * kHeight;
  std::vector<uint8_t> mask((n + 7) / 8, 0);
  std::vector<bool> on(n);
  for (size_t i = 0; i < n; ++i) {
    on[i] = (i * 7919u) % 5u < 2u;  // two pixels in five, scattered
    if (on[i]) mask[i / 8] = uint8_t(mask[i / 8] | (1u << (i % 8)));
  }
  TileBuffer whole, part;
  ASSERT_TRUE(render_rect(*scene, settings, {0, 0, kWidth, kHeight}, 3, 9, &whole, nullptr,
                          rows));
  ASSERT_TRUE(render_rect(*scene, settings, {0, 0, kWidth, kHeight}, 3, 9, &part, nullptr, rows,
                          nullptr, mask.data()));
  size_t active = 0;
  for (size_t i = 0; i < n; ++i) {
    active += on[i] ? 1u : 0u;
    for (size_t c = 0; c < 3; ++c) {
      EXPECT_EQ(part.rgb_sum[3 * i + c], on[i] ? whole.rgb_sum[3 * i + c] : 0.0) << i;
      EXPECT_EQ(part.sum(Id::Albedo)[3 * i + c], on[i] ? whole.sum(Id::Albedo)[3 * i + c] : 0.f);
    }
    EXPECT_EQ(part.luminance_m2[i], on[i] ? whole.luminance_m2[i] : 0.0) << i;
    EXPECT_EQ(part.sum(Id::Coverage)[i], on[i] ? whole.sum(Id::Coverage)[i] : 0.f) << i;
    for (Id id : {Id::CryptoObject, Id::CryptoMaterial})
      for (uint32_t k = 0; k < 2 * kPairs; ++k)
        EXPECT_EQ(part.ranked(id)[2 * kPairs * i + k],
                  on[i] ? whole.ranked(id)[2 * kPairs * i + k] : 0u)
            << i;
  }
  EXPECT_GT(active, n / 4);
  EXPECT_LT(active, n / 2);
  EXPECT_LT(part.rays, whole.rays);  // the stopped pixels were not traced
}

// Over a task of one sample, a pixel's one pair is that sample's first hit: the Instance row's
// node label, and the Material row's material label (its 0 for the default material being
// the ranked row's 0xFFFFFFFF), count 1; nothing where the sample missed.
TEST(CryptoRows, OneSampleIsTheInstanceAndMaterialRowsLabel) {
  const std::unique_ptr<Scene> scene = load_ids_scene();
  TileBuffer tile;
  ASSERT_TRUE(render_rect(*scene, settings_for(IntegratorType::Path), {0, 0, kWidth, kHeight},
                          0, 1, &tile, nullptr,
                          kCryptoRows | channels::bit(Id::Instance) |
                              channels::bit(Id::Material)));
  std::map<uint32_t, int> materials;
  for (size_t i = 0; i < size_t(kWidth) * kHeight; ++i) {
    const Pairs object = pairs_at(tile.ranked(Id::CryptoObject), i);
    const Pairs material = pairs_at(tile.ranked(Id::CryptoMaterial), i);
    if (tile.sum(Id::Coverage)[i] == 0.f) {
      EXPECT_TRUE(object.empty()) << "pixel " << i;
      EXPECT_TRUE(material.empty()) << "pixel " << i;
      continue;
    }
    const uint32_t id = uint32_t(tile.sum(Id::Instance)[i]);
    const uint32_t m = uint32_t(tile.sum(Id::Material)[i]);
    EXPECT_EQ(object, (Pairs{{id, 1}})) << "pixel " << i;
    EXPECT_EQ(material, (Pairs{{m ? m : kDefaultMaterial, 1}})) << "pixel " << i;
    if (!material.empty()) ++materials[material[0].first];
  }
  // The cells' materials (inks and the default material among them).
  EXPECT_GT(materials[kDefaultMaterial], 4);
  EXPECT_GT(materials[1], 4);
  EXPECT_GT(materials[2], 4);
}

}  // namespace
}  // namespace rf
