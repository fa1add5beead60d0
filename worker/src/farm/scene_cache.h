// Scene caches of the farm worker: scene files (and environment maps, which the server stores
// and serves like scenes) on disk, content-addressed by SHA-256
// (<dir>/<sha256>.glb|.gltf|.hdr|.exr), and loaded scenes in memory (an LRU keyed by sha256,
// bounded in count and in bytes, each scene loaded once even when several threads ask for it at
// the same time).
#pragma once

#include <cstdint>
#include <functional>
#include <future>
#include <map>
#include <memory>
#include <mutex>
#include <string>
#include <vector>

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
  // Keeps at most `capacity` loaded scenes and, if memory_budget > 0, evicts the least
  // recently used ones while the loaded scenes hold more than memory_budget bytes
  // (Scene::memory_bytes). The scene just loaded and the most recently used one are always
  // kept, whatever their size: a scene larger than the budget still renders.
  explicit SceneCache(size_t capacity, size_t memory_budget = 0)
      : capacity_(capacity ? capacity : 1), memory_budget_(memory_budget) {}
  // Returns the scene for key, calling load() if it is not in memory. Concurrent callers for
  // the same key wait for one load. If load throws, every waiting caller gets the exception
  // and the next call tries again.
  std::shared_ptr<const Scene> get(const std::string& key, const Loader& load);
  size_t size() const;
  // Bytes held by the loaded scenes in the cache.
  size_t memory_bytes() const;

 private:
  struct Entry {
    std::shared_future<std::shared_ptr<const Scene>> scene;
    uint64_t last_used = 0;
    bool ready = false;
    size_t bytes = 0;  // Scene::memory_bytes once ready
  };
  size_t memory_bytes_locked() const;
  void evict_locked(const std::string& keep);
  size_t capacity_;
  size_t memory_budget_;
  mutable std::mutex mutex_;
  std::map<std::string, Entry> entries_;
  uint64_t clock_ = 0;
};

}  // namespace rf
