// The light groups of a task (aovs `light_groups`, #40): the radiance split by the light it
// came from, one RGB block per group (the LightGroups row of the channel table). The server
// finds the groups in the scene's glTF (server/renderfarm/domain/light_groups.py) and sends
// them in settings.light_groups: a JSON object of group name -> the indices of its glTF
// nodes, in the order of the row's blocks, the environment's group last.
//
// Every contribution to a sample's radiance (add_radiance, render/packet_tracer.h) is the
// light of one source and goes wholly to that source's group, so that the groups sum to the
// radiance and each is an unbiased estimate of its own light:
// - the environment, found by a ray at any bounce or sampled as a light: the last group;
// - what a surface a ray hits emits (its emission, or an unlit surface's colour): the group of
//   its glTF node (Scene::node);
// - a light sample of a punctual light: its node's group (PunctualLight::node); of an
//   emissive triangle: the group of the triangle's node.
// A node in no group cannot be attributed: check_light_groups refuses a scene with an emitting
// node (Scene::emitting_nodes) that no group holds.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "render/light_sampling.h"
#include "scene/scene.h"

namespace rf {

// The most groups a task may have, the environment's included (the server's MAX_GROUPS).
constexpr uint32_t kMaxLightGroups = 32;

// settings.light_groups, parsed.
struct LightGroups {
  std::vector<std::string> names;            // in the row's order, the environment's last
  std::vector<std::vector<uint32_t>> nodes;  // per group, the glTF nodes it holds
  uint32_t count() const { return uint32_t(names.size()); }
};

// Parses settings.light_groups into *out: "" if it is a JSON object of between 1 and
// kMaxLightGroups members, each a list of node indices (integers in [0, 2^32 - 1)), no node
// in two groups; otherwise a message beginning "settings.light_groups: " that says what is
// wrong (and *out is unspecified).
std::string parse_light_groups(const std::string& json, LightGroups* out);

// "" if every node whose light can reach the scene's image (Scene::emitting_nodes) is in a
// group; otherwise a message beginning "settings.light_groups: " naming the first that is not,
// with its glTF name if it has one: a task whose groups would not sum to its image is refused.
std::string check_light_groups(const Scene& scene, const LightGroups& groups);

// The group of each source of light of one scene, for one render (render_rect): built once,
// read per contribution while tracing (only with the LightGroups row on).
class LightGroupMap {
 public:
  // groups must have at least one group; nodes of the scene in none of them (never emitting
  // ones, once check_light_groups has passed) go to the last group, the environment's.
  LightGroupMap(const Scene& scene, const LightGroups& groups);
  uint32_t count() const { return count_; }
  uint32_t environment() const { return count_ - 1; }
  // The group of glTF node `node`.
  uint32_t node(uint32_t node) const {
    return node < by_node_.size() ? by_node_[node] : environment();
  }
  // The group of what triangle prim of geometry slot `slot` emits (a Hit's slot and prim).
  uint32_t surface(const Scene& scene, uint32_t slot, uint32_t prim) const {
    return node(scene.node(slot, prim));
  }
  // The group of a light sample's light (sample_light's *source).
  uint32_t light(const Scene& scene, const LightSampleSource& source) const;

 private:
  // By glTF node index, up to the largest emitting node of the scene: its group.
  std::vector<uint8_t> by_node_;
  uint32_t count_ = 1;
};

}  // namespace rf
