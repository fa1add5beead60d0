// Compressed glTF geometry, decoded before the loader reads any accessor:
// EXT_meshopt_compression buffer views by the meshoptimizer library, and
// KHR_draco_mesh_compression primitives by the Draco library. The decoded bytes are plain glTF
// data (buffer views the accessors already point at, or new buffer views for Draco's
// accessors), so everything after this step - accessor checks, quantization, sparse
// substitution, the memory estimate - sees an ordinary file.
#pragma once

#include <cstddef>
#include <map>
#include <string>

namespace tinygltf {
class Model;
}

namespace rf {

struct SceneLimits;

// Before tinygltf parses the JSON, three things it would refuse or drop in a valid file are
// rewritten:
// - a buffer that exists only to be decoded into (extensions.EXT_meshopt_compression.fallback
//   = true, no uri) has no data in the file (in a .glb tinygltf would even copy the BIN chunk
//   into it). Each such buffer is given a one-byte data URI instead, and its real byteLength is
//   kept in *fallbacks (by buffer index) for decode_compressed_geometry;
// - the indices accessor of a Draco primitive has no bufferView (its data is in the Draco
//   stream), which tinygltf refuses for indices: it is pointed at the primitive's compressed
//   buffer view until decoding gives it one of its own;
// - a KHR_animation_pointer channel has no target node (the extension forbids one), and
//   tinygltf drops a channel without one: it gets node -1, which the loader never reads for a
//   pointer channel (gltf_animation.cpp).
// Returns false (and leaves *json alone) when there is nothing to change or the JSON does not
// parse (tinygltf then reports why).
bool prepare_json(std::string* json, std::map<int, size_t>* fallbacks);

// The same for a .glb held in *glb: its JSON chunk is rewritten (the BIN chunk copied after
// it) when prepare_json changes it.
bool prepare_glb(std::string* glb, std::map<int, size_t>* fallbacks);

// Decodes every compressed buffer view and primitive of *model in place. `source` prefixes
// error messages (the file's display name). Throws SceneError naming the glTF path of the bad
// part (e.g. "bufferViews[3].extensions.EXT_meshopt_compression") for malformed compressed
// data, and refuses decoded data over limits.max_memory_bytes before allocating it.
void decode_compressed_geometry(tinygltf::Model* model, const std::map<int, size_t>& fallbacks,
                                const SceneLimits& limits, const std::string& source);

}  // namespace rf
