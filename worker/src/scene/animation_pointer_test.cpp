// KHR_animation_pointer's pointers: what they resolve to (RFC 6901 tokens against the glTF
// object model), which are refused as missing (the file is invalid) or ignored (not animatable
// here), and the values written into the tinygltf objects the loader then reads.
#include "scene/animation_pointer.h"

#include <gtest/gtest.h>
#include <tiny_gltf.h>

namespace rf {
namespace {

tinygltf::Model model_of(const std::string& json) {
  tinygltf::TinyGLTF gltf;
  gltf.SetImageLoader([](tinygltf::Image*, const int, std::string*, std::string*, int, int,
                         const unsigned char*, int, void*) { return true; },
                      nullptr);
  tinygltf::Model model;
  std::string err, warn;
  EXPECT_TRUE(gltf.LoadASCIIFromString(&model, &err, &warn, json.data(), unsigned(json.size()),
                                       ""))
      << err;
  return model;
}

const char* kDocument = R"({"asset": {"version": "2.0"},
  "nodes": [{"name": "a"}, {"name": "b"}],
  "materials": [{
     "pbrMetallicRoughness": {"baseColorFactor": [1, 0, 0, 1],
       "baseColorTexture": {"index": 0,
         "extensions": {"KHR_texture_transform": {"offset": [0, 0]}}}},
     "normalTexture": {"index": 0},
     "extensions": {
       "KHR_materials_emissive_strength": {"emissiveStrength": 2},
       "KHR_materials_sheen": {},
       "KHR_materials_clearcoat": {"clearcoatFactor": 1,
         "clearcoatTexture": {"index": 0,
           "extensions": {"KHR_texture_transform": {"rotation": 0.5}}}}}}],
  "textures": [{"source": 0}],
  "images": [{"uri": "data:image/png;base64,AAAA"}],
  "cameras": [{"type": "perspective", "perspective": {"yfov": 0.7, "znear": 0.1}}],
  "extensions": {"KHR_lights_punctual": {"lights": [{"type": "point", "intensity": 3},
                                                   {"type": "spot", "spot": {}}]}}})";

struct Resolved {
  bool ok = false, missing = false;
  PointerTarget target;
  std::string why;
};

Resolved resolve(const tinygltf::Model& model, const std::string& pointer) {
  Resolved r;
  r.ok = resolve_pointer(model, pointer, &r.target, &r.why, &r.missing);
  return r;
}

TEST(AnimationPointer, ResolvesTheObjectModelsMutableProperties) {
  const tinygltf::Model model = model_of(kDocument);
  struct Case {
    const char* pointer;
    PointerTarget::Kind kind;
    size_t components;
  };
  const Case cases[] = {
      {"/nodes/1/rotation", PointerTarget::Kind::NodeRotation, 4},
      {"/nodes/0/translation", PointerTarget::Kind::NodeTranslation, 3},
      {"/nodes/0/scale", PointerTarget::Kind::NodeScale, 3},
      {"/nodes/0/extensions/KHR_node_visibility/visible", PointerTarget::Kind::NodeVisible, 1},
      {"/materials/0/pbrMetallicRoughness/baseColorFactor", PointerTarget::Kind::Material, 4},
      {"/materials/0/pbrMetallicRoughness/roughnessFactor", PointerTarget::Kind::Material, 1},
      {"/materials/0/emissiveFactor", PointerTarget::Kind::Material, 3},
      {"/materials/0/normalTexture/scale", PointerTarget::Kind::Material, 1},
      {"/materials/0/extensions/KHR_materials_emissive_strength/emissiveStrength",
       PointerTarget::Kind::Material, 1},
      // Not in the file, but the extension is, and gives it a default: a colour.
      {"/materials/0/extensions/KHR_materials_sheen/sheenColorFactor",
       PointerTarget::Kind::Material, 3},
      {"/materials/0/pbrMetallicRoughness/baseColorTexture/extensions/KHR_texture_transform/"
       "offset",
       PointerTarget::Kind::Material, 2},
      {"/materials/0/extensions/KHR_materials_clearcoat/clearcoatTexture/extensions/"
       "KHR_texture_transform/rotation",
       PointerTarget::Kind::Material, 1},
      {"/extensions/KHR_lights_punctual/lights/0/color", PointerTarget::Kind::Light, 3},
      {"/extensions/KHR_lights_punctual/lights/1/spot/outerConeAngle",
       PointerTarget::Kind::Light, 1},
      {"/cameras/0/perspective/yfov", PointerTarget::Kind::Camera, 1},
  };
  for (const Case& c : cases) {
    const Resolved r = resolve(model, c.pointer);
    ASSERT_TRUE(r.ok) << c.pointer << ": " << r.why;
    EXPECT_EQ(r.target.kind, c.kind) << c.pointer;
    EXPECT_EQ(r.target.components, c.components) << c.pointer;
    EXPECT_EQ(r.target.boolean, c.kind == PointerTarget::Kind::NodeVisible) << c.pointer;
  }
  EXPECT_EQ(resolve(model, "/nodes/1/rotation").target.index, 1);
  EXPECT_EQ(resolve(model, "/extensions/KHR_lights_punctual/lights/1/spot/outerConeAngle")
                .target.path,
            (std::vector<std::string>{"spot", "outerConeAngle"}));
}

// Pointers to what the document does not have make the file invalid (the loader refuses
// them); pointers to properties the renderer does not read are only ignored.
TEST(AnimationPointer, TellsMissingTargetsFromPropertiesNotAnimatedHere) {
  const tinygltf::Model model = model_of(kDocument);
  for (const char* pointer : {
           "/nodes/2/rotation",                     // two nodes
           "/nodes/01/rotation",                    // not an array index
           "materials/0/emissiveFactor",            // not a JSON pointer
           "/materials/0/emissiveFactor~2",         // a bad escape
           "/materials/0/occlusionTexture/strength",  // no occlusion texture
           "/materials/0/extensions/KHR_materials_transmission/transmissionFactor",
           "/materials/0/emissiveTexture/extensions/KHR_texture_transform/offset",
           "/extensions/KHR_lights_punctual/lights/0/spot/innerConeAngle",  // a point light
           "/cameras/0/perspective/zfar",           // no default, not in the file
           "/cameras/0/orthographic/xmag",          // a perspective camera
       }) {
    const Resolved r = resolve(model, pointer);
    EXPECT_FALSE(r.ok) << pointer;
    EXPECT_TRUE(r.missing) << pointer << ": " << r.why;
  }
  for (const char* pointer : {
           "/animations/0/samplers/0/interpolation",
           "/nodes/0/extras/x",
           "/materials/0/doubleSided",
           "/materials/0/extensions/KHR~1private/x",  // an extension the renderer does not read
           "/materials/0/pbrMetallicRoughness/baseColorTexture/extensions/KHR_texture_transform/"
           "texCoord",
       }) {
    const Resolved r = resolve(model, pointer);
    EXPECT_FALSE(r.ok) << pointer;
    EXPECT_FALSE(r.missing) << pointer << ": " << r.why;
    EXPECT_FALSE(r.why.empty());
  }
}

TEST(AnimationPointer, WritesTheValueWhereTheLoaderReadsIt) {
  tinygltf::Model model = model_of(kDocument);
  auto write = [&](const std::string& pointer, std::vector<double> v) {
    const Resolved r = resolve(model, pointer);
    ASSERT_TRUE(r.ok) << pointer << ": " << r.why;
    switch (r.target.kind) {
      case PointerTarget::Kind::Material:
        apply_pointer(r.target, v.data(), &model.materials[size_t(r.target.index)]);
        break;
      case PointerTarget::Kind::Light:
        apply_pointer(r.target, v.data(),
                      &model.extensions.at("KHR_lights_punctual")
                           .Get<tinygltf::Value::Object>()
                           .at("lights")
                           .Get<tinygltf::Value::Array>()[size_t(r.target.index)]);
        break;
      case PointerTarget::Kind::Camera:
        apply_pointer(r.target, v.data(), &model.cameras[size_t(r.target.index)]);
        break;
      default:
        FAIL() << pointer;
    }
  };
  write("/materials/0/pbrMetallicRoughness/baseColorFactor", {0.1, 0.2, 0.3, 0.4});
  write("/materials/0/pbrMetallicRoughness/metallicFactor", {0.25});
  write("/materials/0/emissiveFactor", {1, 0.5, 0});
  write("/materials/0/normalTexture/scale", {0.3});
  write("/materials/0/extensions/KHR_materials_emissive_strength/emissiveStrength", {7});
  write("/materials/0/extensions/KHR_materials_sheen/sheenColorFactor", {0.9, 0.8, 0.7});
  write("/materials/0/pbrMetallicRoughness/baseColorTexture/extensions/KHR_texture_transform/"
        "offset",
        {0.5, -0.25});
  write("/materials/0/extensions/KHR_materials_clearcoat/clearcoatTexture/extensions/"
        "KHR_texture_transform/rotation",
        {1.25});
  write("/extensions/KHR_lights_punctual/lights/1/spot/outerConeAngle", {0.3});
  write("/extensions/KHR_lights_punctual/lights/0/intensity", {5});
  write("/cameras/0/perspective/yfov", {0.4});
  const tinygltf::Material& m = model.materials[0];
  EXPECT_EQ(m.pbrMetallicRoughness.baseColorFactor, (std::vector<double>{0.1, 0.2, 0.3, 0.4}));
  EXPECT_EQ(m.pbrMetallicRoughness.metallicFactor, 0.25);
  EXPECT_EQ(m.emissiveFactor, (std::vector<double>{1, 0.5, 0}));
  EXPECT_EQ(m.normalTexture.scale, 0.3);
  EXPECT_EQ(m.extensions.at("KHR_materials_emissive_strength")
                .Get("emissiveStrength")
                .GetNumberAsDouble(),
            7.0);
  const tinygltf::Value& sheen = m.extensions.at("KHR_materials_sheen").Get("sheenColorFactor");
  ASSERT_TRUE(sheen.IsArray());
  ASSERT_EQ(sheen.ArrayLen(), 3u);
  EXPECT_EQ(sheen.Get(2).GetNumberAsDouble(), 0.7);
  const tinygltf::Value& offset = m.pbrMetallicRoughness.baseColorTexture.extensions
                                      .at("KHR_texture_transform")
                                      .Get("offset");
  ASSERT_TRUE(offset.IsArray());
  EXPECT_EQ(offset.Get(0).GetNumberAsDouble(), 0.5);
  EXPECT_EQ(offset.Get(1).GetNumberAsDouble(), -0.25);
  EXPECT_EQ(m.extensions.at("KHR_materials_clearcoat")
                .Get("clearcoatTexture")
                .Get("extensions")
                .Get("KHR_texture_transform")
                .Get("rotation")
                .GetNumberAsDouble(),
            1.25);
  EXPECT_EQ(m.extensions.at("KHR_materials_clearcoat").Get("clearcoatFactor").GetNumberAsDouble(),
            1.0);  // the rest of the extension untouched
  const tinygltf::Value& lights = model.extensions.at("KHR_lights_punctual").Get("lights");
  EXPECT_EQ(lights.Get(1).Get("spot").Get("outerConeAngle").GetNumberAsDouble(), 0.3);
  EXPECT_EQ(lights.Get(0).Get("intensity").GetNumberAsDouble(), 5.0);
  EXPECT_EQ(lights.Get(0).Get("type").Get<std::string>(), "point");  // the rest untouched
  EXPECT_EQ(model.cameras[0].perspective.yfov, 0.4);
}

}  // namespace
}  // namespace rf
