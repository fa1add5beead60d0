#include "render/guiding.h"

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <limits>
#include <thread>

#include "render/packet_tracer.h"
#include "scene/materials.h"

namespace rf {

namespace {
constexpr float kOneBelow = 0x1.fffffep-1f;  // the largest float below 1

// Splits u in [0, 1) at p (the probability of the low side): which side, and u rescaled to
// [0, 1) within it.
inline bool split_low(float* u, float p) {
  if (*u < p) {
    *u = std::min(*u / p, kOneBelow);
    return true;
  }
  *u = std::min((*u - p) / (1.f - p), kOneBelow);
  return false;
}

}  // namespace

Point2 guide_square(Vec3 d) {
  const Point2 s = invert_uniform_sphere(d);
  return {std::clamp(s.x, 0.f, kOneBelow), std::clamp(s.y, 0.f, kOneBelow)};
}

float guide_fraction(const BsdfLobes& l) {
  if (l.glass > 0.f) return 0.f;  // sampled-only lobes: no density to mix with
  // The diffuse part: the base's share of the layers times the diffuse lobe's of the base.
  return (1.f - l.spec) * (l.layered ? l.base_pick : 1.f);
}

GuideField::GuideField(Vec3 lo, Vec3 hi, std::vector<GuideRecord>* records) {
  // Slightly larger than the box, so that points on its faces fall inside.
  const Vec3 pad = (hi - lo) * 1e-3f + Vec3(1e-4f, 1e-4f, 1e-4f);
  spatial_.resize(1);
  build_spatial(0, records->data(), records->data() + records->size(), lo - pad, hi + pad, 0);
}

void GuideField::build_spatial(uint32_t index, GuideRecord* first, GuideRecord* last, Vec3 lo,
                               Vec3 hi, int depth) {
  const size_t count = size_t(last - first);
  const Vec3 extent = hi - lo;
  const int axis =
      extent.x >= extent.y && extent.x >= extent.z ? 0 : (extent.y >= extent.z ? 1 : 2);
  if (count <= kMaxLeafRecords || depth >= 40 || !(extent[axis] > 1e-6f)) {
    ++leaves_;
    const uint32_t dist = build_distribution(first, last);
    spatial_[index] = {0.f, 3u, dist};
    return;
  }
  const float split = lo[axis] + extent[axis] * 0.5f;
  GuideRecord* middle =
      std::partition(first, last, [&](const GuideRecord& r) { return r.p[axis] < split; });
  Vec3 left_hi = hi, right_lo = lo;
  left_hi[axis] = split;
  right_lo[axis] = split;
  const uint32_t child = uint32_t(spatial_.size());
  spatial_.resize(spatial_.size() + 2);  // the two children, next to each other
  spatial_[index] = {split, uint32_t(axis), child};
  build_spatial(child, first, middle, lo, left_hi, depth + 1);
  build_spatial(child + 1, middle, last, right_lo, hi, depth + 1);
}

uint32_t GuideField::build_distribution(GuideRecord* first, GuideRecord* last) {
  std::vector<QuadRecord> quad;
  quad.reserve(size_t(last - first));
  double energy = 0.0;
  uint32_t lit = 0;
  for (const GuideRecord* r = first; r != last; ++r) {
    if (!(r->value > 0.f) || !std::isfinite(r->value)) continue;
    const Point2 s = guide_square(r->d);
    quad.push_back({s.x, s.y, r->value});
    energy += r->value;
    ++lit;
  }
  if (lit < kMinLitRecords || !(energy > 0.0) || !std::isfinite(energy)) return kNone;
  // The uniform share: a density over the square added to every cell, so that the learned
  // part is (1 - kUniformShare) of the total.
  const float total = float(energy / (1.0 - double(kUniformShare)));
  const float floor_density = total * kUniformShare;  // per unit area of the square
  const uint32_t root = build_quad(quad.data(), quad.data() + quad.size(), 0, floor_density,
                                   float(energy) * kSplitFraction);
  roots_.push_back(root);
  const uint32_t dist = uint32_t(roots_.size() - 1);
  // The guide's share here: the one of kShares whose mixture alpha p_guide + (1 - alpha) p_bsdf
  // has the smallest second moment of L cos / density over this leaf's records, estimated
  // from the densities they were sampled with (importance reweighting:
  // E_s[(L cos)^2 / (p_s q)] is the second moment under q of samples drawn from p_s). Where
  // the light is smooth (a sky over an open surface) the BSDF alone does best and the leaf
  // does not guide; where it comes from a small part of the sphere the guide's share grows.
  double moment[kShareCount] = {};
  for (const GuideRecord* r = first; r != last; ++r) {
    if (!(r->value > 0.f) || !std::isfinite(r->value) || !(r->pdf > 0.f)) continue;
    const double g = double(pdf(dist, r->d)), b = double(r->bsdf_pdf);
    const double v2p = double(r->value) * double(r->value) * double(r->pdf);
    for (int k = 0; k < kShareCount; ++k) {
      const double alpha = kShares[k];
      const double q = alpha * g + (1.0 - alpha) * b;
      moment[k] += q > 0.0 ? v2p / q : std::numeric_limits<double>::infinity();
    }
  }
  int best = 0;
  for (int k = 1; k < kShareCount; ++k)
    if (moment[k] < moment[best] * kShareMargin) best = k;
  if (best == 0) {
    roots_.pop_back();
    return kNone;
  }
  shares_.push_back(kShares[best]);
  return dist;
}

uint32_t GuideField::build_quad(QuadRecord* first, QuadRecord* last, int depth,
                                float floor_density, float split_energy) {
  const uint32_t index = uint32_t(quads_.size());
  quads_.emplace_back();
  // The node's square has area 4^-depth; each quadrant a quarter of it.
  const float quadrant_area = std::ldexp(1.f, -2 * (depth + 1));
  QuadRecord* begin[5];
  begin[0] = first;
  // Partition by quadrant q = (x >= 0.5) + 2 (y >= 0.5), in that order.
  QuadRecord* bottom_end =
      std::partition(first, last, [](const QuadRecord& r) { return r.y < 0.5f; });
  begin[1] = std::partition(first, bottom_end, [](const QuadRecord& r) { return r.x < 0.5f; });
  begin[2] = bottom_end;
  begin[3] = std::partition(bottom_end, last, [](const QuadRecord& r) { return r.x < 0.5f; });
  begin[4] = last;
  for (int q = 0; q < 4; ++q) {
    float energy = 0.f;
    for (QuadRecord* r = begin[q]; r != begin[q + 1]; ++r) energy += r->value;
    quads_[index].sum[q] = energy + floor_density * quadrant_area;
    if (energy > split_energy && depth + 1 < kMaxQuadDepth &&
        begin[q + 1] - begin[q] > kMinSplitRecords) {
      // Into the quadrant's own coordinates.
      const float ox = float(q & 1) * 0.5f, oy = float(q >> 1) * 0.5f;
      for (QuadRecord* r = begin[q]; r != begin[q + 1]; ++r) {
        r->x = std::min((r->x - ox) * 2.f, kOneBelow);
        r->y = std::min((r->y - oy) * 2.f, kOneBelow);
      }
      const uint32_t child = build_quad(begin[q], begin[q + 1], depth + 1, floor_density,
                                        split_energy);
      quads_[index].child[q] = child;
    }
  }
  return index;
}

uint32_t GuideField::distribution_at(Vec3 p) const {
  if (spatial_.empty()) return kNone;
  uint32_t i = 0;
  while (spatial_[i].axis != 3)
    i = spatial_[i].child + (p[int(spatial_[i].axis)] < spatial_[i].split ? 0u : 1u);
  return spatial_[i].child;
}

Vec3 GuideField::sample(uint32_t dist, Point2 u, float* pdf) const {
  uint32_t node = roots_[dist];
  float density = 1.f;  // on the square
  float ox = 0.f, oy = 0.f, size = 1.f;
  for (;;) {
    const QuadNode& n = quads_[node];
    const float left = n.sum[0] + n.sum[2], right = n.sum[1] + n.sum[3];
    const float total = left + right;
    const bool low_x = split_low(&u.x, left / total);
    const float bottom = low_x ? n.sum[0] : n.sum[1], top = low_x ? n.sum[2] : n.sum[3];
    const bool low_y = split_low(&u.y, bottom / (bottom + top));
    const int q = (low_x ? 0 : 1) + (low_y ? 0 : 2);
    density *= 4.f * n.sum[q] / total;
    size *= 0.5f;
    ox += low_x ? 0.f : size;
    oy += low_y ? 0.f : size;
    if (!n.child[q]) break;
    node = n.child[q];
  }
  *pdf = density * (0.25f / kPi);
  return sample_uniform_sphere({std::min(ox + u.x * size, kOneBelow),
                                std::min(oy + u.y * size, kOneBelow)});
}

float GuideField::pdf(uint32_t dist, Vec3 d) const {
  Point2 s = guide_square(d);
  uint32_t node = roots_[dist];
  float density = 1.f;
  for (;;) {
    const QuadNode& n = quads_[node];
    const int q = (s.x < 0.5f ? 0 : 1) + (s.y < 0.5f ? 0 : 2);
    const float total = n.sum[0] + n.sum[1] + n.sum[2] + n.sum[3];
    density *= 4.f * n.sum[q] / total;
    if (!n.child[q]) break;
    s.x = std::min((s.x - float(q & 1) * 0.5f) * 2.f, kOneBelow);
    s.y = std::min((s.y - float(q >> 1) * 0.5f) * 2.f, kOneBelow);
    node = n.child[q];
  }
  return density * (0.25f / kPi);
}

namespace {

// The training pixels: every stride-th pixel in x and y (the first pixel of each stride x
// stride block), so that width * height / stride^2 * spp <= kMaxPaths.
uint32_t training_stride(const RenderSettings& settings) {
  const double paths = double(settings.width) * settings.height *
                       GuideTraining::kSamplesPerPixel;
  uint32_t stride = 1;
  while (paths / (double(stride) * stride) > double(GuideTraining::kMaxPaths)) ++stride;
  return stride;
}

// One iteration: the training paths of every row of training pixels, traced with `threads`
// threads, each row's records in their own vector, then concatenated in row order.
std::vector<GuideRecord> trace_training(const Scene& scene, const RenderSettings& settings,
                                        uint32_t iteration, uint32_t threads, uint64_t* paths) {
  const uint32_t stride = training_stride(settings);
  const uint32_t columns = (settings.width + stride - 1) / stride;
  const uint32_t rows = (settings.height + stride - 1) / stride;
  const uint32_t spp = GuideTraining::kSamplesPerPixel;
  // A sample stream of its own: the training's samples are independent of the render's.
  const Sampler sampler(settings.sampler, hash4(settings.seed, 0x67756964ull, iteration, 0));
  const TraceContext ctx(scene, settings);
  std::vector<std::vector<GuideRecord>> per_row(rows);
  std::atomic<uint32_t> next{0};
  auto work = [&]() {
    SampleResult out[kPacketSize];
    for (;;) {
      const uint32_t row = next.fetch_add(1);
      if (row >= rows) return;
      const uint32_t y = row * stride;
      for (uint32_t c = 0; c < columns; ++c) {
        const uint32_t x = c * stride;
        const PixelSampler pixel(sampler, uint64_t(y) * settings.width + x);
        for (uint32_t first = 0; first < spp; first += kPacketSize)
          trace_samples(ctx, scene, settings, pixel, x, y, first,
                        std::min<uint32_t>(kPacketSize, spp - first), out, nullptr, nullptr,
                        nullptr, &per_row[row]);
      }
    }
  };
  std::vector<std::thread> pool;
  for (uint32_t i = 1; i < std::max(1u, threads); ++i) pool.emplace_back(work);
  work();
  for (std::thread& t : pool) t.join();
  size_t total = 0;
  for (const auto& r : per_row) total += r.size();
  std::vector<GuideRecord> records;
  records.reserve(total);
  for (auto& r : per_row) records.insert(records.end(), r.begin(), r.end());
  *paths += uint64_t(rows) * columns * spp;
  return records;
}

}  // namespace

std::shared_ptr<const GuideField> train_guide(const Scene& scene, const RenderSettings& settings,
                                              uint32_t threads, GuideStats* stats) {
  if (settings.integrator == IntegratorType::AmbientOcclusion) return nullptr;
  const auto t0 = std::chrono::steady_clock::now();
  RenderSettings training = settings;
  std::shared_ptr<const GuideField> field;
  uint64_t paths = 0, records_total = 0;
  for (uint32_t it = 0; it < GuideTraining::kIterations; ++it) {
    training.guide = field;  // the iteration before's field guides this one's paths
    std::vector<GuideRecord> records = trace_training(scene, training, it, threads, &paths);
    records_total += records.size();
    field = std::make_shared<const GuideField>(scene.bounds_min(), scene.bounds_max(), &records);
  }
  if (stats) {
    stats->seconds =
        std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    stats->paths = paths;
    stats->records = records_total;
    stats->distributions = field->distributions();
    stats->spatial_leaves = field->spatial_leaves();
    stats->quad_nodes = field->quad_nodes();
  }
  return field;
}

}  // namespace rf
