// The path-guiding fields (render/guiding.h) a farm worker has trained: one per frame of a
// job (the caller's key), trained once by the first task of that frame that needs it while the
// others wait for it, and kept for the worker's next tasks of the frame; the last kEntries
// fields stay. Every worker trains the same field from the same scene, settings and seed, so
// which worker renders a tile never changes its pixels.
#pragma once

#include <cstddef>
#include <deque>
#include <functional>
#include <future>
#include <memory>
#include <mutex>
#include <string>
#include <utility>

#include "render/guiding.h"

namespace rf {

class GuideCache {
 public:
  // A job renders its frames in order, a few at a time per worker: a handful of fields covers
  // them (each a few MB at most: kMaxPaths records' worth of tree nodes).
  static constexpr size_t kEntries = 4;
  using Train = std::function<std::shared_ptr<const GuideField>()>;

  // The field of `key`: the one trained already, the one being trained (waited for), or
  // train()'s, which becomes the key's. If train() throws, its callers see the exception and
  // the key is forgotten, so that a later task trains again.
  std::shared_ptr<const GuideField> get(const std::string& key, const Train& train);
  size_t size() const;

 private:
  using Field = std::shared_future<std::shared_ptr<const GuideField>>;
  mutable std::mutex mutex_;
  std::deque<std::pair<std::string, Field>> entries_;  // oldest first
};

}  // namespace rf
