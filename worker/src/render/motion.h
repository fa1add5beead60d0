// The Motion row (channel_table.h): the screen-space motion of each pixel's first sample's
// first hit, as Blender's Vector pass has it. The surface point the camera ray hit (its
// geometry slot, triangle and barycentrics, SampleResult) is found again in the scene posed
// at the previous frame's time t - 1 / fps and at the next frame's t + 1 / fps. The poses of
// one AnimatedScene share their static world and their mesh slots, but not always their
// instances: a node hidden by KHR_node_visibility in a pose has no instance there, so the
// later instances' slots shift down in that pose. A slot is therefore mapped to the
// other pose's by the instance's identity (MotionPoses): its glTF node and mesh slot and its
// occurrence k among the pose's instances with that node and mesh (EXT_mesh_gpu_instancing
// gives one node several instances, in the same order in every pose). An instance with no
// such twin in the other pose (its node hidden there) has motion 0: the surface is not in
// that frame. The world slot stays 0 (a static world triangle stays put), an instance's
// triangle moves with that pose's transform, a deformed mesh's vertices are that pose's.
// Points and lines (the pose's thin mesh, one slot for all of them) leave out those of hidden
// nodes, which renumbers the triangles after them; a thin triangle is mapped by its node
// (TriangleMesh::node) and its occurrence among that node's thin triangles (each element
// gives two, in the element's order, in every pose where the node is visible), and has
// motion 0 where the other pose has not the same number of triangles of that node (hidden).
// (motion_row_test: MotionRowVisibility.)
// A deformed mesh has all its triangles in every pose, in the same order:
// the Scene keeps a pose's triangles of zero area (a bone scaled to 0, a morph target that
// collapses a part) with a zero face normal instead of dropping them (clean_mesh's drop
// false), and the transparent ones move after the opaque ones by alphaMode, which does not
// animate. A triangle collapsed in the pose before or after is found there, its point where
// its vertices are (their collapse point), and the triangles after it keep their indices
// (motion_row_test: MotionRowDeformed). Each of the three world positions is projected by the
// camera as posed at its own time (Camera::project: the lens centre, depth of field aside).
//
// The poses before and after are built (or taken from the worker's pose cache) only for a
// task that asks for the row, the first-sample batch of a tile of an animated job; every
// other render passes no MotionPoses and pays nothing. The slot maps are built once per
// MotionPoses (a pass over the instances and the thin triangles of the three poses).
#pragma once

#include <algorithm>
#include <array>
#include <cstdint>
#include <map>
#include <unordered_map>
#include <vector>

#include "render/integrators.h"
#include "scene/animated_scene.h"
#include "scene/scene.h"

namespace rf {

struct MotionPoses {
  // current: the scene rendered (the frame at time t, maybe motion-blurred); previous and
  // next: the same AnimatedScene posed (plain, no shutter) at t - 1 / fps and t + 1 / fps.
  // frame_time: where the frame's time t falls in current's shutter ([0, 1], RTCRay time;
  // 0 for a closed shutter), at which the first hit's point and the camera are taken "now".
  MotionPoses(const Scene& now, float now_time, const Scene& before, const Scene& after,
              uint32_t width, uint32_t height)
      : current(&now), previous(&before), next(&after), frame_time(now_time),
        raster_previous(before.camera().raster(width, height)),
        raster_current(now.camera_at(now_time).raster(width, height)),
        raster_next(after.camera().raster(width, height)) {
    to_previous = map_to(before);
    to_next = map_to(after);
  }
  const Scene* current;
  const Scene* previous;
  const Scene* next;
  float frame_time;
  Camera::Raster raster_previous, raster_current, raster_next;

  static constexpr uint32_t kAbsent = ~0u;
  // current's slots and thin triangles in another pose: slot[s] is current's slot s there
  // (kAbsent: the instance is not in that pose), thin_prim[p] current's thin triangle p there
  // (kAbsent: its node's thin triangles are not all there).
  struct SlotMap {
    std::vector<uint32_t> slot;
    uint32_t thin_slot = kAbsent;  // current's thin mesh slot
    std::vector<uint32_t> thin_prim;
  };
  SlotMap to_previous, to_next;

  // Slot and triangle (slot, prim) of current in the pose `map` leads to; false where the
  // surface is not there.
  static bool find(const SlotMap& map, uint32_t slot, uint32_t prim, uint32_t* other_slot,
                   uint32_t* other_prim) {
    if (slot >= map.slot.size() || map.slot[slot] == kAbsent) return false;
    *other_slot = map.slot[slot];
    *other_prim = prim;
    if (slot != map.thin_slot) return true;
    if (prim >= map.thin_prim.size() || map.thin_prim[prim] == kAbsent) return false;
    *other_prim = map.thin_prim[prim];
    return true;
  }

 private:
  // An instance's identity across poses: node, mesh slot and occurrence among the pose's
  // instances with that node and mesh.
  using InstanceKey = std::array<uint32_t, 3>;
  static std::vector<InstanceKey> instance_keys(const Scene& scene) {
    std::map<std::array<uint32_t, 2>, uint32_t> seen;
    std::vector<InstanceKey> keys(scene.instance_count());
    for (size_t i = 0; i < keys.size(); ++i) {
      const Instance& inst = scene.instance(i);
      keys[i] = {inst.node, inst.mesh, seen[{inst.node, inst.mesh}]++};
    }
    return keys;
  }
  // The slot of the thin mesh's instance, kAbsent for none.
  static uint32_t thin_slot_of(const Scene& scene) {
    if (scene.thin_mesh() < 0) return kAbsent;
    for (size_t i = 0; i < scene.instance_count(); ++i)
      if (scene.instance(i).mesh == uint32_t(scene.thin_mesh())) return uint32_t(1 + i);
    return kAbsent;
  }
  SlotMap map_to(const Scene& other) const {
    SlotMap map;
    map.slot.assign(1 + current->instance_count(), kAbsent);
    map.slot[kWorldSlot] = kWorldSlot;
    std::map<InstanceKey, uint32_t> other_slot;
    const std::vector<InstanceKey> other_keys = instance_keys(other);
    for (size_t i = 0; i < other_keys.size(); ++i) other_slot[other_keys[i]] = uint32_t(1 + i);
    const std::vector<InstanceKey> keys = instance_keys(*current);
    for (size_t i = 0; i < keys.size(); ++i) {
      const auto found = other_slot.find(keys[i]);
      if (found != other_slot.end()) map.slot[1 + i] = found->second;
    }
    map.thin_slot = thin_slot_of(*current);
    const uint32_t other_thin = thin_slot_of(other);
    if (map.thin_slot == kAbsent || other_thin == kAbsent ||
        map.slot[map.thin_slot] != other_thin)
      return map;
    const TriangleMesh& mine = current->slot_mesh(map.thin_slot);
    const TriangleMesh& theirs = other.slot_mesh(other_thin);
    map.thin_prim.assign(mine.size(), kAbsent);
    if (mine.node.empty() || theirs.node.empty()) {
      // No nodes to tell them apart: the same triangles only if as many.
      if (mine.size() == theirs.size())
        for (uint32_t p = 0; p < mine.size(); ++p) map.thin_prim[p] = p;
      return map;
    }
    // Each node's thin triangles in order, in the other pose, and their count in current.
    std::unordered_map<uint32_t, std::vector<uint32_t>> by_node;
    for (uint32_t p = 0; p < theirs.size(); ++p) by_node[theirs.node[p]].push_back(p);
    std::unordered_map<uint32_t, uint32_t> count, rank;
    for (uint32_t p = 0; p < mine.size(); ++p) ++count[mine.node[p]];
    for (uint32_t p = 0; p < mine.size(); ++p) {
      const uint32_t k = rank[mine.node[p]]++;
      const auto found = by_node.find(mine.node[p]);
      if (found != by_node.end() && found->second.size() == count[mine.node[p]])
        map.thin_prim[p] = found->second[k];
    }
    return map;
  }
};

// Motion blur: the frame's time in a shutter's [0, 1] (the RTCRay time of a ray at the frame's
// time). The first hit of a motion-blurred sample was found at the sample's own time in the
// shutter; its surface point is then taken where it is at the frame's time t (the pose's
// time steps interpolated as Embree does), or at the shutter's nearer end if t is outside it
// (a shutter that opens after the frame's time), so that "now" is the frame's time as for the
// frames before and after. Closed shutter: 0, the only time of the pose.
inline float frame_shutter_time(const Shutter& shutter) {
  if (!shutter.is_open()) return 0.f;
  const double t = -shutter.open_s / (shutter.close_s - shutter.open_s);
  return float(std::min(std::max(t, 0.0), 1.0));
}

// The Motion row's four values of a sample into out: with the first hit's raster positions
// prev, cur, next (pixels, y down), X = prev.x - cur.x, Y = -(prev.y - cur.y), Z = cur.x -
// next.x, W = -(cur.y - next.y) (Blender's Vector pass, y up). All 0 where the camera ray hit
// nothing, for a still (poses null), where a pose lacks the surface point (an instance or
// thin triangle of a node hidden in that pose: MotionPoses) and where the point
// is behind a camera (or on its plane) at any of the three times.
inline void motion_values(const MotionPoses* poses, const SampleResult& r, float* out) {
  out[0] = out[1] = out[2] = out[3] = 0.f;
  if (!poses || !(r.depth > 0.f)) return;
  Vec3 p_prev, p_cur, p_next;
  uint32_t prev_slot, prev_prim, next_slot, next_prim;
  if (!MotionPoses::find(poses->to_previous, r.slot, r.prim, &prev_slot, &prev_prim) ||
      !MotionPoses::find(poses->to_next, r.slot, r.prim, &next_slot, &next_prim))
    return;
  if (!poses->current->surface_point(r.slot, r.prim, r.b1, r.b2, poses->frame_time, &p_cur) ||
      !poses->previous->surface_point(prev_slot, prev_prim, r.b1, r.b2, 0.f, &p_prev) ||
      !poses->next->surface_point(next_slot, next_prim, r.b1, r.b2, 0.f, &p_next))
    return;
  float px, py, cx, cy, nx, ny;
  if (!Camera::project(poses->raster_previous, p_prev, &px, &py) ||
      !Camera::project(poses->raster_current, p_cur, &cx, &cy) ||
      !Camera::project(poses->raster_next, p_next, &nx, &ny))
    return;
  out[0] = px - cx;
  out[1] = -(py - cy);
  out[2] = cx - nx;
  out[3] = -(cy - ny);
}

}  // namespace rf
