// The Instance and Material rows of the channel table (a window of one sample, type U32): the
// glTF node and the glTF material of the first hit of each pixel's camera ray, plus one (0:
// none). Expected values come from the construction of the scenes (testing::ids_gltf_json's
// cells, each a quad of a known node and material or nothing, and scenes built here), never
// from the renderer.
#include <gtest/gtest.h>

#include <fstream>
#include <memory>
#include <set>
#include <string>
#include <utility>
#include <vector>

#include "render/channels.h"
#include "render/integrators.h"
#include "render/reference.h"
#include "scene/animated_scene.h"
#include "testing/test_scenes.h"

namespace rf {
namespace {

constexpr uint32_t kWidth = 16, kHeight = 12;
constexpr float kBackground = 1e10f;  // the Depth row where the camera ray hit nothing

constexpr channels::Set kIdRows = channels::bit(channels::Id::Instance) |
                                  channels::bit(channels::Id::Material) |
                                  channels::bit(channels::Id::Depth);

LoadOptions ids_options(const std::string& variant = "") {
  LoadOptions options;
  options.image_height = kHeight;  // the lines one pixel wide
  options.variant = variant;
  return options;
}

std::unique_ptr<Scene> load_ids_scene(const std::string& variant = "") {
  return std::make_unique<Scene>(load_gltf_from_string(
      testing::ids_gltf_json(), ".", "ids.gltf", nullptr, ids_options(variant)));
}

RenderSettings settings_for(IntegratorType integrator) {
  RenderSettings settings;
  settings.width = kWidth;
  settings.height = kHeight;
  settings.seed = 5;
  settings.max_depth = 3;
  settings.integrator = integrator;
  return settings;
}

// The Instance, Material and Depth rows of the whole image over the one-sample batch at
// sample 0 (the only batch a server asks them of).
struct Ids {
  std::vector<float> instance, material, depth;
};
Ids render_ids(const Scene& scene, const RenderSettings& settings) {
  TileBuffer tile;
  EXPECT_TRUE(render_rect(scene, settings, {0, 0, kWidth, kHeight}, 0, 1, &tile, nullptr,
                          kIdRows));
  EXPECT_TRUE(tile.sum(channels::Id::Position).empty()) << "a row not asked for";
  Ids ids{tile.sum(channels::Id::Instance), tile.sum(channels::Id::Material),
          tile.sum(channels::Id::Depth)};
  EXPECT_EQ(ids.instance.size(), size_t(kWidth) * kHeight);
  EXPECT_EQ(ids.material.size(), size_t(kWidth) * kHeight);
  return ids;
}

// Calls f(cell, x, y) for the 2 x 2 inner pixels of each cell of ids_gltf_json's image.
template <typename F>
void for_inner_pixels(F f) {
  for (const testing::IdCell& cell : testing::ids_gltf_cells())
    for (uint32_t dy = 1; dy <= 2; ++dy)
      for (uint32_t dx = 1; dx <= 2; ++dx) f(cell, cell.x0 + dx, cell.y0 + dy);
}

// Every pixel's (instance, material) is one a cell has, or (0, 0): a pixel across a cell's
// edge sees one of the cells around it, never anything else.
void expect_known_pairs(const Ids& ids, bool variant) {
  std::set<std::pair<float, float>> known{{0.f, 0.f}};
  for (const testing::IdCell& cell : testing::ids_gltf_cells())
    known.insert({float(cell.instance),
                  float(variant ? cell.variant_material : cell.material)});
  for (size_t i = 0; i < ids.instance.size(); ++i)
    EXPECT_TRUE(known.count({ids.instance[i], ids.material[i]}))
        << "pixel " << i << ": " << ids.instance[i] << ", " << ids.material[i];
}

void expect_cells(const Ids& ids, bool variant) {
  for_inner_pixels([&](const testing::IdCell& cell, uint32_t x, uint32_t y) {
    const size_t i = size_t(y) * kWidth + x;
    EXPECT_EQ(ids.instance[i], float(cell.instance)) << x << ", " << y << ": " << cell.what;
    EXPECT_EQ(ids.material[i], float(variant ? cell.variant_material : cell.material))
        << x << ", " << y << ": " << cell.what;
    if (cell.instance == 0)
      EXPECT_EQ(ids.depth[i], kBackground) << x << ", " << y << ": " << cell.what;
    else
      EXPECT_LT(ids.depth[i], 11.f) << x << ", " << y << ": " << cell.what;
  });
  expect_known_pairs(ids, variant);
}

const IntegratorType kIntegrators[] = {IntegratorType::Path, IntegratorType::Direct,
                                       IntegratorType::AmbientOcclusion};

// Each cell's inner pixels have its node and material plus one: a node merged into the world
// triangles (after a degenerate triangle the Scene drops, and before transparent ones it
// moves after the opaque ones), the two instances of a shared mesh, EXT_mesh_gpu_instancing's
// two instances of one node, a morphed node, a MASK quad that stops the ray, what lies behind
// a BLEND quad of alpha 0 (and nothing behind a MASK quad under its cutoff), a primitive
// without a material (0), and lines (their material's points-and-lines variant reports the
// material; 0 for lines without one), whatever the integrator.
TEST(IdRows, EachPixelHasItsFirstHitsNodeAndMaterial) {
  const std::unique_ptr<Scene> scene = load_ids_scene();
  for (IntegratorType integrator : kIntegrators) {
    SCOPED_TRACE(integrator_type_name(integrator));
    expect_cells(render_ids(*scene, settings_for(integrator)), false);
  }
}

// KHR_materials_variants: with variant "v0" selected, the primitives it maps report the
// material it maps them to (the shared mesh's green -> blue, the primitive without a material
// -> red); the nodes are the same.
TEST(IdRows, TheSelectedVariantsMaterialIsReported) {
  const std::unique_ptr<Scene> scene = load_ids_scene("v0");
  expect_cells(render_ids(*scene, settings_for(IntegratorType::Path)), true);
}

// The packet tracer (trace_sample, the path and direct integrators), the scalar reference and
// the ao integrator record the same ids for the same sample in every pixel (edges included),
// for several samples; in the cells' inner pixels, the cell's.
TEST(IdRows, IntegratorsRecordTheSameIds) {
  const std::unique_ptr<Scene> scene = load_ids_scene();
  const RenderSettings path = settings_for(IntegratorType::Path);
  const RenderSettings direct = settings_for(IntegratorType::Direct);
  const RenderSettings ao = settings_for(IntegratorType::AmbientOcclusion);
  const Sampler sampler(path.sampler, path.seed);
  std::vector<std::pair<uint32_t, uint32_t>> expected(size_t(kWidth) * kHeight, {~0u, ~0u});
  for_inner_pixels([&](const testing::IdCell& cell, uint32_t x, uint32_t y) {
    expected[size_t(y) * kWidth + x] = {cell.instance, cell.material};
  });
  int hits = 0, misses = 0;
  for (uint32_t y = 0; y < kHeight; ++y)
    for (uint32_t x = 0; x < kWidth; ++x) {
      const PixelSampler pixel(sampler, uint64_t(y) * kWidth + x);
      for (uint32_t index : {0u, 1u, 5u}) {
        const SampleResult results[] = {
            trace_sample(*scene, path, pixel, x, y, index),
            trace_sample_reference(*scene, path, pixel, x, y, index),
            trace_sample(*scene, direct, pixel, x, y, index),
            trace_sample(*scene, ao, pixel, x, y, index),
            trace_sample_reference(*scene, ao, pixel, x, y, index)};
        const SampleResult& first = results[0];
        (first.depth > 0.f ? hits : misses) += 1;
        for (const SampleResult& r : results) {
          EXPECT_EQ(r.depth > 0.f, first.depth > 0.f) << x << ", " << y << " #" << index;
          EXPECT_EQ(r.instance_id, first.instance_id) << x << ", " << y << " #" << index;
          EXPECT_EQ(r.material_id, first.material_id) << x << ", " << y << " #" << index;
        }
        const auto& want = expected[size_t(y) * kWidth + x];
        if (want.first == ~0u) continue;  // an edge pixel
        EXPECT_EQ(first.instance_id, want.first) << x << ", " << y << " #" << index;
        EXPECT_EQ(first.material_id, want.second) << x << ", " << y << " #" << index;
      }
    }
  EXPECT_GT(hits, 100);
  EXPECT_GT(misses, 30);
}

// An animated scene's poses (its static part placed as one instance, the moving node 2 as an
// instance of the shared mesh at its world matrix, the node 4 whose morph weight is animated
// as a deformed mesh of its own at the identity, the lines as the pose's points-and-lines
// mesh) keep every node and material: the same cells at t = 0.25 (where node 2 stands at
// z = -0.125 and node 4's quad at z = 0.0625) and with the shutter open around t = 0.5
// (motion blur: node 2 and node 4 move during it).
TEST(IdRows, AnimatedPosesKeepTheNodes) {
  const std::string path = testing::test_path("ids-animated.gltf");
  {
    std::ofstream out(path, std::ios::binary);
    out << testing::ids_gltf_json(true);
  }
  LoadOptions options = ids_options();
  options.time = 0.25;
  const AnimatedScene animated(parse_gltf(path, nullptr, options), options);
  EXPECT_EQ(animated.moving_nodes(), 1u);    // node 2
  EXPECT_EQ(animated.deformed_nodes(), 1u);  // node 4
  const std::shared_ptr<const Scene> still = animated.pose(0.25);
  EXPECT_FALSE(still->has_motion());
  EXPECT_GE(still->instance_count(), 4u);  // node 2, node 4, crowd's two (and the lines)
  const Ids ids = render_ids(*still, settings_for(IntegratorType::Path));
  expect_cells(ids, false);
  // The posed geometry is where the animation puts it: depth from the camera at z = 10.
  const size_t slid = 1 * kWidth + 9, morphed = 5 * kWidth + 5;  // cells (8, 0) and (4, 4)
  EXPECT_NEAR(ids.depth[slid], 10.125f, 1e-4f);
  EXPECT_NEAR(ids.depth[morphed], 9.9375f, 1e-4f);

  Shutter shutter;
  shutter.open_s = -0.1;
  shutter.close_s = 0.1;
  const std::shared_ptr<const Scene> blurred = animated.pose(0.5, nullptr, shutter);
  EXPECT_TRUE(blurred->has_motion());
  for (IntegratorType integrator : kIntegrators) {
    SCOPED_TRACE(integrator_type_name(integrator));
    expect_cells(render_ids(*blurred, settings_for(integrator)), false);
  }
}

// A scene built from a SceneDescription (not from a glTF file) reports the nodes and glTF
// materials it gives, and 0 where it gives none: a MASK quad of no node (TriangleMesh::add
// leaves earlier triangles without one) whose material says glTF material 3, a degenerate
// triangle of node 99 the Scene drops, a quad of node 41 and a material of none (the Scene
// moves it before the MASK quad, an opaque triangle), and a mesh placed by an instance of
// node 7 and by one of none, whose material says glTF material 0.
TEST(IdRows, HandBuiltScenesReportTheNodesTheyGiveOrNone) {
  SceneDescription desc;
  desc.source = "hand-built";
  Material plain{"plain", {0.5f, 0.5f, 0.5f}, {0, 0, 0}};
  Material mask = plain;
  mask.alpha_mode = AlphaMode::Mask;
  mask.alpha = 0.8f;
  mask.gltf_index = 3;
  Material instanced = plain;
  instanced.gltf_index = 0;
  desc.materials = {plain, mask, instanced};
  // Quads of side 2 at the cells of ids_gltf_json's image (the same camera).
  auto quad = [](Vec3 c, uint32_t material, uint32_t node, TriangleMesh* mesh) {
    Triangle a, b;
    a.p[0] = c + Vec3(-1, -1, 0), a.p[1] = c + Vec3(1, -1, 0), a.p[2] = c + Vec3(1, 1, 0);
    b.p[0] = a.p[0], b.p[1] = a.p[2], b.p[2] = c + Vec3(-1, 1, 0);
    a.material = b.material = material;
    a.node = b.node = node;
    mesh->add(a);
    mesh->add(b);
  };
  quad({-3, 2, 0}, 1, kNoNode, &desc.world);
  Triangle degenerate;
  degenerate.node = 99;
  desc.world.add(degenerate);
  quad({-1, 2, 0}, 0, 41, &desc.world);
  ASSERT_EQ(desc.world.node.size(), 5u);
  EXPECT_EQ(desc.world.node[0], kNoNode);
  EXPECT_EQ(desc.world.triangle(3).node, 41u);
  Mesh mesh;
  mesh.name = "shared";
  quad({0, 0, 0}, 2, kNoNode, &mesh.geometry);
  EXPECT_TRUE(mesh.geometry.node.empty());
  desc.meshes.push_back(mesh);
  for (const auto& [x, node] : {std::pair<double, uint32_t>{1.0, 7}, {3.0, kNoNode}}) {
    Instance inst;
    inst.mesh = 0;
    inst.to_world.m[3][0] = x;
    inst.to_world.m[3][1] = 2.0;
    inst.node = node;
    desc.instances.push_back(inst);
  }
  Camera camera;
  camera.position = {0, 0, 10};
  camera.orthographic = true;
  camera.xmag = 4.f;
  camera.ymag = 3.f;
  desc.camera = camera;
  const Scene scene(std::move(desc));
  EXPECT_TRUE(scene.has_transparency());
  // Cells (0, 0) to (12, 0): instance, material; the row below them sees nothing.
  const std::pair<float, float> want[4] = {{0.f, 4.f}, {42.f, 0.f}, {8.f, 1.f}, {0.f, 1.f}};
  for (IntegratorType integrator : kIntegrators) {
    SCOPED_TRACE(integrator_type_name(integrator));
    const Ids ids = render_ids(scene, settings_for(integrator));
    for (uint32_t cell = 0; cell < 4; ++cell)
      for (uint32_t y : {1u, 2u})
        for (uint32_t x : {4 * cell + 1, 4 * cell + 2}) {
          const size_t i = size_t(y) * kWidth + x;
          EXPECT_LT(ids.depth[i], 11.f) << x << ", " << y;
          EXPECT_EQ(ids.instance[i], want[cell].first) << x << ", " << y;
          EXPECT_EQ(ids.material[i], want[cell].second) << x << ", " << y;
        }
    for (uint32_t x = 0; x < kWidth; ++x) {
      const size_t i = size_t(6) * kWidth + x;
      EXPECT_EQ(ids.depth[i], kBackground);
      EXPECT_EQ(ids.instance[i], 0.f);
      EXPECT_EQ(ids.material[i], 0.f);
    }
  }
}

// A result's U32 rows: the float32 sums of the one-sample batch (integers) packed as
// little-endian uint32, rounded to the nearest; what is not a number in [0, 2^32) as 0.
TEST(IdRows, PackingTurnsTheSumsIntoLittleEndianIntegers) {
  const std::string bytes = pack_f32_as_u32_le({0.f, 1.f, 258.f, 16777215.f, -1.f, 2.9999f});
  const unsigned char want[] = {0, 0, 0, 0, 1, 0, 0, 0, 2, 1, 0, 0,
                                0xff, 0xff, 0xff, 0, 0, 0, 0, 0, 3, 0, 0, 0};
  ASSERT_EQ(bytes.size(), sizeof want);
  for (size_t k = 0; k < sizeof want; ++k)
    EXPECT_EQ(static_cast<unsigned char>(bytes[k]), want[k]) << "byte " << k;
  EXPECT_EQ(unpack_u32_le(bytes), (std::vector<uint32_t>{0, 1, 258, 16777215, 0, 3}));
}

}  // namespace
}  // namespace rf
