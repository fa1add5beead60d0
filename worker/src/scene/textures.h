// Image textures of a scene, read through OpenImageIO: into memory at their first lookup
// (TextureSet::lookup), or beyond a memory budget through its TextureSystem (one
// process-wide, shared instance; MIP levels are generated on demand by its automip
// option). Images embedded in a glTF file (data: URIs, GLB buffer views) are written once to
// a content-addressed directory (<tmp>/renderfarm-textures/<sha256>.<ext>) so that both read
// them like any file.
#pragma once

#include <memory>
#include <string>
#include <vector>

#include "sampling/sampling.h"

namespace rf {

enum class TextureWrap { Repeat, Clamp, Mirror };

class TextureSet {
 public:
  TextureSet();
  ~TextureSet();
  TextureSet(const TextureSet&) = delete;
  TextureSet& operator=(const TextureSet&) = delete;

  // Registers an image given by its encoded bytes (PNG, JPEG, EXR, HDR, ...). Returns the
  // texture index, or -1 with *error set if OpenImageIO cannot read it.
  //
  // srgb: the image's colour channels are sRGB-encoded (glTF base colour and emissive
  // textures, 3.9.2) and lookups return them linear. They are decoded texel by texel before
  // any filtering - a bilinear blend of encoded values decoded afterwards is darker than the
  // blend of the colours (a black and white checker would average 0.21, not 0.5) - into a
  // float copy of the image made at the first lookup (so that checking a scene, which
  // never looks up a texel, costs nothing), next to the encoded image in the cache directory.
  // Alpha is never encoded.
  int add_encoded(const std::vector<unsigned char>& bytes, const std::string& mime_type,
                  TextureWrap wrap_s, TextureWrap wrap_t, std::string* error, bool srgb = false,
                  bool nearest = false);
  // Registers an image file. Returns -1 with *error set if it cannot be read.
  // nearest: lookups take the closest texel instead of the bilinear blend (a glTF sampler's
  // magFilter NEAREST).
  int add_file(const std::string& path, TextureWrap wrap_s, TextureWrap wrap_t,
               std::string* error, bool srgb = false, bool nearest = false);
  size_t size() const { return entries_.size(); }
  // Width x height of texture i's image (its finest level).
  uint64_t pixels(int texture) const;

  // Bilinear lookup at uv (glTF convention: (0, 0) is the top-left corner of the image) of
  // channels [0, n) (RGBA) into out, linear for an sRGB texture; alpha reads 1 in images without it, and gray images
  // (gray, or gray and alpha) give their gray to red, green and blue. Returns false (and
  // leaves out unchanged) if the lookup fails.
  bool lookup(int texture, Point2 uv, int n, float* out) const;

  // A texture's finest level is read whole into memory at its first lookup, and looked up
  // there (four texel reads for a bilinear lookup), while all the textures this process holds
  // so stay within a budget (2 GiB unless set); one that would exceed it is looked up through
  // the TextureSystem's tile cache (1 GiB, paged from the files), as are images whose data
  // window is not their display window. texel_bytes: what the textures in memory take now.
  static void set_texel_budget(size_t bytes);
  static size_t texel_bytes();

 private:
  struct Entry;
  // Through the TextureSystem (a texture beyond the texel budget): channels [0, want) at uv.
  static bool cache_lookup(const Entry& e, Point2 uv, int want, float* result);
  std::vector<std::unique_ptr<Entry>> entries_;
};

// sRGB transfer function (IEC 61966-2-1) to linear: base color and emissive textures are
// stored sRGB-encoded (glTF spec, 3.9.2).
inline float srgb_to_linear(float c) {
  if (c <= 0.04045f) return c * (1.f / 12.92f);
  return std::pow((c + 0.055f) * (1.f / 1.055f), 2.4f);
}

}  // namespace rf
