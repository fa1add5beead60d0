#include "farm/scene_cache.h"

#include <algorithm>
#include <cstdlib>
#include <filesystem>

#include "util/sha256.h"

namespace fs = std::filesystem;

namespace rf {

std::string default_scene_cache_dir() {
  const char* xdg = std::getenv("XDG_CACHE_HOME");
  if (xdg && *xdg) return (fs::path(xdg) / "renderfarm" / "scenes").string();
  const char* home = std::getenv("HOME");
  return (fs::path(home && *home ? home : ".") / ".cache" / "renderfarm" / "scenes").string();
}

std::vector<std::string> list_cached_scenes(const std::string& dir) {
  std::vector<std::string> out;
  std::error_code ec;
  for (fs::directory_iterator it(dir, ec), end; !ec && it != end; it.increment(ec)) {
    const fs::path& p = it->path();
    const std::string ext = p.extension().string();
    if ((ext == ".glb" || ext == ".gltf" || ext == ".hdr" || ext == ".exr") &&
        is_sha256_hex(p.stem().string()) &&
        it->is_regular_file(ec))
      out.push_back(p.stem().string());
  }
  return out;
}

std::string find_cached_scene(const std::string& dir, const std::string& sha256) {
  for (const char* ext : {".glb", ".gltf", ".hdr", ".exr"}) {
    const fs::path p = fs::path(dir) / (sha256 + ext);
    std::error_code ec;
    if (fs::is_regular_file(p, ec)) return p.string();
  }
  return {};
}

std::shared_ptr<const Scene> SceneCache::get(const std::string& key, const Loader& load) {
  std::promise<std::shared_ptr<const Scene>> promise;
  std::shared_future<std::shared_ptr<const Scene>> future;
  bool owner = false;
  {
    std::lock_guard<std::mutex> lock(mutex_);
    auto it = entries_.find(key);
    if (it != entries_.end()) {
      it->second.last_used = ++clock_;
      future = it->second.scene;
    } else {
      future = promise.get_future().share();
      entries_[key] = Entry{future, ++clock_, false};
      owner = true;
    }
  }
  if (owner) {
    // Load outside the lock: other scenes stay available meanwhile.
    try {
      std::shared_ptr<const Scene> scene = load();
      promise.set_value(scene);
      std::lock_guard<std::mutex> lock(mutex_);
      auto it = entries_.find(key);
      if (it != entries_.end()) {
        it->second.ready = true;
        it->second.bytes = scene ? scene->memory_bytes() : 0;
      }
      evict_locked(key);
    } catch (...) {
      promise.set_exception(std::current_exception());
      std::lock_guard<std::mutex> lock(mutex_);
      entries_.erase(key);  // failures are not cached: the next request retries
    }
  }
  return future.get();
}

size_t SceneCache::memory_bytes_locked() const {
  size_t bytes = 0;
  for (const auto& e : entries_) bytes += e.second.bytes;
  return bytes;
}

void SceneCache::evict_locked(const std::string& keep) {
  // Drop the least recently used loaded scenes; callers still rendering keep theirs alive
  // through their shared_ptr.
  while (entries_.size() > capacity_ ||
         (memory_budget_ > 0 && memory_bytes_locked() > memory_budget_)) {
    uint64_t newest = 0;
    for (const auto& e : entries_) newest = std::max(newest, e.second.last_used);
    auto victim = entries_.end();
    for (auto it = entries_.begin(); it != entries_.end(); ++it)
      if (it->second.ready && it->first != keep && it->second.last_used != newest &&
          (victim == entries_.end() || it->second.last_used < victim->second.last_used))
        victim = it;
    if (victim == entries_.end()) return;
    entries_.erase(victim);
  }
}

size_t SceneCache::memory_bytes() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return memory_bytes_locked();
}

size_t SceneCache::size() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return entries_.size();
}

}  // namespace rf
