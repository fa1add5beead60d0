#include "render/packet_tracer.h"

#include <algorithm>
#include <cmath>
#include <new>
#include <type_traits>

#include "math/simd.h"
#include "sampling/sampling.h"

namespace rf {

namespace {

// The BSDF samples' disk warps (bsdf_disks) of a packet's lanes, four lanes at a time: they
// depend on the sample values alone, so they are computed for every live lane before the
// vertices are shaded, both of them (a lane uses one, known only once its material is).
struct DiskBatch {
  static constexpr int kLanes = kPacketSize;
  alignas(16) float cosine[3][kLanes] = {}, polar[2][kLanes] = {};

  // Lanes `lanes` of the pairs (ux[i], uy[i]); the other lanes of a block of four are computed
  // too (from whatever values they hold) and never read.
  void compute(const float* ux, const float* uy, uint32_t lanes) {
    for (int i = 0; i < kLanes; i += 4) {
      if (!((lanes >> i) & 0xfu)) continue;
      const F32x4 x = load4(ux + i), y = load4(uy + i);
      F32x4 cx, cy, cz, px, py;
      sample_cosine_hemisphere4(x, y, &cx, &cy, &cz);
      sample_polar_disk4(x, y, &px, &py);
      store4(&cosine[0][i], cx);
      store4(&cosine[1][i], cy);
      store4(&cosine[2][i], cz);
      store4(&polar[0][i], px);
      store4(&polar[1][i], py);
    }
  }
  BsdfDisks get(int lane) const {
    return {Vec3(cosine[0][lane], cosine[1][lane], cosine[2][lane]),
            Point2{polar[0][lane], polar[1][lane]}};
  }
};

// The light group of what a hit's triangle emits, and of the light a vertex's light sample
// chose: out of line, called only with the light groups on, so that the tracer without them
// keeps the size it had.
__attribute__((noinline)) uint32_t surface_group(const PathGroups& groups, const Scene& scene,
                                                 const Hit& hit) {
  return groups.map->surface(scene, hit.slot, hit.prim);
}
__attribute__((noinline)) uint32_t light_sample_group(const PathGroups& groups,
                                                      const Scene& scene, const LightContext& lc,
                                                      const BounceSamples& u, const float* w,
                                                      float total) {
  return groups.map->light(scene, light_sample_source(scene, lc, u, w, total));
}

// The first half of what a path does at the vertex its ray found (hit null: the ray escaped):
// emission, Russian roulette, the light sample and the BSDF sample's direction. The BSDF values
// both samples need are queued in *batch (one evaluation for a packet's lanes together);
// shade_vertex_end_light and shade_vertex_end_bsdf finish the vertex once the batch has been
// evaluated. lobes: the path's lobe rows (null: off), which keep the first vertex; groups:
// its light groups (null: off).
void shade_vertex_begin(const Scene& scene, const LightContext& lc, PathState& p,
                        const Hit* hit, uint32_t bounce, uint32_t max_depth,
                        const DiskBatch& disks, BsdfEvalBatch* batch, LightBatch* lb,
                        int lane, PathLobes* lobes, PathGroups* groups,
                        const GuideField* guide, PathGuide* pg) {
  const Vec3 d = p.d;
  SampleResult& result = p.result;
  p.alive = false;
  if (pg) pg->frac = 0.f;
  p.light_kind = LightSampleKind::None;
  p.bsdf_slot = -2;
  p.next_medium = p.medium;
  const bool in_medium = !is_zero(p.medium);
  if (!hit) {
    if (lc.env) {
      const Vec3 L = lc.env->eval(d);
      const float w =
          p.prev_delta ? 1.f
                       : power_heuristic(p.prev_bsdf_pdf,
                                         light_env_pmf(lc, p.sel_o, p.sel_ng, p.sel_total, d,
                                                       p.sel_two_sided) *
                                             lc.env->pdf(d));
      add_radiance(p, lobes,
                   (in_medium ? p.beta * transmittance(p.medium, kInfinity) : p.beta) * L * w,
                   bounce, RadianceSource::Environment, groups,
                   groups ? groups->map->environment() : 0u);
    }
    return;
  }
  if (in_medium) p.beta *= transmittance(p.medium, hit->t);
  const Vec3 wo = -d;
  ShadingPoint sp = make_shading_point(scene, *hit, wo);
  if (bounce == 0) record_first_hit(scene, sp, *hit, p.per_axial, &result);
  // Emission: the front (counter-clockwise) face emits, and the back of a double-sided one.
  const Material& hit_material = scene.materials()[hit->material];
  const float cos_emit = emitting_cosine(hit_material, hit->ng, wo);
  if (hit_material.unlit) {
    // KHR_materials_unlit: the base colour as radiance on the faces that would emit, and
    // nothing reflected (the path ends). Not a light of the light set: no MIS weight.
    if (cos_emit > 0.f) {
      const uint32_t group = groups ? surface_group(*groups, scene, *hit) : 0u;
      add_radiance(p, lobes, p.beta * sp.albedo, bounce, RadianceSource::Surface, groups, group);
      // Unlit points and lines add their emission (glTF "Point and Line Materials").
      if (hit_material.unlit_adds_emission)
        add_radiance(p, lobes,
                     p.beta * scene.emission(hit->slot, hit->prim, hit->b1, hit->b2, cos_emit),
                     bounce, RadianceSource::Surface, groups, group);
    }
    return;
  }
  if (cos_emit > 0.f && hit_material.is_emissive()) {
    const Vec3 Le = scene.emission(hit->slot, hit->prim, hit->b1, hit->b2, cos_emit);
    const uint32_t group = groups ? surface_group(*groups, scene, *hit) : 0u;
    if (p.prev_delta) {
      add_radiance(p, lobes, p.beta * Le, bounce, RadianceSource::Surface, groups, group);
    } else {
      // The same point could have come from light sampling at the previous vertex: convert
      // its area pdf to solid angle (pdf_A d^2 / |cos|) and weight by the power heuristic.
      const float pdf_light =
          light_pdf_area(lc, p.sel_o, p.sel_ng, p.sel_total, hit->slot, hit->prim, d,
                         p.sel_two_sided) *
          hit->t * hit->t / cos_emit;
      add_radiance(p, lobes, p.beta * Le * power_heuristic(p.prev_bsdf_pdf, pdf_light), bounce,
                   RadianceSource::Surface, groups, group);
    }
  }
  if (bounce >= max_depth) return;
  const BounceSamples& u = p.u;
  // Russian roulette after 3 bounces (roulette_survival); dividing by the survival
  // probability keeps the estimator unbiased.
  if (bounce >= 3) {
    const float q = roulette_survival(p.beta, p.eta_scale);
    if (!(u.get(dim::kRoulette) < q)) return;
    p.beta = p.beta / q;
  }
  disperse(p, u, &sp.params);
  const Frame frame = sp.frame();
  const Vec3 wo_local = frame.to_local(wo);
  const BsdfLobes bsdf = bsdf_lobes(sp.params, wo_local);
  batch->set_vertex(lane, sp.params, bsdf, wo_local, frame);
  if (lobes && bounce == 0) {
    lobes->params = sp.params;
    lobes->lobes = bsdf;
    lobes->wo = wo_local;
    lobes->frame = frame;
  }
  if (lc.any && bsdf_has_smooth_part(sp.params)) {
    float w[kMaxLightEntries];
    p.sel_o = sp.above();
    p.sel_ng = sp.ng;
    p.sel_two_sided = has_through_lobe(sp.params);
    p.sel_total = light_weights(lc, p.sel_o, p.sel_ng, w, p.sel_two_sided);
    p.light_kind = sample_light(scene, lc, sp, frame, wo_local, u, w, p.sel_total, batch, lb,
                                lane, &p.light);
    if (groups && p.light_kind != LightSampleKind::None)
      groups->light_group = light_sample_group(*groups, scene, lc, u, w, p.sel_total);
    // A punctual light's shadow ray through the surface travels in the medium a transmission
    // enters.
    if (p.light_kind == LightSampleKind::Delta)
      p.light_medium = p.light.through ? medium_after(hit_material, sp.params.front, p.medium)
                                       : p.medium;
  }

  BsdfSample& bs = p.bs;
  BsdfDisks disk = disks.get(lane);
  if (pg) {
    // Path guiding: the direction from the guide with probability alpha, else from the BSDF
    // (render/guiding.h). The choice splits the direction pair's first coordinate at alpha,
    // each side rescaled to [0, 1): the pair's stratification is shared by both strategies
    // rather than dealt to them at random. A guided BSDF has no lobe sampled whole (glass,
    // diffuse BTDF: guide_fraction is 0 there), so its sample always waits for the batch's
    // f and pdf, which shade_vertex_end_bsdf mixes with the guide's.
    const float part = guide_fraction(bsdf);
    const uint32_t dist = part > 0.f ? guide->distribution_at(sp.above()) : GuideField::kNone;
    if (dist != GuideField::kNone) {
      const float alpha = part * guide->share(dist);
      *pg = {alpha, dist, -1.f, 0.f};
      Point2 uv = u.get2(dim::kBsdfU);
      if (uv.x < alpha) {
        uv.x = std::min(uv.x / alpha, 0x1.fffffep-1f);
        float pdf = 0.f;
        const Vec3 wi = guide->sample(dist, uv, &pdf);
        const Vec3 wi_local = frame.to_local(wi);
        // Below the surface every lobe a guided BSDF has is 0 (no transmission): the
        // sample's estimate is 0.
        if (!(wi_local.z > 0.f) || !(pdf > 0.f)) return;
        pg->pdf = pdf;
        bs.wi = wi_local;
        bs.lobe = SampledLobe::Evaluated;
        p.ng = sp.ng;
        p.next_o = sp.above();
        p.bsdf_slot = batch->add_sampled(lane, wi_local);
        return;
      }
      uv.x = std::min((uv.x - alpha) / (1.f - alpha), 0x1.fffffep-1f);
      disk = bsdf_disks(uv);
    }
  }
  const BsdfSampleStep step =
      bsdf_sample_direction(sp.params, bsdf, wo_local, disk, u.get(dim::kLobe),
                            // Read only by the glass lobe: skipped (any value would do) without
                            // one.
                            bsdf.glass > 0.f ? u.get(dim::kFresnel) : 0.f, &bs);
  if (step == BsdfSampleStep::Failed) return;
  p.ng = sp.ng;
  if (step == BsdfSampleStep::NeedsEval) {
    // The batch normalizes the direction and turns it into world space.
    p.next_o = sp.above();
    p.bsdf_slot = batch->add_sampled(lane, bs.wi);
    return;
  }
  const Vec3 wi = normalize(frame.to_world(bs.wi));
  if (wrong_side(wi, sp.ng, bs.transmitted)) return;
  p.next_o = bs.transmitted ? sp.below() : sp.above();
  p.next_d = wi;
  p.bsdf_slot = -1;
  // Only the glass lobe and the diffuse BTDF transmit: the one place the medium changes.
  if (bs.transmitted)
    p.next_medium = medium_after(scene.materials()[hit->material], sp.params.front, p.medium);
}

// The second half, in two parts for the lanes that need them. The light sample's shadow ray
// goes into lane `lane` of *shadow (a light sample was taken)...
void shade_vertex_end_light(PathState& p, const LightBatch& lb, RayPacket* shadow, int lane) {
  if (p.light_kind == LightSampleKind::Delta) {
    shadow->set(lane, p.light.origin, p.light.wi, p.light.tmax);
    p.nee = p.beta * p.light.contribution;
    // The shadow ray leaves on the side of wo, in the medium the path arrived through, or
    // through a rough glass lobe or a diffuse BTDF into the other one.
    if (!is_zero(p.light_medium)) p.nee *= transmittance(p.light_medium, p.light.tmax);
    ++p.result.rays;
    return;
  }
  if (!lb.ok[lane]) return;
  shadow->set(lane, Vec3(lb.o[0][lane], lb.o[1][lane], lb.o[2][lane]),
              Vec3(lb.wi[0][lane], lb.wi[1][lane], lb.wi[2][lane]), lb.tmax[lane]);
  p.nee = p.beta * Vec3(lb.contribution[0][lane], lb.contribution[1][lane],
                        lb.contribution[2][lane]);
  if (!is_zero(p.medium)) p.nee *= transmittance(p.medium, lb.tmax[lane]);
  ++p.result.rays;
}

// ... then, if p.bsdf_slot != -2, the BSDF sample gives the next ray (p.alive) unless the path
// ends here. It runs after the light part, whose throughput is the one before this vertex's
// BSDF.
// A guided vertex's density is the mixture alpha p_guide + (1 - alpha) p_bsdf.
void shade_vertex_end_bsdf(PathState& p, const BsdfEvalBatch& batch, const GuideField* guide,
                           PathGuide* pg) {
  BsdfSample& bs = p.bs;
  if (p.bsdf_slot >= 0) {
    p.next_d = batch.world(p.bsdf_slot);
    if (wrong_side(p.next_d, p.ng, false)) return;
    float pdf = batch.pdf(p.bsdf_slot);
    if (pg && pg->frac > 0.f) {
      const float guide_pdf = pg->pdf >= 0.f ? pg->pdf : guide->pdf(pg->dist, p.next_d);
      pg->bsdf_pdf = pdf;
      pdf = pg->frac * guide_pdf + (1.f - pg->frac) * pdf;
    }
    if (!bsdf_sample_finish(batch.f(p.bsdf_slot), pdf, &bs)) return;
  }
  if (is_zero(bs.weight)) return;
  p.beta *= bs.weight;
  p.eta_scale *= bs.eta2;
  p.prev_bsdf_pdf = bs.pdf;
  p.prev_delta = bs.delta;
  p.o = p.next_o;
  p.d = p.next_d;
  p.medium = p.next_medium;
  p.alive = true;
}

// The lobe rows' shares at the first vertex (bounce 0), once its batch has been evaluated:
// of its light sample, for the lanes `shadowed` whose shadow ray is set (the direction it
// was evaluated at, and for a punctual light the through lobes on the side it is sampled
// from, as punctual_light_sample evaluates them), and of what the path brings after it, for
// the lanes of `live` that go on (shade_vertex_end_bsdf made them alive): the sampled-only
// lobe the BSDF sample came from, or the evaluated lobes' parts at the sampled direction.
// Scalar, outside the batch: only with the lobe rows on.
void first_vertex_shares(const PathState* paths, const LightBatch& lights, uint32_t live,
                         uint32_t shadowed, PathLobes* lobes) {
  Vec3 f[kLobeCategories];
  for (uint32_t m = shadowed; m; m &= m - 1) {
    const int i = __builtin_ctz(m);
    const PathState& p = paths[i];
    PathLobes& l = lobes[i];
    if (p.light_kind == LightSampleKind::Delta) {
      const Vec3 wl = l.frame.to_local(p.light.wi);
      const bool above = !p.light.through;
      if (above) {
        bsdf_eval_lobes(l.params, l.lobes, l.wo, wl, f);
      } else {
        for (Vec3& v : f) v = Vec3(0.f, 0.f, 0.f);
      }
      if (has_through_lobe(l.params) && (wl.z > 0.f) == above)
        through_eval_lobes(l.params, l.wo, wl, f);
    } else {
      const Vec3 wi(lights.wi[0][i], lights.wi[1][i], lights.wi[2][i]);
      bsdf_eval_lobes(l.params, l.lobes, l.wo, l.frame.to_local(wi), f);
    }
    PathLobes::shares(f, l.light_share);
  }
  for (uint32_t m = live; m; m &= m - 1) {
    const int i = __builtin_ctz(m);
    const PathState& p = paths[i];
    if (!p.alive) continue;
    PathLobes& l = lobes[i];
    for (Vec3& v : f) v = Vec3(0.f, 0.f, 0.f);
    switch (p.bs.lobe) {
      case SampledLobe::Evaluated:  // bs.wi: the direction before the batch normalized it
        bsdf_eval_lobes(l.params, l.lobes, l.wo, normalize(p.bs.wi), f);
        break;
      case SampledLobe::Glass:
        f[p.bs.transmitted ? kTransmissionLobes : kGlossyLobes] = Vec3(1.f, 1.f, 1.f);
        break;
      case SampledLobe::DiffuseBtdf:
        f[kDiffuseLobes] = Vec3(1.f, 1.f, 1.f);
        break;
    }
    PathLobes::shares(f, l.path_share);
  }
}

// Path guiding: the guide's density of the light sample's direction at the guided lanes'
// vertices that wait for their BSDF value (after finish_geometry, which sets the area lights'
// directions), for their MIS weight (LightBatch::finish_contributions).
void guided_light_pdfs(const GuideField& guide, const PathGuide* guides, LightBatch* lb) {
  uint32_t guided = 0;
  for (uint32_t m = lb->waiting; m; m &= m - 1) {
    const int i = __builtin_ctz(m);
    const PathGuide& g = guides[i];
    lb->guide_frac[i] = g.frac;
    lb->guide_pdf[i] = 0.f;
    if (!(g.frac > 0.f)) continue;
    guided |= uint32_t(1) << i;
    lb->guide_pdf[i] = guide.pdf(g.dist, Vec3(lb->wi[0][i], lb->wi[1][i], lb->wi[2][i]));
  }
  // The other waiting lanes of a block of four with a guided lane mix with alpha = 0.
  lb->guided = 0;
  for (int i = 0; i < kPacketSize; i += 4)
    if ((guided >> i) & 0xfu) lb->guided |= 0xfu << i;
}

// Path guiding's training: each live path that goes on in a direction it sampled with a
// density records its vertex (render/guiding.h, PathRecorder), at the end of the bounce, when
// the vertex's own light sample is in its radiance.
void record_vertices(const PathState* paths, const PathGuide* guides, uint32_t live,
                     PathRecorder* recorders) {
  for (uint32_t m = live; m; m &= m - 1) {
    const int i = __builtin_ctz(m);
    const PathState& p = paths[i];
    PathRecorder& r = recorders[i];
    if (!p.alive || p.prev_delta || r.n >= PathRecorder::kMaxVertices) continue;
    const bool guided = guides && guides[i].frac > 0.f;
    r.v[r.n++] = {p.o,
                  p.d,
                  p.beta,
                  p.result.radiance,
                  p.prev_bsdf_pdf,
                  guided ? guides[i].bsdf_pdf : p.prev_bsdf_pdf,
                  std::abs(dot(p.d, p.ng))};
  }
}

// Traces the live paths of paths[0, kPacketSize) together, bounce by bounce: the rays of a
// bounce go to Embree as one packet query and their shadow rays as another, and the BSDF
// evaluations of the bounce's vertices are computed together. Each path computes exactly what
// it would alone (the same sample values, the same sums in the same order); the packets only
// let Embree share traversal between similar rays (a pixel's camera rays, shadow rays towards
// the same light) and let the shading of independent paths overlap. lobes: the paths' lobe
// rows (kPacketSize of them), or null when they are off; groups: their light groups likewise.
// guide: the field that guides the paths and guides their PathGuide (both null: unguided);
// recorders: the paths' training records (null: none).
void trace_paths(const Scene& scene, const LightContext& lc, PathState* paths,
                 uint32_t max_depth, PathLobes* lobes, PathGroups* groups,
                 const GuideField* guide, PathGuide* guides, PathRecorder* recorders) {
  constexpr int kFewLanes = 3;
  static_assert(BsdfEvalBatch::kLanes == kPacketSize, "a batch lane per packet lane");
  static_assert(PixelSampler::kLanes16 == kPacketSize, "a sampler lane per packet lane");
  RayPacket rays, shadow;
  Hit hits[kPacketSize];
  bool found[kPacketSize], blocked[kPacketSize];
  BsdfEvalBatch batch;
  LightBatch lights;
  DiskBatch disks;
  // A lane's rays carry its sample index (for the transparency test).
  // And its time within the shutter (motion blur; 0 otherwise).
  for (int i = 0; i < kPacketSize; ++i) {
    rays.id[i] = shadow.id[i] = paths[i].s.index;
    rays.time[i] = shadow.time[i] = paths[i].time;
  }
  // Lanes are visited through bit masks of the live ones: whether a path is still alive is
  // data the branch predictor cannot learn, and a branch per lane per loop mispredicts often.
  for (uint32_t bounce = 0;; ++bounce) {
    uint32_t live = 0;
    for (int i = 0; i < kPacketSize; ++i) {
      rays.active[i] = paths[i].alive;
      shadow.active[i] = false;
      live |= uint32_t(paths[i].alive) << i;
    }
    if (!live) return;
    // This vertex's sample values, for every lane at once: the lanes are samples of one pixel
    // (one PixelSampler) with different sample indices, which the sobol sampler scrambles
    // side by side in SIMD lanes.
    uint32_t index[kPacketSize];
    for (int i = 0; i < kPacketSize; ++i) index[i] = paths[i].s.index;
    // A packet with few live lanes (after Russian roulette, from bounce 4 on, most carry one
    // or two) gets its values lane by lane: the 16-lane kernel costs the same for one lane as
    // for sixteen, about four of value8's single-sample calls (the values are the same).
    float values[8][PixelSampler::kLanes16];
    const bool batched = __builtin_popcount(live) > kFewLanes &&
                         paths[__builtin_ctz(live)].s.sampler->value8_lanes(
                             index, dim::bounce(bounce, 0), values);
    if (!batched) {  // the disk pairs are filled lane by lane below; dead lanes get zeros
      std::fill(values[dim::kBsdfU], values[dim::kBsdfU] + kPacketSize, 0.f);
      std::fill(values[dim::kBsdfV], values[dim::kBsdfV] + kPacketSize, 0.f);
    }
    for (uint32_t m = live; m; m &= m - 1) {
      const int i = __builtin_ctz(m);
      PathState& p = paths[i];
      if (batched) {
        p.u.assign(p.s, bounce, values, i);
      } else {
        p.u.reset(p.s, bounce);
        const Point2 u = p.u.get2(dim::kBsdfU);
        values[dim::kBsdfU][i] = u.x;
        values[dim::kBsdfV][i] = u.y;
      }
      rays.set(i, p.o, p.d, kInfinity);
      ++p.result.rays;
    }
    // The camera rays see what lies between the camera's clipping planes; later rays the
    // whole of (0, infinity).
    if (bounce == 0)
      for (int i = 0; i < kPacketSize; ++i) {
        rays.tnear[i] = paths[i].tmin;
        rays.tfar[i] = paths[i].tmax;
      }
    disks.compute(values[dim::kBsdfU], values[dim::kBsdfV], live);
    // The lanes are samples of one pixel: one transparency key per query for all of them.
    const PixelSampler& pixel = *paths[__builtin_ctz(live)].s.sampler;
    const uint64_t path_query =
        scene.has_transparency()
            ? ray_query(pixel.seed(), pixel.pixel(), bounce, RayKind::Path)
            : 0;
    // The camera rays of a pixel's samples are alike: Embree's coherent traversal (about 3%
    // more samples/s on the Cornell box). Later bounces scatter, where it would be far slower.
    scene.intersect(rays, hits, found, bounce == 0, path_query);
    if (bounce == 0) std::fill(rays.tnear, rays.tnear + kPacketSize, 0.f);
    batch.clear();
    lights.clear();
    for (uint32_t m = live; m; m &= m - 1) {
      const int i = __builtin_ctz(m);
      shade_vertex_begin(scene, lc, paths[i], found[i] ? &hits[i] : nullptr, bounce, max_depth,
                         disks, &batch, &lights, i, lobes ? lobes + i : nullptr,
                         groups ? groups + i : nullptr, guide, guides ? guides + i : nullptr);
    }
    lights.finish_geometry(&batch);
    if (guides) guided_light_pdfs(*guide, guides, &lights);
    batch.evaluate();
    lights.finish_contributions(batch);
    uint32_t with_light = 0, going_on = 0;
    for (int i = 0; i < kPacketSize; ++i) {
      with_light |= uint32_t(paths[i].light_kind != LightSampleKind::None) << i;
      going_on |= uint32_t(paths[i].bsdf_slot != -2) << i;
    }
    for (uint32_t m = with_light & live; m; m &= m - 1) {
      const int i = __builtin_ctz(m);
      shade_vertex_end_light(paths[i], lights, &shadow, i);
    }
    for (uint32_t m = going_on & live; m; m &= m - 1)
      shade_vertex_end_bsdf(paths[__builtin_ctz(m)], batch, guide,
                            guides ? guides + __builtin_ctz(m) : nullptr);
    uint32_t shadowed = 0;
    for (int i = 0; i < kPacketSize; ++i) shadowed |= uint32_t(shadow.active[i]) << i;
    if (lobes && bounce == 0) first_vertex_shares(paths, lights, live, shadowed, lobes);
    if (shadowed) {
      scene.occluded(shadow, blocked,
                     scene.has_transparency()
                         ? ray_query(pixel.seed(), pixel.pixel(), bounce, RayKind::Shadow)
                         : 0);
      for (; shadowed; shadowed &= shadowed - 1) {
        const int i = __builtin_ctz(shadowed);
        PathState& p = paths[i];
        if (!blocked[i])
          add_radiance(p, lobes ? lobes + i : nullptr, p.nee, bounce,
                       RadianceSource::LightSample, groups ? groups + i : nullptr,
                       groups ? groups[i].light_group : 0u);
      }
    }
    if (recorders) record_vertices(paths, guides, live, recorders);
  }
}

}  // namespace

namespace {

// The camera ray through image position (px, py) into *p (whose sample stream is set).
inline __attribute__((always_inline)) void camera_ray(const Camera& cam,
                                                      const Camera::Raster& raster,
                                                      const RenderSettings& settings,
                                                      const float* camera_dims, float px,
                                                      float py, PathState* out) {
  PathState& p = *out;
  p.o = raster.origin(px, py);
  float per_axial;
  p.d = raster.direction(px, py, &per_axial);
  if (settings.aperture_radius > 0.f) {
    // Thin lens: the pinhole ray through the pixel meets the plane of focus (at
    // focus_distance along the viewing axis) at p_focus; the lens ray starts at a uniform
    // point of the aperture disk and aims at p_focus.
    const Point2 lens = sample_concentric_disk(
        camera_dims ? Point2{camera_dims[dim::kLensU], camera_dims[dim::kLensV]}
                    : p.s.get2(dim::kLensU));
    const Vec3 p_focus = p.o + p.d * (settings.focus_distance / dot(p.d, cam.forward));
    p.o = p.o + (cam.right * lens.x + cam.up * lens.y) * settings.aperture_radius;
    p.d = normalize(p_focus - p.o);
    per_axial = 1.f / dot(p.d, cam.forward);
  }
  // The clipping planes are distances along the viewing axis, and so is the first hit's depth.
  p.per_axial = per_axial;
  p.tmin = cam.znear * per_axial;
  p.tmax = cam.zfar * per_axial;
  p.alive = true;
}

}  // namespace

// Sample `index` of pixel (x, y) up to its camera ray: a path ready for its first bounce.
// camera_dims: the sample's values of dimensions kPixelX .. kLensV if already computed, or null.
PathState start_path(const TraceContext& ctx, const Scene& scene, const RenderSettings& settings,
                     const PixelSampler& sampler, uint32_t x, uint32_t y, uint32_t index,
                     const float* camera_dims) {
  PathState p;
  p.s = SampleStream{&sampler, index};
  // Box filter: the sample position is uniform inside the pixel.
  const Point2 jitter = camera_dims ? Point2{camera_dims[dim::kPixelX], camera_dims[dim::kPixelY]}
                                    : p.s.get2(dim::kPixelX);
  const float px = float(x) + jitter.x;
  const float py = float(y) + jitter.y;
  // Motion blur: the sample's time, and the camera where it is then if it moves.
  if (scene.has_motion()) p.time = p.s.get(dim::shutter_time(path_max_depth(settings)));
  if (scene.camera_moves()) {
    const Camera moved = scene.camera_at(p.time);
    camera_ray(moved, moved.raster(settings.width, settings.height), settings, camera_dims, px,
               py, &p);
  } else {
    camera_ray(scene.camera(), ctx.raster, settings, camera_dims, px, py, &p);
  }
  return p;
}



uint32_t path_max_depth(const RenderSettings& settings) {
  return settings.integrator == IntegratorType::Direct ? std::min<uint32_t>(settings.max_depth, 1u)
                                                       : settings.max_depth;
}

void PathLobes::shares(const Vec3 f[kLobeCategories], Vec3 share[kLobeCategories]) {
  const Vec3 sum = f[0] + f[1] + f[2];
  float all = 0.f, all_k[kLobeCategories];
  for (int k = 0; k < kLobeCategories; ++k) {
    all_k[k] = f[k].x + f[k].y + f[k].z;
    all += all_k[k];
  }
  const bool all_ok = all > 0.f && std::isfinite(all);
  for (int c = 0; c < 3; ++c) {
    const bool ok = sum[c] > 0.f && std::isfinite(sum[c]);
    for (int k = 0; k < kLobeCategories; ++k)
      share[k][c] = ok       ? f[k][c] / sum[c]
                    : all_ok ? all_k[k] / all
                             : (k == kDiffuseLobes ? 1.f : 0.f);
  }
}

void PathRecorder::finish(Vec3 radiance, std::vector<GuideRecord>* out) const {
  for (int k = 0; k < n; ++k) {
    const Vertex& x = v[k];
    // The radiance that came back along d: what the path gathered after the vertex over the
    // throughput it had then, per channel that carried any.
    const Vec3 after = radiance - x.gathered;
    float sum = 0.f;
    for (int c = 0; c < 3; ++c)
      if (x.beta[c] > 0.f) sum += std::max(0.f, after[c]) / x.beta[c];
    const float value = sum * (1.f / 3.f) * x.cos / x.pdf;
    if (!std::isfinite(value)) continue;
    out->push_back({x.p, x.d, value, x.pdf, x.bsdf_pdf});
  }
}

namespace {

// trace_paths with the lobe rows or the light groups on (lobes_out, groups not null), guided
// (guide not null) or training a guide (guide_records not null): the paths' PathLobes,
// PathGroups, PathGuide and PathRecorder on this function's stack (not on trace_samples',
// whose frame stays as small as without them); the groups' values in group_values, lane k's
// from k * groups->count(); the training records appended to *guide_records.
__attribute__((noinline)) void trace_paths_with_outputs(
    const Scene& scene, const LightContext& lc, PathState* paths, uint32_t max_depth,
    uint32_t n, LobeValues* lobes_out, const LightGroupMap* groups, Vec3* group_values,
    const GuideField* guide, std::vector<GuideRecord>* guide_records) {
  PathLobes lobes[kPacketSize];
  PathGroups path_groups[kPacketSize];
  if (groups) {
    const uint32_t count = groups->count();
    std::fill(group_values, group_values + size_t(count) * n, Vec3(0.f, 0.f, 0.f));
    for (uint32_t k = 0; k < n; ++k) path_groups[k] = {groups, group_values + k * count, 0u};
  }
  PathGuide guides[kPacketSize];
  if (guide_records) {
    PathRecorder recorders[kPacketSize];
    trace_paths(scene, lc, paths, max_depth, lobes_out ? lobes : nullptr,
                groups ? path_groups : nullptr, guide, guide ? guides : nullptr, recorders);
    for (uint32_t k = 0; k < n; ++k)
      recorders[k].finish(paths[k].result.radiance, guide_records);
  } else {
    trace_paths(scene, lc, paths, max_depth, lobes_out ? lobes : nullptr,
                groups ? path_groups : nullptr, guide, guide ? guides : nullptr, nullptr);
  }
  if (lobes_out)
    for (uint32_t k = 0; k < n; ++k) lobes_out[k] = lobes[k].values;
}

// trace_paths guided by `guide`, without outputs or training: only the paths' PathGuide on this
// function's stack (trace_paths_with_outputs's PathLobes cost more to make than guiding saves).
__attribute__((noinline)) void trace_paths_guided(const Scene& scene, const LightContext& lc,
                                                  PathState* paths, uint32_t max_depth,
                                                  const GuideField* guide) {
  PathGuide guides[kPacketSize];
  trace_paths(scene, lc, paths, max_depth, nullptr, nullptr, guide, guides, nullptr);
}

}  // namespace

// Samples [first, first + n) of pixel (x, y), n <= kPacketSize, into out[0, n).
void trace_samples(const TraceContext& ctx, const Scene& scene, const RenderSettings& settings,
                   const PixelSampler& sampler, uint32_t x, uint32_t y, uint32_t first,
                   uint32_t n, SampleResult* out, LobeValues* lobes,
                   const LightGroupMap* groups, Vec3* group_values,
                   std::vector<GuideRecord>* guide_records) {
  if (settings.integrator == IntegratorType::AmbientOcclusion) {
    for (uint32_t k = 0; k < n; ++k) {
      const PathState p = start_path(ctx, scene, settings, sampler, x, y, first + k);
      out[k] = trace_ao(scene, p);
      if (lobes) lobes[k] = LobeValues{};  // ao attributes nothing to the lobes
    }
    // Nor to the light groups: its value is not light.
    if (groups)
      std::fill(group_values, group_values + size_t(groups->count()) * n, Vec3(0.f, 0.f, 0.f));
    return;
  }
  // The camera dimensions of all lanes at once where the sampler can (sobol).
  uint32_t index[kPacketSize];
  for (uint32_t k = 0; k < uint32_t(kPacketSize); ++k) index[k] = first + k;
  float values[8][PixelSampler::kLanes16];
  const bool batched = sampler.value8_lanes(index, dim::kPixelX, values);
  // Each path made where it lives (start_path's value constructed in place, not a default
  // path assigned over, a copy of its whole state a sample); the packet's lanes past n idle.
  static_assert(std::is_trivially_destructible_v<PathState>, "lanes are never destroyed");
  alignas(PathState) unsigned char storage[kPacketSize * sizeof(PathState)];
  PathState* const paths = reinterpret_cast<PathState*>(storage);
  for (uint32_t k = 0; k < n; ++k) {
    float camera_dims[4];
    for (uint32_t d = 0; d < 4; ++d) camera_dims[d] = values[dim::kPixelX + d][k];
    new (paths + k) PathState(start_path(ctx, scene, settings, sampler, x, y, first + k,
                                         batched ? camera_dims : nullptr));
  }
  for (uint32_t k = n; k < uint32_t(kPacketSize); ++k) new (paths + k) PathState();
  // Training or with outputs, or guided: out of line, so that the plain tracer stays as it
  // was.
  const GuideField* guide = settings.guide.get();
  if (lobes || groups || guide_records)
    trace_paths_with_outputs(scene, ctx.lights, paths, path_max_depth(settings), n, lobes,
                             groups, group_values, guide, guide_records);
  else if (guide)
    trace_paths_guided(scene, ctx.lights, paths, path_max_depth(settings), guide);
  else
    trace_paths(scene, ctx.lights, paths, path_max_depth(settings), nullptr, nullptr, nullptr,
                nullptr, nullptr);
  for (uint32_t k = 0; k < n; ++k) out[k] = paths[k].result;
}

SampleResult trace_sample(const Scene& scene, const RenderSettings& settings,
                          const Sampler& sampler, uint32_t x, uint32_t y, uint32_t index) {
  const PixelSampler pixel_sampler(sampler, uint64_t(y) * settings.width + x);
  return trace_sample(scene, settings, pixel_sampler, x, y, index);
}

SampleResult trace_sample(const Scene& scene, const RenderSettings& settings,
                          const PixelSampler& sampler, uint32_t x, uint32_t y, uint32_t index) {
  SampleResult result;
  trace_samples(TraceContext(scene, settings), scene, settings, sampler, x, y, index, 1, &result);
  return result;
}

}  // namespace rf
