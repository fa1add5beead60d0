#include "farm/scene_cache.h"

#include <gtest/gtest.h>

#include <atomic>
#include <filesystem>
#include <fstream>
#include <stdexcept>
#include <thread>
#include <vector>

#include "render/guiding.h"
#include "testing/test_scenes.h"

namespace rf {
namespace {

// A scene of 2 * rings * segments triangles (a sphere over a quad), to give caches scenes
// of different sizes.
std::shared_ptr<const Scene> sphere_scene(int rings) {
  SceneDescription desc;
  desc.source = "sphere " + std::to_string(rings);
  desc.materials.push_back(Material{});
  testing::add_sphere(&desc, {0.f, 0.f, 0.f}, 1.f, 0, rings, 2 * rings);
  return std::make_shared<const Scene>(std::move(desc));
}

TEST(SceneCache, LoadsOnceAndEvictsTheLeastRecentlyUsedBeyondItsCapacity) {
  SceneCache cache(2);
  int loads = 0;
  auto loader = [&] {
    ++loads;
    return sphere_scene(4);
  };
  const auto a = cache.get("a", loader);
  EXPECT_EQ(cache.get("a", loader), a);
  EXPECT_EQ(loads, 1);
  cache.get("b", loader);
  cache.get("a", loader);  // a is now more recent than b
  cache.get("c", loader);  // evicts b
  EXPECT_EQ(cache.size(), 2u);
  EXPECT_EQ(loads, 3);
  cache.get("a", loader);
  EXPECT_EQ(loads, 3);
  cache.get("b", loader);
  EXPECT_EQ(loads, 4);
}

TEST(SceneCache, KeepsLoadedScenesWithinItsMemoryBudget) {
  const size_t small = sphere_scene(8)->memory_bytes();
  const size_t large = sphere_scene(64)->memory_bytes();
  ASSERT_GT(large, 4 * small);
  // Room for the large scene and one small one, not two small ones besides.
  SceneCache cache(10, large + small + small / 2);
  const auto s1 = cache.get("small1", [] { return sphere_scene(8); });
  const auto s2 = cache.get("small2", [] { return sphere_scene(8); });
  EXPECT_EQ(cache.memory_bytes(), s1->memory_bytes() + s2->memory_bytes());
  const auto l = cache.get("large", [] { return sphere_scene(64); });
  // small1 was the least recently used: it goes, small2 stays.
  EXPECT_EQ(cache.size(), 2u);
  EXPECT_EQ(cache.memory_bytes(), l->memory_bytes() + s2->memory_bytes());
  int reloads = 0;
  cache.get("small2", [&] {
    ++reloads;
    return sphere_scene(8);
  });
  EXPECT_EQ(reloads, 0);

  // A scene larger than the whole budget is still kept (alone): every task would reload it.
  SceneCache tight(10, small);
  tight.get("small", [] { return sphere_scene(8); });
  const auto big = tight.get("large", [] { return sphere_scene(64); });
  EXPECT_EQ(tight.size(), 1u);
  EXPECT_EQ(tight.memory_bytes(), big->memory_bytes());
  EXPECT_EQ(tight.get("large", [] { return sphere_scene(8); }), big);
}

TEST(SceneCache, ConcurrentRequestsShareOneLoadAndFailuresAreRetried) {
  SceneCache cache(4);
  std::atomic<int> loads{0};
  std::vector<std::thread> threads;
  std::vector<std::shared_ptr<const Scene>> got(4);
  for (int i = 0; i < 4; ++i)
    threads.emplace_back([&, i] {
      got[size_t(i)] = cache.get("s", [&] {
        ++loads;
        std::this_thread::sleep_for(std::chrono::milliseconds(50));
        return sphere_scene(4);
      });
    });
  for (auto& t : threads) t.join();
  EXPECT_EQ(loads.load(), 1);
  for (const auto& s : got) EXPECT_EQ(s, got[0]);
  EXPECT_THROW(cache.get("bad", []() -> std::shared_ptr<const Scene> {
    throw std::runtime_error("broken file");
  }),
               std::runtime_error);
  EXPECT_EQ(cache.size(), 1u);  // the failure is not cached
  EXPECT_NE(cache.get("bad", [] { return sphere_scene(4); }), nullptr);
}

TEST(SceneCache, PreparesAnAnimatedSceneOnceAndKeepsAFewPosesOfIt) {
  const std::string path = testing::test_path("scene_cache_animated.gltf");
  {
    std::ofstream out(path);
    out << testing::animated_gltf_json();
  }
  SceneCache cache(8, 0, 2);
  int prepares = 0, poses = 0;
  auto prepare = [&] {
    ++prepares;
    return std::make_shared<const AnimatedScene>(parse_gltf(path, nullptr), LoadOptions{});
  };
  auto pose_at = [&](double t) {
    return [&, t](const AnimatedScene& animated) {
      ++poses;
      return animated.pose(t);
    };
  };
  const auto a = cache.get_posed("s", "", "0", prepare, pose_at(0.0));
  const auto b = cache.get_posed("s", "", "1", prepare, pose_at(1.0));
  EXPECT_EQ(cache.get_posed("s", "", "0", prepare, pose_at(0.0)), a);  // a is now newer than b
  EXPECT_EQ(prepares, 1);
  EXPECT_EQ(poses, 2);
  // The poses differ: the light moved by 0.75 along x between t = 0 and t = 1.
  EXPECT_NEAR(b->bounds_max().x - a->bounds_max().x, 0.75f, 1e-5f);
  // A third pose of the scene evicts its least recently used one (b), not the animated scene.
  cache.get_posed("s", "", "2", prepare, pose_at(2.0));
  EXPECT_EQ(cache.size(), 3u);  // the animated scene and two poses
  cache.get_posed("s", "", "0", prepare, pose_at(0.0));
  EXPECT_EQ(poses, 3);
  cache.get_posed("s", "", "1", prepare, pose_at(1.0));
  EXPECT_EQ(poses, 4);
  EXPECT_EQ(prepares, 1);
  // The animated scene and the poses count in the memory the cache holds.
  EXPECT_GT(cache.memory_bytes(), 2 * a->memory_bytes());
  // Another animation selection is an animated scene of its own.
  cache.get_posed("s", "1", "1 1", prepare, pose_at(1.0));
  EXPECT_EQ(prepares, 2);
  // A still of the same scene is an entry of its own.
  const size_t before = cache.size();
  cache.get("s", [] { return sphere_scene(4); });
  EXPECT_EQ(cache.size(), before + 1);
  std::filesystem::remove(path);
}

TEST(SceneCache, AFailedPoseIsNotCachedAndKeepsTheAnimatedScene) {
  const std::string path = testing::test_path("scene_cache_animated_fail.gltf");
  {
    std::ofstream out(path);
    out << testing::animated_gltf_json();
  }
  SceneCache cache(8);
  int prepares = 0;
  auto prepare = [&] {
    ++prepares;
    return std::make_shared<const AnimatedScene>(parse_gltf(path, nullptr), LoadOptions{});
  };
  auto failing = [](const AnimatedScene&) -> std::shared_ptr<const Scene> {
    throw std::runtime_error("no such animation");
  };
  EXPECT_THROW(cache.get_posed("s", "", "bad", prepare, failing), std::runtime_error);
  EXPECT_THROW(cache.get_posed("s", "", "bad", prepare, failing), std::runtime_error);
  EXPECT_EQ(prepares, 1);
  EXPECT_EQ(cache.size(), 1u);  // the animated scene only
  std::filesystem::remove(path);
}

// Derived values (path guiding's fields, farm_client.cpp: a SceneCache of their own, one per
// frame of a job).

// A field of its own for each call (an empty one: no records).
std::shared_ptr<const GuideField> empty_field() {
  std::vector<GuideRecord> none;
  return std::make_shared<const GuideField>(Vec3(0.f, 0.f, 0.f), Vec3(1.f, 1.f, 1.f), &none);
}

// Eight tasks of one frame asking at once: one trains, the others get its field.
TEST(SceneCache, ADerivedValueIsMadeOnceWhileItsOtherCallersWait) {
  SceneCache cache(4);
  std::atomic<int> trained{0};
  std::atomic<bool> release{false};
  std::vector<std::shared_ptr<const GuideField>> got(8);
  std::vector<std::thread> tasks;
  for (int i = 0; i < 8; ++i)
    tasks.emplace_back([&, i] {
      got[size_t(i)] = cache.get_derived<GuideField>("job/frame1", [&] {
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

TEST(SceneCache, KeepsTheLastDerivedValuesAndMakesAnEvictedOneAgain) {
  constexpr size_t kEntries = 4;
  SceneCache cache(kEntries);
  int trained = 0;
  const std::function<std::shared_ptr<const GuideField>()> train = [&] {
    ++trained;
    return empty_field();
  };
  const auto first = cache.get_derived<GuideField>("f0", train);
  for (size_t k = 1; k <= kEntries; ++k)
    cache.get_derived<GuideField>("f" + std::to_string(k), train);
  EXPECT_EQ(cache.size(), kEntries);
  EXPECT_EQ(trained, int(kEntries) + 1);
  // The newest are kept...
  cache.get_derived<GuideField>("f" + std::to_string(kEntries), train);
  EXPECT_EQ(trained, int(kEntries) + 1);
  // ... the first was evicted: trained again, a new field.
  EXPECT_NE(cache.get_derived<GuideField>("f0", train), first);
  EXPECT_EQ(trained, int(kEntries) + 2);
}

TEST(SceneCache, AFailedDerivedValueIsMadeAgainByTheNextCaller) {
  SceneCache cache(4);
  EXPECT_THROW(cache.get_derived<GuideField>("f", []() -> std::shared_ptr<const GuideField> {
    throw std::runtime_error("out of memory");
  }),
               std::runtime_error);
  EXPECT_EQ(cache.size(), 0u);
  EXPECT_NE(cache.get_derived<GuideField>("f", empty_field), nullptr);
}

}  // namespace
}  // namespace rf
