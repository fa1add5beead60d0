#include "scene/animated_scene.h"

#include <cmath>

#include "scene/animation.h"

namespace rf {

namespace {
// Deformed mesh sets kept for the next poses: as many as poses are usually alive at once on a
// worker is enough (the others are built when needed and freed after).
constexpr size_t kPooledSets = 4;
}  // namespace

AnimatedScene::AnimatedScene(std::shared_ptr<const GltfDocument> document,
                             const LoadOptions& options, std::vector<std::string>* warnings)
    : document_(std::move(document)), options_(options), pool_(std::make_shared<Pool>()) {
  options_.pose_report = nullptr;
  options_.layout = nullptr;
  AnimatedLayout layout;
  LoadOptions load = options_;
  // The static part does not depend on the time; any time evaluates the channels (and checks
  // them, as every pose will).
  load.time = std::isfinite(options_.time) ? options_.time : 0.0;
  load.layout = &layout;
  SceneDescription desc = describe_gltf(*document_, warnings, load);
  moving_nodes_ = layout.moving_nodes;
  deformed_nodes_ = layout.deformed_nodes;
  // The poses place every mesh themselves and have their own camera and lights.
  desc.instances.clear();
  desc.punctual_lights.clear();
  desc.camera.reset();
  base_ = std::make_shared<const Scene>(Scene::StaticPart{}, std::move(desc), warnings,
                                        options_.bvh);
}

AnimatedScene::~AnimatedScene() = default;

size_t AnimatedScene::memory_bytes() const {
  return gltf_document_bytes(*document_) + base_->memory_bytes();
}

bool parse_shutter(const std::string& text, double fps, Shutter* out, std::string* err) {
  *out = Shutter{};
  if (text.find_first_not_of(" \t") == std::string::npos) return true;
  const size_t comma = text.find(',');
  double open = 0.0, close = 0.0;
  bool ok = comma != std::string::npos && text.find(',', comma + 1) == std::string::npos;
  if (ok) {
    try {
      size_t end = 0;
      const std::string a = text.substr(0, comma), b = text.substr(comma + 1);
      open = std::stod(a, &end);
      ok = a.find_first_not_of(" \t", end) == std::string::npos;
      close = std::stod(b, &end);
      ok = ok && b.find_first_not_of(" \t", end) == std::string::npos;
    } catch (const std::exception&) {
      ok = false;
    }
  }
  if (!ok) {
    *err = "settings.shutter: '" + text + "' is not OPEN,CLOSE (fractions of a frame)";
    return false;
  }
  if (!(open >= -1.0 && open < close && close <= 1.0 && close - open <= 1.0)) {
    *err = "settings.shutter: '" + text + "': the shutter must open before it closes, both " +
           "within [-1, 1] frames of the frame's time and at most one frame apart";
    return false;
  }
  if (!(fps > 0.0) || !std::isfinite(fps)) {
    *err = "settings.fps must be positive for a shutter";
    return false;
  }
  out->open_s = open / fps;
  out->close_s = close / fps;
  return true;
}

std::shared_ptr<const Scene> AnimatedScene::pose(double time, std::vector<std::string>* warnings,
                                                 const Shutter& shutter,
                                                 uint32_t image_height) const {
  if (!std::isfinite(time))
    throw SceneError(base_->source() + ": animation: the time is not finite");
  // One description per time step: the frame's time, or the shutter's steps.
  std::vector<SceneDescription> steps;
  const uint32_t count = shutter.is_open() ? kShutterSteps : 1;
  for (uint32_t k = 0; k < count; ++k) {
    AnimatedLayout layout;
    layout.pose_only = true;
    LoadOptions load = options_;
    load.time = shutter.is_open() ? time + shutter.open_s +
                                        (shutter.close_s - shutter.open_s) * k / (count - 1)
                                  : time;
    load.visibility_time = time + (shutter.is_open() ? shutter.open_s : 0.0);
    if (image_height) load.image_height = image_height;
    load.layout = &layout;
    // The loader's warnings are the construction's: the same at every time.
    steps.push_back(describe_gltf(*document_, nullptr, load));
  }
  std::unique_ptr<DeformedMeshes> set;
  {
    std::lock_guard<std::mutex> lock(pool_->mutex);
    if (!pool_->free.empty()) {
      set = std::move(pool_->free.back());
      pool_->free.pop_back();
    }
  }
  if (!set) set = std::make_unique<DeformedMeshes>();
  // The set goes back to the pool when the pose is destroyed (or dropped if the pool is full
  // or the animated scene gone).
  const std::weak_ptr<Pool> pool = pool_;
  std::shared_ptr<DeformedMeshes> held(set.release(), [pool](DeformedMeshes* d) {
    std::unique_ptr<DeformedMeshes> owned(d);
    if (const std::shared_ptr<Pool> p = pool.lock()) {
      std::lock_guard<std::mutex> lock(p->mutex);
      if (p->free.size() < kPooledSets) p->free.push_back(std::move(owned));
    }
  });
  return std::make_shared<const Scene>(base_, std::move(steps), std::move(held), warnings);
}

std::shared_ptr<const Scene> load_animated_scene(const std::string& path,
                                                 std::vector<std::string>* warnings,
                                                 const LoadOptions& options) {
  const AnimatedScene animated(parse_gltf(path, warnings, options), options, warnings);
  return animated.pose(options.time, warnings);
}

}  // namespace rf
