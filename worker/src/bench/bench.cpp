#include "bench/bench.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <nlohmann/json.hpp>
#include <thread>

#include "render/channels.h"
#include "render/integrators.h"
#include "render/render.h"

namespace rf {

namespace {

using Clock = std::chrono::steady_clock;

double seconds_since(Clock::time_point t0) {
  return std::chrono::duration<double>(Clock::now() - t0).count();
}

// Replays rays with bare Embree queries on `threads` threads (contiguous slices), `passes`
// times over; returns rays per second. The checksum keeps the compiler from dropping the
// queries.
double replay_rate(const Scene& scene, const RayLog& rays, uint32_t threads, uint32_t passes,
                   uint64_t* checksum) {
  std::vector<uint64_t> sums(threads, 0);
  const auto t0 = Clock::now();
  auto work = [&](uint32_t k) {
    const size_t begin = rays.size() * k / threads, end = rays.size() * (k + 1) / threads;
    uint64_t sum = 0;
    for (uint32_t pass = 0; pass < passes; ++pass)
      for (size_t i = begin; i < end; ++i) {
        const LoggedRay& r = rays[i];
        if (r.shadow) {
          sum += scene.occluded(r.o, r.d, r.tmax) ? 1 : 0;
        } else {
          float t = 0.f;
          sum += scene.intersect_t(r.o, r.d, r.tmax, &t) ? 2 : 0;
        }
      }
    sums[k] = sum;
  };
  std::vector<std::thread> pool;
  for (uint32_t k = 1; k < threads; ++k) pool.emplace_back(work, k);
  work(0);
  for (auto& t : pool) t.join();
  const double s = seconds_since(t0);
  for (uint64_t v : sums) *checksum += v;
  return double(rays.size()) * passes / s;
}

nlohmann::json bench_scene(const std::string& name, const Scene& scene,
                           const BenchOptions& options) {
  RenderSettings settings;
  settings.width = options.width;
  settings.height = options.height;
  settings.seed = 1;
  nlohmann::json out;
  out["scene"] = name;
  out["triangles"] = scene.world_triangle_count();
  // Everything the scene holds (Scene::memory_bytes). Instances share their mesh's storage:
  // for the instanced scene this does not grow with `triangles`.
  out["scene_memory_bytes"] = scene.memory_bytes();
  // 16: one native 16-wide Embree query per packet; 8: two 8-wide ones (no AVX-512).
  out["packet_query_width"] = scene.packet_query_width();
  out["width"] = options.width;
  out["height"] = options.height;
  out["spp"] = options.spp;
  out["integrator"] = "path";
  out["sampler"] = "sobol";
  out["max_depth"] = settings.max_depth;

  // Record the path tracer's rays (one thread, a quarter of the samples) for the replay.
  RayLog log;
  log.reserve(1 << 20);
  set_thread_ray_log(&log);
  {
    TileBuffer tile;
    // The rows of a standalone image: the farm's outputs (lobes, Cryptomatte's counts, ...)
    // add no rays, only time.
    render_rect(scene, settings, {0, 0, options.width, options.height}, 0,
                std::max<uint32_t>(1, options.spp / 4), &tile, nullptr, channels::kImageRows);
  }
  set_thread_ray_log(nullptr);
  size_t shadow = 0;
  for (const LoggedRay& r : log) shadow += r.shadow;
  out["recorded_rays"] = log.size();
  out["recorded_shadow_fraction"] = double(shadow) / double(std::max<size_t>(1, log.size()));

  // Enough passes over the log that one replay lasts about half a second on one thread, so
  // that thread start-up and scheduling noise do not decide the figure.
  uint64_t calibration = 0;
  const double rate0 = replay_rate(scene, log, 1, 1, &calibration);
  const uint32_t passes =
      std::max<uint32_t>(1, uint32_t(0.5 * rate0 / double(std::max<size_t>(1, log.size()))));
  out["replay_passes"] = passes;

  nlohmann::json by_threads = nlohmann::json::object();
  double rate1 = 0.0, raw1 = 0.0;
  for (uint32_t threads : options.threads) {
    // Warm-up at the first thread count only: page in the BVH and code.
    if (threads == options.threads.front()) render_image(scene, settings, 1, threads, nullptr);
    // Best of kRepeats for both rates: on a shared machine the fastest run is the one least
    // disturbed by other processes, and the two sides get the same treatment.
    constexpr int kRepeats = 5;
    RenderStats stats;
    uint64_t checksum = 0;
    double raw = 0.0;
    for (int rep = 0; rep < kRepeats; ++rep) {
      RenderStats run;
      render_image(scene, settings, options.spp, threads, &run);
      if (rep == 0 || run.seconds < stats.seconds) stats = run;
      raw = std::max(raw, replay_rate(scene, log, threads, passes, &checksum));
    }
    const double samples_per_s = double(stats.samples) / stats.seconds;
    const double rays_per_s = double(stats.rays) / stats.seconds;
    nlohmann::json t;
    t["repeats"] = kRepeats;
    t["seconds"] = stats.seconds;
    t["samples_per_s"] = samples_per_s;
    t["mrays_per_s"] = rays_per_s * 1e-6;
    t["raw_embree_mrays_per_s"] = raw * 1e-6;
    t["ray_rate_vs_raw"] = rays_per_s / raw;
    t["nonfinite_samples"] = stats.nonfinite_samples;
    t["replay_checksum"] = checksum;
    if (threads == options.threads.front()) {
      rate1 = samples_per_s;
      raw1 = raw;
    } else if (rate1 > 0.0) {
      t["scaling_vs_first"] = samples_per_s / rate1;
      t["raw_scaling_vs_first"] = raw / raw1;
    }
    std::printf("%-10s %8llu tris  %u thread%s: %10.0f samples/s  %7.2f Mrays/s  "
                "raw Embree %7.2f Mrays/s  ratio %.2f%s\n",
                name.c_str(), static_cast<unsigned long long>(scene.world_triangle_count()),
                threads, threads == 1 ? " " : "s", samples_per_s, rays_per_s * 1e-6, raw * 1e-6,
                rays_per_s / raw,
                t.contains("scaling_vs_first")
                    ? ("  scaling " + std::to_string(double(t["scaling_vs_first"]))).c_str()
                    : "");
    std::fflush(stdout);
    by_threads[std::to_string(threads)] = t;
  }
  out["threads"] = by_threads;
  return out;
}

// About `triangles` flat triangles (at least that many) of a bumpy unit sphere centred at
// (0, 1.05, 0), appended to *out with material `material`: an indexed mesh, each vertex shared
// by the triangles around it, as in a glTF file.
void append_displaced_sphere(uint32_t triangles, uint32_t material, TriangleMesh* out) {
  // rings x segments quads, 2 triangles each, segments = 2 rings; the pole rows lose their
  // degenerate halves, so add a ring to stay above the requested count.
  const uint32_t rings = uint32_t(std::ceil(std::sqrt(double(triangles) / 4.0))) + 1;
  const uint32_t segments = 2 * rings;
  const uint32_t first = uint32_t(out->positions.size());
  out->positions.reserve(out->positions.size() + size_t(rings + 1) * segments + 1);
  for (uint32_t i = 0; i <= rings; ++i)
    for (uint32_t j = 0; j < segments; ++j) {
      const float theta = kPi * float(i) / float(rings);
      const float phi = 2.f * kPi * float(j) / float(segments);
      const float r = 1.f + 0.04f * std::sin(13.f * theta) * std::sin(11.f * phi) +
                      0.01f * std::sin(61.f * theta + 3.f * phi);
      out->positions.push_back(Vec3(r * std::sin(theta) * std::cos(phi),
                                    1.05f + r * std::cos(theta),
                                    -r * std::sin(theta) * std::sin(phi)));
    }
  auto vertex = [&](uint32_t i, uint32_t j) { return first + i * segments + j % segments; };
  const size_t quads = size_t(rings) * segments;
  out->indices.reserve(out->indices.size() + 6 * quads);
  out->material.reserve(out->material.size() + 2 * quads);
  out->flags.reserve(out->flags.size() + 2 * quads);
  for (uint32_t i = 0; i < rings; ++i)
    for (uint32_t j = 0; j < segments; ++j) {
      const uint32_t a = vertex(i, j), b = vertex(i + 1, j), c = vertex(i + 1, j + 1),
                     d = vertex(i, j + 1);
      out->indices.insert(out->indices.end(), {a, b, c, a, c, d});
      out->material.insert(out->material.end(), {material, material});
      out->flags.insert(out->flags.end(), {uint8_t(0), uint8_t(0)});
    }
}

// The bench scenes' floor (material 1) and lamp (material 2).
void append_floor_and_lamp(float half_size, float lamp_half, TriangleMesh* out) {
  auto quad = [&](Vec3 p0, Vec3 p1, Vec3 p2, Vec3 p3, uint32_t m) {
    Triangle a, b;
    a.p[0] = p0, a.p[1] = p1, a.p[2] = p2;
    b.p[0] = p0, b.p[1] = p2, b.p[2] = p3;
    a.material = b.material = m;
    out->add(a);
    out->add(b);
  };
  const float h = half_size, l = lamp_half;
  quad({-h, 0, h}, {h, 0, h}, {h, 0, -h}, {-h, 0, -h}, 1);  // floor, faces +y
  quad({-l, 3.5f, -l}, {l, 3.5f, -l}, {l, 3.5f, l}, {-l, 3.5f, l}, 2);  // lamp, faces -y
}

// Plastic spheres (material 0), a grey floor (1) and a warm lamp (2).
std::vector<Material> bench_materials() {
  Material sphere;
  sphere.name = "plastic";
  sphere.albedo = Vec3(0.6f, 0.35f, 0.2f);
  sphere.roughness = 0.4f;
  sphere.specular = 1.f;
  Material floor;
  floor.name = "floor";
  floor.albedo = Vec3(0.7f, 0.7f, 0.7f);
  Material lamp;
  lamp.name = "lamp";
  lamp.albedo = Vec3(0.f, 0.f, 0.f);
  lamp.emission = Vec3(12.f, 11.f, 9.f);
  return {sphere, floor, lamp};
}

Camera bench_camera(Vec3 position, Vec3 target, float yfov) {
  Camera cam;
  cam.position = position;
  cam.forward = normalize(target - position);
  cam.right = normalize(cross(cam.forward, Vec3(0.f, 1.f, 0.f)));
  cam.up = cross(cam.right, cam.forward);
  cam.yfov = yfov;
  return cam;
}

}  // namespace

SceneDescription generate_bench_scene(uint32_t triangles) {
  SceneDescription desc;
  desc.source = "generated:" + std::to_string(triangles) + "-triangle displaced sphere";
  desc.materials = bench_materials();
  append_displaced_sphere(triangles, 0, &desc.world);
  append_floor_and_lamp(4.f, 0.6f, &desc.world);
  desc.camera = bench_camera(Vec3(0.f, 1.6f, 4.2f), Vec3(0.f, 1.f, 0.f), 0.7f);
  return desc;
}

SceneDescription generate_instanced_bench_scene(uint32_t triangles_per_mesh, uint32_t grid) {
  SceneDescription desc;
  desc.source = "generated:" + std::to_string(grid * grid) + " instances of a " +
                std::to_string(triangles_per_mesh) + "-triangle displaced sphere";
  desc.materials = bench_materials();
  Mesh mesh;
  mesh.name = "sphere";
  append_displaced_sphere(triangles_per_mesh, 0, &mesh.geometry);
  desc.meshes.push_back(std::move(mesh));
  // A grid of spheres on the floor, each turned about +y and scaled by its own amount
  // (deterministic), every third one mirrored.
  const float spacing = 7.f / float(grid);
  for (uint32_t i = 0; i < grid; ++i)
    for (uint32_t j = 0; j < grid; ++j) {
      const uint32_t k = i * grid + j;
      const double angle = 2.399963 * k;  // the golden angle: no two alike
      const double scale = spacing * (0.3 + 0.12 * std::sin(1.7 * k));
      const double mirror = k % 3 == 0 ? -1.0 : 1.0;
      Instance inst;
      Mat4& m = inst.to_world;
      m.m[0][0] = mirror * scale * std::cos(angle);
      m.m[0][2] = -mirror * scale * std::sin(angle);
      m.m[1][1] = scale;
      m.m[2][0] = scale * std::sin(angle);
      m.m[2][2] = scale * std::cos(angle);
      m.m[3][0] = -3.5 + spacing * (double(j) + 0.5);
      m.m[3][2] = -3.5 + spacing * (double(i) + 0.5);
      desc.instances.push_back(inst);
    }
  append_floor_and_lamp(4.f, 1.2f, &desc.world);
  desc.camera = bench_camera(Vec3(0.f, 3.2f, 4.6f), Vec3(0.f, 0.f, -0.3f), 0.9f);
  return desc;
}

std::string run_bench(const BenchOptions& options) {
  nlohmann::json doc;
  doc["benchmark"] = "worker_throughput";
  doc["hardware_threads"] = std::thread::hardware_concurrency();
  doc["targets"] = {{"ray_rate_vs_raw", 0.6}, {"scaling_1_to_2_threads", 1.8}};
  nlohmann::json scenes = nlohmann::json::array();
  if (options.cornell) {
    std::vector<std::string> warnings;
    auto cornell = load_scene(options.cornell_path, &warnings);
    scenes.push_back(bench_scene("cornell", *cornell, options));
  }
  if (options.mesh) {
    const auto t0 = Clock::now();
    Scene big(generate_bench_scene(options.mesh_triangles));
    const double build = seconds_since(t0);
    std::printf("generated scene: %llu triangles, built in %.2f s, %s in memory (%.0f bytes "
                "per triangle)\n",
                static_cast<unsigned long long>(big.world_triangle_count()), build,
                format_bytes(big.memory_bytes()).c_str(),
                double(big.memory_bytes()) / double(big.world_triangle_count()));
    nlohmann::json s = bench_scene("1M-mesh", big, options);
    s["build_seconds"] = build;
    scenes.push_back(s);
  }
  if (options.instanced) {
    const auto t0 = Clock::now();
    Scene forest(generate_instanced_bench_scene(options.instance_triangles, options.instance_grid));
    const double build = seconds_since(t0);
    std::printf("generated scene: %zu instances of one mesh, %llu triangles in all, built in "
                "%.2f s, %s in memory\n",
                forest.instance_count(),
                static_cast<unsigned long long>(forest.world_triangle_count()), build,
                format_bytes(forest.memory_bytes()).c_str());
    nlohmann::json s = bench_scene("instanced", forest, options);
    s["build_seconds"] = build;
    s["instances"] = forest.instance_count();
    scenes.push_back(s);
  }
  doc["scenes"] = scenes;
  return doc.dump(2);
}

}  // namespace rf
