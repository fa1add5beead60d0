#include "farm/guide_cache.h"

#include <algorithm>
#include <exception>

namespace rf {

std::shared_ptr<const GuideField> GuideCache::get(const std::string& key, const Train& train) {
  std::promise<std::shared_ptr<const GuideField>> promise;
  Field field;
  bool trains = false;
  {
    std::lock_guard<std::mutex> lock(mutex_);
    for (const auto& entry : entries_)
      if (entry.first == key) field = entry.second;
    if (!field.valid()) {
      field = promise.get_future().share();
      entries_.emplace_back(key, field);
      while (entries_.size() > kEntries) entries_.pop_front();
      trains = true;
    }
  }
  if (trains) {
    try {
      promise.set_value(train());
    } catch (...) {
      promise.set_exception(std::current_exception());
      std::lock_guard<std::mutex> lock(mutex_);
      entries_.erase(std::remove_if(entries_.begin(), entries_.end(),
                                    [&](const auto& e) { return e.first == key; }),
                     entries_.end());
    }
  }
  return field.get();  // trained here, before, or by another task (waits for it)
}

size_t GuideCache::size() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return entries_.size();
}

}  // namespace rf
