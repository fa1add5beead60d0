// Animated farm tasks (Task.animated, proto/renderfarm/v1/workers.proto): which glTF animations
// settings.animation selects, and the seed of a frame (docs/architecture.md, "Determinism").
#pragma once

#include <cstdint>
#include <stdexcept>
#include <string>
#include <vector>

namespace rf {

// The seed every random number of frame `frame` of an animated job uses in place of the job's
// seed: mix64(seed ^ mix64(uint64_t(int64_t(frame)))), with mix64 SplitMix64's output function
// (sampling/samplers.h). A pure function of (seed,
// frame), so frame 5 is the same image whoever renders it and whatever the job's frame list;
// the two rounds of mixing make the seeds of neighbouring frames unrelated, so frames get
// independent noise. Stills keep the job's seed.
uint64_t frame_seed(uint64_t seed, int32_t frame);

// A settings.animation that names no animation of the scene.
class AnimationSelectionError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

// The glTF animation indices settings.animation selects, given the scene's animation names by
// index: a comma list of items, each a decimal index (digits only) or an animation's name
// (case-sensitive; every animation of that name), blanks around an item ignored; the indices
// in the order given, each once. "" (or blanks) selects every animation: the empty list
// (LoadOptions::animations). Throws AnimationSelectionError, naming settings.animation, for an
// empty item, an index the scene lacks or a name it lacks.
std::vector<int> resolve_animation_selection(const std::string& selection,
                                             const std::vector<std::string>& names);

}  // namespace rf
