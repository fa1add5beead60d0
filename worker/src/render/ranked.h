// Ranked ID coverage (the channel table's ranked rows, Cryptomatte): one pixel's labels counted
// over a task's samples, and the largest counts emitted as (label, count) pairs
// (server/renderfarm/domain/cryptomatte.py reads them; docs/architecture.md, "Ranked rows").
#pragma once

#include <algorithm>
#include <cstdint>

namespace rf::channels {

// (label, count) pairs a ranked row carries per pixel: its components / 2 (the server's
// cryptomatte.RANKS).
constexpr uint32_t kRanks = 6;

// The labels of one pixel's samples, counted in sample order. Label 0 is no label (a sample
// whose camera ray hit nothing, or hit geometry the row has no label for) and is not counted.
// The counts are exact for the first kSlots distinct labels of the task's samples: once every
// slot holds a label, a sample of a label not yet seen is dropped (not counted). The emitted
// ranking is exact whenever a pixel sees at most kSlots distinct labels in a task (always when
// it sees at most kRanks); beyond that a label first seen after the slots filled is missing,
// even if it would have ranked among the kRanks largest. The result depends only on the labels
// in the order they were added, so a pixel filled in sample order by one thread always gives
// the same pairs.
struct RankedCounts {
  static constexpr uint32_t kSlots = 16;
  uint32_t label[kSlots];
  uint32_t count[kSlots];
  uint32_t used = 0;

  void clear() { used = 0; }

  void add(uint32_t l) {
    if (l == 0) return;
    for (uint32_t s = 0; s < used; ++s)
      if (label[s] == l) {
        ++count[s];
        return;
      }
    if (used == kSlots) return;  // full: a new label is dropped (see above)
    label[used] = l;
    count[used] = 1;
    ++used;
  }

  // The kRanks labels of the largest counts as out[2 k] = label, out[2 k + 1] = count: by count
  // descending, equal counts by the smaller label first (as unsigned: 0xFFFFFFFF is the
  // largest); (0, 0) in the slots no label fills.
  void emit(uint32_t* out) const {
    uint32_t order[kSlots];
    for (uint32_t s = 0; s < used; ++s) order[s] = s;
    const uint32_t ranked = std::min(used, kRanks);
    // Labels are distinct, so this is a strict total order: the result is unique.
    std::partial_sort(order, order + ranked, order + used, [this](uint32_t a, uint32_t b) {
      return count[a] != count[b] ? count[a] > count[b] : label[a] < label[b];
    });
    for (uint32_t k = 0; k < kRanks; ++k) {
      out[2 * k] = k < ranked ? label[order[k]] : 0u;
      out[2 * k + 1] = k < ranked ? count[order[k]] : 0u;
    }
  }
};

}  // namespace rf::channels
