#include "scene/animation.h"

#include <algorithm>
#include <cmath>

namespace rf {

bool parse_interpolation(const std::string& name, Interpolation* out) {
  if (name == "STEP") {
    *out = Interpolation::Step;
  } else if (name == "LINEAR") {
    *out = Interpolation::Linear;
  } else if (name == "CUBICSPLINE") {
    *out = Interpolation::CubicSpline;
  } else {
    return false;
  }
  return true;
}

Quat normalize_quat(const Quat& q) {
  const double n = std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
  if (!(n > 0.0)) return q;
  return {q[0] / n, q[1] / n, q[2] / n, q[3] / n};
}

Quat slerp(const Quat& a, Quat b, double s) {
  double d = a[0] * b[0] + a[1] * b[1] + a[2] * b[2] + a[3] * b[3];
  // The shorter path: q and -q are the same rotation.
  if (d < 0.0) {
    for (double& c : b) c = -c;
    d = -d;
  }
  Quat r;
  if (d > 0.9995) {
    // Nearly the same rotation: linear interpolation of the 4D vectors.
    for (int i = 0; i < 4; ++i) r[size_t(i)] = (1.0 - s) * a[size_t(i)] + s * b[size_t(i)];
    return normalize_quat(r);
  }
  const double theta0 = std::acos(d);
  const double theta = s * theta0;
  const double sin_theta = std::sin(theta), sin_theta0 = std::sin(theta0);
  const double scale_a = std::cos(theta) - d * sin_theta / sin_theta0;
  const double scale_b = sin_theta / sin_theta0;
  for (int i = 0; i < 4; ++i) r[size_t(i)] = scale_a * a[size_t(i)] + scale_b * b[size_t(i)];
  return normalize_quat(r);
}

namespace {

// Element e of the track's values (a pointer to its components).
const double* element(const KeyframeTrack& track, size_t e) {
  return track.values.data() + e * track.components;
}

// The value (not a tangent) of keyframe k.
const double* key_value(const KeyframeTrack& track, size_t k) {
  return element(track, track.interpolation == Interpolation::CubicSpline ? 3 * k + 1 : k);
}

void normalize_into(const KeyframeTrack& track, double* out) {
  if (!track.rotation || track.components != 4) return;
  const Quat q = normalize_quat({out[0], out[1], out[2], out[3]});
  for (int i = 0; i < 4; ++i) out[i] = q[size_t(i)];
}

}  // namespace

void evaluate_track(const KeyframeTrack& track, double t, double* out) {
  const size_t n = track.times.size(), c = track.components;
  if (n == 0 || c == 0) return;
  auto copy_key = [&](size_t k) {
    const double* v = key_value(track, k);
    std::copy(v, v + c, out);
    normalize_into(track, out);
  };
  // Outside the keyframes (and a single keyframe): the nearest keyframe's value.
  if (n == 1 || !(t > track.times.front())) return copy_key(0);
  if (!(t < track.times.back())) return copy_key(n - 1);
  // t_k <= t < t_k+1.
  const size_t k =
      size_t(std::upper_bound(track.times.begin(), track.times.end(), t) - track.times.begin()) -
      1;
  const double td = track.times[k + 1] - track.times[k];
  const double s = (t - track.times[k]) / td;
  switch (track.interpolation) {
    case Interpolation::Step:
      return copy_key(k);
    case Interpolation::Linear: {
      const double* a = key_value(track, k);
      const double* b = key_value(track, k + 1);
      if (track.rotation && c == 4) {
        const Quat q = slerp(normalize_quat({a[0], a[1], a[2], a[3]}),
                             normalize_quat({b[0], b[1], b[2], b[3]}), s);
        for (int i = 0; i < 4; ++i) out[i] = q[size_t(i)];
        return;
      }
      for (size_t i = 0; i < c; ++i) out[i] = (1.0 - s) * a[i] + s * b[i];
      return;
    }
    case Interpolation::CubicSpline: {
      const double* vk = element(track, 3 * k + 1);
      const double* bk = element(track, 3 * k + 2);      // out-tangent of k
      const double* ak1 = element(track, 3 * (k + 1));    // in-tangent of k + 1
      const double* vk1 = element(track, 3 * (k + 1) + 1);
      const double s2 = s * s, s3 = s2 * s;
      const double h00 = 2.0 * s3 - 3.0 * s2 + 1.0, h10 = s3 - 2.0 * s2 + s,
                   h01 = -2.0 * s3 + 3.0 * s2, h11 = s3 - s2;
      for (size_t i = 0; i < c; ++i)
        out[i] = h00 * vk[i] + td * h10 * bk[i] + h01 * vk1[i] + td * h11 * ak1[i];
      normalize_into(track, out);
      return;
    }
  }
}

std::vector<double> evaluate_track(const KeyframeTrack& track, double t) {
  std::vector<double> out(track.components, 0.0);
  evaluate_track(track, t, out.data());
  return out;
}

std::map<int, NodePose> evaluate_pose(const std::vector<ChannelTrack>& channels, double t) {
  std::map<int, NodePose> poses;
  for (const ChannelTrack& ch : channels) {
    NodePose& pose = poses[ch.node];
    const std::vector<double> v = evaluate_track(ch.track, t);
    switch (ch.path) {
      case AnimationPath::Translation:
        if (v.size() != 3) break;
        pose.has_translation = true;
        std::copy(v.begin(), v.end(), pose.translation.begin());
        break;
      case AnimationPath::Rotation:
        if (v.size() != 4) break;
        pose.has_rotation = true;
        std::copy(v.begin(), v.end(), pose.rotation.begin());
        break;
      case AnimationPath::Scale:
        if (v.size() != 3) break;
        pose.has_scale = true;
        std::copy(v.begin(), v.end(), pose.scale.begin());
        break;
      case AnimationPath::Weights:
        pose.has_weights = true;
        pose.weights = v;
        break;
    }
  }
  return poses;
}

Mat4 blend_skin_matrix(const std::vector<Mat4>& joint_matrices, const uint32_t* joints,
                       const double* weights, size_t n) {
  Mat4 r;  // zeros
  for (size_t i = 0; i < n; ++i) {
    const double w = weights[i];
    if (w == 0.0) continue;
    const Mat4& m = joint_matrices[joints[i]];
    for (size_t c = 0; c < 4; ++c)
      for (size_t k = 0; k < 4; ++k) r.m[c][k] += w * m.m[c][k];
  }
  return r;
}

Vec3 transform_point(const Mat4& m, const double* p) {
  double out[3];
  for (size_t r = 0; r < 3; ++r)
    out[r] = m.m[0][r] * p[0] + m.m[1][r] * p[1] + m.m[2][r] * p[2] + m.m[3][r];
  return {float(out[0]), float(out[1]), float(out[2])};
}

Vec3 transform_normal(const Mat4& m, const double* n) {
  double nm[3][3];
  m.normal_matrix(nm);
  double out[3];
  for (int r = 0; r < 3; ++r) out[r] = nm[r][0] * n[0] + nm[r][1] * n[1] + nm[r][2] * n[2];
  return {float(out[0]), float(out[1]), float(out[2])};
}

}  // namespace rf
