#include "farm/guide_cache.h"

#include <gtest/gtest.h>

#include <atomic>
#include <stdexcept>
#include <thread>
#include <vector>

namespace rf {
namespace {

// A field of its own for each call (an empty one: no records).
std::shared_ptr<const GuideField> empty_field() {
  std::vector<GuideRecord> none;
  return std::make_shared<const GuideField>(Vec3(0.f, 0.f, 0.f), Vec3(1.f, 1.f, 1.f), &none);
}

// Eight tasks of one frame asking at once: one trains, the others get its field.
TEST(GuideCache, AFrameIsTrainedOnceWhileItsOtherTasksWait) {
  GuideCache cache;
  std::atomic<int> trained{0};
  std::atomic<bool> release{false};
  std::vector<std::shared_ptr<const GuideField>> got(8);
  std::vector<std::thread> tasks;
  for (int i = 0; i < 8; ++i)
    tasks.emplace_back([&, i] {
      got[size_t(i)] = cache.get("job/frame1", [&] {
        ++trained;
        while (!release) std::this_thread::yield();  // the others arrive meanwhile
        return empty_field();
      });
    });
  // Every task is either training or waiting: none can finish before the release.
  for (const auto& g : got) EXPECT_EQ(g, nullptr);
  release = true;
  for (std::thread& t : tasks) t.join();
  EXPECT_EQ(trained.load(), 1);
  for (const auto& g : got) EXPECT_EQ(g, got[0]);
  EXPECT_NE(got[0], nullptr);
}

TEST(GuideCache, KeepsTheLastFramesAndTrainsAnEvictedOneAgain) {
  GuideCache cache;
  int trained = 0;
  auto train = [&] {
    ++trained;
    return empty_field();
  };
  const auto first = cache.get("f0", train);
  for (size_t k = 1; k <= GuideCache::kEntries; ++k) cache.get("f" + std::to_string(k), train);
  EXPECT_EQ(cache.size(), GuideCache::kEntries);
  EXPECT_EQ(trained, int(GuideCache::kEntries) + 1);
  // The newest are kept...
  cache.get("f" + std::to_string(GuideCache::kEntries), train);
  EXPECT_EQ(trained, int(GuideCache::kEntries) + 1);
  // ... the first was evicted: trained again, a new field.
  EXPECT_NE(cache.get("f0", train), first);
  EXPECT_EQ(trained, int(GuideCache::kEntries) + 2);
}

TEST(GuideCache, AFailedTrainingIsRetriedByTheNextTask) {
  GuideCache cache;
  EXPECT_THROW(cache.get("f", []() -> std::shared_ptr<const GuideField> {
    throw std::runtime_error("out of memory");
  }),
               std::runtime_error);
  EXPECT_EQ(cache.size(), 0u);
  EXPECT_NE(cache.get("f", empty_field), nullptr);
}

}  // namespace
}  // namespace rf
