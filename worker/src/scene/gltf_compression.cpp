// EXT_meshopt_compression and KHR_draco_mesh_compression, decoded into plain glTF buffers by
// the libraries made for them (meshoptimizer and Draco, from Debian's libmeshoptimizer-dev and
// libdraco-dev). This file only moves bytes between the file's structures and the decoders,
// and checks what the extension texts require of the file before any decoder runs.
#include "scene/gltf_compression.h"

#include <draco/compression/decode.h>
#include <meshoptimizer.h>
#include <tiny_gltf.h>

#include <cstdint>
#include <cstring>
#include <map>
#include <memory>
#include <nlohmann/json.hpp>
#include <set>
#include <vector>

#include "scene/scene.h"

namespace rf {
namespace {

constexpr const char* kMeshopt = "EXT_meshopt_compression";
constexpr const char* kDraco = "KHR_draco_mesh_compression";
// One byte of data: what a meshopt fallback buffer holds until it is decoded into.
constexpr const char* kOneByte = "data:application/octet-stream;base64,AA==";

[[noreturn]] void fail(const std::string& source, const std::string& path,
                       const std::string& what) {
  throw SceneError(source + ": " + path + ": " + what, path);
}

// A required non-negative integer member of an extension object.
size_t required_size(const tinygltf::Value& obj, const char* key, const std::string& source,
                     const std::string& path) {
  const tinygltf::Value& v = obj.Get(key);
  if (!v.IsNumber() || v.GetNumberAsDouble() < 0 || v.GetNumberAsDouble() > 9.0e15 ||
      v.GetNumberAsDouble() != double(uint64_t(v.GetNumberAsDouble())))
    fail(source, path, std::string("'") + key + "' must be a non-negative integer");
  return size_t(v.GetNumberAsDouble());
}

std::string string_or(const tinygltf::Value& obj, const char* key, const std::string& fallback) {
  if (!obj.Has(key)) return fallback;
  const tinygltf::Value& v = obj.Get(key);
  return v.IsString() ? v.Get<std::string>() : std::string("(not a string)");
}

// Whether [offset, offset + length) lies in `size` bytes, without overflow.
bool in_range(size_t size, size_t offset, size_t length) {
  return offset <= size && length <= size - offset;
}

// The meshopt buffer views, checked; decoded afterwards in one pass.
struct MeshoptView {
  int view;
  std::string path;
  size_t source_buffer, source_offset, source_length, stride, count;
  std::string mode, filter;
};

std::vector<MeshoptView> meshopt_views(const tinygltf::Model& model,
                                       const std::string& source) {
  std::vector<MeshoptView> views;
  for (size_t i = 0; i < model.bufferViews.size(); ++i) {
    const tinygltf::BufferView& bv = model.bufferViews[i];
    auto it = bv.extensions.find(kMeshopt);
    if (it == bv.extensions.end()) continue;
    MeshoptView v;
    v.view = int(i);
    v.path = "bufferViews[" + std::to_string(i) + "].extensions." + kMeshopt;
    const tinygltf::Value& ext = it->second;
    if (!ext.IsObject()) fail(source, v.path, "must be an object");
    v.source_buffer = required_size(ext, "buffer", source, v.path);
    v.source_offset = ext.Has("byteOffset") ? required_size(ext, "byteOffset", source, v.path) : 0;
    v.source_length = required_size(ext, "byteLength", source, v.path);
    v.stride = required_size(ext, "byteStride", source, v.path);
    v.count = required_size(ext, "count", source, v.path);
    v.mode = string_or(ext, "mode", "");
    v.filter = string_or(ext, "filter", "NONE");
    if (v.source_buffer >= model.buffers.size())
      fail(source, v.path, "'buffer' refers to missing buffer " + std::to_string(v.source_buffer));
    if (!in_range(model.buffers[v.source_buffer].data.size(), v.source_offset, v.source_length))
      fail(source, v.path, "the compressed data exceeds its buffer");
    if (v.mode == "ATTRIBUTES") {
      if (v.stride == 0 || v.stride % 4 != 0 || v.stride > 256)
        fail(source, v.path, "'byteStride' of ATTRIBUTES must be a multiple of 4 in 4..256");
      if (v.filter == "OCTAHEDRAL" ? (v.stride != 4 && v.stride != 8)
          : v.filter == "QUATERNION" ? v.stride != 8
          : v.filter != "NONE" && v.filter != "EXPONENTIAL")
        fail(source, v.path,
             "'filter' " + v.filter + " with 'byteStride' " + std::to_string(v.stride) +
                 " (NONE, OCTAHEDRAL with 4 or 8, QUATERNION with 8, EXPONENTIAL)");
    } else if (v.mode == "TRIANGLES" || v.mode == "INDICES") {
      if (v.stride != 2 && v.stride != 4)
        fail(source, v.path, "'byteStride' of " + v.mode + " must be 2 or 4");
      if (v.filter != "NONE") fail(source, v.path, "'filter' must be NONE for " + v.mode);
      if (v.mode == "TRIANGLES" && v.count % 3 != 0)
        fail(source, v.path, "'count' of TRIANGLES must be a multiple of 3");
    } else {
      fail(source, v.path, "'mode' must be ATTRIBUTES, TRIANGLES or INDICES, not '" + v.mode +
                               "'");
    }
    // The extension: the uncompressed view is count x byteStride bytes.
    if (v.count > SIZE_MAX / v.stride || v.count * v.stride != bv.byteLength)
      fail(source, v.path,
           "'count' x 'byteStride' (" + std::to_string(v.count) + " x " +
               std::to_string(v.stride) + ") differs from the buffer view's byteLength " +
               std::to_string(bv.byteLength));
    if (bv.buffer < 0 || size_t(bv.buffer) >= model.buffers.size())
      fail(source, "bufferViews[" + std::to_string(i) + "]",
           "refers to missing buffer " + std::to_string(bv.buffer));
    views.push_back(v);
  }
  return views;
}

void decode_meshopt(tinygltf::Model* model, const MeshoptView& v, const std::string& source) {
  const tinygltf::BufferView& bv = model->bufferViews[size_t(v.view)];
  std::vector<unsigned char>& target = model->buffers[size_t(bv.buffer)].data;
  if (!in_range(target.size(), bv.byteOffset, bv.byteLength))
    fail(source, "bufferViews[" + std::to_string(v.view) + "]", "buffer view exceeds its buffer");
  // The source is copied first: a view may decode into the buffer that holds its own
  // compressed bytes (both are plain buffers of the file).
  const std::vector<unsigned char>& from = model->buffers[v.source_buffer].data;
  const std::vector<unsigned char> src(from.begin() + long(v.source_offset),
                                       from.begin() + long(v.source_offset + v.source_length));
  unsigned char* dst = target.data() + bv.byteOffset;
  int rc = 0;
  if (v.mode == "ATTRIBUTES") {
    rc = meshopt_decodeVertexBuffer(dst, v.count, v.stride, src.data(), src.size());
    if (rc == 0 && v.filter == "OCTAHEDRAL") meshopt_decodeFilterOct(dst, v.count, v.stride);
    if (rc == 0 && v.filter == "QUATERNION") meshopt_decodeFilterQuat(dst, v.count, v.stride);
    if (rc == 0 && v.filter == "EXPONENTIAL") meshopt_decodeFilterExp(dst, v.count, v.stride);
  } else if (v.mode == "TRIANGLES") {
    rc = meshopt_decodeIndexBuffer(dst, v.count, v.stride, src.data(), src.size());
  } else {
    rc = meshopt_decodeIndexSequence(dst, v.count, v.stride, src.data(), src.size());
  }
  if (rc != 0)
    fail(source, v.path,
         "the compressed data does not decode (meshoptimizer error " + std::to_string(rc) + ")");
}

// A Draco primitive: its compressed bytes and the accessors its decoding fills.
struct DracoPrimitive {
  size_t mesh, primitive;
  std::string path;
  size_t buffer = 0, offset = 0, length = 0;  // the compressed bytes
  std::vector<std::pair<int, uint32_t>> attributes;  // (accessor, Draco attribute id)
  double bytes = 0.0;  // decoded size, from the accessors' declared counts
  // Every accessor it decodes into is decoded the same way (the same compressed buffer view
  // and attribute id) by an earlier primitive: exporters write the primitives of one Draco
  // mesh that differ only in material so. Decoded once, by the first.
  bool duplicate = false;
};

size_t round4(size_t n) { return (n + 3) & ~size_t(3); }

size_t element_size(const tinygltf::Accessor& acc) {
  const int ncomp = tinygltf::GetNumComponentsInType(uint32_t(acc.type));
  const int csize = tinygltf::GetComponentSizeInBytes(uint32_t(acc.componentType));
  return ncomp > 0 && csize > 0 ? size_t(ncomp) * size_t(csize) : 0;
}

std::vector<DracoPrimitive> draco_primitives(tinygltf::Model* model_ptr,
                                             const std::string& source) {
  tinygltf::Model& model = *model_ptr;
  std::vector<DracoPrimitive> prims;
  // The accessors Draco primitives decode into, with what fills each: (compressed buffer view,
  // attribute id; -1 for the indices). Primitives that fill an accessor from the same data
  // share it, decoded once. An accessor named for different data (two attributes of one
  // primitive, or two primitives, decoding other Draco attributes into it, as some exporters
  // write) is copied for each further use, and that attribute refers to its copy: each
  // attribute gets the data its Draco attribute holds, as viewers decode them.
  std::map<int, std::pair<size_t, int64_t>> claimed;
  auto claim = [&](int* accessor, size_t view, int64_t id, const std::string& path) {
    if (*accessor < 0 || size_t(*accessor) >= model.accessors.size())
      fail(source, path, "refers to missing accessor " + std::to_string(*accessor));
    {
      const tinygltf::Accessor& acc = model.accessors[size_t(*accessor)];
      if (acc.sparse.isSparse) fail(source, path, "a Draco accessor cannot be sparse");
      if (!element_size(acc)) fail(source, path, "unsupported 'type' or 'componentType'");
    }
    const auto [it, fresh] = claimed.emplace(*accessor, std::make_pair(view, id));
    if (fresh || it->second == std::make_pair(view, id)) return fresh;
    const tinygltf::Accessor copy = model.accessors[size_t(*accessor)];
    model.accessors.push_back(copy);
    *accessor = int(model.accessors.size()) - 1;
    claimed.emplace(*accessor, std::make_pair(view, id));
    return true;
  };
  for (size_t m = 0; m < model.meshes.size(); ++m) {
    for (size_t p = 0; p < model.meshes[m].primitives.size(); ++p) {
      tinygltf::Primitive& prim = model.meshes[m].primitives[p];
      auto it = prim.extensions.find(kDraco);
      if (it == prim.extensions.end()) continue;
      DracoPrimitive d;
      d.mesh = m;
      d.primitive = p;
      const std::string prim_path =
          "meshes[" + std::to_string(m) + "].primitives[" + std::to_string(p) + "]";
      d.path = prim_path + ".extensions." + kDraco;
      const tinygltf::Value& ext = it->second;
      if (!ext.IsObject()) fail(source, d.path, "must be an object");
      if (prim.mode != TINYGLTF_MODE_TRIANGLES && prim.mode != TINYGLTF_MODE_TRIANGLE_STRIP)
        fail(source, prim_path + ".mode", "a Draco primitive must be TRIANGLES or TRIANGLE_STRIP");
      const size_t view = required_size(ext, "bufferView", source, d.path);
      if (view >= model.bufferViews.size())
        fail(source, d.path, "'bufferView' refers to missing buffer view " + std::to_string(view));
      const tinygltf::BufferView& bv = model.bufferViews[view];
      if (bv.buffer < 0 || size_t(bv.buffer) >= model.buffers.size() ||
          !in_range(model.buffers[size_t(bv.buffer)].data.size(), bv.byteOffset, bv.byteLength))
        fail(source, d.path, "the compressed data exceeds its buffer");
      d.buffer = size_t(bv.buffer);
      d.offset = bv.byteOffset;
      d.length = bv.byteLength;
      const tinygltf::Value& attrs = ext.Get("attributes");
      if (!attrs.IsObject()) fail(source, d.path, "'attributes' must be an object");
      int fresh = 0;  // accessors no earlier primitive decodes
      for (const std::string& name : attrs.Keys()) {
        const std::string where = d.path + ".attributes." + name;
        auto a = prim.attributes.find(name);
        if (a == prim.attributes.end())
          fail(source, where, "the primitive has no attribute " + name);
        const tinygltf::Value& id = attrs.Get(name);
        if (!id.IsNumber() || id.GetNumberAsDouble() < 0 || id.GetNumberAsDouble() > 4.0e9 ||
            id.GetNumberAsDouble() != double(uint32_t(id.GetNumberAsDouble())))
          fail(source, where, "must be a Draco attribute id (a non-negative integer)");
        const uint32_t draco_id = uint32_t(id.GetNumberAsDouble());
        fresh += claim(&a->second, view, draco_id, where);
        d.attributes.push_back({a->second, draco_id});
        const tinygltf::Accessor& acc = model.accessors[size_t(a->second)];
        d.bytes += double(acc.count) * double(element_size(acc));
      }
      if (prim.indices >= 0) {
        fresh += claim(&prim.indices, view, -1, prim_path + ".indices");
        d.bytes += double(model.accessors[size_t(prim.indices)].count) * 4.0;
      } else {
        fail(source, prim_path, "a Draco primitive needs an 'indices' accessor (the triangles)");
      }
      d.duplicate = fresh == 0;
      if (d.duplicate) d.bytes = 0.0;
      prims.push_back(std::move(d));
    }
  }
  return prims;
}

// Draco's values of one attribute for every point, converted to the accessor's component
// type (ConvertValue: Draco's dequantization and normalization) and packed tightly.
template <typename T>
void write_points(const draco::PointAttribute& att, const draco::Mesh& mesh, int ncomp,
                  unsigned char* out) {
  std::vector<T> value(static_cast<size_t>(ncomp));
  for (uint32_t i = 0; i < mesh.num_points(); ++i) {
    att.ConvertValue<T>(att.mapped_index(draco::PointIndex(i)), int8_t(ncomp), value.data());
    std::memcpy(out + size_t(i) * size_t(ncomp) * sizeof(T), value.data(),
                size_t(ncomp) * sizeof(T));
  }
}

void decode_draco(tinygltf::Model* model, const DracoPrimitive& d, const std::string& source) {
  draco::DecoderBuffer buffer;
  // Buffers are only appended below: the compressed bytes stay where they are.
  buffer.Init(reinterpret_cast<const char*>(model->buffers[d.buffer].data.data() + d.offset),
              d.length);
  auto type = draco::Decoder::GetEncodedGeometryType(&buffer);
  if (!type.ok() || type.value() != draco::TRIANGULAR_MESH)
    fail(source, d.path, "the compressed data is not a Draco triangle mesh");
  draco::Decoder decoder;
  auto decoded = decoder.DecodeMeshFromBuffer(&buffer);
  if (!decoded.ok())
    fail(source, d.path,
         "the compressed data does not decode (Draco: " + decoded.status().error_msg_string() +
             ")");
  const std::unique_ptr<draco::Mesh> mesh = std::move(decoded).value();

  // The declared counts must be what Draco decoded before anything is sized from them.
  tinygltf::Primitive& prim = model->meshes[d.mesh].primitives[d.primitive];
  size_t total = size_t(mesh->num_faces()) * 3 * 4;
  for (const auto& [accessor, id] : d.attributes) {
    const tinygltf::Accessor& acc = model->accessors[size_t(accessor)];
    if (acc.count != mesh->num_points())
      fail(source, d.path + ".attributes",
           "accessor " + std::to_string(accessor) + " declares " + std::to_string(acc.count) +
               " elements; the Draco data decodes " + std::to_string(mesh->num_points()));
    total += round4(acc.count * element_size(acc));
  }
  if (model->accessors[size_t(prim.indices)].count != size_t(mesh->num_faces()) * 3)
    fail(source, d.path,
         "the indices accessor declares " +
             std::to_string(model->accessors[size_t(prim.indices)].count) +
             " indices; the Draco data decodes " + std::to_string(mesh->num_faces()) +
             " triangles");
  tinygltf::Buffer out;
  out.data.resize(total);
  size_t offset = 0;
  const int buffer_index = int(model->buffers.size());
  auto add_view = [&](int accessor, size_t length) {
    tinygltf::BufferView bv;
    bv.buffer = buffer_index;
    bv.byteOffset = offset;
    bv.byteLength = length;
    model->bufferViews.push_back(bv);
    tinygltf::Accessor& acc = model->accessors[size_t(accessor)];
    acc.bufferView = int(model->bufferViews.size()) - 1;
    acc.byteOffset = 0;
    offset += round4(length);  // every view 4-byte aligned, as glTF asks of accessors
  };
  for (const auto& [accessor, id] : d.attributes) {
    tinygltf::Accessor& acc = model->accessors[size_t(accessor)];
    const std::string where = d.path + ".attributes";
    const draco::PointAttribute* att = mesh->GetAttributeByUniqueId(id);
    if (att == nullptr)
      fail(source, where, "the Draco data has no attribute with id " + std::to_string(id));
    const int ncomp = tinygltf::GetNumComponentsInType(uint32_t(acc.type));
    if (ncomp != att->num_components())
      fail(source, where,
           "accessor " + std::to_string(accessor) + " has " + std::to_string(ncomp) +
               " components; the Draco attribute " + std::to_string(id) + " has " +
               std::to_string(att->num_components()));
    unsigned char* dst = out.data.data() + offset;
    switch (acc.componentType) {
      case TINYGLTF_COMPONENT_TYPE_FLOAT: write_points<float>(*att, *mesh, ncomp, dst); break;
      case TINYGLTF_COMPONENT_TYPE_BYTE: write_points<int8_t>(*att, *mesh, ncomp, dst); break;
      case TINYGLTF_COMPONENT_TYPE_UNSIGNED_BYTE:
        write_points<uint8_t>(*att, *mesh, ncomp, dst);
        break;
      case TINYGLTF_COMPONENT_TYPE_SHORT: write_points<int16_t>(*att, *mesh, ncomp, dst); break;
      case TINYGLTF_COMPONENT_TYPE_UNSIGNED_SHORT:
        write_points<uint16_t>(*att, *mesh, ncomp, dst);
        break;
      case TINYGLTF_COMPONENT_TYPE_UNSIGNED_INT:
        write_points<uint32_t>(*att, *mesh, ncomp, dst);
        break;
      default:
        fail(source, where, "unsupported componentType " + std::to_string(acc.componentType));
    }
    add_view(accessor, acc.count * element_size(acc));
  }
  {
    tinygltf::Accessor& acc = model->accessors[size_t(prim.indices)];
    // Faces come out as triangles whatever the primitive's mode, as 32-bit indices.
    acc.componentType = TINYGLTF_COMPONENT_TYPE_UNSIGNED_INT;
    acc.type = TINYGLTF_TYPE_SCALAR;
    acc.normalized = false;
    unsigned char* idx = out.data.data() + offset;
    for (uint32_t f = 0; f < mesh->num_faces(); ++f)
      for (int k = 0; k < 3; ++k) {
        const uint32_t v = mesh->face(draco::FaceIndex(f))[k].value();
        std::memcpy(idx + (size_t(f) * 3 + size_t(k)) * 4, &v, 4);
      }
    add_view(prim.indices, acc.count * 4);
    prim.mode = TINYGLTF_MODE_TRIANGLES;
  }
  model->buffers.push_back(std::move(out));
}

}  // namespace

bool prepare_json(std::string* json, std::map<int, size_t>* fallbacks) {
  nlohmann::json doc = nlohmann::json::parse(*json, nullptr, /*allow_exceptions=*/false);
  if (doc.is_discarded() || !doc.is_object()) return false;
  bool changed = false;
  // KHR_animation_pointer's channels have no target node; tinygltf drops such a channel.
  auto animations = doc.find("animations");
  if (animations != doc.end() && animations->is_array())
    for (nlohmann::json& anim : *animations) {
      if (!anim.is_object() || !anim.contains("channels") || !anim["channels"].is_array())
        continue;
      for (nlohmann::json& ch : anim["channels"]) {
        if (!ch.is_object() || !ch.contains("target") || !ch["target"].is_object()) continue;
        nlohmann::json& target = ch["target"];
        if (target.contains("path") && target["path"] == "pointer" && !target.contains("node")) {
          target["node"] = -1;
          changed = true;
        }
      }
    }
  auto meshes = doc.find("meshes");
  auto accessors = doc.find("accessors");
  if (meshes != doc.end() && meshes->is_array() && accessors != doc.end() &&
      accessors->is_array())
    for (nlohmann::json& mesh : *meshes) {
      if (!mesh.is_object() || !mesh.contains("primitives") || !mesh["primitives"].is_array())
        continue;
      for (nlohmann::json& prim : mesh["primitives"]) {
        if (!prim.is_object() || !prim.contains("indices") ||
            !prim["indices"].is_number_unsigned() || !prim.contains("extensions") ||
            !prim["extensions"].is_object() || !prim["extensions"].contains(kDraco))
          continue;
        const nlohmann::json& draco = prim["extensions"][kDraco];
        const size_t index = prim["indices"].get<size_t>();
        if (!draco.is_object() || !draco.contains("bufferView") ||
            !draco["bufferView"].is_number_unsigned() || index >= accessors->size())
          continue;  // decode_compressed_geometry says what is wrong
        nlohmann::json& acc = (*accessors)[index];
        if (acc.is_object() && !acc.contains("bufferView")) {
          acc["bufferView"] = draco["bufferView"];
          changed = true;
        }
      }
    }
  auto buffers = doc.find("buffers");
  if (buffers == doc.end() || !buffers->is_array()) {
    if (changed) *json = doc.dump();
    return changed;
  }
  for (size_t i = 0; i < buffers->size(); ++i) {
    nlohmann::json& b = (*buffers)[i];
    if (!b.is_object() || b.contains("uri")) continue;
    const auto ext = b.find("extensions");
    if (ext == b.end() || !ext->is_object() || !ext->contains(kMeshopt)) continue;
    const nlohmann::json& m = (*ext)[kMeshopt];
    if (!m.is_object() || !m.contains("fallback") || m["fallback"] != true) continue;
    const auto length = b.find("byteLength");
    if (length == b.end() || !length->is_number_unsigned()) continue;  // tinygltf says why
    (*fallbacks)[int(i)] = length->get<size_t>();
    b["uri"] = kOneByte;
    b["byteLength"] = 1;
    changed = true;
  }
  if (changed) *json = doc.dump();
  return changed;
}

bool prepare_glb(std::string* glb, std::map<int, size_t>* fallbacks) {
  auto u32 = [&](size_t at) {
    uint32_t v;
    std::memcpy(&v, glb->data() + at, 4);
    return v;
  };
  // 12-byte header, then the JSON chunk (length, type "JSON", data).
  if (glb->size() < 20 || u32(16) != 0x4E4F534Au) return false;
  const size_t json_length = u32(12);
  if (json_length > glb->size() - 20) return false;
  std::string json = glb->substr(20, json_length);
  if (!prepare_json(&json, fallbacks)) return false;
  while (json.size() % 4) json += ' ';  // chunks are 4-byte aligned, padded with spaces
  std::string out = glb->substr(0, 12);
  const uint32_t chunk = uint32_t(json.size());
  out.append(reinterpret_cast<const char*>(&chunk), 4);
  out.append(glb->data() + 16, 4);
  out += json;
  out.append(*glb, 20 + json_length, std::string::npos);
  const uint32_t total = uint32_t(out.size());
  std::memcpy(out.data() + 8, &total, 4);
  *glb = std::move(out);
  return true;
}

void decode_compressed_geometry(tinygltf::Model* model, const std::map<int, size_t>& fallbacks,
                                const SceneLimits& limits, const std::string& source) {
  const std::vector<MeshoptView> views = meshopt_views(*model, source);
  const std::vector<DracoPrimitive> dracos = draco_primitives(model, source);
  if (views.empty() && dracos.empty()) return;
  // What decoding will hold, from declared sizes, before anything is allocated: the file's
  // buffers, the fallback buffers at their real size, the Draco primitives' arrays.
  double bytes = 0.0;
  for (const tinygltf::Buffer& b : model->buffers) bytes += double(b.data.size());
  for (const auto& [index, length] : fallbacks) bytes += double(length);
  for (const DracoPrimitive& d : dracos) bytes += d.bytes;
  if (limits.max_memory_bytes && bytes > double(limits.max_memory_bytes))
    fail(source, "meshes",
         "the compressed geometry decodes to about " + format_bytes(size_t(bytes)) +
             ", over the scene memory limit of " + format_bytes(limits.max_memory_bytes));
  for (const auto& [index, length] : fallbacks)
    if (index < int(model->buffers.size())) model->buffers[size_t(index)].data.assign(length, 0);
  for (const MeshoptView& v : views) decode_meshopt(model, v, source);
  for (const DracoPrimitive& d : dracos) {
    if (!d.duplicate) {
      decode_draco(model, d, source);
    } else {
      // Its accessors hold the first primitive's decoded triangles (a list, whatever the
      // mode was).
      model->meshes[d.mesh].primitives[d.primitive].mode = TINYGLTF_MODE_TRIANGLES;
    }
  }
}

}  // namespace rf
