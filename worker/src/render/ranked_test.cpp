// The per-pixel ranking of the ranked rows (channels::RankedCounts): labels counted in sample
// order, the 6 largest counts emitted as (label, count) pairs. Expected pairs are counted by
// hand from the label sequences.
#include "render/ranked.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <array>
#include <vector>

namespace rf::channels {
namespace {

using Pairs = std::array<uint32_t, 2 * kRanks>;
constexpr uint32_t kDefault = 0xFFFFFFFFu;  // the default material's label

Pairs ranked(const std::vector<uint32_t>& labels) {
  RankedCounts counts;
  for (uint32_t l : labels) counts.add(l);
  Pairs out;
  out.fill(0xDEADBEEFu);  // every component must be written
  counts.emit(out.data());
  return out;
}

TEST(RankedCounts, NoLabelsGiveSixEmptyPairs) {
  EXPECT_EQ(ranked({}), Pairs{});
  // 0 is no label (a miss): never counted.
  EXPECT_EQ(ranked({0, 0, 0}), Pairs{});
}

TEST(RankedCounts, CountsLabelsByCountDescendingAndPadsWithZeros) {
  // 5 three times, 3 twice, 7 once; the misses (0) not counted.
  EXPECT_EQ(ranked({3, 0, 5, 3, 0, 5, 5, 7}), (Pairs{5, 3, 3, 2, 7, 1, 0, 0, 0, 0, 0, 0}));
  // One label every sample.
  EXPECT_EQ(ranked({9, 9, 9, 9}), (Pairs{9, 4, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0}));
}

TEST(RankedCounts, EqualCountsGoSmallerLabelFirst) {
  // 9 and 2 twice each (9 seen first), 4 once.
  EXPECT_EQ(ranked({9, 2, 9, 2, 4}), (Pairs{2, 2, 9, 2, 4, 1, 0, 0, 0, 0, 0, 0}));
  // Six labels once each, in descending order: emitted ascending.
  EXPECT_EQ(ranked({60, 50, 40, 30, 20, 10}), (Pairs{10, 1, 20, 1, 30, 1, 40, 1, 50, 1, 60, 1}));
}

TEST(RankedCounts, TheDefaultMaterialLabelIsTheLargestLabel) {
  // A tie: 0xFFFFFFFF (unsigned) after 1.
  EXPECT_EQ(ranked({kDefault, 1, kDefault, 1}), (Pairs{1, 2, kDefault, 2, 0, 0, 0, 0, 0, 0, 0, 0}));
  // More samples: first whatever its label.
  EXPECT_EQ(ranked({1, kDefault, kDefault, 1, kDefault}),
            (Pairs{kDefault, 3, 1, 2, 0, 0, 0, 0, 0, 0, 0, 0}));
  // Among equal counts of several labels: last.
  EXPECT_EQ(ranked({kDefault, 7, 3, 0, kDefault, 7, 3}),
            (Pairs{3, 2, 7, 2, kDefault, 2, 0, 0, 0, 0, 0, 0}));
}

TEST(RankedCounts, MoreThanSixLabelsKeepTheSixLargest) {
  // 9 labels, interleaved: 40 x7, 20 x5, 70 x4, 60 x3, 30, 50 and 90 x2, 10 and 80 x1. The
  // ties at count 2 keep 30 and 50, not 90.
  const std::vector<uint32_t> labels = {10, 20, 30, 40, 50, 60, 70, 80, 90, 20, 40, 60, 70,
                                        90, 40, 20, 70, 40, 30, 60, 40, 50, 20, 70, 40, 0,
                                        20, 40};
  EXPECT_EQ(ranked(labels), (Pairs{40, 7, 20, 5, 70, 4, 60, 3, 30, 2, 50, 2}));
  // A label counted after the others filled six ranks still takes its place.
  EXPECT_EQ(ranked({1, 2, 3, 4, 5, 6, 8, 8}), (Pairs{8, 2, 1, 1, 2, 1, 3, 1, 4, 1, 5, 1}));
}

// The pairs depend only on how many samples had each label, not on their order, while a pixel
// sees at most RankedCounts::kSlots labels: exact then.
TEST(RankedCounts, UpToSixteenLabelsAreCountedExactlyInAnyOrder) {
  std::vector<uint32_t> labels;
  for (uint32_t l = 1; l <= 16; ++l)
    for (uint32_t k = 0; k < l; ++k) labels.push_back(100 + l);  // label 100 + l, l times
  const Pairs want{116, 16, 115, 15, 114, 14, 113, 13, 112, 12, 111, 11};
  EXPECT_EQ(ranked(labels), want);
  std::reverse(labels.begin(), labels.end());
  EXPECT_EQ(ranked(labels), want);
  for (size_t i = 0; i < labels.size(); ++i)  // a fixed interleaving
    std::swap(labels[i], labels[(i * 37 + 11) % labels.size()]);
  EXPECT_EQ(ranked(labels), want);
}

// Beyond kSlots distinct labels, a label first seen once every slot is taken is not counted
// (the documented limit): here the 17th label, however many samples have it.
TEST(RankedCounts, ALabelAfterSixteenOthersIsDropped) {
  static_assert(RankedCounts::kSlots == 16, "the test's sequence assumes 16 slots");
  std::vector<uint32_t> labels;
  for (uint32_t l = 1; l <= 16; ++l) labels.push_back(l);
  for (int k = 0; k < 10; ++k) labels.push_back(99);
  labels.push_back(16);  // the labels already held are still counted
  EXPECT_EQ(ranked(labels), (Pairs{16, 2, 1, 1, 2, 1, 3, 1, 4, 1, 5, 1}));
}

TEST(RankedCounts, ClearForgetsTheLabels) {
  RankedCounts counts;
  counts.add(4);
  counts.add(4);
  counts.clear();
  counts.add(2);
  Pairs out;
  counts.emit(out.data());
  EXPECT_EQ(out, (Pairs{2, 1, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0}));
}

}  // namespace
}  // namespace rf::channels
