// Path guiding (settings.guiding): a learned distribution of the light arriving at surfaces,
// sampled beside the BSDF where paths scatter diffusely, so that the directions that carry
// light found only indirectly (caustics through glass, light bounced off a bright wall, a sky
// seen through a window) are tried more often than the BSDF alone would.
//
// What is learned: after Mueller, Gross and Novak 2017 ("Practical path guiding"), a spatial
// binary tree over the scene whose leaves each hold a quadtree over directions (the sphere
// mapped to the unit square by the cylindrical equal-area map), each node storing the incident
// radiance that training paths brought from its directions, as the Monte Carlo estimate
// L / pdf of each direction's sample. Sampling descends the quadtree in proportion to those
// sums; the density is piecewise constant on the square.
//
// How it stays unbiased: at a guided vertex the direction comes from the guide with
// probability alpha and from the BSDF otherwise (one-sample MIS: the estimate divides by
// alpha p_guide + (1 - alpha) p_bsdf, which covers the BSDF's support whatever was learned),
// and the light sample's MIS weight uses the same mixed density. The guide only changes which
// directions are tried, never what a path's estimate converges to. The choice splits the
// direction pair's first coordinate at alpha (each side rescaled), so that the sampler's
// stratification of the pair serves both strategies: choosing by another dimension dealt the
// stratified points to them at random, and made a sky-lit product shot noisier.
//
// Where it guides: each leaf takes the share alpha (GuideField::kShares, 0 among them) that
// its own training records say gives the smallest second moment, and only a vertex's diffuse
// part is guided (guide_fraction). Where the BSDF alone does best (smooth light, a uniform sky)
// nothing changes.
//
// How it stays a pure function of scene, settings and seed: the training paths are a fixed set
// (train_guide: the image's pixels, or a fixed stride of them, at a fixed number of samples,
// on a sample stream of its own derived from the seed), their records are gathered per row of
// pixels and inserted in row order, so every worker, whatever its thread count, builds the
// same field bit for bit and renders the same image.
#pragma once

#include <cstdint>
#include <memory>
#include <vector>

#include "math/vecmath.h"
#include "sampling/sampling.h"

namespace rf {

class Scene;
struct RenderSettings;
struct BsdfLobes;

// One training vertex: a path left surface point p in the unit direction d, which it had
// sampled with solid-angle density pdf; value is the radiance that came back along d (the mean
// of its channels) times |cos| to the vertex's geometric normal, divided by pdf: the estimate
// of the integral of the cosine-weighted incident radiance that the quadtree sums. A leaf's
// points mostly share one surface's normal, so the distribution follows L cos, the diffuse
// part of the integrand, and spends no samples on grazing light the cosine cancels.
struct GuideRecord {
  Vec3 p, d;
  float value = 0.f;
  // The solid-angle density d was sampled with, and the BSDF's own density of d (the same
  // unless the training path was guided): what the choice of a leaf's share weighs by.
  float pdf = 0.f, bsdf_pdf = 0.f;
};

// The learned field: immutable once built, shared by every thread of a render.
class GuideField {
 public:
  static constexpr uint32_t kNone = ~0u;
  // A spatial leaf splits while it holds more than this many records.
  static constexpr uint32_t kMaxLeafRecords = 4000;
  // A leaf guides only with at least this many records that brought light.
  static constexpr uint32_t kMinLitRecords = 16;
  // A quadtree cell splits while it holds more than this fraction of its leaf's energy and
  // more than kMinSplitRecords records, down to depth kMaxQuadDepth (cells 1/2^depth of the
  // square's edge, about 3.6 degrees at 6). Deeper or from fewer records, the cells follow
  // single bright training paths rather than where the light comes from: measured on the
  // realistic suite, depth 10 from any 2 records made the guided images noisier than the
  // unguided ones (docs/parity.md).
  static constexpr float kSplitFraction = 0.01f;
  static constexpr int kMinSplitRecords = 32;
  static constexpr int kMaxQuadDepth = 6;
  // The share of a leaf's density spread uniformly over the sphere, so that no direction has
  // density 0 where the training found nothing.
  static constexpr float kUniformShare = 0.05f;

  // Builds the field of records (reordered in place); the spatial tree starts from the box
  // [lo, hi]. Deterministic: the same records in the same order give the same field.
  GuideField(Vec3 lo, Vec3 hi, std::vector<GuideRecord>* records);

  // The guide's shares a leaf may take (the probability alpha of sampling the guide at a
  // vertex whose lobes are all guided; 0: the leaf does not guide), the first the BSDF alone,
  // and the factor by which another's estimated second moment must beat the best before it
  // (so that noise in the estimate does not turn guiding on where it saves nothing).
  static constexpr int kShareCount = 4;
  static constexpr float kShares[kShareCount] = {0.f, 0.25f, 0.5f, 0.75f};
  static constexpr double kShareMargin = 0.95;

  // The distribution that guides at point p, or kNone where nothing was learned or the BSDF
  // alone does better.
  uint32_t distribution_at(Vec3 p) const;
  // The guide's share alpha at distribution `dist` (for a vertex whose lobes are all guided).
  float share(uint32_t dist) const { return shares_[dist]; }
  // A direction of distribution `dist` from u in [0, 1)^2, and its solid-angle density.
  Vec3 sample(uint32_t dist, Point2 u, float* pdf) const;
  // The solid-angle density of unit direction d in distribution `dist`.
  float pdf(uint32_t dist, Vec3 d) const;

  uint32_t distributions() const { return uint32_t(roots_.size()); }
  uint32_t spatial_leaves() const { return leaves_; }
  uint32_t quad_nodes() const { return uint32_t(quads_.size()); }

 private:
  struct SpatialNode {
    float split = 0.f;
    uint32_t axis = 3;   // 0..2: inner node (children child, child + 1); 3: leaf
    uint32_t child = 0;  // leaf: its distribution (kNone: none)
  };
  // Quadrant q of a node: x half (q & 1), y half (q >> 1); child 0: the quadrant is a leaf.
  struct QuadNode {
    float sum[4] = {0.f, 0.f, 0.f, 0.f};
    uint32_t child[4] = {0, 0, 0, 0};
  };
  struct QuadRecord {
    float x, y, value;
  };
  // Fills spatial_[index] with the tree of records [first, last) in box [lo, hi].
  void build_spatial(uint32_t index, GuideRecord* first, GuideRecord* last, Vec3 lo, Vec3 hi,
                     int depth);
  uint32_t build_distribution(GuideRecord* first, GuideRecord* last);
  uint32_t build_quad(QuadRecord* first, QuadRecord* last, int depth, float floor_density,
                      float split_energy);

  std::vector<SpatialNode> spatial_;
  std::vector<QuadNode> quads_;
  std::vector<uint32_t> roots_;  // per distribution: its root quad node
  std::vector<float> shares_;    // per distribution: the guide's share
  uint32_t leaves_ = 0;
};

// The quadtrees' square: the cylindrical equal-area map of the sphere (sampling.h's uniform
// sphere, z = 1 - 2x, phi = 2 pi y; sample_uniform_sphere maps a point back), its coordinates
// kept in [0, 1) so that every direction falls in a cell. The Jacobian is constant: a density on
// the square is 4 pi times the solid-angle density.
Point2 guide_square(Vec3 d);

// The part of a vertex with lobes l (bsdf_lobes) the guide may take (the leaf's share times
// this is the probability of sampling the guide; 0: not guided): none where the BSDF has
// sampled-only lobes (glass, diffuse transmission), otherwise its diffuse part, the
// probability with which it samples its diffuse lobe. Glossy lobes keep their own sampling:
// the guide learns the light, not its product with a peaked BSDF, and on the realistic floor's
// glossy tiles (roughness 0.35) guiding their GGX lobe made the highlights noisier.
float guide_fraction(const BsdfLobes& l);

// How train_guide trains: the number of training paths it aims at per iteration (the image's
// pixels at kSamplesPerPixel, or a regular stride of them when that is more), over
// kIterations iterations, each but the first guided by the field the one before learned.
// Measured on the realistic suite at 320x240 (docs/parity.md): 4 samples learned too little
// to pay, 32 paid more per sample than their 8 s of training did.
struct GuideTraining {
  static constexpr uint32_t kSamplesPerPixel = 8;
  static constexpr uint32_t kMaxPaths = 1u << 21;
  static constexpr uint32_t kIterations = 2;
};

// What train_guide did, for logs and the benchmarks.
struct GuideStats {
  double seconds = 0.0;
  uint64_t paths = 0, records = 0;
  uint32_t distributions = 0, spatial_leaves = 0, quad_nodes = 0;
};

// Learns the field of a render of `scene` at `settings` (its size, seed, depth, sampler,
// environment; settings.guide is ignored) with `threads` threads; the result does not depend
// on the thread count. Null when the integrator traces no paths to guide (ao).
std::shared_ptr<const GuideField> train_guide(const Scene& scene, const RenderSettings& settings,
                                              uint32_t threads, GuideStats* stats = nullptr);

}  // namespace rf
