// Textures through the glTF loader and the integrators' shading: base color (sRGB),
// KHR_texture_transform, normal maps, emissive textures; and unsupported extensions, which
// must produce a warning naming them, never a failure.
#include <gtest/gtest.h>

#include <cmath>
#include <cstring>

#include "render/integrators.h"
#include "render/shading.h"
#include "testing/test_scenes.h"

namespace rf {
namespace {

// 2 x 2 texels, sRGB: red green / blue white (top row first).
std::string checker_uri() {
  return testing::png_data_uri(2, 2, 3, {255, 0, 0, 0, 255, 0, 0, 0, 255, 255, 255, 255});
}

// A quad (see quad_gltf_buffers_json) with one material, seen by a narrow camera at +z.
std::string quad_scene(const std::string& material, const std::string& images,
                       const std::string& extra = "") {
  return R"({"asset": {"version": "2.0"}, )" + extra + R"(
  "scene": 0, "scenes": [{"nodes": [0]}],
  "nodes": [{"mesh": 0}],
  "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "NORMAL": 1, "TEXCOORD_0": 2},
                              "indices": 3, "material": 0}]}],
  "materials": [)" + material + R"(],
  "textures": [{"source": 0, "sampler": 0}],
  "samplers": [{"magFilter": 9728, "wrapS": 10497, "wrapT": 10497}],
  "images": [)" + images + R"(],
  )" + testing::quad_gltf_buffers_json() + "}";
}

// First-hit AOVs of the scene's 1x1 image (its camera is a narrow probe).
void probe(const Scene& scene, Vec3* albedo, Vec3* normal) {
  RenderSettings settings;
  settings.width = settings.height = 1;
  settings.integrator = IntegratorType::AmbientOcclusion;
  TileBuffer tile;
  EXPECT_TRUE(render_rect(scene, settings, {0, 0, 1, 1}, 0, 4, &tile));
  const std::vector<float>& a = tile.sum(channels::Id::Albedo);
  const std::vector<float>& n = tile.sum(channels::Id::Normal);
  *albedo = Vec3(a[0], a[1], a[2]) / 4.f;
  *normal = Vec3(n[0], n[1], n[2]) / 4.f;
}

std::unique_ptr<Scene> load_at(const std::string& json, float x, float y,
                               std::vector<std::string>* warnings) {
  SceneDescription desc = load_gltf_from_string(json, "", "quad.gltf", warnings);
  desc.camera = testing::look_at({x, y, 2.f}, {x, y, 0.f}, 1e-4f);
  return std::make_unique<Scene>(std::move(desc), warnings);
}

Vec3 albedo_at(const std::string& json, float x, float y) {
  std::vector<std::string> warnings;
  auto scene = load_at(json, x, y, &warnings);
  for (const auto& w : warnings) ADD_FAILURE() << "unexpected warning: " << w;
  Vec3 albedo, normal;
  probe(*scene, &albedo, &normal);
  return albedo;
}

void expect_color(Vec3 got, Vec3 want, const char* what) {
  for (int c = 0; c < 3; ++c) EXPECT_NEAR(got[c], want[c], 2e-3f) << what << " channel " << c;
}

// The shading point of the quad scene `json` at (0.1, 0.2), seen from +z; every warning the
// load gives is a failure.
ShadingPoint shade_quad(const std::string& json) {
  std::vector<std::string> warnings;
  SceneDescription desc = load_gltf_from_string(json, "", "quad.gltf", &warnings);
  for (const auto& w : warnings) ADD_FAILURE() << "unexpected warning: " << w;
  desc.camera = testing::look_at({0.f, 0.f, 2.f}, {0.f, 0.f, 0.f}, 1e-4f);
  const Scene scene(std::move(desc), &warnings);
  Hit hit;
  EXPECT_TRUE(scene.intersect({0.1f, 0.2f, 2.f}, {0.f, 0.f, -1.f}, 10.f, &hit, 0, 0));
  return make_shading_point(scene, hit, {0.f, 0.f, 1.f});
}

TEST(Textures, BaseColorTextureIsSampledInGltfUvConvention) {
  const std::string images = R"({"uri": ")" + checker_uri() + R"("})";
  const std::string mat = R"({"pbrMetallicRoughness": {"baseColorTexture": {"index": 0},
      "baseColorFactor": [1, 1, 1, 1], "metallicFactor": 0}})";
  const std::string json = quad_scene(mat, images);
  // Texel centers: uv (0.25, 0.25) is the top-left texel, at x = -0.5, y = +0.5.
  expect_color(albedo_at(json, -0.5f, 0.5f), {1, 0, 0}, "top-left red");
  expect_color(albedo_at(json, 0.5f, 0.5f), {0, 1, 0}, "top-right green");
  expect_color(albedo_at(json, -0.5f, -0.5f), {0, 0, 1}, "bottom-left blue");
  expect_color(albedo_at(json, 0.5f, -0.5f), {1, 1, 1}, "bottom-right white");
  // baseColorFactor multiplies; mid-gray sRGB 188 is linear ~0.5.
  const std::string gray = testing::png_data_uri(1, 1, 3, {188, 188, 188});
  const std::string json2 =
      quad_scene(R"({"pbrMetallicRoughness": {"baseColorTexture": {"index": 0},
                     "baseColorFactor": [0.5, 1, 1, 1], "metallicFactor": 0}})",
                 R"({"uri": ")" + gray + R"("})");
  const float lin = srgb_to_linear(188.f / 255.f);
  expect_color(albedo_at(json2, 0.f, 0.f), {0.5f * lin, lin, lin}, "factor x sRGB texel");
}

TEST(Textures, KhrTextureTransformOffsetScaleRotation) {
  const std::string images = R"({"uri": ")" + checker_uri() + R"("})";
  auto with = [&](const std::string& transform) {
    return quad_scene(R"({"pbrMetallicRoughness": {"metallicFactor": 0, "baseColorTexture":
        {"index": 0, "extensions": {"KHR_texture_transform": )" + transform + "}}}}",
                      images, R"("extensionsUsed": ["KHR_texture_transform"],)");
  };
  // uv (0.25, 0.25) + (0.5, 0) = (0.75, 0.25): top-right green.
  expect_color(albedo_at(with(R"({"offset": [0.5, 0]})"), -0.5f, 0.5f), {0, 1, 0}, "offset");
  // Rotation pi/2: u' = v, v' = -u -> (0.25, -0.25) wraps to (0.25, 0.75): bottom-left blue.
  expect_color(albedo_at(with(R"({"rotation": 1.5707963})"), -0.5f, 0.5f), {0, 0, 1},
               "rotation");
  // Scale 2 about the origin: (0.25, 0.25) -> (0.5, 0.5) + offset (0.25, 0.25) = (0.75, 0.75)
  // -> bottom-right white.
  expect_color(albedo_at(with(R"({"scale": [2, 2], "offset": [0.25, 0.25]})"), -0.5f, 0.5f),
               {1, 1, 1}, "scale");
}

TEST(Textures, NormalMapTiltsTheShadingNormal) {
  // Tangent-space normal (0.6, 0, 0.8) encoded as (n + 1) / 2 in 8 bits.
  const std::string nm = testing::png_data_uri(1, 1, 3, {204, 128, 230});
  const std::string json =
      quad_scene(R"({"pbrMetallicRoughness": {"metallicFactor": 0}, "normalTexture": {"index": 0}})",
                 R"({"uri": ")" + nm + R"("})");
  std::vector<std::string> warnings;
  auto scene = load_at(json, 0.1f, 0.2f, &warnings);
  Vec3 albedo, normal;
  probe(*scene, &albedo, &normal);
  // u grows along +x (tangent), v down the image = -y, so the bitangent (green up) is +y.
  EXPECT_NEAR(normal.x, 0.6f, 0.01f);
  EXPECT_NEAR(normal.y, 0.0f, 0.01f);
  EXPECT_NEAR(normal.z, 0.8f, 0.01f);
}

TEST(Textures, EmissiveTextureModulatesEmission) {
  // Emissive texture: left half black, right half white (2 x 1 texels).
  const std::string em = testing::png_data_uri(2, 1, 3, {0, 0, 0, 255, 255, 255});
  const std::string json = quad_scene(
      R"({"pbrMetallicRoughness": {"baseColorFactor": [0, 0, 0, 1], "metallicFactor": 0},
          "emissiveFactor": [2, 2, 2], "emissiveTexture": {"index": 0}})",
      R"({"uri": ")" + em + R"("})");
  for (float x : {-0.5f, 0.5f}) {
    std::vector<std::string> warnings;
    auto scene = load_at(json, x, 0.f, &warnings);
    RenderSettings settings;
    settings.width = settings.height = 1;
    TileBuffer tile;
    ASSERT_TRUE(render_rect(*scene, settings, {0, 0, 1, 1}, 0, 4, &tile));
    EXPECT_NEAR(tile.rgb_sum[0] / 4.0, x < 0.f ? 0.0 : 2.0, 1e-3) << x;
  }
}

TEST(Textures, UnsupportedExtensionsAndBrokenImagesWarnAndStillRender) {
  const std::string json = quad_scene(
      R"({"pbrMetallicRoughness": {"baseColorTexture": {"index": 0}, "metallicFactor": 0},
          "extensions": {"ADOBE_materials_thin_transparency": {"transmissionFactor": 1},
                         "KHR_materials_clearcoat": {"clearcoatFactor": 1}}})",
      R"({"uri": "data:image/png;base64,AAAA"})",
      R"("extensionsUsed": ["ADOBE_materials_thin_transparency", "KHR_materials_clearcoat"],)");
  std::vector<std::string> warnings;
  auto scene = load_at(json, 0.f, 0.f, &warnings);
  bool named = false, texture = false, clearcoat = false;
  for (const auto& w : warnings) {
    named = named || w.find("ADOBE_materials_thin_transparency") != std::string::npos;
    texture = texture || w.find("textures[0]") != std::string::npos;
    clearcoat = clearcoat || w.find("KHR_materials_clearcoat") != std::string::npos;
  }
  EXPECT_TRUE(named);
  EXPECT_TRUE(texture);
  EXPECT_FALSE(clearcoat);  // supported (layers_test.cpp)
  Vec3 albedo, normal;
  probe(*scene, &albedo, &normal);
  expect_color(albedo, {1, 1, 1}, "constant factor used");
}

// The layers' textures: clearcoatTexture (R) and clearcoatRoughnessTexture (G) linear,
// sheenColorTexture (RGB) sRGB, sheenRoughnessTexture (A) linear, and the coat's normal map
// with its scale, each read through its own slot.
TEST(Textures, LayerTexturesAreReadFromTheirChannels) {
  // One RGBA texel: (R, G, B, A) = (128, 64, 255, 51).
  const std::string texel = testing::png_data_uri(1, 1, 4, {128, 64, 255, 51});
  const std::string json = R"({"asset": {"version": "2.0"},
  "extensionsUsed": ["KHR_materials_clearcoat", "KHR_materials_sheen"],
  "scene": 0, "scenes": [{"nodes": [0]}],
  "nodes": [{"mesh": 0}],
  "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "NORMAL": 1, "TEXCOORD_0": 2},
                              "indices": 3, "material": 0}]}],
  "materials": [{"extensions": {
      "KHR_materials_clearcoat": {"clearcoatFactor": 1, "clearcoatTexture": {"index": 0},
                                  "clearcoatRoughnessFactor": 1,
                                  "clearcoatRoughnessTexture": {"index": 0}},
      "KHR_materials_sheen": {"sheenColorFactor": [1, 1, 1], "sheenColorTexture": {"index": 0},
                              "sheenRoughnessFactor": 1, "sheenRoughnessTexture": {"index": 0}}}}],
  "textures": [{"source": 0, "sampler": 0}],
  "samplers": [{"magFilter": 9728}],
  "images": [{"uri": ")" + texel + R"("}],
  )" + testing::quad_gltf_buffers_json() + "}";
  const ShadingPoint sp = shade_quad(json);
  EXPECT_NEAR(sp.params.clearcoat, 128.f / 255.f, 1e-3f);
  const float rc = 64.f / 255.f;
  EXPECT_NEAR(sp.params.clearcoat_alpha, rc * rc, 1e-3f);
  EXPECT_NEAR(sp.params.sheen.x, srgb_to_linear(128.f / 255.f), 1e-3f);
  EXPECT_NEAR(sp.params.sheen.y, srgb_to_linear(64.f / 255.f), 1e-3f);
  EXPECT_NEAR(sp.params.sheen.z, 1.f, 1e-3f);
  const float rs = 51.f / 255.f;
  EXPECT_NEAR(sp.params.sheen_alpha, rs * rs, 1e-3f);
  // No coat normal map: the coat's normal is the (flat) shading normal.
  EXPECT_NEAR(sp.params.clearcoat_n.z, 1.f, 1e-6f);
}

// ---- Image formats: EXT_texture_webp and EXT_texture_avif name their image in the
// extension's `source`, which replaces the texture's own (the PNG fallback below, black, so a
// texture that read the fallback would show black); KHR_texture_basisu, which this renderer
// cannot decode, falls back to the texture's own `source`.

// 16 x 16 texels in four solid 8 x 8 quadrants, sRGB: red green / blue white (top row
// first), so that the lossy codecs' 4:2:0 chroma and 8 x 8 blocks keep each quadrant's colour.
std::vector<unsigned char> quadrant_texels() {
  const unsigned char colours[4][3] = {{255, 0, 0}, {0, 255, 0}, {0, 0, 255}, {255, 255, 255}};
  std::vector<unsigned char> px;
  for (int y = 0; y < 16; ++y)
    for (int x = 0; x < 16; ++x)
      for (int c = 0; c < 3; ++c) px.push_back(colours[(y / 8) * 2 + x / 8][c]);
  return px;
}

// A quad whose base colour texture 0 has `texture` as its JSON (sampler 0, images: 0 a black
// PNG, 1 `image`).
std::string format_scene(const std::string& texture, const std::string& image,
                         const std::string& extensions) {
  const std::string black = testing::png_data_uri(1, 1, 3, {0, 0, 0});
  return R"({"asset": {"version": "2.0"}, )" + extensions + R"(
  "scene": 0, "scenes": [{"nodes": [0]}],
  "nodes": [{"mesh": 0}],
  "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "NORMAL": 1, "TEXCOORD_0": 2},
                              "indices": 3, "material": 0}]}],
  "materials": [{"pbrMetallicRoughness": {"baseColorTexture": {"index": 0},
                                          "metallicFactor": 0}}],
  "textures": [)" + texture + R"(],
  "samplers": [{"magFilter": 9728, "wrapS": 33071, "wrapT": 33071}],
  "images": [{"uri": ")" + black + R"("}, {"uri": ")" + image + R"("}],
  )" + testing::quad_gltf_buffers_json() + "}";
}

// The quadrants' centres (uv 0.25 / 0.75 at x, y = -+0.5) against the sRGB colours, within
// what a lossy codec at quality 100 changes (0.03 linear is about 4 levels at the top).
void expect_quadrants(const std::string& json, float tolerance, const char* what) {
  const struct {
    float x, y;
    Vec3 colour;
  } quadrants[] = {{-0.5f, 0.5f, {1, 0, 0}},
                   {0.5f, 0.5f, {0, 1, 0}},
                   {-0.5f, -0.5f, {0, 0, 1}},
                   {0.5f, -0.5f, {1, 1, 1}}};
  for (const auto& q : quadrants) {
    const Vec3 got = albedo_at(json, q.x, q.y);
    for (int c = 0; c < 3; ++c)
      EXPECT_NEAR(got[c], q.colour[c], tolerance) << what << " at " << q.x << ", " << q.y;
  }
}

TEST(TextureFormats, WebpAndAvifImagesReplaceTheTexturesSource) {
  for (const char* format : {"webp", "avif"}) {
    const std::string ext = std::string("EXT_texture_") + format;
    const std::string image = testing::image_data_uri(format, 16, 16, 3, quadrant_texels());
    // Used only, with the black PNG as the texture's own source (the fallback).
    expect_quadrants(
        format_scene(R"({"source": 0, "sampler": 0, "extensions": {")" + ext +
                         R"(": {"source": 1}}})",
                     image, R"("extensionsUsed": [")" + ext + R"("],)"),
        0.03f, format);
    // Required, without a fallback.
    expect_quadrants(format_scene(R"({"sampler": 0, "extensions": {")" + ext +
                                      R"(": {"source": 1}}})",
                                  image,
                                  R"("extensionsUsed": [")" + ext +
                                      R"("], "extensionsRequired": [")" + ext + R"("],)"),
                     0.03f, format);
  }
}

TEST(TextureFormats, ABrokenFormatExtensionIsRefusedNamingItsSource) {
  const std::string image = testing::png_data_uri(1, 1, 3, {255, 255, 255});
  for (const char* source : {R"("source": 7)", R"("source": "one")", R"("other": 1)"}) {
    const std::string json = format_scene(
        std::string(R"({"source": 0, "extensions": {"EXT_texture_webp": {)") + source + "}}}",
        image, R"("extensionsUsed": ["EXT_texture_webp"],)");
    try {
      load_gltf_from_string(json, "", "quad.gltf", nullptr);
      ADD_FAILURE() << source << " was accepted";
    } catch (const SceneError& e) {
      EXPECT_EQ(e.path(), "textures[0].extensions.EXT_texture_webp.source") << e.what();
    }
  }
}

TEST(TextureFormats, BasisUniversalFallsBackToTheSourceImageOrIsRefused) {
  const std::string white = testing::png_data_uri(1, 1, 3, {255, 255, 255});
  // With a fallback: the texture's own source (image 1, white), and a warning naming the
  // extension (the KTX2 image itself, image 0 here, is never read).
  {
    const std::string json = format_scene(
        R"({"source": 1, "sampler": 0, "extensions": {"KHR_texture_basisu": {"source": 0}}})",
        white, R"("extensionsUsed": ["KHR_texture_basisu"],)");
    std::vector<std::string> warnings;
    auto scene = load_at(json, 0.5f, 0.5f, &warnings);
    bool named = false;
    for (const auto& w : warnings)
      named = named || (w.find("textures[0]") != std::string::npos &&
                        w.find("KHR_texture_basisu") != std::string::npos &&
                        w.find("fallback") != std::string::npos);
    EXPECT_TRUE(named);
    Vec3 albedo, normal;
    probe(*scene, &albedo, &normal);
    expect_color(albedo, {1, 1, 1}, "the fallback image");
  }
  // Without one: refused, naming the texture's extension.
  try {
    load_gltf_from_string(
        format_scene(R"({"extensions": {"KHR_texture_basisu": {"source": 0}}})", white,
                     R"("extensionsUsed": ["KHR_texture_basisu"],)"),
        "", "quad.gltf", nullptr);
    ADD_FAILURE() << "a Basis Universal texture without a fallback was accepted";
  } catch (const SceneError& e) {
    EXPECT_EQ(e.path(), "textures[0].extensions.KHR_texture_basisu") << e.what();
  }
  // Required: refused at extensionsRequired, naming the extension.
  try {
    load_gltf_from_string(
        format_scene(R"({"extensions": {"KHR_texture_basisu": {"source": 0}}})", white,
                     R"("extensionsUsed": ["KHR_texture_basisu"],
                        "extensionsRequired": ["KHR_texture_basisu"],)"),
        "", "quad.gltf", nullptr);
    ADD_FAILURE() << "a scene requiring KHR_texture_basisu was accepted";
  } catch (const SceneError& e) {
    EXPECT_EQ(e.path(), "extensionsRequired[0]") << e.what();
    EXPECT_NE(std::string(e.what()).find("KHR_texture_basisu"), std::string::npos);
  }
}

// ---- Factors a rounding error outside [0, 1] are clamped with a warning naming the field;
// further out they are refused.

std::string factor_scene(const std::string& material) {
  return quad_scene(material, R"({"uri": ")" + testing::png_data_uri(1, 1, 3, {255, 255, 255}) +
                                  R"("})",
                    R"("extensionsUsed": ["KHR_materials_transmission"],)");
}

TEST(MaterialFactors, SlightlyOutOfRangeFactorsAreClampedWithAWarningNamingThem) {
  const std::string json = factor_scene(
      R"({"pbrMetallicRoughness": {"baseColorFactor": [1.0000001, 1.004, 0.5, 1],
                                   "metallicFactor": -0.002, "roughnessFactor": 1.001}})");
  std::vector<std::string> warnings;
  SceneDescription desc = load_gltf_from_string(json, "", "quad.gltf", &warnings);
  ASSERT_FALSE(desc.materials.empty());
  const Material& m = desc.materials[0];
  EXPECT_EQ(m.albedo.x, 1.f);
  EXPECT_EQ(m.albedo.y, 1.f);
  EXPECT_EQ(m.albedo.z, 0.5f);
  EXPECT_EQ(m.metallic, 0.f);
  EXPECT_EQ(m.roughness, 1.f);
  for (const char* field :
       {"materials[0].pbrMetallicRoughness.baseColorFactor[0]",
        "materials[0].pbrMetallicRoughness.baseColorFactor[1]",
        "materials[0].pbrMetallicRoughness.metallicFactor",
        "materials[0].pbrMetallicRoughness.roughnessFactor"}) {
    bool named = false;
    for (const auto& w : warnings)
      named = named || (w.find(field + std::string(":")) != std::string::npos &&
                        w.find("clamped") != std::string::npos);
    EXPECT_TRUE(named) << field;
  }
  for (const auto& w : warnings)
    EXPECT_EQ(w.find("baseColorFactor[2]"), std::string::npos) << "0.5 is in range: " << w;
}

TEST(MaterialFactors, FactorsFurtherOutAreRefusedNamingTheField) {
  const struct {
    const char* material;
    const char* path;
  } cases[] = {
      {R"({"pbrMetallicRoughness": {"baseColorFactor": [1, 1.5, 1, 1]}})",
       "materials[0].pbrMetallicRoughness.baseColorFactor[1]"},
      {R"({"pbrMetallicRoughness": {"metallicFactor": -0.5}})",
       "materials[0].pbrMetallicRoughness.metallicFactor"},
      {R"({"pbrMetallicRoughness": {"roughnessFactor": 1.02}})",
       "materials[0].pbrMetallicRoughness.roughnessFactor"},
      {R"({"extensions": {"KHR_materials_transmission": {"transmissionFactor": 2}}})",
       "materials[0].extensions.KHR_materials_transmission.transmissionFactor"},
  };
  for (const auto& c : cases) {
    try {
      load_gltf_from_string(factor_scene(c.material), "", "quad.gltf", nullptr);
      ADD_FAILURE() << c.material << " was accepted";
    } catch (const SceneError& e) {
      EXPECT_EQ(e.path(), c.path) << e.what();
    }
  }
}

// ---- A supplied TANGENT is used (glTF 3.7.2.1: MikkTSpace tangents only where it is absent):
// bitangent = cross(normal, tangent.xyz) x tangent.w.

// The quad facing +z with TEXCOORD_0 as quad_gltf_buffers_json's (u along +x) and the given
// TANGENT on every vertex, normal-mapped by one texel.
std::string tangent_scene(const float tangent[4], const std::string& texel) {
  std::vector<float> floats = {-1, -1, 0, 1, -1, 0, 1, 1, 0, -1, 1, 0,  // POSITION
                               0,  0,  1, 0, 0,  1, 0, 0, 1, 0,  0, 1,  // NORMAL
                               0,  1,  1, 1, 1,  0, 0, 0};              // TEXCOORD_0
  for (int v = 0; v < 4; ++v) floats.insert(floats.end(), tangent, tangent + 4);
  std::vector<unsigned char> bytes(floats.size() * 4);
  std::memcpy(bytes.data(), floats.data(), bytes.size());
  for (uint16_t i : {0, 1, 2, 0, 2, 3}) {
    bytes.push_back(uint8_t(i & 0xff));
    bytes.push_back(uint8_t(i >> 8));
  }
  return R"({"asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}],
  "nodes": [{"mesh": 0}],
  "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "NORMAL": 1, "TEXCOORD_0": 2,
                                             "TANGENT": 3}, "indices": 4, "material": 0}]}],
  "materials": [{"pbrMetallicRoughness": {"metallicFactor": 0}, "normalTexture": {"index": 0}}],
  "textures": [{"source": 0, "sampler": 0}], "samplers": [{"magFilter": 9728}],
  "images": [{"uri": ")" + texel + R"("}],
  "accessors": [
    {"bufferView": 0, "componentType": 5126, "count": 4, "type": "VEC3",
     "min": [-1, -1, 0], "max": [1, 1, 0]},
    {"bufferView": 0, "byteOffset": 48, "componentType": 5126, "count": 4, "type": "VEC3"},
    {"bufferView": 0, "byteOffset": 96, "componentType": 5126, "count": 4, "type": "VEC2"},
    {"bufferView": 0, "byteOffset": 128, "componentType": 5126, "count": 4, "type": "VEC4"},
    {"bufferView": 1, "componentType": 5123, "count": 6, "type": "SCALAR"}],
  "bufferViews": [{"buffer": 0, "byteLength": 192}, {"buffer": 0, "byteOffset": 192,
                                                     "byteLength": 12}],
  "buffers": [{"byteLength": 204, "uri": ")" +
         testing::data_uri("application/octet-stream", bytes) + R"("}]})";
}

TEST(Textures, ASuppliedTangentFramesTheNormalMap) {
  // Tangent-space normal (0, 0.6, 0.8) (green: along the bitangent), encoded (n + 1) / 2.
  const std::string texel = testing::png_data_uri(1, 1, 3, {128, 204, 230});
  const float c[3] = {128.f / 255.f, 204.f / 255.f, 230.f / 255.f};
  const Vec3 tn(2.f * c[0] - 1.f, 2.f * c[1] - 1.f, 2.f * c[2] - 1.f);
  const Vec3 n(0.f, 0.f, 1.f);
  const float tangents[3][4] = {{0, 1, 0, 1}, {0, 1, 0, -1}, {1, 0, 0, 1}};
  for (const auto& tangent : tangents) {
    const Vec3 t(tangent[0], tangent[1], tangent[2]);
    const Vec3 b = cross(n, t) * tangent[3];
    const Vec3 want = normalize(t * tn.x + b * tn.y + n * tn.z);
    std::vector<std::string> warnings;
    auto scene = load_at(tangent_scene(tangent, texel), 0.1f, 0.2f, &warnings);
    for (const auto& w : warnings) ADD_FAILURE() << "unexpected warning: " << w;
    Vec3 albedo, normal;
    probe(*scene, &albedo, &normal);
    for (int k = 0; k < 3; ++k)
      EXPECT_NEAR(normal[k], want[k], 0.01f)
          << "tangent (" << t.x << ", " << t.y << ", " << t.z << ", " << tangent[3] << ")";
  }
}

// KHR_materials_transmission: transmissionFactor x transmissionTexture.r (linear), and the
// material's roughness now shapes the glass lobe (no warning says it is dropped).
TEST(Textures, TransmissionTextureScalesTheFactorByItsRedChannel) {
  const std::string texel = testing::png_data_uri(1, 1, 3, {128, 255, 0});
  const std::string json = quad_scene(
      R"({"pbrMetallicRoughness": {"metallicFactor": 0, "roughnessFactor": 0.4},
          "extensions": {"KHR_materials_transmission": {"transmissionFactor": 0.8,
                                                        "transmissionTexture": {"index": 0}}}})",
      R"({"uri": ")" + texel + R"("})", R"("extensionsUsed": ["KHR_materials_transmission"],)");
  const ShadingPoint sp = shade_quad(json);
  EXPECT_NEAR(sp.params.transmission, 0.8f * 128.f / 255.f, 1e-3f);
  EXPECT_NEAR(sp.params.alpha, 0.4f * 0.4f, 1e-6f);
}

// KHR_materials_pbrSpecularGlossiness: specularGlossinessTexture's RGB (sRGB) times
// specularFactor is F0, its A (linear) times glossinessFactor the glossiness; the diffuse is
// diffuseFactor x diffuseTexture x (1 - max(F0)); the metallic-roughness fallback is not used.
TEST(Textures, SpecularGlossinessTexturesGiveTheExtensionsBrdfInputs) {
  const std::string texel = testing::png_data_uri(1, 1, 4, {128, 64, 200, 51});
  const std::string white = testing::png_data_uri(1, 1, 3, {255, 255, 255});
  const std::string json = R"({"asset": {"version": "2.0"},
  "extensionsUsed": ["KHR_materials_pbrSpecularGlossiness"],
  "scene": 0, "scenes": [{"nodes": [0]}],
  "nodes": [{"mesh": 0}],
  "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "NORMAL": 1, "TEXCOORD_0": 2},
                              "indices": 3, "material": 0}]}],
  "materials": [{"pbrMetallicRoughness": {"baseColorFactor": [1, 0, 1, 1], "metallicFactor": 1},
                 "extensions": {"KHR_materials_pbrSpecularGlossiness": {
                     "diffuseFactor": [0.5, 1, 1, 1], "diffuseTexture": {"index": 1},
                     "specularFactor": [1, 1, 0.5], "glossinessFactor": 0.8,
                     "specularGlossinessTexture": {"index": 0}}}}],
  "textures": [{"source": 0, "sampler": 0}, {"source": 1, "sampler": 0}],
  "samplers": [{"magFilter": 9728}],
  "images": [{"uri": ")" + texel + R"("}, {"uri": ")" + white + R"("}],
  )" + testing::quad_gltf_buffers_json() + "}";
  const ShadingPoint sp = shade_quad(json);
  const Vec3 f0(srgb_to_linear(128.f / 255.f), srgb_to_linear(64.f / 255.f),
                0.5f * srgb_to_linear(200.f / 255.f));
  const float rough = 1.f - 0.8f * 51.f / 255.f;
  EXPECT_EQ(sp.params.metallic, 0.f);
  EXPECT_NEAR(sp.params.alpha, rough * rough, 1e-4f);
  EXPECT_EQ(sp.params.specular, 1.f);
  const float keep = 1.f - std::max(f0.x, std::max(f0.y, f0.z));
  EXPECT_NEAR(sp.params.base.x, 0.5f * keep, 1e-3f);
  EXPECT_NEAR(sp.params.base.y, keep, 1e-3f);
  // F0 = ((ior - 1) / (ior + 1))^2 x specular colour, at the dielectric's ior 1.5.
  const float r2 = (sp.params.ior - 1.f) * (sp.params.ior - 1.f) /
                   ((sp.params.ior + 1.f) * (sp.params.ior + 1.f));
  for (int k = 0; k < 3; ++k) EXPECT_NEAR(r2 * sp.params.specular_color[k], f0[k], 1e-3f);
}

// KHR_materials_anisotropy: the direction in the tangent frame (here TEXCOORD_0's: tangent +x,
// bitangent +y), turned counter-clockwise by anisotropyRotation, becomes the shading frame's x
// axis, with alpha mix(alpha, 1, strength^2) along it; the texture's RG give the direction
// before the rotation and its B scales the strength.
TEST(Textures, AnisotropyDirectionAndStrengthFromFactorsAndTexture) {
  const std::string texel = testing::png_data_uri(1, 1, 3, {128, 255, 128});
  auto shade = [&](const std::string& anisotropy) {
    const std::string json = quad_scene(
        R"({"pbrMetallicRoughness": {"metallicFactor": 1, "roughnessFactor": 0.4},
            "extensions": {"KHR_materials_anisotropy": )" + anisotropy + "}}",
        R"({"uri": ")" + texel + R"("})", R"("extensionsUsed": ["KHR_materials_anisotropy"],)");
    return shade_quad(json);
  };
  const float alpha = 0.4f * 0.4f;
  // Rotation pi/2: from the tangent to the bitangent, +y.
  ShadingPoint sp = shade(R"({"anisotropyStrength": 0.5, "anisotropyRotation": 1.5707963})");
  EXPECT_NEAR(sp.tangent.x, 0.f, 1e-5f);
  EXPECT_NEAR(sp.tangent.y, 1.f, 1e-5f);
  EXPECT_NEAR(sp.params.alpha_t, alpha * 0.75f + 0.25f, 1e-6f);
  EXPECT_NEAR(sp.params.alpha, alpha, 1e-6f);
  // The texture: RG (0.5, 1) is direction (0, 1) (normalized), turned by pi/2 to -x; B 0.5
  // halves the strength.
  sp = shade(R"({"anisotropyStrength": 0.8, "anisotropyRotation": 1.5707963,
                 "anisotropyTexture": {"index": 0}})");
  const float dx = 2.f * 128.f / 255.f - 1.f;
  EXPECT_NEAR(sp.tangent.x, -1.f, 1e-4f);
  EXPECT_NEAR(sp.tangent.y, dx, 1e-3f);
  const float strength = 0.8f * 128.f / 255.f;
  EXPECT_NEAR(sp.params.alpha_t, alpha * (1.f - strength * strength) + strength * strength, 1e-4f);
  // Strength 0: isotropic.
  sp = shade(R"({"anisotropyStrength": 0})");
  EXPECT_FALSE(sp.params.anisotropic());
}

// KHR_materials_iridescence: iridescenceFactor x iridescenceTexture.r, the film's ior, and its
// thickness mix(minimum, maximum, iridescenceThicknessTexture.g) (the maximum without it).
TEST(Textures, IridescenceFactorsAndTexturesReachTheBsdf) {
  const std::string texel = testing::png_data_uri(1, 1, 3, {128, 64, 255});
  auto shade = [&](const std::string& iridescence) {
    const std::string json = quad_scene(
        R"({"pbrMetallicRoughness": {"metallicFactor": 0},
            "extensions": {"KHR_materials_iridescence": )" + iridescence + "}}",
        R"({"uri": ")" + texel + R"("})", R"("extensionsUsed": ["KHR_materials_iridescence"],)");
    return shade_quad(json).params;
  };
  BsdfParams p = shade(R"({"iridescenceFactor": 0.6, "iridescenceIor": 1.42,
                           "iridescenceThicknessMaximum": 620})");
  EXPECT_NEAR(p.iridescence, 0.6f, 1e-6f);
  EXPECT_NEAR(p.iridescence_ior, 1.42f, 1e-6f);
  EXPECT_NEAR(p.iridescence_thickness, 620.f, 1e-3f);
  p = shade(R"({"iridescenceFactor": 0.6, "iridescenceTexture": {"index": 0},
                "iridescenceThicknessMinimum": 100, "iridescenceThicknessMaximum": 500,
                "iridescenceThicknessTexture": {"index": 0}})");
  EXPECT_NEAR(p.iridescence, 0.6f * 128.f / 255.f, 1e-3f);
  EXPECT_NEAR(p.iridescence_ior, 1.3f, 1e-6f);  // the default
  EXPECT_NEAR(p.iridescence_thickness, 100.f + 400.f * 64.f / 255.f, 0.5f);
}

// KHR_materials_diffuse_transmission: diffuseTransmissionFactor x diffuseTransmissionTexture.a
// (linear), diffuseTransmissionColorFactor x diffuseTransmissionColorTexture.rgb (sRGB,
// decoded: 188 is 0.5029 linear by the sRGB transfer function).
TEST(Textures, DiffuseTransmissionFactorsAndTexturesReachTheBsdf) {
  const std::string texel = testing::png_data_uri(1, 1, 4, {188, 255, 0, 51});
  auto shade = [&](const std::string& dt) {
    const std::string json = quad_scene(
        R"({"pbrMetallicRoughness": {"metallicFactor": 0},
            "extensions": {"KHR_materials_diffuse_transmission": )" + dt + "}}",
        R"({"uri": ")" + texel + R"("})",
        R"("extensionsUsed": ["KHR_materials_diffuse_transmission"],)");
    return shade_quad(json).params;
  };
  BsdfParams p = shade(R"({"diffuseTransmissionFactor": 0.6,
                           "diffuseTransmissionColorFactor": [0.2, 0.4, 0.8]})");
  EXPECT_NEAR(p.diffuse_transmission, 0.6f, 1e-6f);
  EXPECT_NEAR(p.diffuse_transmission_color.y, 0.4f, 1e-6f);
  p = shade(R"({"diffuseTransmissionFactor": 0.6, "diffuseTransmissionTexture": {"index": 0},
                "diffuseTransmissionColorTexture": {"index": 0}})");
  EXPECT_NEAR(p.diffuse_transmission, 0.6f * 51.f / 255.f, 1e-3f);
  const double linear = std::pow((188.0 / 255.0 + 0.055) / 1.055, 2.4);
  EXPECT_NEAR(p.diffuse_transmission_color.x, linear, 2e-3);
  EXPECT_NEAR(p.diffuse_transmission_color.y, 1.f, 1e-3f);
  EXPECT_NEAR(p.diffuse_transmission_color.z, 0.f, 1e-3f);
  p = shade(R"({})");  // the default factor is 0: no BTDF
  EXPECT_EQ(p.diffuse_transmission, 0.f);
}

// KHR_materials_ior: any index from the schema's minimum of 1 up renders as given (a real
// asset writes 1000 for a near-perfect mirror); below 1 the default 1.5 with a warning.
TEST(Textures, AnyIorFromOneUpIsTheFilesValue) {
  const std::string texel = testing::png_data_uri(1, 1, 3, {255, 255, 255});
  const std::string images = R"({"uri": ")" + texel + R"("})";
  const std::string used = R"("extensionsUsed": ["KHR_materials_ior"],)";
  for (float ior : {1.f, 2.4f, 1000.f}) {
    const BsdfParams p = shade_quad(quad_scene(
        R"({"extensions": {"KHR_materials_ior": {"ior": )" + std::to_string(ior) + "}}}",
        images, used)).params;
    EXPECT_NEAR(p.ior, ior, 1e-3f * ior);
  }
  std::vector<std::string> warnings;
  const SceneDescription d = load_gltf_from_string(
      quad_scene(R"({"extensions": {"KHR_materials_ior": {"ior": 0.5}}})", images, used), "",
      "quad.gltf", &warnings);
  EXPECT_EQ(d.materials[0].ior, 1.5f);
  bool warned = false;
  for (const std::string& w : warnings)
    warned = warned || w.find("materials[0]: KHR_materials_ior.ior") != std::string::npos;
  EXPECT_TRUE(warned);
}

// KHR_materials_dispersion: the dispersion reaches a transmissive material's BSDF (the path
// tracer then picks the wavelength), not an opaque one's; a negative value is refused by path.
TEST(Textures, DispersionReachesTransmissiveMaterials) {
  const std::string texel = testing::png_data_uri(1, 1, 3, {255, 255, 255});
  auto material = [](const std::string& transmission, const std::string& dispersion) {
    return R"({"pbrMetallicRoughness": {"metallicFactor": 0}, "extensions": {
               "KHR_materials_transmission": {"transmissionFactor": )" + transmission + R"(},
               "KHR_materials_dispersion": {"dispersion": )" + dispersion + "}}}";
  };
  const std::string used =
      R"("extensionsUsed": ["KHR_materials_transmission", "KHR_materials_dispersion"],)";
  const std::string images = R"({"uri": ")" + texel + R"("})";
  BsdfParams p = shade_quad(quad_scene(material("1", "0.36"), images, used)).params;
  EXPECT_NEAR(p.dispersion, 0.36f, 1e-6f);
  EXPECT_NEAR(p.ior, 1.5f, 1e-6f);  // n_d: the index at the d line until a path disperses it
  p = shade_quad(quad_scene(material("0", "0.36"), images, used)).params;
  EXPECT_EQ(p.dispersion, 0.f);
  std::vector<std::string> warnings;
  try {
    load_gltf_from_string(quad_scene(material("1", "-0.5"), images, used), "", "quad.gltf",
                          &warnings);
    ADD_FAILURE() << "a negative dispersion was accepted";
  } catch (const SceneError& e) {
    EXPECT_EQ(e.path(), "materials[0].extensions.KHR_materials_dispersion.dispersion");
  }
}

}  // namespace
}  // namespace rf
