// renderfarm-worker: standalone `render` and farm `connect` commands.
// Exit codes: 0 success, 1 runtime error (unreadable scene, write failure), 2 usage error.
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cerrno>
#include <chrono>
#include <cctype>
#include <cmath>
#include <csignal>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <map>
#include <string>
#include <thread>
#include <vector>

#include <nlohmann/json.hpp>

#include "bench/bench.h"
#include "scene/animated_scene.h"
#include "scene/animation.h"
#include "farm/farm_client.h"
#include "farm/frames.h"
#include "render/film.h"
#include "render/integrators.h"
#include "render/render.h"
#include "scene/scene.h"
#include "scene/textures.h"
#include "farm/scene_cache.h"
#include "util/isa.h"

namespace {

constexpr int kExitRuntime = 1;
constexpr int kExitUsage = 2;

const char* kUsage =
    "usage:\n"
    "  renderfarm-worker render SCENE.gltf|SCENE.glb -o OUT.exr --spp N [--width W]\n"
    "      [--height H] [--threads T] [--seed S]\n"
    "      [--sampler sobol|halton|stratified|independent] [--integrator path|direct|ao]\n"
    "      [--max-depth D] [--aperture-radius R --focus-distance F]\n"
    "      [--environment MAP.hdr|MAP.exr [--environment-intensity X]\n"
    "       [--environment-rotation-deg D]] [--bvh fast|compact]\n"
    "      [--time T | --times T0,T1,... [--animation I]...] [--stats-json FILE]\n"
    "      --time T: pose the scene with its glTF animations at T seconds (default: no\n"
    "      animation, the nodes' own transforms); --animation I: only animation I drives the\n"
    "      pose (repeatable, or I,J,...; default: every animation); --times: one image per\n"
    "      time from one load, OUT's '{i}' replaced by the time's index (0000, 0001, ...);\n"
    "      --stats-json: the load's and each frame's scene update and render times as JSON\n"
    "      [--shutter OPEN,CLOSE [--fps F]]: motion blur over the shutter, its open and close\n"
    "      times fractions of a frame of 1/F seconds (default 24) after each time\n"
    "      [--variant NAME|INDEX]: KHR_materials_variants: render that variant's materials\n"
    "      [--guiding on|off]: path guiding (default off here, the farm's setting `guiding`):\n"
    "      learn the incident light first, then sample it beside the BSDF\n"
    "  renderfarm-worker pose SCENE.gltf|SCENE.glb [--time T [--animation I]...] [--json]\n"
    "      the posed scene as JSON (indented without --json): every node's world matrix\n"
    "      (column-major), the camera, the world mesh's vertex positions and normals, the\n"
    "      shared meshes and their instances, and per mesh node the range of its vertices\n"
    "      ({node, mesh, first_vertex, count, instance, mesh_slot, skinned, morphed})\n"
    "  renderfarm-worker camera SCENE.gltf|SCENE.glb [--times T0,T1,... [--animations SEL]\n"
    "      [--shutter OPEN,CLOSE [--fps F]]] [--json]\n"
    "      the camera each image is rendered through, as JSON: without --times the still's,\n"
    "      with them the camera at each time, posed by the animations SEL names (a job's\n"
    "      settings.animation: indices or names; default every one); a scene without a camera\n"
    "      gets the camera that frames its bounds (\"framing\": true)\n"
    "  renderfarm-worker bench --cornell SCENE.gltf [--json OUT.json] [--width W]\n"
    "      [--height H] [--spp N] [--triangles T] [--threads 1,2]\n"
    "      [--scenes cornell,mesh,instanced]\n"
    "  renderfarm-worker inspect SCENE.gltf|SCENE.glb [--json] [--name NAME]\n"
    "      [--max-nodes N] [--max-depth D] [--max-triangles T] [--max-texture-pixels P]\n"
    "      [--max-memory-mb M] [--bvh fast|compact]\n"
    "  renderfarm-worker connect --server HOST:PORT[,HOST:PORT...] [--threads N]\n"
    "      [--prefetch P] [--result-interval-ms MS]\n"
    "      [--cache-dir DIR] [--token TOKEN] [--id ID] [--bvh fast|compact]\n"
    "      [--scene-memory-mb M] [--task-timeout-s S] [--max-scene-memory-mb M]\n"
    "      [--tls] [--ca-file CA.pem] [--cert CERT.pem --key KEY.pem]\n"
    "      [--tls-server-name NAME] [--tag TAG]...\n"
    "  renderfarm-worker --help | --version\n";

struct UsageError {
  std::string message;
};

// Parses "--flag value" pairs against the allowed flags; a positional argument is allowed
// only where `positional` is non-null.
std::map<std::string, std::string> parse_flags(const std::vector<std::string>& args,
                                               const std::vector<std::string>& allowed,
                                               std::vector<std::string>* positional) {
  std::map<std::string, std::string> out;
  for (size_t i = 0; i < args.size(); ++i) {
    const std::string& a = args[i];
    if (a.size() > 1 && a[0] == '-') {
      bool known = false;
      for (const auto& f : allowed) known = known || f == a;
      if (!known) throw UsageError{"unknown flag '" + a + "'"};
      if (i + 1 >= args.size()) throw UsageError{"flag '" + a + "' needs a value"};
      out[a] = args[++i];
    } else if (positional) {
      positional->push_back(a);
    } else {
      throw UsageError{"unexpected argument '" + a + "'"};
    }
  }
  return out;
}

uint64_t parse_uint(const std::string& flag, const std::string& value, uint64_t min,
                    uint64_t max) {
  if (value.empty() || value.find_first_not_of("0123456789") != std::string::npos)
    throw UsageError{flag + " expects a non-negative integer, got '" + value + "'"};
  errno = 0;
  const unsigned long long v = std::strtoull(value.c_str(), nullptr, 10);
  if (errno == ERANGE || v < min || v > max)
    throw UsageError{flag + " must be in [" + std::to_string(min) + ", " + std::to_string(max) +
                     "], got " + value};
  return v;
}

double parse_double(const std::string& flag, const std::string& value) {
  char* end = nullptr;
  errno = 0;
  const double v = std::strtod(value.c_str(), &end);
  if (value.empty() || end != value.c_str() + value.size() || errno == ERANGE || !std::isfinite(v))
    throw UsageError{flag + " expects a finite number, got '" + value + "'"};
  return v;
}

uint32_t default_threads() {
  const unsigned n = std::thread::hardware_concurrency();
  return n ? n : 1;
}

// The output must be an .exr (10 channels: RGB and the AOVs) in an existing, writable
// directory.
void check_output_path(const std::string& path) {
  const std::filesystem::path p(path);
  std::string ext = p.extension().string();
  for (char& c : ext) c = char(std::tolower(static_cast<unsigned char>(c)));
  if (ext != ".exr")
    throw UsageError{"-o must name an .exr file (RGB, albedo, normal and depth channels), got '" +
                     path + "'"};
  const std::filesystem::path dir = p.has_parent_path() ? p.parent_path() : ".";
  std::error_code ec;
  if (!std::filesystem::is_directory(dir, ec))
    throw UsageError{"-o " + path + ": directory " + dir.string() + " does not exist"};
  if (::access(dir.c_str(), W_OK) != 0)
    throw UsageError{"-o " + path + ": directory " + dir.string() + " is not writable"};
}

// --bvh fast|compact (default fast): the layout of the scenes' Embree BVH.
rf::BvhLayout parse_bvh_flag(std::map<std::string, std::string>& flags) {
  rf::BvhLayout bvh = rf::BvhLayout::Fast;
  if (flags.count("--bvh") && !rf::parse_bvh_layout(flags["--bvh"], &bvh))
    throw UsageError{"unknown --bvh '" + flags["--bvh"] + "' (expected fast or compact)"};
  return bvh;
}

// "a,b,,c" -> {"a", "b", "", "c"}: empty items are kept, for the caller to reject.
std::vector<std::string> split_commas(const std::string& list) {
  std::vector<std::string> items;
  size_t pos = 0;
  for (;;) {
    const size_t comma = list.find(',', pos);
    items.push_back(list.substr(pos, comma == std::string::npos ? std::string::npos : comma - pos));
    if (comma == std::string::npos) return items;
    pos = comma + 1;
  }
}

// --time T and --animation I (repeatable, or I,J,...) onto the load options: the animations'
// pose at T (animation.h). Takes --animation out of *args (parse_flags takes a flag once).
// With times given (the render command), also --times T0,T1,...: a sequence of poses, the
// first of which is options->time.
void take_animation_flags(std::vector<std::string>* args, rf::LoadOptions* options,
                          std::vector<double>* times = nullptr) {
  std::vector<std::string> rest;
  bool time = false;
  for (size_t i = 0; i < args->size(); ++i) {
    const std::string& a = (*args)[i];
    if (a == "--animation" || a == "--time" || (times && a == "--times")) {
      if (i + 1 >= args->size()) throw UsageError{"flag '" + a + "' needs a value"};
      const std::string& value = (*args)[++i];
      if (a == "--time" || a == "--times") {
        if (time) throw UsageError{"give one of --time and --times, once"};
        if (a == "--time") {
          options->time = parse_double("--time", value);
        } else {
          for (const std::string& item : split_commas(value))
            times->push_back(parse_double("--times", item));
          options->time = times->front();
        }
        if (!std::isfinite(options->time)) throw UsageError{a + " must be finite"};
        time = true;
        continue;
      }
      for (const std::string& item : split_commas(value))
        options->animations.push_back(int(parse_uint("--animation", item, 0, INT32_MAX)));
    } else {
      rest.push_back(a);
    }
  }
  if (!time && !options->animations.empty())
    throw UsageError{"--animation needs --time (without a time no animation applies)"};
  if (times)
    for (double t : *times)
      if (!std::isfinite(t)) throw UsageError{"--times must be finite"};
  *args = rest;
}

int cmd_render(const std::vector<std::string>& arguments) {
  std::vector<std::string> positional;
  std::vector<std::string> args = arguments;
  rf::LoadOptions load;
  std::vector<double> times;
  take_animation_flags(&args, &load, &times);
  auto flags = parse_flags(args,
                           {"-o", "--spp", "--width", "--height", "--threads", "--seed",
                            "--sampler", "--integrator", "--max-depth", "--aperture-radius",
                            "--focus-distance", "--environment", "--environment-intensity",
                            "--environment-rotation-deg", "--bvh", "--stats-json", "--shutter",
                            "--fps", "--variant", "--guiding"},
                           &positional);
  if (positional.size() != 1) throw UsageError{"render expects exactly one scene file"};
  if (!flags.count("-o")) throw UsageError{"render needs -o OUT.exr"};
  if (!flags.count("--spp")) throw UsageError{"render needs --spp N"};
  if (flags.count("--variant")) load.variant = flags["--variant"];
  rf::RenderSettings settings;
  const uint32_t spp =
      uint32_t(parse_uint("--spp", flags["--spp"], 1, rf::kMaxSamplesPerPixel));
  if (flags.count("--width")) settings.width = uint32_t(parse_uint("--width", flags["--width"], 1, 65536));
  if (flags.count("--height"))
    settings.height = uint32_t(parse_uint("--height", flags["--height"], 1, 65536));
  uint32_t threads = default_threads();
  if (flags.count("--threads")) threads = uint32_t(parse_uint("--threads", flags["--threads"], 1, 4096));
  if (flags.count("--seed")) settings.seed = parse_uint("--seed", flags["--seed"], 0, UINT64_MAX);
  if (flags.count("--max-depth"))
    settings.max_depth = uint32_t(parse_uint("--max-depth", flags["--max-depth"], 0, 1024));
  if (flags.count("--sampler") && !rf::parse_sampler_type(flags["--sampler"], &settings.sampler))
    throw UsageError{"unknown sampler '" + flags["--sampler"] +
                     "' (expected sobol, halton, stratified or independent)"};
  if (flags.count("--integrator") &&
      !rf::parse_integrator_type(flags["--integrator"], &settings.integrator))
    throw UsageError{"unknown integrator '" + flags["--integrator"] +
                     "' (expected path, direct or ao)"};
  if (flags.count("--guiding")) {
    const std::string& g = flags["--guiding"];
    if (g != "on" && g != "off")
      throw UsageError{"--guiding must be on or off, not '" + g + "'"};
    settings.guiding = g == "on";
  }
  if (flags.count("--aperture-radius"))
    settings.aperture_radius = float(parse_double("--aperture-radius", flags["--aperture-radius"]));
  if (flags.count("--focus-distance"))
    settings.focus_distance = float(parse_double("--focus-distance", flags["--focus-distance"]));
  float env_intensity = 1.f, env_rotation = 0.f;
  if (flags.count("--environment-intensity")) {
    env_intensity = float(parse_double("--environment-intensity", flags["--environment-intensity"]));
    if (!(env_intensity > 0.f)) throw UsageError{"--environment-intensity must be > 0"};
  }
  if (flags.count("--environment-rotation-deg"))
    env_rotation =
        float(parse_double("--environment-rotation-deg", flags["--environment-rotation-deg"]));
  if (!flags.count("--environment") &&
      (flags.count("--environment-intensity") || flags.count("--environment-rotation-deg")))
    throw UsageError{"--environment-intensity/--environment-rotation-deg need --environment"};
  load.bvh = parse_bvh_flag(flags);
  rf::Shutter shutter;
  if (flags.count("--shutter") || flags.count("--fps")) {
    if (!load.animated()) throw UsageError{"--shutter and --fps need --time or --times"};
    const double fps = flags.count("--fps") ? parse_double("--fps", flags["--fps"]) : 24.0;
    std::string shutter_err;
    if (!rf::parse_shutter(flags.count("--shutter") ? flags["--shutter"] : "", fps, &shutter,
                           &shutter_err))
      throw UsageError{shutter_err.rfind("settings.", 0) == 0 ? "--" + shutter_err.substr(9)
                                                             : shutter_err};
  }
  const std::string& scene_path = positional[0];
  const std::string& out_pattern = flags["-o"];
  const bool sequence = !times.empty();
  if (times.empty()) times.push_back(load.time);
  if (sequence && out_pattern.find("{i}") == std::string::npos)
    throw UsageError{"--times needs '{i}' in -o (each time's image has its own file)"};
  auto out_path_of = [&](size_t i) {
    std::string path = out_pattern;
    char index[16];
    std::snprintf(index, sizeof index, "%04zu", i);
    for (size_t at; sequence && (at = path.find("{i}")) != std::string::npos;)
      path.replace(at, 3, index);
    return path;
  };
  // Checked before the render, not after it: a long render must not be lost to a typo.
  for (size_t i = 0; i < times.size(); ++i) check_output_path(out_path_of(i));
  const std::string err = rf::validate_render_request(
      settings, {0, 0, settings.width, settings.height}, 0, spp);
  if (!err.empty()) throw UsageError{err};

  // An animated scene is split once into its static part and what moves (animated_scene.h);
  // each time is a pose of it, as on a farm worker.
  load.image_height = settings.height;  // points and lines are one pixel wide
  std::vector<std::string> warnings;
  std::shared_ptr<const rf::Scene> scene;
  std::unique_ptr<rf::AnimatedScene> animated;
  const auto load_start = std::chrono::steady_clock::now();
  try {
    if (load.animated())
      animated = std::make_unique<rf::AnimatedScene>(rf::parse_gltf(scene_path, &warnings, load),
                                                     load, &warnings);
    else
      scene = rf::load_scene(scene_path, &warnings, load);
  } catch (const std::exception& e) {
    for (const auto& w : warnings) std::cerr << "warning: " << w << "\n";
    std::cerr << "error: " << e.what() << "\n";
    return kExitRuntime;
  }
  const double load_seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - load_start).count();
  for (const auto& w : warnings) std::cerr << "warning: " << w << "\n";
  if (flags.count("--environment")) {
    try {
      settings.environment =
          rf::Environment::load(flags["--environment"], env_intensity, env_rotation);
    } catch (const std::exception& e) {
      std::cerr << "error: " << e.what() << "\n";
      return kExitRuntime;
    }
  }
  nlohmann::json stats_json = {{"scene", scene_path},
                               {"load_s", load_seconds},
                               {"width", settings.width},
                               {"height", settings.height},
                               {"spp", spp},
                               {"threads", threads},
                               {"frames", nlohmann::json::array()}};
  if (animated) {
    stats_json["static_triangles"] = animated->static_part().world_triangle_count();
    stats_json["moving_nodes"] = animated->moving_nodes();
    stats_json["deformed_nodes"] = animated->deformed_nodes();
  }
  for (size_t i = 0; i < times.size(); ++i) {
    const std::string out_path = out_path_of(i);
    double update_seconds = 0.0;
    if (animated) {
      // The previous pose goes first: its deformed meshes are this pose's, refit.
      scene.reset();
      std::vector<std::string> pose_warnings;
      const auto pose_start = std::chrono::steady_clock::now();
      try {
        scene = animated->pose(times[i], &pose_warnings, shutter);
      } catch (const std::exception& e) {
        std::cerr << "error: " << e.what() << "\n";
        return kExitRuntime;
      }
      update_seconds =
          std::chrono::duration<double>(std::chrono::steady_clock::now() - pose_start).count();
      if (i == 0)
        for (const auto& w : pose_warnings) std::cerr << "warning: " << w << "\n";
    }
    std::cerr << "rendering " << scene_path;
    if (load.animated()) std::cerr << " at " << times[i] << " s";
    std::cerr << ": " << scene->world_triangle_count() << " triangles ("
              << rf::format_bytes(scene->memory_bytes()) << " in memory), "
              << scene->lights().size() << " emissive, " << settings.width << "x"
              << settings.height << ", " << spp << " spp, " << threads << " threads, "
              << rf::sampler_type_name(settings.sampler) << "/"
              << rf::integrator_type_name(settings.integrator) << ", Embree up to "
              << rf::isa_cap_name(rf::isa_cap()) << "\n";
    rf::RenderStats stats;
    int last_percent = -1;
    const rf::Image image =
        rf::render_image(*scene, settings, spp, threads, &stats, [&](size_t done, size_t total) {
          const int percent = int(100 * done / total);
          if (percent != last_percent) {
            last_percent = percent;
            std::fprintf(stderr, "\rprogress: %3d%%", percent);
            std::fflush(stderr);
          }
        });
    std::fprintf(stderr, "\n");
    try {
      rf::write_exr(out_path, image);
    } catch (const std::exception& e) {
      std::cerr << "error: " << e.what() << "\n";
      return kExitRuntime;
    }
    std::fprintf(stderr, "wrote %s in %.3f s: %.0f samples/s, %.2f Mrays/s", out_path.c_str(),
                 stats.seconds, double(stats.samples) / stats.seconds,
                 double(stats.rays) / stats.seconds * 1e-6);
    if (animated) std::fprintf(stderr, " (scene update %.4f s)", update_seconds);
    if (settings.guiding)
      std::fprintf(stderr, " (guide: %.3f s of it training on %llu paths, %u distributions)",
                   stats.guide.seconds, static_cast<unsigned long long>(stats.guide.paths),
                   stats.guide.distributions);
    if (stats.nonfinite_samples)
      std::fprintf(stderr, " (%llu non-finite samples recorded as 0)",
                   static_cast<unsigned long long>(stats.nonfinite_samples));
    std::fprintf(stderr, "\n");
    nlohmann::json frame = {{"index", i},
                            {"output", out_path},
                            {"update_s", update_seconds},
                            {"render_s", stats.seconds},
                            {"samples", stats.samples},
                            {"rays", stats.rays},
                            {"guide_s", stats.guide.seconds},
                            {"triangles", scene->world_triangle_count()}};
    if (load.animated()) frame["time"] = times[i];
    if (const rf::DeformedMeshes* d = scene->deformed_meshes()) {
      frame["refits"] = d->refits();
      frame["builds"] = d->builds();
    }
    stats_json["frames"].push_back(frame);
  }
  if (flags.count("--stats-json")) {
    std::ofstream out(flags["--stats-json"]);
    out << stats_json.dump(2) << "\n";
    if (!out) {
      std::cerr << "error: cannot write " << flags["--stats-json"] << "\n";
      return kExitRuntime;
    }
  }
  return 0;
}

// --max-* flags of inspect and connect onto the loader's limits.
void parse_limit_flags(std::map<std::string, std::string>& flags, rf::SceneLimits* limits) {
  if (flags.count("--max-nodes"))
    limits->max_nodes = parse_uint("--max-nodes", flags["--max-nodes"], 1, UINT64_MAX);
  if (flags.count("--max-depth"))
    limits->max_depth = uint32_t(parse_uint("--max-depth", flags["--max-depth"], 1, 1u << 20));
  if (flags.count("--max-triangles"))
    limits->max_instanced_triangles =
        parse_uint("--max-triangles", flags["--max-triangles"], 1, UINT64_MAX);
  if (flags.count("--max-texture-pixels"))
    limits->max_texture_pixels =
        parse_uint("--max-texture-pixels", flags["--max-texture-pixels"], 0, UINT64_MAX);
}

// Loads a scene exactly as a farm worker does (self-contained, within the limits: the loader,
// the textures' headers, the lights and the BVH) and describes it, or says why it is refused.
// The server runs it on every uploaded scene, under CPU-time and memory limits of its own, so
// that it accepts a scene only if the workers' loader does. Exit 0 if the scene loads, 1 if it
// is refused (with --json: {"ok": false, "error": ..., "path": ...} on stdout either way).
int cmd_inspect(const std::vector<std::string>& args) {
  std::vector<std::string> positional;
  std::vector<std::string> allowed = {"--name", "--max-nodes", "--max-depth", "--max-triangles",
                                      "--max-texture-pixels", "--max-memory-mb", "--bvh"};
  std::vector<std::string> rest;
  bool json = false;
  for (const std::string& a : args) {
    if (a == "--json") json = true;
    else rest.push_back(a);
  }
  auto flags = parse_flags(rest, allowed, &positional);
  if (positional.size() != 1) throw UsageError{"inspect expects exactly one scene file"};
  rf::LoadOptions options;
  options.allow_external_files = false;
  options.bvh = parse_bvh_flag(flags);
  parse_limit_flags(flags, &options.limits);
  if (flags.count("--max-memory-mb"))
    options.limits.max_memory_bytes =
        parse_uint("--max-memory-mb", flags["--max-memory-mb"], 1, UINT64_MAX / 1000000) *
        1000000;
  options.display_name = flags.count("--name")
                             ? flags["--name"]
                             : std::filesystem::path(positional[0]).filename().string();
  std::vector<std::string> warnings;
  nlohmann::json out;
  std::unique_ptr<rf::Scene> scene;
  try {
    scene = rf::load_scene(positional[0], &warnings, options);
  } catch (const rf::SceneError& e) {
    out = {{"ok", false}, {"error", e.what()}, {"path", e.path()}, {"warnings", warnings}};
  } catch (const std::bad_alloc&) {
    out = {{"ok", false}, {"error", options.display_name + ": out of memory while loading"},
           {"path", ""}, {"warnings", warnings}};
  }
  if (scene) {
    const rf::SceneStats& st = scene->stats();
    out = {{"ok", true},
           {"triangles", scene->world_triangle_count()},
           {"instanced_triangles", st.instanced_triangles},
           {"nodes", st.nodes},
           {"depth", st.depth},
           {"meshes", scene->mesh_count()},
           {"instances", scene->instance_count()},
           {"materials", scene->materials().size()},
           {"textures", scene->textures().size()},
           {"texture_pixels", st.texture_pixels},
           {"emissive_triangles", scene->lights().size()},
           {"camera", scene->has_file_camera()},
           {"memory_bytes", scene->memory_bytes()},
           {"estimated_memory_bytes", st.estimated_bytes},
           {"extensions_used", st.extensions_used},
           {"warnings", warnings}};
  }
  if (json) {
    std::cout << out.dump() << "\n";
  } else if (scene) {
    for (const auto& w : warnings) std::cerr << "warning: " << w << "\n";
    std::cout << options.display_name << ": " << scene->world_triangle_count() << " triangles ("
              << out["instanced_triangles"] << " over every mesh use), " << out["nodes"]
              << " nodes, depth " << out["depth"] << ", " << out["textures"] << " textures ("
              << out["texture_pixels"] << " pixels), "
              << rf::format_bytes(scene->memory_bytes()) << " in memory\n";
  } else {
    for (const auto& w : warnings) std::cerr << "warning: " << w << "\n";
    std::cerr << "error: " << out["error"].get<std::string>() << "\n";
  }
  return scene ? 0 : kExitRuntime;
}

// The posed scene as the loader flattens it, for tests and users checking an animation:
// every node's world matrix, the camera, the world mesh's vertices, the shared meshes and
// their instances, and where each mesh node's vertices are (PoseReport::Range). Exit 0, or 1
// if the scene is refused ({"ok": false, "error": ..., "path": ...}).
int cmd_pose(const std::vector<std::string>& arguments) {
  std::vector<std::string> args, positional;
  bool json = false;
  for (const std::string& a : arguments) {
    if (a == "--json") json = true;
    else args.push_back(a);
  }
  rf::LoadOptions options;
  take_animation_flags(&args, &options);
  parse_flags(args, {}, &positional);
  if (positional.size() != 1) throw UsageError{"pose expects exactly one scene file"};
  rf::PoseReport report;
  options.pose_report = &report;
  std::vector<std::string> warnings;
  nlohmann::json out;
  auto vec3 = [](rf::Vec3 v) { return nlohmann::json::array({v.x, v.y, v.z}); };
  auto mat4 = [](const rf::Mat4& m) {
    nlohmann::json a = nlohmann::json::array();
    for (int c = 0; c < 4; ++c)
      for (int r = 0; r < 4; ++r) a.push_back(m.m[size_t(c)][size_t(r)]);
    return a;
  };
  auto vertices = [&](const rf::TriangleMesh& mesh) {
    nlohmann::json positions = nlohmann::json::array(), normals = nlohmann::json::array();
    for (const rf::Vec3& p : mesh.positions) positions.push_back(vec3(p));
    for (const rf::Vec3& n : mesh.normals) normals.push_back(vec3(n));
    return nlohmann::json{{"positions", positions}, {"normals", normals}};
  };
  try {
    const rf::SceneDescription desc = rf::load_gltf(positional[0], &warnings, options);
    out = {{"ok", true}, {"warnings", warnings}};
    out["time"] = options.animated() ? nlohmann::json(options.time) : nlohmann::json();
    out["animations"] = options.animations;
    nlohmann::json nodes = nlohmann::json::array();
    for (size_t i = 0; i < report.node_world.size(); ++i)
      nodes.push_back({{"index", i}, {"world", mat4(report.node_world[i])}});
    out["nodes"] = nodes;
    if (desc.camera) {
      const rf::Camera& c = *desc.camera;
      out["camera"] = {{"node", report.camera_node},  {"position", vec3(c.position)},
                       {"forward", vec3(c.forward)}, {"up", vec3(c.up)},
                       {"right", vec3(c.right)}};
    } else {
      out["camera"] = nullptr;
    }
    out["world"] = vertices(desc.world);
    nlohmann::json meshes = nlohmann::json::array(), instances = nlohmann::json::array();
    for (const rf::Mesh& m : desc.meshes) {
      nlohmann::json mesh = vertices(m.geometry);
      mesh["name"] = m.name;
      meshes.push_back(mesh);
    }
    for (const rf::Instance& inst : desc.instances)
      instances.push_back({{"mesh_slot", inst.mesh}, {"to_world", mat4(inst.to_world)}});
    out["meshes"] = meshes;
    out["instances"] = instances;
    nlohmann::json ranges = nlohmann::json::array();
    for (const rf::PoseReport::Range& r : report.ranges) {
      auto or_null = [](int v) { return v >= 0 ? nlohmann::json(v) : nlohmann::json(); };
      ranges.push_back({{"node", r.node},
                        {"mesh", r.mesh},
                        {"first_vertex", r.first_vertex},
                        {"count", r.count},
                        {"instance", or_null(r.instance)},
                        {"mesh_slot", or_null(r.mesh_slot)},
                        {"skinned", r.skinned},
                        {"morphed", r.morphed}});
    }
    out["ranges"] = ranges;
  } catch (const rf::SceneError& e) {
    out = {{"ok", false}, {"error", e.what()}, {"path", e.path()}, {"warnings", warnings}};
  }
  std::cout << (json ? out.dump() : out.dump(2)) << "\n";
  return out["ok"].get<bool>() ? 0 : kExitRuntime;
}

// The camera every image of a job is rendered through, as the farm worker builds it: a still's
// from the scene as stored (load_scene), a frame's from the scene posed at its time by the
// animations the selection names (the farm worker's posed_scene_for); a scene without a camera
// gets the one that frames its bounds (Scene's), posed as the renderer poses it (with the
// shutter's steps). The server publishes it (camera.json, the EXR's worldToCamera). Exit 0, or 1
// if the scene is refused ({"ok": false, "error": ..., "path": ...}).
int cmd_camera(const std::vector<std::string>& arguments) {
  std::vector<std::string> args, positional;
  bool json = false;
  for (const std::string& a : arguments) {
    if (a == "--json") json = true;
    else args.push_back(a);
  }
  auto flags = parse_flags(args, {"--times", "--animations", "--shutter", "--fps"}, &positional);
  if (positional.size() != 1) throw UsageError{"camera expects exactly one scene file"};
  std::vector<double> times;
  if (flags.count("--times"))
    for (const std::string& item : split_commas(flags["--times"]))
      times.push_back(parse_double("--times", item));
  if (times.empty() && (flags.count("--animations") || flags.count("--shutter")))
    throw UsageError{"--animations and --shutter need --times"};
  rf::Shutter shutter;
  if (flags.count("--shutter") || flags.count("--fps")) {
    const double fps = flags.count("--fps") ? parse_double("--fps", flags["--fps"]) : 24.0;
    std::string err;
    if (!rf::parse_shutter(flags.count("--shutter") ? flags["--shutter"] : "", fps, &shutter,
                           &err))
      throw UsageError{err};
  }
  rf::LoadOptions load;
  load.allow_external_files = false;  // an upload, as the farm worker loads it
  load.display_name = std::filesystem::path(positional[0]).filename().string();
  std::vector<std::string> warnings;
  auto vec3 = [](rf::Vec3 v) { return nlohmann::json::array({v.x, v.y, v.z}); };
  auto describe = [&](const rf::Camera& c, int node, bool framing, nlohmann::json time) {
    return nlohmann::json{
        {"time", time},
        {"node", node >= 0 ? nlohmann::json(node) : nlohmann::json()},
        {"framing", framing},
        {"projection", c.orthographic ? "orthographic" : "perspective"},
        {"position", vec3(c.position)},
        {"right", vec3(c.right)},
        {"up", vec3(c.up)},
        {"forward", vec3(c.forward)},
        {"yfov", c.yfov},
        {"xmag", c.xmag},
        {"ymag", c.ymag},
        {"znear", c.znear},
        {"zfar", std::isfinite(c.zfar) ? nlohmann::json(c.zfar) : nlohmann::json()}};
  };
  nlohmann::json out;
  try {
    nlohmann::json cameras = nlohmann::json::array();
    if (times.empty()) {
      rf::PoseReport report;
      rf::LoadOptions options = load;
      options.pose_report = &report;
      const rf::SceneDescription desc = rf::load_gltf(positional[0], &warnings, options);
      if (desc.camera) {
        cameras.push_back(describe(*desc.camera, report.camera_node, false, nullptr));
      } else {  // the camera Scene frames the scene's bounds with
        const std::unique_ptr<rf::Scene> scene = rf::load_scene(positional[0], &warnings, load);
        cameras.push_back(describe(scene->camera(), -1, true, nullptr));
      }
    } else {
      std::shared_ptr<const rf::GltfDocument> document =
          rf::parse_gltf(positional[0], &warnings, load);
      try {
        load.animations = rf::resolve_animation_selection(
            flags.count("--animations") ? flags["--animations"] : "",
            rf::gltf_animation_names(*document));
      } catch (const rf::AnimationSelectionError& e) {
        throw UsageError{e.what()};
      }
      std::unique_ptr<rf::AnimatedScene> animated;  // built for a scene without a camera only
      for (double t : times) {
        rf::PoseReport report;
        rf::LoadOptions options = load;
        options.time = t;
        options.pose_report = &report;
        const rf::SceneDescription desc = rf::describe_gltf(*document, &warnings, options);
        if (desc.camera) {
          cameras.push_back(describe(*desc.camera, report.camera_node, false, t));
          continue;
        }
        if (!animated) {
          options.pose_report = nullptr;
          animated = std::make_unique<rf::AnimatedScene>(document, options, &warnings);
        }
        const std::shared_ptr<const rf::Scene> scene = animated->pose(t, &warnings, shutter);
        cameras.push_back(describe(scene->camera(), -1, true, t));
      }
    }
    out = {{"ok", true}, {"cameras", cameras}};
  } catch (const rf::SceneError& e) {
    out = {{"ok", false}, {"error", e.what()}, {"path", e.path()}};
  }
  // Each time's load repeats the scene's warnings: each once.
  std::vector<std::string> once;
  for (const std::string& w : warnings)
    if (std::find(once.begin(), once.end(), w) == once.end()) once.push_back(w);
  out["warnings"] = once;
  std::cout << (json ? out.dump() : out.dump(2)) << "\n";
  return out["ok"].get<bool>() ? 0 : kExitRuntime;
}

int cmd_bench(const std::vector<std::string>& args) {
  auto flags = parse_flags(args,
                           {"--cornell", "--json", "--width", "--height", "--spp", "--triangles",
                            "--threads", "--scenes"},
                           nullptr);
  rf::BenchOptions options;
  options.cornell_path = flags.count("--cornell") ? flags["--cornell"] : "";
  if (flags.count("--width")) options.width = uint32_t(parse_uint("--width", flags["--width"], 1, 8192));
  if (flags.count("--height"))
    options.height = uint32_t(parse_uint("--height", flags["--height"], 1, 8192));
  if (flags.count("--spp")) options.spp = uint32_t(parse_uint("--spp", flags["--spp"], 1, 65536));
  if (flags.count("--triangles"))
    options.mesh_triangles =
        uint32_t(parse_uint("--triangles", flags["--triangles"], 16, 100000000));
  if (flags.count("--threads")) {
    options.threads.clear();
    for (const std::string& item : split_commas(flags["--threads"]))
      options.threads.push_back(uint32_t(parse_uint("--threads", item, 1, 4096)));
  }
  if (flags.count("--scenes")) {
    options.cornell = options.mesh = options.instanced = false;
    for (const std::string& item : split_commas(flags["--scenes"])) {
      if (item == "cornell") {
        options.cornell = true;
      } else if (item == "mesh") {
        options.mesh = true;
      } else if (item == "instanced") {
        options.instanced = true;
      } else {
        throw UsageError{"--scenes takes a comma-separated list of cornell, mesh and "
                         "instanced, not '" + item + "'"};
      }
    }
  }
  if (options.cornell && options.cornell_path.empty())
    throw UsageError{"bench needs --cornell SCENE.gltf (or --scenes without cornell)"};
  const std::string json = rf::run_bench(options);
  if (flags.count("--json")) {
    std::ofstream out(flags["--json"]);
    out << json << "\n";
    if (!out) {
      std::cerr << "error: cannot write " << flags["--json"] << "\n";
      return kExitRuntime;
    }
  } else {
    std::cout << json << "\n";
  }
  return 0;
}

// The memory this process may use: the machine's, or less under a cgroup limit (a container's
// memory limit, v2 memory.max or v1 memory.limit_in_bytes). 0 if unknown.
size_t available_memory() {
  const long pages = sysconf(_SC_PHYS_PAGES), page_size = sysconf(_SC_PAGESIZE);
  size_t bytes = pages > 0 && page_size > 0 ? size_t(pages) * size_t(page_size) : 0;
  for (const char* path :
       {"/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory/memory.limit_in_bytes"}) {
    std::ifstream in(path);
    unsigned long long limit = 0;
    if (in >> limit && limit > 0 && (bytes == 0 || limit < bytes)) bytes = size_t(limit);
  }
  return bytes;
}

std::atomic<bool> g_stop{false};
extern "C" void on_stop_signal(int) { g_stop.store(true); }

int cmd_connect(const std::vector<std::string>& args) {
  std::vector<std::string> rest;
  bool tls = false;
  std::vector<std::string> tags;  // --tag is repeatable, so it is taken out before parse_flags
  for (size_t i = 0; i < args.size(); ++i) {
    const std::string& a = args[i];
    if (a == "--tls") {
      tls = true;
    } else if (a == "--tag") {
      if (i + 1 >= args.size()) throw UsageError{"flag '--tag' needs a value"};
      const std::string& tag = args[++i];
      // The server's rule (jobspec.TAG_PATTERN): 1..64 of a-z, 0-9, '.', '_', '-', starting
      // with a letter or digit.
      bool ok = !tag.empty() && tag.size() <= 64 && std::isalnum((unsigned char)tag[0]);
      for (char c : tag)
        ok = ok && ((c >= 'a' && c <= 'z') || (c >= '0' && c <= '9') || c == '.' || c == '_' ||
                    c == '-');
      if (!ok)
        throw UsageError{"--tag '" + tag +
                         "': 1 to 64 of a-z, 0-9, '.', '_', '-', starting with a letter or digit"};
      tags.push_back(tag);
    } else {
      rest.push_back(a);
    }
  }
  auto flags = parse_flags(
      rest,
      {"--server", "--threads", "--prefetch", "--result-interval-ms", "--cache-dir", "--token",
       "--id", "--bvh", "--scene-memory-mb", "--task-timeout-s", "--max-scene-memory-mb",
       "--ca-file", "--cert", "--key", "--tls-server-name", "--max-nodes", "--max-depth",
       "--max-triangles", "--max-texture-pixels"},
      nullptr);
  if (!flags.count("--server") || flags["--server"].empty())
    throw UsageError{"connect needs --server HOST:PORT (several: A:PORT,B:PORT)"};
  rf::FarmOptions options;
  options.server = flags["--server"];
  options.tags = tags;
  options.threads = default_threads();
  if (flags.count("--threads"))
    options.threads = uint32_t(parse_uint("--threads", flags["--threads"], 1, 4096));
  if (flags.count("--prefetch"))
    options.prefetch = uint32_t(parse_uint("--prefetch", flags["--prefetch"], 0, 4096));
  if (flags.count("--result-interval-ms"))
    options.result_interval_ms =
        uint32_t(parse_uint("--result-interval-ms", flags["--result-interval-ms"], 0, 10000));
  options.cache_dir =
      flags.count("--cache-dir") ? flags["--cache-dir"] : rf::default_scene_cache_dir();
  if (flags.count("--token")) options.token = flags["--token"];
  options.bvh = parse_bvh_flag(flags);
  // Loaded scenes kept in memory between tasks: half the worker's memory unless told.
  options.scene_memory_budget =
      flags.count("--scene-memory-mb")
          ? size_t(parse_uint("--scene-memory-mb", flags["--scene-memory-mb"], 1, 1u << 30)) *
                1000000
          : available_memory() / 2;
  // Textures read into memory for their lookups: at most a quarter of the worker's memory,
  // and 2 GiB; beyond, they are paged through OpenImageIO's tile cache (scene/textures.h).
  if (const size_t memory = available_memory())
    rf::TextureSet::set_texel_budget(std::min(memory / 4, size_t(2) << 30));
  // A task that renders longer than this fails for good (a scene that costs this much per
  // batch is broken or hostile); its render stops at once.
  if (flags.count("--task-timeout-s"))
    options.task_timeout_s = double(parse_uint("--task-timeout-s", flags["--task-timeout-s"], 1,
                                               7 * 24 * 3600));
  // A scene whose estimated memory exceeds this is refused for good before it is allocated:
  // by default, the memory this worker has.
  options.limits.max_memory_bytes =
      flags.count("--max-scene-memory-mb")
          ? parse_uint("--max-scene-memory-mb", flags["--max-scene-memory-mb"], 1,
                       UINT64_MAX / 1000000) *
                1000000
          : available_memory();
  parse_limit_flags(flags, &options.limits);
  // TLS: --ca-file, --cert/--key and --tls-server-name imply --tls.
  auto read_pem = [&](const char* flag) {
    const std::string& path = flags[flag];
    std::ifstream in(path, std::ios::binary);
    if (!in) throw UsageError{std::string(flag) + " " + path + ": cannot read the file"};
    std::string text((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
    if (text.find("-----BEGIN ") == std::string::npos)
      throw UsageError{std::string(flag) + " " + path + ": not a PEM file"};
    return text;
  };
  if (flags.count("--cert") != flags.count("--key"))
    throw UsageError{"--cert and --key go together (the client certificate of mutual TLS)"};
  options.tls = tls || flags.count("--ca-file") || flags.count("--cert") ||
                flags.count("--tls-server-name");
  if (flags.count("--ca-file")) options.tls_ca_pem = read_pem("--ca-file");
  if (flags.count("--cert")) {
    options.tls_cert_pem = read_pem("--cert");
    options.tls_key_pem = read_pem("--key");
  }
  if (flags.count("--tls-server-name")) options.tls_server_name = flags["--tls-server-name"];
  char host[256] = {0};
  if (gethostname(host, sizeof(host) - 1) != 0) std::snprintf(host, sizeof(host), "unknown");
  options.hostname = host;
  options.worker_id = flags.count("--id") ? flags["--id"]
                                          : options.hostname + "-" + std::to_string(getpid());
  // The instruction set every worker of a farm should share for the same bits (util/isa.h).
  std::cerr << "renderfarm-worker: Embree's kernels up to " << rf::isa_cap_name(rf::isa_cap())
            << " (RENDERFARM_ISA)\n";
  struct sigaction sa = {};
  sa.sa_handler = on_stop_signal;
  sigemptyset(&sa.sa_mask);
  sigaction(SIGINT, &sa, nullptr);
  sigaction(SIGTERM, &sa, nullptr);
  return rf::run_farm_client(options, g_stop);
}

}  // namespace

int main(int argc, char** argv) {
  std::vector<std::string> args(argv + 1, argv + argc);
  try {
    if (args.empty()) throw UsageError{"missing command"};
    const std::string cmd = args[0];
    args.erase(args.begin());
    if (cmd == "--help" || cmd == "-h" || cmd == "help") {
      std::cout << kUsage;
      return 0;
    }
    if (cmd == "--version") {
      std::cout << "renderfarm-worker " << RENDERFARM_VERSION << "\n";
      return 0;
    }
    // RENDERFARM_ISA (util/isa.h) checked before any work: a bad value fails at start.
    rf::isa_cap();
    if (cmd == "render") return cmd_render(args);
    if (cmd == "connect") return cmd_connect(args);
    if (cmd == "bench") return cmd_bench(args);
    if (cmd == "inspect") return cmd_inspect(args);
    if (cmd == "pose") return cmd_pose(args);
    if (cmd == "camera") return cmd_camera(args);
    throw UsageError{"unknown command '" + cmd + "'"};
  } catch (const UsageError& e) {
    std::cerr << "renderfarm-worker: " << e.message << " (see renderfarm-worker --help)\n";
    return kExitUsage;
  } catch (const std::exception& e) {
    std::cerr << "renderfarm-worker: error: " << e.what() << "\n";
    return kExitRuntime;
  }
}
