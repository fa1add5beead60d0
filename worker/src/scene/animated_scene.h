// An animated glTF scene loaded once and posed at any time without being loaded again
// (docs/scenes.md, "Animated farm tasks"). At construction the loader splits the scene
// (AnimatedLayout, animation.h): the static part - every node that no chosen animation moves
// or deforms, flattened into world triangles or instanced as in a still, and the meshes of the
// moving nodes in their own space - is built once, with its Embree BVHs. A pose at time t
// then costs the evaluation of the animations, the placement of the moving meshes by Embree
// instances, the skinned and morphed vertices rewritten in place with their BVHs refit, and
// the build of the top level (the instances) only.
//
// Concurrency: pose() may be called from several threads at once, and its scenes rendered
// concurrently, each at its own time. Every pose is a Scene of its own that shares the static
// part (read only, never copied: one static BVH in memory however many poses are alive) and
// owns its top-level BVH, its instances' transforms and one set of deformed meshes
// (DeformedMeshes, scene.h). A set serves one pose at a time: when a pose is destroyed its set
// goes back to a small pool, and the next pose rewrites and refits it; when every set is in use
// (several times alive together) a new pose builds a set of its own.
//
// A pose renders the image a pose made the first time would render (bit for bit: the same
// triangles, transforms and materials; a refit BVH has another shape than a built one but the
// same closest hits). Against the loader's flattened scene (load_scene with LoadOptions::time,
// the `pose` command's layout) it differs at float rounding: a moving mesh is transformed by
// its instance's matrix at ray time instead of in its vertices.
#pragma once

#include <cstdint>
#include <memory>
#include <mutex>
#include <string>
#include <vector>

#include "scene/scene.h"

namespace rf {

// A motion-blurred frame's shutter: open and close in seconds from the frame's time (close >
// open: blurred; otherwise closed, no motion blur).
struct Shutter {
  double open_s = 0.0, close_s = 0.0;
  bool is_open() const { return close_s > open_s; }
};
// The time steps of a motion-blurred pose: the scene is posed at this many times evenly
// spaced over the shutter, and Embree interpolates linearly between them.
constexpr uint32_t kShutterSteps = 5;
// The setting `shutter` ("OPEN,CLOSE", fractions of a frame; "" closed) at fps frames per
// second into *out; false with *err set for anything else (the server's rule: finite, -1 <=
// OPEN < CLOSE <= 1, at most one frame apart).
bool parse_shutter(const std::string& text, double fps, Shutter* out, std::string* err);

class AnimatedScene {
 public:
  // Splits the document's scene for options.animations (empty: every animation; options.time
  // is not used) and builds the static part with options.bvh; warnings of the load go to
  // *warnings. Throws SceneError as describe_gltf and Scene do.
  AnimatedScene(std::shared_ptr<const GltfDocument> document, const LoadOptions& options,
                std::vector<std::string>* warnings = nullptr);
  ~AnimatedScene();
  AnimatedScene(const AnimatedScene&) = delete;
  AnimatedScene& operator=(const AnimatedScene&) = delete;

  // The scene at time t (seconds, finite). Thread-safe. *warnings gets the pose's own
  // (a missing camera); the load's were given at construction. With an open shutter the
  // scene is posed at kShutterSteps times from t + open_s to t + close_s and moves between
  // them during the shutter (motion blur: Scene's posing constructor). image_height sizes the
  // pose's points and lines (LoadOptions::image_height; 0: the construction's options').
  std::shared_ptr<const Scene> pose(double time, std::vector<std::string>* warnings = nullptr,
                                    const Shutter& shutter = {},
                                    uint32_t image_height = 0) const;

  const Scene& static_part() const { return *base_; }
  // Bytes the document and the static part hold (a pose's own: Scene::memory_bytes).
  size_t memory_bytes() const;
  // Mesh nodes placed by instances that move, and meshes deformed per time.
  uint32_t moving_nodes() const { return moving_nodes_; }
  uint32_t deformed_nodes() const { return deformed_nodes_; }

 private:
  struct Pool {
    std::mutex mutex;
    std::vector<std::unique_ptr<DeformedMeshes>> free;
  };
  std::shared_ptr<const GltfDocument> document_;
  LoadOptions options_;
  std::shared_ptr<const Scene> base_;
  std::shared_ptr<Pool> pool_;
  uint32_t moving_nodes_ = 0, deformed_nodes_ = 0;
};

// parse_gltf + AnimatedScene + pose(options.time): the standalone `render --time` and the farm
// worker render the same scene this way.
std::shared_ptr<const Scene> load_animated_scene(const std::string& path,
                                                 std::vector<std::string>* warnings,
                                                 const LoadOptions& options);

}  // namespace rf
