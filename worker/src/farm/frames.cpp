#include "farm/frames.h"

#include <algorithm>

#include "sampling/samplers.h"

namespace rf {

uint64_t frame_seed(uint64_t seed, int32_t frame) {
  return mix64(seed ^ mix64(uint64_t(int64_t(frame))));
}

namespace {

std::string trimmed(const std::string& s) {
  const size_t first = s.find_first_not_of(" \t");
  if (first == std::string::npos) return {};
  return s.substr(first, s.find_last_not_of(" \t") - first + 1);
}

// What the scene offers, for messages: 0 "walk", 1 (unnamed), ...
std::string offered(const std::vector<std::string>& names) {
  if (names.empty()) return "the scene has no animations";
  std::string list;
  for (size_t i = 0; i < names.size(); ++i) {
    if (i) list += ", ";
    list += std::to_string(i) + (names[i].empty() ? " (unnamed)" : " \"" + names[i] + "\"");
  }
  return "the scene has " + std::to_string(names.size()) + ": " + list;
}

}  // namespace

std::vector<int> resolve_animation_selection(const std::string& selection,
                                             const std::vector<std::string>& names) {
  std::vector<int> chosen;
  if (trimmed(selection).empty()) return chosen;
  auto add = [&](int index) {
    if (std::find(chosen.begin(), chosen.end(), index) == chosen.end()) chosen.push_back(index);
  };
  size_t start = 0;
  for (;;) {
    const size_t comma = selection.find(',', start);
    const std::string item =
        trimmed(selection.substr(start, comma == std::string::npos ? std::string::npos
                                                                   : comma - start));
    if (item.empty())
      throw AnimationSelectionError("settings.animation: '" + selection +
                                    "' has an empty item (expected a comma list of animation "
                                    "indices or names)");
    if (item.find_first_not_of("0123456789") == std::string::npos) {
      const size_t digits = item.find_first_not_of('0');
      const bool small = digits == std::string::npos || item.size() - digits <= 9;
      const long index = small ? std::stol(item) : -1;
      if (index < 0 || size_t(index) >= names.size())
        throw AnimationSelectionError("settings.animation: no animation " + item + " (" +
                                      offered(names) + ")");
      add(int(index));
    } else {
      bool found = false;
      for (size_t i = 0; i < names.size(); ++i)
        if (names[i] == item) {
          add(int(i));
          found = true;
        }
      if (!found)
        throw AnimationSelectionError("settings.animation: no animation named \"" + item +
                                      "\" (" + offered(names) +
                                      "; names are case-sensitive)");
    }
    if (comma == std::string::npos) break;
    start = comma + 1;
  }
  return chosen;
}

}  // namespace rf
