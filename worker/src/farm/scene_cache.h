// Scene caches of the farm worker: scene files (and environment maps, which the server stores
// and serves like scenes) on disk, content-addressed by SHA-256
// (<dir>/<sha256>.glb|.gltf|.hdr|.exr), and loaded scenes in memory (an LRU keyed by sha256,
// bounded in count and in bytes, each scene loaded once even when several threads ask for it at
// the same time). Animated tasks share the LRU: a scene's AnimatedScene (its parsed glTF
// document and static part, animated_scene.h), once per animation selection, and its posed
// render scenes, one per (animation selection, time), a few per scene. A pose is cheap to make
// from the AnimatedScene and shares its static BVH; poses of different times render
// concurrently, each its own Scene (the AnimatedScene's concurrency rules).
#pragma once

#include <cstdint>
#include <functional>
#include <future>
#include <map>
#include <memory>
#include <mutex>
#include <string>
#include <vector>

#include "scene/animated_scene.h"
#include "scene/scene.h"

namespace rf {

// $XDG_CACHE_HOME/renderfarm/scenes, else ~/.cache/renderfarm/scenes.
std::string default_scene_cache_dir();
// sha256 names of the cached files in dir (files named <64 hex>.glb/.gltf/.hdr/.exr).
std::vector<std::string> list_cached_scenes(const std::string& dir);
// Path of the cached file for sha256, or "" if there is none.
std::string find_cached_scene(const std::string& dir, const std::string& sha256);

class SceneCache {
 public:
  using Loader = std::function<std::shared_ptr<const Scene>()>;
  using AnimatedLoader = std::function<std::shared_ptr<const AnimatedScene>()>;
  using Poser = std::function<std::shared_ptr<const Scene>(const AnimatedScene&)>;
  // Keeps at most `capacity` loaded scenes (stills, animated scenes and posed scenes alike)
  // and, if memory_budget > 0, evicts the least recently used ones while they hold more than
  // memory_budget bytes (Scene::memory_bytes, AnimatedScene::memory_bytes). The entry just loaded and
  // the most recently used one are always kept, whatever their size: a scene larger than the
  // budget still renders. At most posed_per_scene posed scenes of one scene are kept: frames
  // are leased mostly in order, and the tasks of one frame arrive together.
  explicit SceneCache(size_t capacity, size_t memory_budget = 0, size_t posed_per_scene = 3)
      : capacity_(capacity ? capacity : 1),
        memory_budget_(memory_budget),
        posed_per_scene_(posed_per_scene ? posed_per_scene : 1) {}
  // Returns the scene for key, calling load() if it is not in memory. Concurrent callers for
  // the same key wait for one load. If load throws, every waiting caller gets the exception
  // and the next call tries again.
  std::shared_ptr<const Scene> get(const std::string& key, const Loader& load);
  // The scene sha256 posed as pose_key says (the caller's name for an animation selection and
  // a time: equal keys must mean equal poses), made by pose() from the scene's AnimatedScene
  // for the animation selection `selection`, which prepare() makes once per (sha256,
  // selection) while it stays cached. The same waiting, failure and eviction rules as get().
  std::shared_ptr<const Scene> get_posed(const std::string& sha256, const std::string& selection,
                                         const std::string& pose_key,
                                         const AnimatedLoader& prepare, const Poser& pose);
  // A value the worker derives from a scene and keeps the same way (path guiding's fields, in
  // a SceneCache of their own so that they never evict a scene): key's value, made by make()
  // once, with the same waiting, failure and eviction rules as get() (no bytes counted).
  template <typename T>
  std::shared_ptr<const T> get_derived(const std::string& key,
                                       const std::function<std::shared_ptr<const T>()>& make) {
    return std::static_pointer_cast<const T>(
        get_value(key, "", [&] { return Loaded{make(), 0}; }));
  }
  size_t size() const;
  // Bytes held by the loaded entries in the cache.
  size_t memory_bytes() const;

 private:
  using Value = std::shared_ptr<const void>;
  struct Loaded {
    Value value;
    size_t bytes = 0;
  };
  struct Entry {
    std::shared_future<Value> value;
    uint64_t last_used = 0;
    bool ready = false;
    size_t bytes = 0;     // the value's memory once ready
    std::string posed_of;  // a posed scene: the sha256 it poses; "" otherwise
  };
  Value get_value(const std::string& key, const std::string& posed_of,
                  const std::function<Loaded()>& load);
  size_t memory_bytes_locked() const;
  void evict_locked(const std::string& keep);
  size_t capacity_;
  size_t memory_budget_;
  size_t posed_per_scene_;
  mutable std::mutex mutex_;
  std::map<std::string, Entry> entries_;
  uint64_t clock_ = 0;
};

}  // namespace rf
