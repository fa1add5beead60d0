// render_rect: a tile's samples traced pixel by pixel and accumulated into a TileBuffer.
#include <algorithm>
#include <optional>
#include <vector>

#include "math/estimators.h"
#include "render/channels.h"
#include "render/light_groups.h"
#include "render/packet_tracer.h"

namespace rf {

bool render_rect(const Scene& scene, const RenderSettings& settings, PixelRect rect,
                 uint64_t start, uint32_t count, TileBuffer* out,
                 const std::atomic<bool>* cancel, uint32_t rows,
                 const MotionPoses* motion, const uint8_t* active) {
  // The light groups: traced (PathGroups, packet_tracer.h) only when their row is asked for
  // and the settings have groups (without them the row is not rendered); each sample's
  // radiance by group lands here, kPacketSize samples at a time like the results, and is
  // summed per pixel in float32 in sample order like the other rows.
  std::optional<LightGroupMap> groups;
  if ((rows & channels::bit(channels::Id::LightGroups)) && settings.light_groups &&
      settings.light_groups->count() > 0)
    groups.emplace(scene, *settings.light_groups);
  else
    rows &= ~channels::bit(channels::Id::LightGroups);
  const uint32_t n_groups = groups ? groups->count() : 0u;
  std::vector<Vec3> group_values(size_t(kPacketSize) * n_groups);
  std::vector<float> group_acc(3 * size_t(n_groups));
  out->reset(rect, start, count, rows, n_groups);
  const Sampler sampler(settings.sampler, settings.seed);
  const TraceContext ctx(scene, settings);
  // The rows summed in float32 (channels::sample_values) and where each one's sums start in a
  // pixel's accumulator.
  channels::Id summed[channels::kCount];
  uint32_t offset[channels::kCount + 1] = {0};
  uint32_t n_summed = 0;
  for (const channels::Spec& s : channels::kSpecs)
    if ((rows & channels::bit(s.id)) && channels::summed_in_float(s.id)) {
      summed[n_summed] = s.id;
      offset[n_summed + 1] = offset[n_summed] + s.components;
      ++n_summed;
    }
  // The ranked rows asked for (Cryptomatte): each pixel's labels counted in a RankedCounts on
  // the stack (132 bytes a row, reused pixel after pixel), in sample order, then its largest
  // counts written out. When none is asked for, a sample costs one comparison of
  // n_ranked = 0 more.
  constexpr uint32_t kMaxRanked = [] {
    uint32_t n = 0;
    for (const channels::Spec& s : channels::kSpecs) n += s.ranked ? 1u : 0u;
    return n;
  }();
  channels::Id ranked[kMaxRanked > 0 ? kMaxRanked : 1];
  uint32_t n_ranked = 0;
  for (const channels::Spec& s : channels::kSpecs)
    if ((rows & channels::bit(s.id)) && s.ranked) ranked[n_ranked++] = s.id;
  // The lobe rows: traced (PathLobes, packet_tracer.h) only when one of them is asked for; the
  // samples' values land here, kPacketSize at a time like the results.
  const bool lobes = (rows & channels::kLobes) != 0;
  LobeValues lobe_values[kPacketSize];
  for (uint32_t ty = 0; ty < rect.height; ++ty) {
    for (uint32_t tx = 0; tx < rect.width; ++tx) {
      // Checked every pixel, so that a cancel (or the worker's time budget) stops even a
      // render whose pixels are very costly within a second.
      if (cancel && cancel->load(std::memory_order_relaxed)) return false;
      const size_t i = size_t(ty) * rect.width + tx;
      // A pixel adaptive sampling has stopped: its values stay the reset's zeros.
      if (active && !((active[i / 8] >> (i % 8)) & 1u)) continue;
      double sum[3] = {0.0, 0.0, 0.0};
      RunningStats luminance_stats;
      float acc[channels::kCount * channels::kMaxComponents] = {};
      float depth = 0.f;
      channels::RankedCounts counts[kMaxRanked > 0 ? kMaxRanked : 1];  // empty
      const PixelSampler pixel_sampler(sampler, uint64_t(rect.y0 + ty) * settings.width +
                                                    (rect.x0 + tx));
      SampleResult results[kPacketSize];
      std::fill(group_acc.begin(), group_acc.end(), 0.f);
      for (uint32_t k = 0; k < count; ++k) {
        // The pixel's samples go through the path tracer kPacketSize at a time.
        const uint32_t lane = k % kPacketSize;
        if (lane == 0)
          trace_samples(ctx, scene, settings, pixel_sampler, rect.x0 + tx, rect.y0 + ty,
                        uint32_t(start + k), std::min<uint32_t>(kPacketSize, count - k), results,
                        lobes ? lobe_values : nullptr, groups ? &*groups : nullptr,
                        group_values.data());
        const SampleResult& r = results[lane];
        out->rays += r.rays;
        Vec3 L = r.radiance;
        const LobeValues* lobe = lobes ? &lobe_values[lane] : nullptr;
        const Vec3* by_group = groups ? &group_values[size_t(lane) * n_groups] : nullptr;
        if (!is_finite(L)) {
          L = Vec3(0.f, 0.f, 0.f);  // counted, recorded as zero radiance
          lobe = nullptr;           // and zero in every lobe row, which sum to it
          by_group = nullptr;       // and in every light group
          ++out->nonfinite_samples;
        }
        if (by_group)
          for (uint32_t g = 0; g < n_groups; ++g)
            for (int c = 0; c < 3; ++c) group_acc[3 * g + uint32_t(c)] += by_group[g][c];
        for (int c = 0; c < 3; ++c) sum[c] += double(L[c]);
        for (uint32_t j = 0; j < n_summed; ++j) {
          float v[channels::kMaxComponents];
          channels::sample_values(summed[j], r, v, motion, lobe);
          for (uint32_t c = 0; c < offset[j + 1] - offset[j]; ++c) acc[offset[j] + c] += v[c];
        }
        for (uint32_t j = 0; j < n_ranked; ++j)
          counts[j].add(channels::sample_label(ranked[j], r));
        depth += r.depth;
        // Welford's update of the luminance mean and M2.
        luminance_stats.add(0.2126 * double(L.x) + 0.7152 * double(L.y) + 0.0722 * double(L.z));
      }
      for (int c = 0; c < 3; ++c) out->rgb_sum[3 * i + size_t(c)] = sum[c];
      for (uint32_t j = 0; j < n_summed; ++j) {
        const uint32_t components = offset[j + 1] - offset[j];
        float* plane = out->sum(summed[j]).data() + components * i;
        for (uint32_t c = 0; c < components; ++c) plane[c] = acc[offset[j] + c];
      }
      for (uint32_t j = 0; j < n_ranked; ++j)
        counts[j].emit(out->ranked(ranked[j]).data() + 2 * channels::kRanks * i);
      if (groups)
        std::copy(group_acc.begin(), group_acc.end(),
                  out->sum(channels::Id::LightGroups).begin() + group_acc.size() * i);
      out->luminance_m2[i] = luminance_stats.m2;
      out->depth_sum[i] = depth;
    }
  }
  return true;
}

}  // namespace rf
