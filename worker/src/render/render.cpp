#include "render/render.h"

#include <atomic>
#include <chrono>
#include <mutex>
#include <thread>
#include <vector>

#include "render/channels.h"
#include "render/guiding.h"

namespace rf {

Image render_image(const Scene& scene, const RenderSettings& given, uint32_t spp,
                   uint32_t threads, RenderStats* stats,
                   const std::function<void(size_t, size_t)>& progress) {
  const auto t0 = std::chrono::steady_clock::now();
  RenderSettings settings = given;
  GuideStats guide_stats;
  if (settings.guiding && !settings.guide)
    settings.guide = train_guide(scene, settings, threads, &guide_stats);
  Image image(settings.width, settings.height);
  std::vector<PixelRect> tiles;
  for (uint32_t y = 0; y < settings.height; y += kTileSize)
    for (uint32_t x = 0; x < settings.width; x += kTileSize)
      tiles.push_back({x, y, std::min(kTileSize, settings.width - x),
                       std::min(kTileSize, settings.height - y)});
  std::atomic<size_t> next{0};
  std::atomic<uint64_t> rays{0}, nonfinite{0};
  std::mutex progress_mutex;
  size_t done = 0;
  auto worker = [&]() {
    TileBuffer buffer;
    for (;;) {
      const size_t t = next.fetch_add(1);
      if (t >= tiles.size()) return;
      render_rect(scene, settings, tiles[t], 0, spp, &buffer, nullptr, channels::kImageRows);
      image.set_from_tile(buffer);  // tiles are disjoint: no lock needed
      rays += buffer.rays;
      nonfinite += buffer.nonfinite_samples;
      std::lock_guard<std::mutex> lock(progress_mutex);
      ++done;
      if (progress) progress(done, tiles.size());
    }
  };
  std::vector<std::thread> pool;
  for (uint32_t i = 1; i < std::max(1u, threads); ++i) pool.emplace_back(worker);
  worker();  // the calling thread works too
  for (auto& th : pool) th.join();
  if (stats) {
    stats->seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    stats->rays = rays;
    stats->samples = uint64_t(settings.width) * settings.height * spp;
    stats->nonfinite_samples = nonfinite;
    stats->guide = guide_stats;
  }
  return image;
}

}  // namespace rf
