// What a worker computes for each row of the channel table (channel_table.h, generated from
// server/renderfarm/domain/channels.py): a row's per-sample values. Adding a row to the table
// adds an enumerator, and the switch below (no default) fails to compile until it has a case.
#pragma once

#include <cstdint>

#include "render/channel_table.h"
#include "render/integrators.h"
#include "render/motion.h"
#include "render/ranked.h"

namespace rf::channels {

// A set of rows, one bit per Id.
using Set = uint32_t;
constexpr Set kAll = (Set(1) << kCount) - 1;
constexpr Set bit(Id id) { return Set(1) << uint32_t(id); }
constexpr const Spec& spec(Id id) { return kSpecs[uint32_t(id)]; }
// The largest number of components of a row render_rect sums (not the ranked rows, which
// render_rect counts per pixel in a RankedCounts, ranked.h).
constexpr uint32_t kMaxComponents = 4;
// The ranked rows (Cryptomatte): their labels are counted, not summed.
constexpr Set kRanked = [] {
  Set s = 0;
  for (const Spec& row : kSpecs)
    if (row.ranked) s |= bit(row.id);
  return s;
}();
// The lobe rows (aovs `lobes`): the radiance split by the first scattering vertex's lobes
// (LobeValues, integrators.h; render/packet_tracer.h, PathLobes), traced only when render_rect
// is asked for one of them. They are contiguous in the table, in LobeValues' order.
constexpr Set kLobes = bit(Id::DiffuseDirect) | bit(Id::DiffuseIndirect) |
                       bit(Id::GlossyDirect) | bit(Id::GlossyIndirect) |
                       bit(Id::TransmissionDirect) | bit(Id::TransmissionIndirect) |
                       bit(Id::Emission) | bit(Id::Background);
static_assert(uint32_t(Id::Background) - uint32_t(Id::DiffuseDirect) + 1 == kLobeRows &&
                  uint32_t(Id::GlossyDirect) - uint32_t(Id::DiffuseDirect) == 2 &&
                  uint32_t(Id::TransmissionDirect) - uint32_t(Id::DiffuseDirect) == 4 &&
                  uint32_t(Id::Emission) - uint32_t(Id::DiffuseDirect) == 6,
              "the lobe rows are not the table's eight contiguous rows in LobeValues' order");
// A lobe row's place in LobeValues.
constexpr uint32_t lobe_index(Id id) { return uint32_t(id) - uint32_t(Id::DiffuseDirect); }
// The rows a standalone image keeps (Image::set_from_tile, render_image) and the bench
// traces: not the first-sample rows (depth, position, motion, instance, material), the ranked
// rows, the lobe rows nor the light groups, which only the farm's results carry.
constexpr Set kImageRows = bit(Id::Rgb) | bit(Id::Luminance) | bit(Id::Albedo) |
                           bit(Id::Normal) | bit(Id::Coverage);
// The crypto_material row's label of a hit on a primitive without a material (glTF's default
// material, Material::gltf_index -1): the server's cryptomatte.DEFAULT_MATERIAL_LABEL, which
// it names "default material" (the Material row has 0 there).
constexpr uint32_t kDefaultMaterialLabel = 0xFFFFFFFFu;
// The Depth row's value where the camera ray hit nothing: Blender's Depth pass has 1e10 there
// (the server's BACKGROUND_DEPTH, server/renderfarm/domain/channels.py).
constexpr float kBackgroundDepth = 1e10f;

// Writes the sample's values of a row render_rect sums in float32, spec(id).components of
// them: every row but the radiance and its luminance M2, which render_rect sums in double
// (the fused path of the radiance's statistics). motion: the Motion row's other poses (null:
// a still, its Motion row 0). lobes: the sample's lobe rows (null: 0, as for a sample whose
// radiance is not finite, which render_rect records as 0).
inline void sample_values(Id id, const SampleResult& r, float* out,
                          const MotionPoses* motion = nullptr,
                          const LobeValues* lobes = nullptr) {
  switch (id) {
    case Id::Rgb:
    case Id::Luminance:
      return;  // summed in double by render_rect
    case Id::Albedo:
      for (int c = 0; c < 3; ++c) out[c] = r.albedo[c];
      return;
    case Id::Normal:
      for (int c = 0; c < 3; ++c) out[c] = r.normal[c];
      return;
    case Id::Coverage:
      // Every integrator sets depth to the camera ray's hit distance (> 0), 0 on a miss.
      out[0] = r.depth > 0.f ? 1.f : 0.f;
      return;
    // The first-hit rows of a window of one sample: the server asks for them only in the
    // batch that starts at sample 0, one sample long, so their sum is the first sample's value.
    case Id::Depth:
      out[0] = r.depth > 0.f ? r.z : kBackgroundDepth;
      return;
    case Id::Position:
      for (int c = 0; c < 3; ++c) out[c] = r.depth > 0.f ? r.position[c] : 0.f;
      return;
    case Id::Motion:  // 0 on a miss and for a still (render/motion.h)
      motion_values(motion, r, out);
      return;
    // First-sample rows of type U32, summed in float32 like the others: the sum over the
    // one-sample batch is the id itself, exact below 2^24, which a result sends as uint32
    // (pack_f32_as_u32_le, film.h).
    case Id::Instance:
      out[0] = r.depth > 0.f ? float(r.instance_id) : 0.f;
      return;
    case Id::Material:
      out[0] = r.depth > 0.f ? float(r.material_id) : 0.f;
      return;
    case Id::CryptoObject:
    case Id::CryptoMaterial:
      return;  // ranked: counted by render_rect through sample_label
    case Id::DiffuseDirect:
    case Id::DiffuseIndirect:
    case Id::GlossyDirect:
    case Id::GlossyIndirect:
    case Id::TransmissionDirect:
    case Id::TransmissionIndirect:
    case Id::Emission:
    case Id::Background:
      for (int c = 0; c < 3; ++c) out[c] = lobes ? lobes->row[lobe_index(id)][c] : 0.f;
      return;
    case Id::LightGroups:
      return;  // per group: summed by render_rect (render/light_groups.h), not through here
  }
}

// The sample's label of a ranked row (Spec::ranked), 0 for none (not counted: the camera ray
// hit nothing, or hit geometry without a glTF node); 0 for every other row.
inline uint32_t sample_label(Id id, const SampleResult& r) {
  switch (id) {
    case Id::CryptoObject:  // the first hit's glTF node plus one, as the Instance row
      return r.depth > 0.f ? r.instance_id : 0u;
    case Id::CryptoMaterial:  // its glTF material plus one, or the default material's label
      return r.depth > 0.f ? (r.material_id ? r.material_id : kDefaultMaterialLabel) : 0u;
    case Id::Rgb:
    case Id::Luminance:
    case Id::Albedo:
    case Id::Normal:
    case Id::Coverage:
    case Id::Depth:
    case Id::Position:
    case Id::Motion:
    case Id::Instance:
    case Id::Material:
    case Id::DiffuseDirect:
    case Id::DiffuseIndirect:
    case Id::GlossyDirect:
    case Id::GlossyIndirect:
    case Id::TransmissionDirect:
    case Id::TransmissionIndirect:
    case Id::Emission:
    case Id::Background:
    case Id::LightGroups:
      return 0u;  // not ranked
  }
  return 0u;
}

// Whether render_rect sums the row in float32 through sample_values (not the per-group row,
// which it sums per light group itself).
constexpr bool summed_in_float(Id id) {
  return id != Id::Rgb && id != Id::Luminance && !spec(id).ranked && !spec(id).per_group;
}
// The components a pixel of row `id` has in a result of a task with `groups` light groups:
// the table's, times the groups for the per-group row.
constexpr uint32_t components(Id id, uint32_t groups) {
  return spec(id).per_group ? spec(id).components * groups : spec(id).components;
}

static_assert([] {
  for (const Spec& s : kSpecs)
    if (s.ranked ? s.components != 2 * kRanks || s.type != Type::U32
                 : s.components > kMaxComponents)
      return false;
  return true;
}(), "a summed row has more components than kMaxComponents, or a ranked row is not "
     "kRanks (label, count) pairs of uint32");

}  // namespace rf::channels
