// The glTF loader's geometry (Loader, gltf_loader_internal.h): the vertex attributes it reads
// (TEXCOORD sets and their TriangleMesh::uv arrays), accessors and their checks (buffer views,
// formats with KHR_mesh_quantization, sparse accessors), EXT_mesh_gpu_instancing, and
// primitives appended to a TriangleMesh (strips and fans, shared vertices, mirroring
// transforms, materials). Compressed geometry is plain glTF by then (gltf_compression.h).
#include "scene/gltf_loader_internal.h"

#include <algorithm>
#include <cctype>
#include <cmath>
#include <cstring>
#include <map>
#include <optional>
#include <string>
#include <vector>

namespace rf::gltf_detail {

// The vertex attributes the renderer reads: POSITION, NORMAL, COLOR_0, TEXCOORD_0 and _1,
// and the other TEXCOORD_<n> that a material reads.
bool Loader::reads_attribute(const std::string& name) const {
  if (name == "POSITION" || name == "NORMAL" || name == "COLOR_0" || name == "TANGENT")
    return true;
  uint32_t array = 0;
  return uv_array(name, &array);
}

// For a TEXCOORD_<n> attribute the renderer reads: the TriangleMesh::uv array it goes to.
bool Loader::uv_array(const std::string& name, uint32_t* array) const {
  uint32_t set = 0;
  if (!texcoord_set(name, &set)) return false;
  if (set < 2) {
    *array = set;
    return true;
  }
  const auto it = uv_array_of_set_.find(set);
  if (it == uv_array_of_set_.end()) return false;
  *array = it->second;
  return true;
}

// n of an attribute named TEXCOORD_<n>.
bool Loader::texcoord_set(const std::string& name, uint32_t* set) {
  static const std::string prefix = "TEXCOORD_";
  if (name.compare(0, prefix.size(), prefix) != 0 || name.size() == prefix.size() ||
      name.size() > prefix.size() + 9)
    return false;
  uint32_t n = 0;
  for (size_t i = prefix.size(); i < name.size(); ++i) {
    if (!std::isdigit(static_cast<unsigned char>(name[i]))) return false;
    n = 10 * n + uint32_t(name[i] - '0');
  }
  // glTF attribute names have no leading zeros ("TEXCOORD_01" is not set 1).
  if (name.size() > prefix.size() + 1 && name[prefix.size()] == '0') return false;
  *set = n;
  return true;
}

Loader::VertexKey Loader::vertex_key(const tinygltf::Primitive& prim) const {
  VertexKey key;
  for (const auto& [name, accessor] : prim.attributes)
    if (reads_attribute(name)) key.emplace(name, accessor);
  return key;
}

// Whether bytes [offset, offset + count - 1 strides + elem) lie in a buffer view of length
// `length`, without overflow.
bool Loader::fits(size_t length, size_t offset, size_t count, size_t elem, size_t stride) {
  if (count == 0) return offset <= length;
  return offset <= length && elem <= length - offset &&
         (count - 1) <= (length - offset - elem) / stride;
}

// "" if buffer view `index` exists and lies in its buffer, otherwise why not.
std::string Loader::view_problem(int index) const {
  if (index < 0 || index >= int(model_.bufferViews.size()))
    return "refers to missing buffer view " + std::to_string(index);
  const tinygltf::BufferView& bv = model_.bufferViews[size_t(index)];
  if (bv.buffer < 0 || bv.buffer >= int(model_.buffers.size()))
    return "buffer view refers to a missing buffer";
  const tinygltf::Buffer& buf = model_.buffers[size_t(bv.buffer)];
  if (bv.byteOffset > buf.data.size() || bv.byteLength > buf.data.size() - bv.byteOffset)
    return "buffer view exceeds its buffer";
  return {};
}

// Why an accessor's data is not all in its buffers ("" if it is): its own buffer view (none:
// zeros, glTF 2.0 3.6.2.3) and a sparse accessor's indices and values. check_accessor
// reports it.
std::string Loader::accessor_problem(const tinygltf::Accessor& acc) const {
  const int ncomp = tinygltf::GetNumComponentsInType(uint32_t(acc.type));
  const int csize = tinygltf::GetComponentSizeInBytes(uint32_t(acc.componentType));
  if (ncomp <= 0 || csize <= 0) return "unsupported 'type' or 'componentType'";
  const size_t elem = size_t(ncomp) * size_t(csize);
  if (acc.bufferView >= 0 || !acc.sparse.isSparse) {
    if (acc.bufferView < 0 || acc.bufferView >= int(model_.bufferViews.size()))
      return "missing or invalid 'bufferView'";
    const std::string view = view_problem(acc.bufferView);
    if (!view.empty()) return view;
    const tinygltf::BufferView& bv = model_.bufferViews[size_t(acc.bufferView)];
    const size_t stride = bv.byteStride ? bv.byteStride : elem;
    if (stride < elem) return "'byteStride' smaller than the element";
    if (!fits(bv.byteLength, acc.byteOffset, acc.count, elem, stride))
      return "data exceeds its buffer view";
  }
  if (!acc.sparse.isSparse) return {};
  const auto& sp = acc.sparse;
  if (sp.count < 1 || size_t(sp.count) > acc.count)
    return "sparse.count " + std::to_string(sp.count) + " is not in [1, count = " +
           std::to_string(acc.count) + "]";
  const int isize = tinygltf::GetComponentSizeInBytes(uint32_t(sp.indices.componentType));
  if (sp.indices.componentType != TINYGLTF_COMPONENT_TYPE_UNSIGNED_BYTE &&
      sp.indices.componentType != TINYGLTF_COMPONENT_TYPE_UNSIGNED_SHORT &&
      sp.indices.componentType != TINYGLTF_COMPONENT_TYPE_UNSIGNED_INT)
    return "sparse.indices.componentType must be 5121, 5123 or 5125";
  const struct {
    const char* name;
    int view, offset;
    size_t elem;
  } parts[2] = {{"sparse.indices", sp.indices.bufferView, sp.indices.byteOffset, size_t(isize)},
                {"sparse.values", sp.values.bufferView, sp.values.byteOffset, elem}};
  for (const auto& part : parts) {
    const std::string view = view_problem(part.view);
    if (!view.empty()) return std::string(part.name) + ": " + view;
    if (part.offset < 0) return std::string(part.name) + ".byteOffset is negative";
    const tinygltf::BufferView& bv = model_.bufferViews[size_t(part.view)];
    if (!fits(bv.byteLength, size_t(part.offset), size_t(sp.count), part.elem, part.elem))
      return std::string(part.name) + ": data exceeds its buffer view";
  }
  return {};
}

// EXT_mesh_gpu_instancing: the node's mesh is drawn once per instance, at the node's
// transform times the instance's T R S (TRANSLATION, ROTATION, SCALE accessors of one
// count; a missing one is the identity), and not at the node's own transform. -1 when the
// node has no such extension. The accessors' counts are checked here; their formats and
// values when the transforms are read (gpu_instances).
const tinygltf::Value* Loader::gpu_instancing(const tinygltf::Node& node) const {
  auto ext = node.extensions.find("EXT_mesh_gpu_instancing");
  if (ext == node.extensions.end() || node.mesh < 0) return nullptr;
  return &ext->second;
}

int64_t Loader::gpu_instance_count(const tinygltf::Node& node, int index) const {
  const tinygltf::Value* ext = gpu_instancing(node);
  if (!ext) return -1;
  const std::string where =
      "nodes[" + std::to_string(index) + "].extensions.EXT_mesh_gpu_instancing.attributes";
  if (!ext->Has("attributes") || !ext->Get("attributes").IsObject())
    fail(where + named(node.name) + ": must be an object of accessors");
  const tinygltf::Value& attrs = ext->Get("attributes");
  int64_t count = -1;
  for (const char* name : kInstanceAttributes) {
    if (!attrs.Has(name)) continue;
    const tinygltf::Value& a = attrs.Get(name);
    const int acc = a.IsNumber() ? a.GetNumberAsInt() : -1;
    if (acc < 0 || acc >= int(model_.accessors.size()))
      fail(where + "." + name + named(node.name) + ": refers to missing accessor " +
           std::to_string(acc));
    const int64_t n = int64_t(model_.accessors[size_t(acc)].count);
    if (count >= 0 && n != count)
      fail(where + "." + name + named(node.name) + ": " + std::to_string(n) +
           " instances, but another attribute has " + std::to_string(count));
    count = n;
  }
  if (count < 0)
    fail(where + named(node.name) + ": needs TRANSLATION, ROTATION or SCALE");
  return count;
}

// The instances' transforms in the node's space (gpu_instance_count's order).
std::vector<Mat4> Loader::gpu_instances(const tinygltf::Node& node, int index) {
  const int64_t count = gpu_instance_count(node, index);
  const std::string where =
      "nodes[" + std::to_string(index) + "].extensions.EXT_mesh_gpu_instancing.attributes";
  const tinygltf::Value& attrs = gpu_instancing(node)->Get("attributes");
  std::optional<View> views[3];
  const Attribute kinds[3] = {Attribute::AnimationVec3, Attribute::AnimationRotation,
                              Attribute::AnimationVec3};
  for (int k = 0; k < 3; ++k)
    if (attrs.Has(kInstanceAttributes[k]))
      views[k] = check_accessor(attrs.Get(kInstanceAttributes[k]).GetNumberAsInt(), kinds[k],
                                where + "." + kInstanceAttributes[k]);
  std::vector<Mat4> out;
  out.reserve(size_t(count));
  for (size_t i = 0; i < size_t(count); ++i) {
    double v[3][4];
    for (int k = 0; k < 3; ++k) {
      if (!views[k]) continue;
      for (int c = 0; c < views[k]->components; ++c) {
        v[k][c] = views[k]->get(i, c);
        if (!std::isfinite(v[k][c]))
          fail(where + "." + kInstanceAttributes[k] + named(node.name) + ": element " +
               std::to_string(i) + " is not finite");
      }
    }
    out.push_back(trs(views[0] ? v[0] : nullptr, views[1] ? v[1] : nullptr,
                      views[2] ? v[2] : nullptr,
                      where + " (instance " + std::to_string(i) + ")"));
  }
  return out;
}

const char* Loader::component_name(int type) {
  switch (type) {
    case TINYGLTF_COMPONENT_TYPE_BYTE: return "byte";
    case TINYGLTF_COMPONENT_TYPE_UNSIGNED_BYTE: return "unsigned byte";
    case TINYGLTF_COMPONENT_TYPE_SHORT: return "short";
    case TINYGLTF_COMPONENT_TYPE_UNSIGNED_SHORT: return "unsigned short";
    case TINYGLTF_COMPONENT_TYPE_UNSIGNED_INT: return "unsigned int";
    case TINYGLTF_COMPONENT_TYPE_FLOAT: return "float";
    default: return "unknown";
  }
}

// "" if the accessor's type, componentType and normalized suit the attribute (glTF 2.0,
// 3.7.2.1, and KHR_mesh_quantization's table when the scene uses the extension), otherwise
// why not.
std::string Loader::format_problem(Attribute kind, const tinygltf::Accessor& acc) const {
  const int ct = acc.componentType;
  const bool norm = acc.normalized;
  const bool small_int = ct == TINYGLTF_COMPONENT_TYPE_BYTE ||
                         ct == TINYGLTF_COMPONENT_TYPE_UNSIGNED_BYTE ||
                         ct == TINYGLTF_COMPONENT_TYPE_SHORT ||
                         ct == TINYGLTF_COMPONENT_TYPE_UNSIGNED_SHORT;
  const bool unsigned_norm =
      norm && (ct == TINYGLTF_COMPONENT_TYPE_UNSIGNED_BYTE ||
               ct == TINYGLTF_COMPONENT_TYPE_UNSIGNED_SHORT);
  const bool float_type = ct == TINYGLTF_COMPONENT_TYPE_FLOAT;
  const bool signed_small =
      ct == TINYGLTF_COMPONENT_TYPE_BYTE || ct == TINYGLTF_COMPONENT_TYPE_SHORT;
  bool type_ok = false, ok = false;
  const char* allowed = "";
  switch (kind) {
    case Attribute::Position:
      type_ok = acc.type == TINYGLTF_TYPE_VEC3;
      ok = ct == TINYGLTF_COMPONENT_TYPE_FLOAT || (quantization_ && small_int);
      allowed = "float (8- and 16-bit integers with KHR_mesh_quantization)";
      break;
    case Attribute::Normal:
      type_ok = acc.type == TINYGLTF_TYPE_VEC3;
      ok = ct == TINYGLTF_COMPONENT_TYPE_FLOAT ||
           (quantization_ && norm &&
            (ct == TINYGLTF_COMPONENT_TYPE_BYTE || ct == TINYGLTF_COMPONENT_TYPE_SHORT));
      allowed = "float (normalized byte and short with KHR_mesh_quantization)";
      break;
    case Attribute::Texcoord:
      type_ok = acc.type == TINYGLTF_TYPE_VEC2;
      ok = ct == TINYGLTF_COMPONENT_TYPE_FLOAT || unsigned_norm || (quantization_ && small_int);
      allowed = "float, normalized unsigned byte or short (any 8- and 16-bit integers with "
                "KHR_mesh_quantization)";
      break;
    case Attribute::Color:
      type_ok = acc.type == TINYGLTF_TYPE_VEC3 || acc.type == TINYGLTF_TYPE_VEC4;
      ok = ct == TINYGLTF_COMPONENT_TYPE_FLOAT || unsigned_norm;
      allowed = "float, normalized unsigned byte or short";
      break;
    case Attribute::Indices:
      type_ok = acc.type == TINYGLTF_TYPE_SCALAR;
      ok = ct == TINYGLTF_COMPONENT_TYPE_UNSIGNED_BYTE ||
           ct == TINYGLTF_COMPONENT_TYPE_UNSIGNED_SHORT ||
           ct == TINYGLTF_COMPONENT_TYPE_UNSIGNED_INT;
      allowed = "unsigned byte, short or int";
      break;
    case Attribute::AnimationInput:
      type_ok = acc.type == TINYGLTF_TYPE_SCALAR;
      ok = float_type;
      allowed = "float (keyframe times in seconds)";
      break;
    case Attribute::AnimationVec3:  // translation, scale
      type_ok = acc.type == TINYGLTF_TYPE_VEC3;
      ok = float_type;
      allowed = "float";
      break;
    case Attribute::AnimationRotation:
    case Attribute::AnimationWeights:
      type_ok = acc.type == (kind == Attribute::AnimationRotation ? TINYGLTF_TYPE_VEC4
                                                                  : TINYGLTF_TYPE_SCALAR);
      ok = float_type || (norm && small_int);
      allowed = "float or a normalized byte, unsigned byte, short or unsigned short";
      break;
    case Attribute::AnimationPointer:  // read_sampler_as checks the size
      type_ok = acc.type == TINYGLTF_TYPE_SCALAR || acc.type == TINYGLTF_TYPE_VEC2 ||
                acc.type == TINYGLTF_TYPE_VEC3 || acc.type == TINYGLTF_TYPE_VEC4;
      ok = float_type || ct == TINYGLTF_COMPONENT_TYPE_BYTE ||
           ct == TINYGLTF_COMPONENT_TYPE_UNSIGNED_BYTE || ct == TINYGLTF_COMPONENT_TYPE_SHORT ||
           ct == TINYGLTF_COMPONENT_TYPE_UNSIGNED_SHORT ||
           (!norm && ct == TINYGLTF_COMPONENT_TYPE_UNSIGNED_INT);
      allowed = "float or an integer type";
      break;
    case Attribute::AnimationBool:
      type_ok = acc.type == TINYGLTF_TYPE_SCALAR;
      ok = !norm && ct == TINYGLTF_COMPONENT_TYPE_UNSIGNED_BYTE;
      allowed = "unsigned byte (0 is false; KHR_animation_pointer's bool)";
      break;
    case Attribute::Joints:
      type_ok = acc.type == TINYGLTF_TYPE_VEC4;
      ok = !norm && (ct == TINYGLTF_COMPONENT_TYPE_UNSIGNED_BYTE ||
                     ct == TINYGLTF_COMPONENT_TYPE_UNSIGNED_SHORT);
      allowed = "unsigned byte or unsigned short";
      break;
    case Attribute::Weights:
      type_ok = acc.type == TINYGLTF_TYPE_VEC4;
      ok = float_type || unsigned_norm;
      allowed = "float, normalized unsigned byte or short";
      break;
    case Attribute::InverseBindMatrices:
      type_ok = acc.type == TINYGLTF_TYPE_MAT4;
      ok = float_type;
      allowed = "float";
      break;
    case Attribute::MorphPosition:
      type_ok = acc.type == TINYGLTF_TYPE_VEC3;
      ok = float_type || (quantization_ && signed_small);
      allowed = "float (byte and short, normalized or not, with KHR_mesh_quantization)";
      break;
    case Attribute::Tangent:
      type_ok = acc.type == TINYGLTF_TYPE_VEC4;
      ok = ct == TINYGLTF_COMPONENT_TYPE_FLOAT ||
           (quantization_ && norm &&
            (ct == TINYGLTF_COMPONENT_TYPE_BYTE || ct == TINYGLTF_COMPONENT_TYPE_SHORT));
      allowed = "float (normalized byte and short with KHR_mesh_quantization)";
      break;
    case Attribute::MorphNormal:
      type_ok = acc.type == TINYGLTF_TYPE_VEC3;
      ok = float_type || (quantization_ && norm && signed_small);
      allowed = "float (normalized byte and short with KHR_mesh_quantization)";
      break;
  }
  if (!type_ok) return "unexpected accessor 'type'";
  if (ok) return {};
  return std::string("componentType ") + std::to_string(ct) + " (" + component_name(ct) +
         (small_int ? (norm ? ", normalized" : ", not normalized") : "") +
         ") is not allowed here: it must be " + allowed;
}

Loader::View Loader::check_accessor(int index, Attribute kind, const std::string& where) {
  if (index < 0 || index >= int(model_.accessors.size()))
    fail(where + " refers to missing accessor " + std::to_string(index));
  const tinygltf::Accessor& acc = model_.accessors[size_t(index)];
  const std::string aw = "accessors[" + std::to_string(index) + "] (" + where + ")";
  const std::string format = format_problem(kind, acc);
  if (!format.empty()) fail(aw + ": " + format);
  const std::string problem = accessor_problem(acc);
  if (!problem.empty()) fail(aw + ": " + problem);
  const size_t elem = size_t(tinygltf::GetNumComponentsInType(uint32_t(acc.type))) *
                      size_t(tinygltf::GetComponentSizeInBytes(uint32_t(acc.componentType)));
  View v;
  v.component_type = acc.componentType;
  v.components = tinygltf::GetNumComponentsInType(uint32_t(acc.type));
  v.count = acc.count;
  v.normalized = acc.normalized;
  if (acc.sparse.isSparse) {
    auto [it, fresh] = sparse_data_.try_emplace(index);
    if (fresh) it->second = materialize_sparse(index, elem, where);
    v.base = it->second.data();
    v.stride = elem;
  } else {
    const tinygltf::BufferView& bv = model_.bufferViews[size_t(acc.bufferView)];
    const tinygltf::Buffer& buf = model_.buffers[size_t(bv.buffer)];
    v.stride = bv.byteStride ? bv.byteStride : elem;
    v.base = buf.data.data() + bv.byteOffset + acc.byteOffset;
  }
  return v;
}

// A sparse accessor's elements (glTF 2.0, 3.6.2.3): those of its buffer view, or zeros
// without one, with the elements its sparse indices name replaced by its sparse values;
// packed (stride = elem). accessor_problem has checked that every byte read is there.
std::vector<unsigned char> Loader::materialize_sparse(int index, size_t elem,
                                                      const std::string& where) const {
  const tinygltf::Accessor& acc = model_.accessors[size_t(index)];
  std::vector<unsigned char> data(acc.count * elem, 0);
  if (acc.bufferView >= 0) {
    const tinygltf::BufferView& bv = model_.bufferViews[size_t(acc.bufferView)];
    const unsigned char* base =
        model_.buffers[size_t(bv.buffer)].data.data() + bv.byteOffset + acc.byteOffset;
    const size_t stride = bv.byteStride ? bv.byteStride : elem;
    for (size_t i = 0; i < acc.count; ++i) std::memcpy(&data[i * elem], base + i * stride, elem);
  }
  auto start = [&](int view, int offset) {
    const tinygltf::BufferView& bv = model_.bufferViews[size_t(view)];
    return model_.buffers[size_t(bv.buffer)].data.data() + bv.byteOffset + size_t(offset);
  };
  View indices;
  indices.base = start(acc.sparse.indices.bufferView, acc.sparse.indices.byteOffset);
  indices.component_type = acc.sparse.indices.componentType;
  indices.stride = size_t(tinygltf::GetComponentSizeInBytes(uint32_t(indices.component_type)));
  const unsigned char* values = start(acc.sparse.values.bufferView, acc.sparse.values.byteOffset);
  double previous = -1.0;
  for (size_t k = 0; k < size_t(acc.sparse.count); ++k) {
    const double i = indices.raw(k, 0);
    if (!(i > previous) || !(i < double(acc.count)))
      fail("accessors[" + std::to_string(index) + "].sparse.indices (" + where + "): index " +
           std::to_string(k) + " is " + std::to_string(uint64_t(i)) +
           (i < double(acc.count) ? ", not above the one before it (sparse indices strictly "
                                    "increase)"
                                  : ", out of range (count " + std::to_string(acc.count) + ")"));
    std::memcpy(&data[size_t(i) * elem], values + k * elem, elem);
    previous = i;
  }
  return data;
}

// Appends a primitive's vertices to *out, transformed by world: *first is the index of the
// first, bad_normal[i] tells the vertices whose normal does not survive the transform (zero
// or non-finite), which take the normals of the triangles that use them away.
// posed: the vertices' world positions and normals when a skin or morph targets deform
// them (world is then not used).
void Loader::append_vertices(const VertexAttributes& a, const Mat4& world, TriangleMesh* out,
                             uint32_t* first, std::vector<bool>* bad_normal,
                             const std::string& where, const PosedVertices* posed) {
  const View& pos = a.position;
  const View* nrm = a.normal ? &*a.normal : nullptr;
  const View* col = a.color ? &*a.color : nullptr;
  *first = uint32_t(out->positions.size());
  if (size_t(*first) + pos.count > size_t(UINT32_MAX))
    fail(where + ": more than 2^32 vertices in one mesh");
  // Attribute arrays are written for every vertex once any primitive has them (zeros, or
  // white for colours, where a primitive has not).
  const bool write_normals = out->use_normals(nrm != nullptr);
  const bool write_colors = out->use_colors(col != nullptr);
  const View* tan = a.tangent ? &*a.tangent : nullptr;
  const bool write_tangents = out->use_tangents(tan != nullptr);
  // A tangent is a direction on the surface: transformed as positions' differences are;
  // a mirroring transform reverses the bitangent cross(normal, tangent), so the handedness
  // turns (the winding, which add_mesh swaps, does not enter it).
  const float handedness = world.det3() < 0.0 ? -1.f : 1.f;
  std::vector<const View*> uv_of;  // per set: this primitive's view, or null
  for (const auto& [set, view] : a.uv) {
    out->use_uv(set, true);
    if (uv_of.size() <= set) uv_of.resize(set + 1, nullptr);
    uv_of[set] = &view;
  }
  uv_of.resize(out->uv.size(), nullptr);
  std::vector<uint32_t> write_uv;  // the sets to write
  for (uint32_t set = 0; set < out->uv.size(); ++set)
    if (uv_of[set] || !out->uv[set].empty()) write_uv.push_back(set);
  if (nrm) bad_normal->assign(pos.count, false);
  for (size_t vi = 0; vi < pos.count; ++vi) {
    out->positions.push_back(
        posed ? posed->positions[vi]
              : world.transform_point({pos.get(vi, 0), pos.get(vi, 1), pos.get(vi, 2)}));
    if (write_normals) {
      Vec3 n;
      if (nrm) {
        n = posed ? posed->normals[vi]
                  : world.transform_normal({nrm->get(vi, 0), nrm->get(vi, 1), nrm->get(vi, 2)});
        const float len = length(n);
        if (len > 0.f && std::isfinite(len)) {
          n = n / len;
        } else {
          n = Vec3();
          (*bad_normal)[vi] = true;
        }
      }
      out->normals.push_back(n);
    }
    for (uint32_t set : write_uv)
      out->uv[set].push_back(uv_of[set] ? Point2{uv_of[set]->get(vi, 0), uv_of[set]->get(vi, 1)}
                                        : Point2{0.f, 0.f});
    if (write_colors)
      out->colors.push_back(col ? Rgba{col->get(vi, 0), col->get(vi, 1), col->get(vi, 2),
                                       col->components == 4 ? col->get(vi, 3) : 1.f}
                                : Rgba{});
    if (write_tangents) {
      TriangleMesh::Tangent t;
      if (tan) {
        t.xyz = world.transform_vector({tan->get(vi, 0), tan->get(vi, 1), tan->get(vi, 2)});
        const float w = tan->get(vi, 3);
        t.w = std::isfinite(length(t.xyz)) && w != 0.f ? (w < 0.f ? -handedness : handedness)
                                                       : 0.f;
      }
      out->tangents.push_back(t);
    }
  }
}

// glTF primitive modes that are surfaces: TRIANGLES (the default), TRIANGLE_STRIP and
// TRIANGLE_FAN.
bool Loader::is_triangles(int mode) {
  return mode == -1 || mode == TINYGLTF_MODE_TRIANGLES ||
         mode == TINYGLTF_MODE_TRIANGLE_STRIP || mode == TINYGLTF_MODE_TRIANGLE_FAN;
}

size_t Loader::triangle_count(int mode, size_t indices) {
  if (mode == TINYGLTF_MODE_TRIANGLE_STRIP || mode == TINYGLTF_MODE_TRIANGLE_FAN)
    return indices >= 3 ? indices - 2 : 0;
  return indices / 3;
}

// Vertex k (0, 1, 2) of triangle t of a primitive of that mode with these indices (glTF
// 2.0, 3.7.2.1, "Topology types"): strips alternate their winding so that every triangle
// keeps the first one's orientation; fans turn around their first vertex.
uint32_t Loader::corner(int mode, const std::vector<uint32_t>& indices, size_t t, int k) {
  if (mode == TINYGLTF_MODE_TRIANGLE_STRIP) {
    const size_t odd = t % 2;
    return indices[t + (k == 0 ? 0 : k == 1 ? 1 + odd : 2 - odd)];
  }
  if (mode == TINYGLTF_MODE_TRIANGLE_FAN) return indices[k == 2 ? 0 : t + size_t(k) + 1];
  return indices[3 * t + size_t(k)];
}

// The vertex attributes of a primitive that the renderer reads, checked (TANGENT only for
// rigid meshes: a deformed one takes its tangents from the texture coordinates).
Loader::VertexAttributes Loader::read_attributes(const tinygltf::Primitive& prim,
                                                 const std::string& where, bool deformed) {
  const auto pos_it = prim.attributes.find("POSITION");
  if (pos_it == prim.attributes.end()) fail(where + ": missing required attribute POSITION");
  VertexAttributes attrs;
  attrs.position = check_accessor(pos_it->second, Attribute::Position, where + " POSITION");
  const View& pos = attrs.position;
  for (const auto& [name, accessor] : prim.attributes) {
    if (name == "POSITION" || !reads_attribute(name)) continue;
    if (name == "TANGENT") {
      if (deformed) continue;
      attrs.tangent = check_accessor(accessor, Attribute::Tangent, where + " TANGENT");
      if (attrs.tangent->count != pos.count) fail(where + ": TANGENT and POSITION counts differ");
      continue;
    }
    uint32_t array = 0;
    const bool texcoord = uv_array(name, &array);
    const Attribute kind = name == "NORMAL"    ? Attribute::Normal
                           : name == "COLOR_0" ? Attribute::Color
                                               : Attribute::Texcoord;
    const View view = check_accessor(accessor, kind, where + " " + name);
    if (view.count != pos.count) fail(where + ": " + name + " and POSITION counts differ");
    if (kind == Attribute::Normal) attrs.normal = view;
    if (kind == Attribute::Color) attrs.color = view;
    if (texcoord) attrs.uv.push_back({array, view});
  }
  std::sort(attrs.uv.begin(), attrs.uv.end(),
            [](const auto& a, const auto& b) { return a.first < b.first; });
  return attrs;
}

// The material of primitive pi of a mesh: its own, the selected variant's, or the default.
uint32_t Loader::primitive_material(const tinygltf::Primitive& prim, size_t mesh_index,
                                    size_t pi, const std::string& where) const {
  uint32_t material = default_material_;
  if (prim.material >= 0) {
    if (prim.material >= int(model_.materials.size()))
      fail(where + ": 'material' refers to missing material " + std::to_string(prim.material));
    material = uint32_t(prim.material);
  }
  const int mapped = variant_material(prim, mesh_index, pi);
  if (mapped >= 0) material = uint32_t(mapped);
  return material;
}

// A primitive's vertex indices (0, 1, 2, ... without an indices accessor), each checked
// against the vertex count.
std::vector<uint32_t> Loader::read_indices(const tinygltf::Primitive& prim, size_t vertices,
                                           const std::string& where) {
  std::vector<uint32_t> indices;
  if (prim.indices >= 0) {
    const View idx = check_accessor(prim.indices, Attribute::Indices, where + " indices");
    indices.resize(idx.count);
    for (size_t i = 0; i < idx.count; ++i) {
      const double v = idx.raw(i, 0);
      if (v >= double(vertices))
        fail(where + ": index " + std::to_string(uint64_t(v)) + " out of range (" +
             std::to_string(vertices) + " vertices)");
      indices[i] = uint32_t(v);
    }
  } else {
    indices.resize(vertices);
    for (size_t i = 0; i < vertices; ++i) indices[i] = uint32_t(i);
  }
  return indices;
}

// deform: the node's skin and morph target weights (null: none; world places the mesh).
// node: the glTF node the triangles belong to (TriangleMesh::node: the world's), kNoNode for a
// mesh placed by instances.
void Loader::add_mesh(size_t mesh_index, const Mat4& world, TriangleMesh* out,
                      const Deformation* deform, uint32_t node) {
  const tinygltf::Mesh& mesh = model_.meshes[mesh_index];
  const bool nodes = out->use_nodes(node != kNoNode);
  const bool mirror = world.det3() < 0.0;
  // Vertices already appended for this mesh by an earlier primitive with the same
  // attribute accessors: their first index, and which of them lost their normal.
  struct Appended {
    uint32_t first = 0;
    std::vector<bool> bad_normal;
    std::vector<uint8_t> mirrored;  // skinned: per vertex, whether its skin matrix mirrors
  };
  std::map<VertexKey, Appended> appended;
  for (size_t pi = 0; pi < mesh.primitives.size(); ++pi) {
    const tinygltf::Primitive& prim = mesh.primitives[pi];
    const std::string where = "meshes[" + std::to_string(mesh_index) + "].primitives[" +
                              std::to_string(pi) + "]" + named(mesh.name);
    if (!is_triangles(prim.mode)) continue;  // points and lines: add_thin
    const VertexAttributes attrs = read_attributes(prim, where, deform != nullptr);
    const View& pos = attrs.position;
    const bool has_normals = attrs.normal.has_value();
    if (deform && prim.attributes.count("TANGENT") && !warned_tangent_ &&
        prim.material >= 0 && prim.material < int(model_.materials.size()) &&
        model_.materials[size_t(prim.material)].normalTexture.index >= 0) {
      warn(where + " (and possibly others): TANGENT of a skinned or morphed mesh is not "
                   "used; its normal maps take their tangents from the texture coordinates");
      warned_tangent_ = true;
    }
    bool has_uv[2] = {false, false};
    for (const auto& uv : attrs.uv)
      if (uv.first < 2) has_uv[uv.first] = true;
    const uint32_t material = primitive_material(prim, mesh_index, pi, where);
    const std::vector<uint32_t> indices = read_indices(prim, pos.count, where);
    if (prim.mode != TINYGLTF_MODE_TRIANGLE_STRIP && prim.mode != TINYGLTF_MODE_TRIANGLE_FAN &&
        indices.size() % 3 != 0)
      warn(where + ": index count is not a multiple of 3; trailing indices ignored");
    // The primitive's vertices, each transformed once, appended after the mesh's others
    // (or those of an earlier primitive with the same attribute accessors).
    VertexKey key = vertex_key(prim);
    if (deform) add_deformation_key(prim, &key);
    const auto [entry, fresh] = appended.try_emplace(key);
    if (fresh && deform) {
      PosedVertices posed = pose_vertices(prim, attrs, *deform, world, where);
      append_vertices(attrs, world, out, &entry->second.first, &entry->second.bad_normal, where,
                      &posed);
      entry->second.mirrored = std::move(posed.mirrored);
    } else if (fresh) {
      append_vertices(attrs, world, out, &entry->second.first, &entry->second.bad_normal, where);
    }
    const uint32_t first = entry->second.first;
    const std::vector<bool>& bad_normal = entry->second.bad_normal;
    const std::vector<uint8_t>& mirrored = entry->second.mirrored;
    const uint8_t base_flags = uint8_t((has_uv[0] ? TriangleMesh::kHasUv0 : 0) |
                                       (has_uv[1] ? TriangleMesh::kHasUv1 : 0) |
                                       (attrs.tangent ? TriangleMesh::kHasTangents : 0));
    const size_t triangles = triangle_count(prim.mode, indices.size());
    for (size_t t = 0; t < triangles; ++t) {
      bool normals_ok = has_normals;
      // A skinned triangle mirrors if its first vertex's skin matrix does.
      const bool flip = mirrored.empty() ? mirror : mirrored[corner(prim.mode, indices, t, 0)];
      for (int k = 0; k < 3; ++k) {
        // A mirroring transform flips the winding (glTF spec, "Transformations"): swap two
        // vertices so that counter-clockwise stays the front face in world space.
        const int src = flip ? (k == 0 ? 0 : 3 - k) : k;
        const uint32_t vi = corner(prim.mode, indices, t, src);
        if (has_normals && bad_normal[vi]) normals_ok = false;
        out->indices.push_back(first + vi);
      }
      out->material.push_back(material);
      out->flags.push_back(uint8_t(base_flags | (normals_ok ? TriangleMesh::kHasNormals : 0)));
      if (nodes) out->node.push_back(node);
    }
    // Degenerate triangles are dropped by Scene.
  }
}

// How a points-and-lines primitive is shaded, from the attributes it has (below).
Loader::ThinKind Loader::thin_kind(const tinygltf::Primitive& prim) {
  if (!prim.attributes.count("NORMAL")) return ThinKind::Unlit;
  return prim.attributes.count("TANGENT") ? ThinKind::Lit : ThinKind::LitFlat;
}

// glTF 2.0, "Point and Line Materials": points and lines without NORMAL are unlit (base colour
// plus emission), with NORMAL but no TANGENT lit without normal textures, with both lit as
// triangles are. Either face of a line or point faces the camera, so each is double-sided.
// Gives every material a points-and-lines primitive uses, per kind, a variant of its own
// (appended to desc->materials, in mesh and primitive order so that a static part and its
// poses number them alike; animated with the material they copy).
void Loader::derive_thin_materials(SceneDescription* desc) {
  for (size_t mi = 0; mi < model_.meshes.size(); ++mi) {
    const tinygltf::Mesh& mesh = model_.meshes[mi];
    for (size_t pi = 0; pi < mesh.primitives.size(); ++pi) {
      const tinygltf::Primitive& prim = mesh.primitives[pi];
      if (is_triangles(prim.mode) || prim.mode < 0 || prim.mode > TINYGLTF_MODE_LINE_STRIP)
        continue;
      const std::string where = "meshes[" + std::to_string(mi) + "].primitives[" +
                                std::to_string(pi) + "]" + named(mesh.name);
      has_thin_ = true;
      const uint32_t base = primitive_material(prim, mi, pi, where);
      const ThinKind kind = thin_kind(prim);
      const auto [it, fresh] = thin_materials_.try_emplace({base, kind}, 0);
      if (!fresh) continue;
      Material m = desc->materials[base];
      m.double_sided = true;
      if (kind == ThinKind::Unlit) {
        m.unlit = true;
        m.unlit_adds_emission = true;
      } else if (kind == ThinKind::LitFlat) {
        m.normal_tex = TextureRef{};
        m.clearcoat_normal_tex = TextureRef{};
      }
      it->second = uint32_t(desc->materials.size());
      desc->materials.push_back(m);
      if (animated_materials_.count(int(base)))
        desc->animated_materials.push_back(it->second);
    }
  }
}

// The points and lines of a mesh (modes 0-3) placed by `world` (deform: the node's skin and
// morph target weights), appended to *out as elements: a point per index (POINTS), a segment
// per pair (LINES), between consecutive indices (LINE_STRIP) and back to the first
// (LINE_LOOP), each of the glTF node `node`. A segment whose two ends are one vertex is
// dropped, as the spec says lines should not be degenerate.
void Loader::add_thin(size_t mesh_index, const Mat4& world, ThinGeometry* out, uint32_t node,
                      const Deformation* deform) {
  const tinygltf::Mesh& mesh = model_.meshes[mesh_index];
  for (size_t pi = 0; pi < mesh.primitives.size(); ++pi) {
    const tinygltf::Primitive& prim = mesh.primitives[pi];
    if (is_triangles(prim.mode)) continue;
    const std::string where = "meshes[" + std::to_string(mesh_index) + "].primitives[" +
                              std::to_string(pi) + "]" + named(mesh.name);
    if (prim.mode < 0 || prim.mode > TINYGLTF_MODE_LINE_STRIP)
      fail(where + ".mode: " + std::to_string(prim.mode) +
           " is not a glTF primitive mode (0 POINTS to 6 TRIANGLE_FAN)");
    const VertexAttributes attrs = read_attributes(prim, where, deform != nullptr);
    const std::vector<uint32_t> indices = read_indices(prim, attrs.position.count, where);
    const uint32_t base = primitive_material(prim, mesh_index, pi, where);
    const auto material = thin_materials_.find({base, thin_kind(prim)});
    if (material == thin_materials_.end()) fail(where + ": no material for points or lines");
    uint32_t first = 0;
    std::vector<bool> bad_normal;
    if (deform) {
      const PosedVertices posed = pose_vertices(prim, attrs, *deform, world, where);
      append_vertices(attrs, world, &out->vertices, &first, &bad_normal, where, &posed);
    } else {
      append_vertices(attrs, world, &out->vertices, &first, &bad_normal, where);
    }
    bool has_uv[2] = {false, false};
    for (const auto& uv : attrs.uv)
      if (uv.first < 2) has_uv[uv.first] = true;
    const uint8_t base_flags = uint8_t((has_uv[0] ? TriangleMesh::kHasUv0 : 0) |
                                       (has_uv[1] ? TriangleMesh::kHasUv1 : 0) |
                                       (attrs.tangent ? TriangleMesh::kHasTangents : 0));
    auto add = [&](uint32_t a, uint32_t b) {
      if (a == b && prim.mode != TINYGLTF_MODE_POINTS) return;
      const bool normals = attrs.normal && !bad_normal[a] && !bad_normal[b];
      out->elements.push_back(
          {first + a, first + b, material->second,
           uint8_t(base_flags | (normals ? TriangleMesh::kHasNormals : 0)), node});
    };
    const size_t n = indices.size();
    if (prim.mode == TINYGLTF_MODE_POINTS) {
      for (size_t i = 0; i < n; ++i) add(indices[i], indices[i]);
    } else if (prim.mode == TINYGLTF_MODE_LINE) {
      if (n % 2) warn(where + ": index count of LINES is odd; the last index is ignored");
      for (size_t i = 0; i + 1 < n; i += 2) add(indices[i], indices[i + 1]);
    } else {
      for (size_t i = 0; i + 1 < n; ++i) add(indices[i], indices[i + 1]);
      if (prim.mode == TINYGLTF_MODE_LINE_LOOP && n > 2) add(indices[n - 1], indices[0]);
    }
  }
}

// The points and lines of a visible mesh node: in world space, for every node that uses the
// mesh (each element of EXT_mesh_gpu_instancing too), posed if the node is deformed. An
// animated layout's static part has none: every pose has them all.
void Loader::visit_thin(int index, const tinygltf::Node& node, const Mat4& world,
                        const std::string& where, SceneDescription* desc) {
  if (split_ && !split_->pose_only) return;
  const size_t mi = size_t(node.mesh);
  bool any = false;
  for (const tinygltf::Primitive& prim : model_.meshes[mi].primitives)
    any = any || !is_triangles(prim.mode);
  if (!any) return;
  const uint32_t id = uint32_t(index);
  if (gpu_instancing(node)) {
    for (const Mat4& local : gpu_instances(node, index))
      add_thin(mi, world * local, &desc->thin, id);
  } else if (is_deformed(index)) {
    const Deformation deformation = deformation_of(index, where);
    add_thin(mi, world, &desc->thin, id, &deformation);
  } else {
    add_thin(mi, world, &desc->thin, id);
  }
}

}  // namespace rf::gltf_detail
