#include "farm/frames.h"

#include <gtest/gtest.h>

#include <set>

#include "sampling/samplers.h"

namespace rf {
namespace {

TEST(FrameSeed, Mix64IsSplitMix64WithItsPublishedOutputs) {
  // The first two outputs of the SplitMix64 generator seeded with 0 (the state advances by
  // 0x9E3779B97F4A7C15 per output), as published with Vigna's reference implementation:
  // the frame seed's mixer is the samplers' mix64.
  EXPECT_EQ(mix64(0), 0xE220A8397B1DCDAFull);
  EXPECT_EQ(mix64(0x9E3779B97F4A7C15ull), 0x6E789E6AA1B965F4ull);
}

TEST(FrameSeed, IsTheDocumentedMixOfSeedAndFrame) {
  EXPECT_EQ(frame_seed(77, 5), mix64(77 ^ mix64(5)));
  EXPECT_EQ(frame_seed(0, 0), mix64(mix64(0)));
  // A negative frame is its 64-bit two's complement.
  EXPECT_EQ(frame_seed(3, -1), mix64(3 ^ mix64(~0ull)));
}

TEST(FrameSeed, FramesAndSeedsGetDistinctWellMixedSeeds) {
  std::set<uint64_t> seen;
  for (uint64_t seed : {0ull, 1ull, 77ull})
    for (int32_t frame = 0; frame < 1000; ++frame) seen.insert(frame_seed(seed, frame));
  EXPECT_EQ(seen.size(), 3000u);
  // Neighbouring frames differ in about half their bits (avalanche): 32 on average.
  double bits = 0.0;
  for (int32_t frame = 0; frame < 1000; ++frame)
    bits += __builtin_popcountll(frame_seed(77, frame) ^ frame_seed(77, frame + 1));
  EXPECT_NEAR(bits / 1000.0, 32.0, 1.0);
}

std::string refusal(const std::string& selection, const std::vector<std::string>& names) {
  try {
    resolve_animation_selection(selection, names);
  } catch (const AnimationSelectionError& e) {
    return e.what();
  }
  return "";
}

TEST(AnimationSelection, ResolvesIndicesAndCaseSensitiveNames) {
  const std::vector<std::string> names = {"walk", "run", "", "walk"};
  EXPECT_EQ(resolve_animation_selection("", names), std::vector<int>{});
  EXPECT_EQ(resolve_animation_selection("  ", names), std::vector<int>{});
  EXPECT_EQ(resolve_animation_selection("1", names), std::vector<int>({1}));
  EXPECT_EQ(resolve_animation_selection("run, 2", names), std::vector<int>({1, 2}));
  // Every animation of a name, each index once, in the order given.
  EXPECT_EQ(resolve_animation_selection("walk", names), std::vector<int>({0, 3}));
  EXPECT_EQ(resolve_animation_selection("3,walk,0", names), std::vector<int>({3, 0}));
  EXPECT_EQ(resolve_animation_selection("002", names), std::vector<int>({2}));
}

TEST(AnimationSelection, RefusesWhatTheSceneLacksNamingTheSetting) {
  const std::vector<std::string> names = {"walk", "run"};
  const std::string upper = refusal("Walk", names);
  EXPECT_NE(upper.find("settings.animation"), std::string::npos) << upper;
  EXPECT_NE(upper.find("\"Walk\""), std::string::npos) << upper;
  EXPECT_NE(upper.find("0 \"walk\", 1 \"run\""), std::string::npos) << upper;
  const std::string index = refusal("0,2", names);
  EXPECT_NE(index.find("settings.animation: no animation 2"), std::string::npos) << index;
  EXPECT_NE(refusal("99999999999999999999", names).find("settings.animation"), std::string::npos);
  EXPECT_NE(refusal("walk,,run", names).find("empty item"), std::string::npos);
  EXPECT_NE(refusal("0", {}).find("the scene has no animations"), std::string::npos);
}

}  // namespace
}  // namespace rf
