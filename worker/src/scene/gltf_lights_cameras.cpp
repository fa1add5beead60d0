// The glTF loader's lights and cameras (Loader, gltf_loader_internal.h): KHR_lights_punctual's
// lights, which the node walk places (gltf_loader.cpp), and the first camera it meets.
#include "scene/gltf_loader_internal.h"

#include <cmath>
#include <optional>
#include <string>

namespace rf::gltf_detail {

void Loader::load_lights() {
  auto it = model_.extensions.find("KHR_lights_punctual");
  if (it == model_.extensions.end()) return;
  const tinygltf::Value& root = it->second;
  if (!root.Has("lights") || !root.Get("lights").IsArray()) return;
  const tinygltf::Value& list = root.Get("lights");
  for (size_t i = 0; i < list.ArrayLen(); ++i) {
    const tinygltf::Value& l = light_source(i, list.Get(int(i)));  // as animated
    PunctualLight light;
    const std::string where = "extensions.KHR_lights_punctual.lights[" + std::to_string(i) + "]";
    const std::string type = l.Has("type") && l.Get("type").IsString()
                                 ? l.Get("type").Get<std::string>()
                                 : std::string();
    if (type == "point") light.type = PunctualType::Point;
    else if (type == "spot") light.type = PunctualType::Spot;
    else if (type == "directional") light.type = PunctualType::Directional;
    else {
      warn(where + ": unknown type '" + type + "'; light ignored");
      lights_.push_back(std::nullopt);
      continue;
    }
    Vec3 color(1.f, 1.f, 1.f);
    if (l.Has("color") && l.Get("color").IsArray() && l.Get("color").ArrayLen() == 3)
      for (int c = 0; c < 3; ++c)
        color[c] = float(l.Get("color").Get(c).GetNumberAsDouble());
    const float intensity = number_or(l, "intensity", 1.f);
    light.intensity = color * intensity;
    if (!is_finite(light.intensity) || light.intensity.x < 0.f || light.intensity.y < 0.f ||
        light.intensity.z < 0.f)
      fail(where + ": color x intensity must be finite and >= 0");
    if (l.Has("range")) warn(where + ": 'range' is ignored (physically based falloff)");
    if (light.type == PunctualType::Spot) {
      const tinygltf::Value spot = l.Has("spot") ? l.Get("spot") : tinygltf::Value();
      const float inner = number_or(spot, "innerConeAngle", 0.f);
      const float outer = number_or(spot, "outerConeAngle", kPi / 4.f);
      if (!(inner >= 0.f && inner < outer && outer <= kPi / 2.f))
        fail(where + ": spot cone angles must satisfy 0 <= inner < outer <= pi/2");
      light.cos_inner = std::cos(inner);
      light.cos_outer = std::cos(outer);
    }
    lights_.push_back(light);
  }
}

// The first camera the walk from the roots meets, of either type (glTF 2.0, 3.10).
void Loader::take_camera(const tinygltf::Node& node, const Mat4& world, const std::string& where,
                         SceneDescription* desc) {
  if (node.camera >= int(model_.cameras.size()))
    fail(where + ": 'camera' refers to missing camera " + std::to_string(node.camera));
  const tinygltf::Camera& gc = camera_source(size_t(node.camera));  // as animated
  const std::string at = "cameras[" + std::to_string(node.camera) + "]";
  const std::string of = " (camera of " + where + ")";
  Camera cam;
  double znear = 0.0, zfar = 0.0;
  if (gc.type == "perspective") {
    cam.yfov = float(gc.perspective.yfov);
    if (!(cam.yfov > 0.f && cam.yfov < kPi))
      fail(at + ".perspective.yfov: " + std::to_string(gc.perspective.yfov) +
           " is outside (0, pi)" + of);
    znear = gc.perspective.znear;
    zfar = gc.perspective.zfar;  // 0: absent, an infinite projection
    if (!(znear >= 0.0 && std::isfinite(znear)))
      fail(at + ".perspective.znear: " + std::to_string(znear) + " is not >= 0" + of);
    if (zfar != 0.0 && !(zfar > znear))
      fail(at + ".perspective.zfar: " + std::to_string(zfar) + " is not greater than znear" +
           of);
  } else if (gc.type == "orthographic") {
    const tinygltf::OrthographicCamera& o = gc.orthographic;
    cam.orthographic = true;
    cam.xmag = float(o.xmag);
    cam.ymag = float(o.ymag);
    if (!(cam.xmag != 0.f && std::isfinite(cam.xmag)))
      fail(at + ".orthographic.xmag: " + std::to_string(o.xmag) + " must be finite and not 0" +
           of);
    if (!(cam.ymag != 0.f && std::isfinite(cam.ymag)))
      fail(at + ".orthographic.ymag: " + std::to_string(o.ymag) + " must be finite and not 0" +
           of);
    znear = o.znear;
    zfar = o.zfar;
    if (!(znear >= 0.0 && std::isfinite(znear)))
      fail(at + ".orthographic.znear: " + std::to_string(znear) + " is not >= 0" + of);
    if (!(zfar > znear && std::isfinite(zfar)))
      fail(at + ".orthographic.zfar: " + std::to_string(zfar) +
           " is not finite and greater than znear" + of);
  } else {
    fail(at + ".type: '" + gc.type + "' is not perspective or orthographic" + of);
  }
  cam.znear = float(znear);
  if (zfar != 0.0) cam.zfar = float(zfar);
  cam.position = world.transform_point({0.f, 0.f, 0.f});
  const Vec3 fwd = world.transform_vector({0.f, 0.f, -1.f});
  const Vec3 up = world.transform_vector({0.f, 1.f, 0.f});
  if (!(length(fwd) > 0.f) || !(length(cross(fwd, up)) > 0.f))
    fail(where + ": camera transform is singular");
  cam.forward = normalize(fwd);
  // Re-orthogonalize in case of shear: right = fwd x up, up = right x fwd.
  cam.right = normalize(cross(cam.forward, up));
  cam.up = cross(cam.right, cam.forward);
  desc->camera = cam;
}

}  // namespace rf::gltf_detail
