// Internal to src/scene (the glTF loader's files only, gltf_*.cpp): the loader's one class,
// Loader, and the helpers its files share. Loader reads a parsed tinygltf::Model into a
// SceneDescription; its member functions are defined by concern in
// - gltf_loader.cpp: the driver (run), messages, the node hierarchy and its traversal;
// - gltf_materials.cpp: textures, materials and their extensions, KHR_materials_variants;
// - gltf_geometry.cpp: vertex attributes, accessors, EXT_mesh_gpu_instancing, primitives;
// - gltf_lights_cameras.cpp: KHR_lights_punctual and cameras;
// - gltf_animation.cpp: animations, skins and morph targets;
// - gltf_limits.cpp: mesh counts, and the scene's cost checked against its limits.
// The loader's API is scene.h's (parse_gltf, describe_gltf, load_gltf, ...).
#pragma once

#include <tiny_gltf.h>

#include <algorithm>
#include <cstddef>
#include <cstdint>
#include <cstring>
#include <map>
#include <optional>
#include <set>
#include <string>
#include <utility>
#include <vector>

#include "scene/animation.h"
#include "scene/animation_pointer.h"
#include "scene/scene.h"

namespace rf::gltf_detail {

// The extensions the renderer implements (gltf_loader.cpp).
const std::set<std::string>& supported_extensions();
// obj[key] if it is a number, else fallback (gltf_loader.cpp).
float number_or(const tinygltf::Value& obj, const char* key, float fallback);

class Loader {
 public:
  Loader(const tinygltf::Model& model, std::string source, std::vector<std::string>* warnings,
         const LoadOptions& options);
  SceneDescription run();
  static std::vector<std::string> variant_names(const tinygltf::Model& model);

 private:
  // The accessors of the attributes a primitive has that the renderer reads. Primitives of one
  // mesh with the same key share their vertices (exporters often give every material's
  // primitive the whole vertex buffer).
  using VertexKey = std::map<std::string, int>;

  // Vertex and triangle counts of meshes, for reserving TriangleMesh arrays exactly (no
  // growth slack, no copies while a scene of millions of triangles loads). Accessors that are
  // invalid count as empty here; add_mesh reports them.
  struct Counts {
    size_t vertices = 0, triangles = 0;
    size_t thin = 0;  // points and line segments (not in vertices and triangles)
    bool normals = false, colors = false, tangents = false;
    std::set<uint32_t> uv;  // TriangleMesh::uv arrays
    void operator+=(const Counts& o) {
      vertices += o.vertices;
      triangles += o.triangles;
      thin += o.thin;
      normals = normals || o.normals;
      colors = colors || o.colors;
      tangents = tangents || o.tangents;
      uv.insert(o.uv.begin(), o.uv.end());
    }
  };

  // Element i, component c of an accessor's data (range-checked by check_accessor, which made
  // the view).
  struct View {
    const unsigned char* base = nullptr;
    size_t stride = 0;
    int component_type = 0;
    int components = 0;
    size_t count = 0;
    bool normalized = false;
    // The stored number.
    double raw(size_t i, int c) const {
      const unsigned char* p = base + i * stride;
      switch (component_type) {
        case TINYGLTF_COMPONENT_TYPE_FLOAT: {
          float f;
          std::memcpy(&f, p + 4 * c, 4);
          return f;
        }
        case TINYGLTF_COMPONENT_TYPE_UNSIGNED_INT: {
          uint32_t u;
          std::memcpy(&u, p + 4 * c, 4);
          return u;
        }
        case TINYGLTF_COMPONENT_TYPE_UNSIGNED_SHORT: {
          uint16_t u;
          std::memcpy(&u, p + 2 * c, 2);
          return u;
        }
        case TINYGLTF_COMPONENT_TYPE_SHORT: {
          int16_t v;
          std::memcpy(&v, p + 2 * c, 2);
          return v;
        }
        case TINYGLTF_COMPONENT_TYPE_UNSIGNED_BYTE:
          return p[c];
        case TINYGLTF_COMPONENT_TYPE_BYTE:
          return double(int8_t(p[c]));
        default:
          return 0.0;
      }
    }
    // The attribute value: a normalized integer as glTF 2.0 (3.11) maps it to [0, 1] or
    // [-1, 1] (c / 255, c / 65535, max(c / 127, -1), max(c / 32767, -1)), any other number as
    // it is (quantized data that a node transform or KHR_texture_transform dequantizes).
    float get(size_t i, int c) const {
      const double v = raw(i, c);
      if (!normalized) return float(v);
      switch (component_type) {
        case TINYGLTF_COMPONENT_TYPE_UNSIGNED_BYTE:
          return float(v / 255.0);
        case TINYGLTF_COMPONENT_TYPE_UNSIGNED_SHORT:
          return float(v / 65535.0);
        case TINYGLTF_COMPONENT_TYPE_BYTE:
          return float(std::max(v / 127.0, -1.0));
        case TINYGLTF_COMPONENT_TYPE_SHORT:
          return float(std::max(v / 32767.0, -1.0));
        default:
          return float(v);
      }
    }
  };

  // What an accessor holds: vertex attributes and indices (3.7.2.1), animation sampler inputs
  // and outputs (3.11), skin joints, weights and inverse bind matrices (3.7.3), and morph
  // target displacements (3.7.2.2).
  enum class Attribute {
    Position, Normal, Texcoord, Color, Indices,
    AnimationInput, AnimationVec3, AnimationRotation, AnimationWeights,
    // KHR_animation_pointer's outputs: numbers of any component type (SCALAR to VEC4), and
    // bools (unsigned byte).
    AnimationPointer, AnimationBool,
    Joints, Weights, InverseBindMatrices, MorphPosition, MorphNormal, Tangent
  };

  // A primitive's vertex attributes that the renderer reads, checked.
  struct VertexAttributes {
    View position;
    std::optional<View> normal, color, tangent;
    std::vector<std::pair<uint32_t, View>> uv;  // (TriangleMesh::uv array, view), ascending
  };

  // ---- Animation, skins and morph targets (glTF 2.0, 3.11, 3.7.3, 3.7.2.2; animation.h).

  // A deformed mesh node: its morph target weights (empty: none apply) and, if it is skinned,
  // its skin's joint matrices globalTransform(joints[j]) * inverseBindMatrices[j].
  struct Deformation {
    std::vector<double> weights;
    int skin = -1;
    std::vector<Mat4> joint_matrices;
  };

  // A deformed primitive's vertices in world space: positions, normals (not normalized;
  // empty without NORMAL) and, for skinned ones, whether each vertex's skin matrix mirrors.
  struct PosedVertices {
    std::vector<Vec3> positions, normals;
    std::vector<uint8_t> mirrored;
  };

  // gltf_loader.cpp: the driver, messages, the node hierarchy and its traversal.
  //
  // what starts with the glTF path of the offending part ("nodes[3] ('Cube'): ..."): that path
  // becomes the error's path().
  [[noreturn]] void fail(const std::string& what) const;
  static std::string leading_path(const std::string& what);
  static std::string named(const std::string& name);
  void warn(const std::string& what);
  std::vector<int> check_hierarchy() const;
  void check_roots(const std::vector<int>& roots, const std::string& path,
                   const std::vector<int>& parent) const;
  void count_mesh_uses();
  Mat4 local_transform(const tinygltf::Node& node, const std::string& where,
                       const NodePose* pose = nullptr) const;
  Mat4 trs(const double* translation, const double* rotation, const double* scale,
           const std::string& where) const;
  bool node_visible(const tinygltf::Node& node, int index) const;
  void visit(int index, const Mat4& parent, SceneDescription* desc, int depth,
             bool visible = true);
  void visit_split(int index, const tinygltf::Node& node, const Mat4& world,
                   const std::string& where, SceneDescription* desc, bool visible = true);
  void classify_nodes();
  bool mesh_may_emit(size_t mesh_index, const SceneDescription& desc);

  // gltf_materials.cpp: textures, materials and their extensions, variants.
  void load_textures(SceneDescription* desc);
  int texture_image(const tinygltf::Texture& gt, size_t i);
  void load_volume(const tinygltf::Value& ext, const std::string& where, const std::string& name,
                   Material* m) const;
  TextureRef texture_ref(int index, int texcoord, const tinygltf::ExtensionMap& extensions,
                         const std::string& where);
  TextureRef texture_ref(const tinygltf::Value& ext, const char* key, const std::string& where,
                         float* scale = nullptr);
  float unit_number(double x, const std::string& field, const std::string& name);
  float unit_factor(const tinygltf::Value& ext, const char* key, float fallback,
                    const std::string& where);
  Vec3 unit_color(const tinygltf::Value& ext, const char* key, Vec3 fallback,
                  const std::string& where);
  void load_specular_glossiness(const tinygltf::Value& ext, size_t i, const std::string& name,
                                Material* m);
  void load_layers(const tinygltf::Material& gm, size_t i, Material* m);
  void load_materials(SceneDescription* desc);
  int selected_variant() const;
  int variant_material(const tinygltf::Primitive& prim, size_t mesh_index, size_t pi) const;
  static constexpr double kFactorSlack = 0.01;  // unit_number's tolerance outside [0, 1]

  // gltf_geometry.cpp: vertex attributes, accessors, GPU instancing, primitives.
  bool reads_attribute(const std::string& name) const;
  bool uv_array(const std::string& name, uint32_t* array) const;
  static bool texcoord_set(const std::string& name, uint32_t* set);
  VertexKey vertex_key(const tinygltf::Primitive& prim) const;
  static bool fits(size_t length, size_t offset, size_t count, size_t elem, size_t stride);
  std::string view_problem(int index) const;
  std::string accessor_problem(const tinygltf::Accessor& acc) const;
  const tinygltf::Value* gpu_instancing(const tinygltf::Node& node) const;
  int64_t gpu_instance_count(const tinygltf::Node& node, int index) const;
  std::vector<Mat4> gpu_instances(const tinygltf::Node& node, int index);
  static const char* component_name(int type);
  std::string format_problem(Attribute kind, const tinygltf::Accessor& acc) const;
  View check_accessor(int index, Attribute kind, const std::string& where);
  std::vector<unsigned char> materialize_sparse(int index, size_t elem,
                                                const std::string& where) const;
  void append_vertices(const VertexAttributes& a, const Mat4& world, TriangleMesh* out,
                       uint32_t* first, std::vector<bool>* bad_normal, const std::string& where,
                       const PosedVertices* posed = nullptr);
  static bool is_triangles(int mode);
  static size_t triangle_count(int mode, size_t indices);
  static uint32_t corner(int mode, const std::vector<uint32_t>& indices, size_t t, int k);
  void add_mesh(size_t mesh_index, const Mat4& world, TriangleMesh* out,
                const Deformation* deform = nullptr, uint32_t node = kNoNode);
  VertexAttributes read_attributes(const tinygltf::Primitive& prim, const std::string& where,
                                   bool deformed);
  uint32_t primitive_material(const tinygltf::Primitive& prim, size_t mesh_index, size_t pi,
                              const std::string& where) const;
  std::vector<uint32_t> read_indices(const tinygltf::Primitive& prim, size_t vertices,
                                     const std::string& where);
  // Points and lines (ThinGeometry): their materials' variants, and their elements.
  enum class ThinKind { Unlit, LitFlat, Lit };
  static ThinKind thin_kind(const tinygltf::Primitive& prim);
  void derive_thin_materials(SceneDescription* desc);
  void add_thin(size_t mesh_index, const Mat4& world, ThinGeometry* out, uint32_t node,
                const Deformation* deform = nullptr);
  void visit_thin(int index, const tinygltf::Node& node, const Mat4& world,
                  const std::string& where, SceneDescription* desc);
  // EXT_mesh_gpu_instancing's attributes, in gpu_instance_count's order.
  static constexpr const char* kInstanceAttributes[3] = {"TRANSLATION", "ROTATION", "SCALE"};

  // gltf_lights_cameras.cpp: KHR_lights_punctual and cameras.
  void load_lights();
  void take_camera(const tinygltf::Node& node, const Mat4& world, const std::string& where,
                   SceneDescription* desc);

  // gltf_animation.cpp: animations, skins and morph targets.
  void evaluate_animations();
  bool pointer_channel(const tinygltf::AnimationChannel& ch, int a, const std::string& cw,
                       ChannelTrack* node_track);
  void evaluate_pointers(double time);
  KeyframeTrack read_sampler(int a, int j, AnimationPath path, size_t components);
  KeyframeTrack read_sampler_as(int a, int j, Attribute kind, size_t components,
                                size_t per_element, bool rotation);
  // The objects the loader reads, animated by KHR_animation_pointer at the load's time where
  // a channel targets them, else the file's.
  const tinygltf::Material& material_source(size_t i) const;
  const tinygltf::Value& light_source(size_t i, const tinygltf::Value& file) const;
  const tinygltf::Camera& camera_source(size_t i) const;
  const NodePose* pose_of(int node) const;
  size_t morph_target_count(int mesh) const;
  const std::vector<double>& morph_weights(int index) const;
  bool is_deformed(int index) const;
  Mat4 global_transform(int index);
  const std::vector<Mat4>& joint_matrices(int s);
  Deformation deformation_of(int index, const std::string& where);
  static void add_deformation_key(const tinygltf::Primitive& prim, VertexKey* key);
  PosedVertices pose_vertices(const tinygltf::Primitive& prim, const VertexAttributes& a,
                              const Deformation& d, const Mat4& world, const std::string& where);

  // gltf_limits.cpp: mesh counts, the scene's cost against its limits.
  size_t accessor_count(int index) const;
  Counts mesh_counts(size_t mesh_index) const;
  Counts world_counts(const std::vector<int>& roots) const;
  static void reserve(const Counts& c, TriangleMesh* mesh);
  void check_cost(const std::vector<int>& roots, SceneStats* stats) const;

  // KHR_animation_pointer: the channels that animate materials, lights and cameras, and node
  // visibility; their values at the load's time (visibility at options_.visibility_time if
  // set) written into copies of the objects they target.
  struct PointerTrack {
    PointerTarget target;
    KeyframeTrack track;
  };
  std::vector<PointerTrack> pointer_tracks_, visibility_tracks_;
  std::set<int> visibility_animated_;
  std::map<int, bool> visible_at_;
  std::map<int, tinygltf::Material> animated_materials_;
  std::map<int, tinygltf::Value> animated_lights_;
  std::map<int, tinygltf::Camera> animated_cameras_;
  std::vector<std::optional<PunctualLight>> lights_;
  std::vector<int> parent_;                   // per node: its parent, -1 for none
  std::map<int, NodePose> poses_;             // the animated nodes' poses at options_.time
  std::map<int, Mat4> global_;                // world matrices global_transform computed
  std::map<int, std::vector<Mat4>> joint_matrices_;  // per skin
  std::vector<int> mesh_uses_;
  std::vector<int> mesh_slot_;
  std::vector<int8_t> mesh_emits_;  // per mesh: mesh_may_emit's answer, -1 not known yet
  // The animated layout (AnimatedLayout), if the options ask for one: the nodes whose TRS or
  // weights a chosen channel animates, per node whether it moves and whether its deformation
  // varies, and the meshes of varying deformed nodes.
  AnimatedLayout* split_ = nullptr;
  std::set<int> trs_animated_, weights_animated_;
  std::vector<char> moving_, varying_;
  std::vector<int> deformed_slots_;
  uint32_t moving_mesh_nodes_ = 0;
  std::set<std::string> warned_material_ext_, warned_texture_ext_;
  int variant_ = -1;  // KHR_materials_variants: the selected variant, -1 for none
  // Points and lines: whether any mesh has them, and the material each (material, kind) uses.
  bool has_thin_ = false;
  std::map<std::pair<uint32_t, ThinKind>, uint32_t> thin_materials_;
  bool warned_occlusion_ = false, warned_unskinned_ = false;
  bool warned_tangent_ = false;
  bool quantization_ = false;         // KHR_mesh_quantization's attribute types are allowed
  // The TriangleMesh::uv array of each TEXCOORD set above 1 that a material reads.
  std::map<uint32_t, uint32_t> uv_array_of_set_;
  // Sparse accessors, materialized: each one's elements with its sparse values applied,
  // packed in its componentType.
  std::map<int, std::vector<unsigned char>> sparse_data_;
  const tinygltf::Model& model_;
  std::string source_;
  std::vector<std::string>* warnings_;
  const LoadOptions& options_;
  uint32_t default_material_ = 0;
};

}  // namespace rf::gltf_detail
