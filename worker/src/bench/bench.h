// `renderfarm-worker bench`: throughput of the renderer on the Cornell box, on a generated
// scene of at least a million triangles and on a generated scene of instances, at 1 and 2 (or
// more) threads, compared with Embree's raw rtcIntersect1/rtcOccluded1 rate on the very rays
// the path tracer traced (recorded in the same process and replayed). Prints a summary and returns the figures as JSON.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "scene/scene.h"

namespace rf {

struct BenchOptions {
  std::string cornell_path;      // the Cornell box .gltf
  uint32_t mesh_triangles = 1u << 20;  // generated scene size (>= 1M by default)
  uint32_t instance_triangles = 1u << 14;  // the instanced scene's mesh
  uint32_t instance_grid = 12;             // ... placed on a grid x grid of instances
  uint32_t width = 96, height = 96;
  uint32_t spp = 16;
  std::vector<uint32_t> threads = {1, 2};
  // Which scenes to run (all by default): the Cornell box, the generated >= 1M-triangle mesh
  // and the instanced scene.
  bool cornell = true, mesh = true, instanced = true;
};

// A procedural scene: a displaced sphere of about `triangles` flat triangles on a floor under
// an emissive quad, with a camera. Deterministic.
SceneDescription generate_bench_scene(uint32_t triangles);

// The same sphere (about `triangles_per_mesh` triangles) as one mesh placed by grid x grid
// Embree instances (turned, scaled, some mirrored) on the floor under the lamp. Deterministic.
SceneDescription generate_instanced_bench_scene(uint32_t triangles_per_mesh, uint32_t grid);

// Runs the benchmark; returns a JSON document (as text) with every figure.
std::string run_bench(const BenchOptions& options);

}  // namespace rf
