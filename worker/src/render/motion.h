// The Motion row (channel_table.h): the screen-space motion of each pixel's first sample's
// first hit, as Blender's Vector pass has it. The surface point the camera ray hit (its
// geometry slot, triangle and barycentrics, SampleResult) is found again in the scene posed
// at the previous frame's time t - 1 / fps and at the next frame's t + 1 / fps: the poses of
// one AnimatedScene place the same instances in the same order over the same static world,
// so a slot and triangle name the same surface in every pose (a static world triangle stays
// put, an instance's triangle moves with that pose's transform, a deformed mesh's vertices
// are that pose's). A deformed mesh has all its triangles in every pose, in the same order:
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
// other render passes no MotionPoses and pays nothing.
#pragma once

#include <algorithm>
#include <cstdint>

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
        raster_next(after.camera().raster(width, height)) {}
  const Scene* current;
  const Scene* previous;
  const Scene* next;
  float frame_time;
  Camera::Raster raster_previous, raster_current, raster_next;
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
// nothing, for a still (poses null), where a pose lacks the surface point and where the point
// is behind a camera (or on its plane) at any of the three times.
inline void motion_values(const MotionPoses* poses, const SampleResult& r, float* out) {
  out[0] = out[1] = out[2] = out[3] = 0.f;
  if (!poses || !(r.depth > 0.f)) return;
  Vec3 p_prev, p_cur, p_next;
  if (!poses->current->surface_point(r.slot, r.prim, r.b1, r.b2, poses->frame_time, &p_cur) ||
      !poses->previous->surface_point(r.slot, r.prim, r.b1, r.b2, 0.f, &p_prev) ||
      !poses->next->surface_point(r.slot, r.prim, r.b1, r.b2, 0.f, &p_next))
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
