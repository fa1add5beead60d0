#include "render/light_groups.h"

#include <nlohmann/json.hpp>

#include <algorithm>
#include <map>

namespace rf {

namespace {

constexpr const char* kPrefix = "settings.light_groups: ";

// A group's name as messages quote it (at most 40 characters of it).
std::string in_quotes(const std::string& name) {
  return "\"" + (name.size() > 40 ? name.substr(0, 40) + "..." : name) + "\"";
}

}  // namespace

std::string parse_light_groups(const std::string& json, LightGroups* out) {
  *out = LightGroups{};
  const std::string shape =
      "must be a JSON object of group name -> a list of glTF node indices";
  if (json.empty())
    return std::string(kPrefix) +
           "empty, while the task asks for the light_groups row (the server fills it in from "
           "the scene for a job whose aovs name light_groups)";
  // Ordered: the members' order is the row's.
  const nlohmann::ordered_json value =
      nlohmann::ordered_json::parse(json, nullptr, /*allow_exceptions=*/false);
  if (value.is_discarded()) return std::string(kPrefix) + "not JSON: it " + shape;
  if (!value.is_object()) return std::string(kPrefix) + "not a JSON object: it " + shape;
  if (value.empty())
    return std::string(kPrefix) + "no light group (at least the environment's is needed)";
  if (value.size() > kMaxLightGroups)
    return std::string(kPrefix) + std::to_string(value.size()) + " light groups, more than " +
           std::to_string(kMaxLightGroups);
  std::map<uint32_t, uint32_t> group_of;  // node -> the first group that holds it
  for (const auto& [name, nodes] : value.items()) {
    const uint32_t g = out->count();
    if (!nodes.is_array())
      return std::string(kPrefix) + "group " + in_quotes(name) + " is not a list of node indices";
    std::vector<uint32_t> list;
    for (const auto& n : nodes) {
      // JSON's non-negative integers parse as unsigned; negative ones, fractions, strings,
      // booleans and the rest are not indices.
      if (!n.is_number_unsigned() || n.get<uint64_t>() >= uint64_t(kNoNode))
        return std::string(kPrefix) + "group " + in_quotes(name) + " holds " +
               n.dump().substr(0, 40) + ", not a glTF node index (an integer >= 0)";
      const uint32_t node = uint32_t(n.get<uint64_t>());
      const auto [at, fresh] = group_of.emplace(node, g);
      if (!fresh) {
        if (at->second == g) continue;  // listed twice in one group: once
        return std::string(kPrefix) + "node " + std::to_string(node) + " is in two light " +
               "groups, " + in_quotes(out->names[at->second]) + " and " + in_quotes(name);
      }
      list.push_back(node);
    }
    out->names.push_back(name);
    out->nodes.push_back(std::move(list));
  }
  return {};
}

std::string check_light_groups(const Scene& scene, const LightGroups& groups) {
  std::vector<uint32_t> grouped;
  for (const std::vector<uint32_t>& nodes : groups.nodes)
    grouped.insert(grouped.end(), nodes.begin(), nodes.end());
  std::sort(grouped.begin(), grouped.end());
  for (const uint32_t node : scene.emitting_nodes()) {
    if (std::binary_search(grouped.begin(), grouped.end(), node)) continue;
    if (node == kNoNode)
      return std::string(kPrefix) + "the scene has light that comes from no glTF node, which " +
             "no light group can hold";
    const std::string& name = scene.node_name(node);
    return std::string(kPrefix) + "node " + std::to_string(node) +
           (name.empty() ? std::string() : " (" + in_quotes(name) + ")") +
           " emits light but is in no light group";
  }
  return {};
}

LightGroupMap::LightGroupMap(const Scene& scene, const LightGroups& groups)
    : count_(std::max(1u, std::min(groups.count(), kMaxLightGroups))) {
  // Only the nodes that emit are ever looked up: the table ends with the last of them.
  const std::vector<uint32_t>& emitting = scene.emitting_nodes();
  uint32_t size = 0;
  for (const uint32_t node : emitting)
    if (node != kNoNode) size = std::max(size, node + 1);
  by_node_.assign(size, uint8_t(environment()));
  // A node listed by two groups (parse_light_groups refuses that) goes to the first.
  for (uint32_t g = count_; g-- > 0;)
    if (g < groups.nodes.size())
      for (const uint32_t node : groups.nodes[g])
        if (node < size) by_node_[node] = uint8_t(g);
}

uint32_t LightGroupMap::light(const Scene& scene, const LightSampleSource& source) const {
  if (source.environment) return environment();
  if (source.punctual >= 0) return node(scene.lights().punctual()[size_t(source.punctual)].node);
  return surface(scene, source.slot, source.prim);
}

}  // namespace rf
