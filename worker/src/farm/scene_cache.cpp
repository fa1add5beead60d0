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
  return std::static_pointer_cast<const Scene>(get_value(key, "", [&] {
    std::shared_ptr<const Scene> scene = load();
    return Loaded{scene, scene ? scene->memory_bytes() : 0};
  }));
}

std::shared_ptr<const Scene> SceneCache::get_posed(const std::string& sha256,
                                                   const std::string& selection,
                                                   const std::string& pose_key,
                                                   const AnimatedLoader& prepare,
                                                   const Poser& pose) {
  // Keys no still (a sha256) can take: an animated scene, and a pose of one.
  const std::string animated_key = sha256 + " animated " + selection;
  auto animated = [&] {
    return std::static_pointer_cast<const AnimatedScene>(get_value(animated_key, "", [&] {
      std::shared_ptr<const AnimatedScene> made = prepare();
      return Loaded{made, made ? made->memory_bytes() : 0};
    }));
  };
  const std::string key = sha256 + " pose " + pose_key;
  bool built = false;
  Value scene = get_value(key, sha256, [&] {
    built = true;
    std::shared_ptr<const AnimatedScene> source = animated();
    std::shared_ptr<const Scene> posed = pose(*source);
    return Loaded{posed, posed ? posed->memory_bytes() : 0};
  });
  // A pose found in memory still counts as a use of its animated scene, which the next frame
  // needs.
  if (!built) {
    std::lock_guard<std::mutex> lock(mutex_);
    auto it = entries_.find(animated_key);
    if (it != entries_.end()) it->second.last_used = ++clock_;
  }
  return std::static_pointer_cast<const Scene>(scene);
}

SceneCache::Value SceneCache::get_value(const std::string& key, const std::string& posed_of,
                                        const std::function<Loaded()>& load) {
  std::promise<Value> promise;
  std::shared_future<Value> future;
  bool owner = false;
  {
    std::lock_guard<std::mutex> lock(mutex_);
    auto it = entries_.find(key);
    if (it != entries_.end()) {
      it->second.last_used = ++clock_;
      future = it->second.value;
    } else {
      future = promise.get_future().share();
      Entry entry;
      entry.value = future;
      entry.last_used = ++clock_;
      entry.posed_of = posed_of;
      entries_[key] = std::move(entry);
      owner = true;
    }
  }
  if (owner) {
    // Load outside the lock: other scenes stay available meanwhile.
    try {
      Loaded loaded = load();
      promise.set_value(loaded.value);
      std::lock_guard<std::mutex> lock(mutex_);
      auto it = entries_.find(key);
      if (it != entries_.end()) {
        it->second.ready = true;
        it->second.bytes = loaded.bytes;
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
  // Drop the least recently used loaded entries; callers still rendering keep theirs alive
  // through their shared_ptr.
  uint64_t newest = 0;
  for (const auto& e : entries_) newest = std::max(newest, e.second.last_used);
  auto evictable = [&](const std::map<std::string, Entry>::const_iterator& it) {
    return it->second.ready && it->first != keep && it->second.last_used != newest;
  };
  // A scene's posed scenes beyond posed_per_scene: its least recently used ones go first.
  const auto kept = entries_.find(keep);
  if (kept != entries_.end() && !kept->second.posed_of.empty()) {
    const std::string& of = kept->second.posed_of;
    for (;;) {
      size_t posed = 0;
      auto victim = entries_.end();
      for (auto it = entries_.begin(); it != entries_.end(); ++it) {
        if (it->second.posed_of != of) continue;
        ++posed;
        if (evictable(it) &&
            (victim == entries_.end() || it->second.last_used < victim->second.last_used))
          victim = it;
      }
      if (posed <= posed_per_scene_ || victim == entries_.end()) break;
      entries_.erase(victim);
    }
  }
  while (entries_.size() > capacity_ ||
         (memory_budget_ > 0 && memory_bytes_locked() > memory_budget_)) {
    auto victim = entries_.end();
    for (auto it = entries_.begin(); it != entries_.end(); ++it)
      if (evictable(it) &&
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
