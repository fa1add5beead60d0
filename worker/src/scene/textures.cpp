#include "scene/textures.h"

#include <OpenImageIO/imageio.h>
#include <OpenImageIO/texture.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <atomic>
#include <cstring>
#include <iterator>
#include <filesystem>
#include <fstream>
#include <mutex>
#include <new>
#include <unistd.h>

#include "util/sha256.h"

namespace fs = std::filesystem;

namespace rf {

namespace {

OIIO::TextureSystem* texture_system() {
  static OIIO::TextureSystem* ts = [] {
    OIIO::TextureSystem* t = OIIO::TextureSystem::create(true);
    t->attribute("automip", 1);          // MIP-map plain PNG/JPEG on demand
    // glTF colours are not premultiplied by their alpha (a PNG's never are): keep them as they
    // are rather than let the readers associate alpha (which would darken every texel of
    // alpha below 1, also on opaque materials, whose alpha glTF ignores).
    t->attribute("unassociatedalpha", 1);
    t->attribute("max_memory_MB", 1024.f);
    return t;
  }();
  return ts;
}

// The colour channels of an image of nc channels, the ones an sRGB texture encodes: gray
// (one or two channels: gray and alpha) or RGB; alpha is never encoded.
int colour_channels(int nc) { return nc <= 2 ? 1 : std::min(3, nc); }

OIIO::TextureOpt::Wrap to_oiio(TextureWrap w) {
  switch (w) {
    case TextureWrap::Clamp:
      return OIIO::TextureOpt::WrapClamp;
    case TextureWrap::Mirror:
      return OIIO::TextureOpt::WrapMirror;
    case TextureWrap::Repeat:
      break;
  }
  return OIIO::TextureOpt::WrapPeriodic;
}

std::string extension_for(const std::vector<unsigned char>& b, const std::string& mime) {
  if (b.size() >= 8 && b[0] == 0x89 && b[1] == 'P' && b[2] == 'N' && b[3] == 'G') return ".png";
  if (b.size() >= 3 && b[0] == 0xff && b[1] == 0xd8 && b[2] == 0xff) return ".jpg";
  if (b.size() >= 4 && b[0] == 0x76 && b[1] == 0x2f && b[2] == 0x31 && b[3] == 0x01)
    return ".exr";
  if (b.size() >= 2 && b[0] == '#' && b[1] == '?') return ".hdr";
  // RIFF....WEBP (EXT_texture_webp); an ISO-BMFF box "ftyp" with brand avif or avis
  // (EXT_texture_avif). OpenImageIO picks its reader by the file's extension.
  if (b.size() >= 12 && std::memcmp(b.data(), "RIFF", 4) == 0 &&
      std::memcmp(b.data() + 8, "WEBP", 4) == 0)
    return ".webp";
  if (b.size() >= 12 && std::memcmp(b.data() + 4, "ftyp", 4) == 0 &&
      (std::memcmp(b.data() + 8, "avif", 4) == 0 || std::memcmp(b.data() + 8, "avis", 4) == 0))
    return ".avif";
  if (mime == "image/png") return ".png";
  if (mime == "image/webp") return ".webp";
  if (mime == "image/avif") return ".avif";
  if (mime == "image/jpeg") return ".jpg";
  return ".img";
}


// Writes `linear`: the image at `encoded` with its colour channels (gray, or RGB) decoded from
// sRGB, as floats (the values srgb_to_linear gives, and alpha exactly as read, so that MASK
// cutoffs decide as on the encoded image), a band of rows at a time into 64 x 64 tiles (a
// texture may be far larger than the memory one lookup should take; the TextureSystem then
// pages tiles into its bounded cache). Written under a temporary name and renamed, so that concurrent
// renders never read a partial file. False if any step fails.
bool write_linear_copy(const std::string& encoded, const fs::path& linear) {
  OIIO::ImageSpec config;
  config.attribute("oiio:UnassociatedAlpha", 1);  // as the TextureSystem reads it
  auto in = OIIO::ImageInput::open(encoded, &config);
  if (!in) return false;
  const OIIO::ImageSpec spec = in->spec();
  const int nc = spec.nchannels;
  const int colour = colour_channels(nc);
  static std::atomic<uint64_t> counter{0};
  const fs::path tmp = linear.parent_path() /
                       ("." + linear.filename().string() + "." + std::to_string(::getpid()) +
                        "." + std::to_string(++counter) + ".tmp.exr");
  auto out = OIIO::ImageOutput::create(tmp.string());
  constexpr int kRows = 64;  // the tile size: a band is one row of tiles
  OIIO::ImageSpec out_spec(spec.width, spec.height, nc, OIIO::TypeFloat);
  out_spec.channelnames = spec.channelnames;
  out_spec.alpha_channel = spec.alpha_channel;
  out_spec.tile_width = out_spec.tile_height = kRows;
  if (!out || !out->open(tmp.string(), out_spec)) return false;
  std::vector<float> rows(size_t(spec.width) * kRows * size_t(nc));
  bool ok = true;
  for (int y = spec.y; ok && y < spec.y + spec.height; y += kRows) {
    const int y1 = std::min(spec.y + spec.height, y + kRows);
    ok = in->read_scanlines(0, 0, y, y1, 0, 0, nc, OIIO::TypeFloat, rows.data());
    const size_t texels = size_t(spec.width) * size_t(y1 - y);
    for (size_t i = 0; ok && i < texels; ++i)
      for (int c = 0; c < colour; ++c) {
        float& v = rows[i * size_t(nc) + size_t(c)];
        v = srgb_to_linear(v);
      }
    ok = ok && out->write_tiles(spec.x, spec.x + spec.width, y, y1, 0, 1, OIIO::TypeFloat,
                                rows.data());
  }
  ok = out->close() && ok;
  std::error_code ec;
  if (ok) fs::rename(tmp, linear, ec);
  if (!ok || ec) fs::remove(tmp, ec);
  return ok && !ec;
}

// A texture's finest level held in memory, read whole at its first lookup: a bilinear lookup
// is then four texel reads, where the TextureSystem's tile cache (for textures beyond the
// budget below) costs a tile search, its locks and its statistics' clock readings per lookup
// (half the worker's time on the realistic floor's textures, docs/parity.md). 8-bit images
// keep their bytes (a texel's value is a table's, 1 / 255 steps or, for sRGB textures, their
// decoded values: texel by texel before filtering, as the linear copy does); others are read
// as floats, sRGB ones decoded as they are read.
struct Texels {
  int width = 0, height = 0, channels = 0;  // channels: the first min(4, image's) kept
  std::vector<uint8_t> bytes;               // 8-bit images
  std::vector<float> floats;                // the others
  // 8-bit images: the 256 values of a byte in channel c, table[c] (the colour channels of an
  // sRGB texture decoded, its alpha as it is).
  std::array<const float*, 4> table{};
  size_t memory() const { return bytes.size() + floats.size() * sizeof(float); }
};

// The texels held in memory by all the scenes of this process, and the most they may hold:
// a texture that would take more goes through the TextureSystem's bounded tile cache.
std::atomic<size_t> g_texel_bytes{0};
std::atomic<size_t> g_texel_budget{size_t(2) << 30};

const float* byte_table(bool srgb) {
  static const auto tables = [] {
    std::array<std::array<float, 256>, 2> t{};
    for (int v = 0; v < 256; ++v) {
      t[0][size_t(v)] = float(v) / 255.f;
      t[1][size_t(v)] = srgb_to_linear(float(v) / 255.f);
    }
    return t;
  }();
  return tables[srgb ? 1 : 0].data();
}

// The image at `path` (its first subimage's finest level), or null if it cannot be read
// whole here (a data window that is not its display window, a deep image, the budget spent):
// the caller then goes through the TextureSystem, which handles those.
std::unique_ptr<Texels> load_texels(const std::string& path, bool srgb) {
  OIIO::ImageSpec config;
  config.attribute("oiio:UnassociatedAlpha", 1);  // as the TextureSystem reads it
  auto in = OIIO::ImageInput::open(path, &config);
  if (!in) return nullptr;
  const OIIO::ImageSpec& spec = in->spec();
  if (spec.deep || spec.depth > 1 || spec.width <= 0 || spec.height <= 0 ||
      spec.nchannels <= 0 || spec.x != spec.full_x || spec.y != spec.full_y ||
      spec.width != spec.full_width || spec.height != spec.full_height)
    return nullptr;
  auto t = std::make_unique<Texels>();
  t->width = spec.width;
  t->height = spec.height;
  t->channels = std::min(4, spec.nchannels);
  const bool u8 = spec.format == OIIO::TypeDesc::UINT8;
  const size_t values = size_t(spec.width) * size_t(spec.height) * size_t(t->channels);
  const size_t bytes = values * (u8 ? 1 : sizeof(float));
  size_t held = g_texel_bytes.load();
  do {
    if (held + bytes > g_texel_budget.load()) return nullptr;
  } while (!g_texel_bytes.compare_exchange_weak(held, held + bytes));
  bool ok;
  // Memory refused (a process under a memory limit): the texture goes through the
  // TextureSystem's bounded cache instead.
  try {
    if (u8) t->bytes.resize(values);
    else t->floats.resize(values);
  } catch (const std::bad_alloc&) {
    g_texel_bytes -= bytes;
    return nullptr;
  }
  if (u8) {
    ok = in->read_image(0, 0, 0, t->channels, OIIO::TypeDesc::UINT8, t->bytes.data());
    for (int c = 0; c < t->channels; ++c)
      t->table[size_t(c)] = byte_table(srgb && c < colour_channels(t->channels));
  } else {
    ok = in->read_image(0, 0, 0, t->channels, OIIO::TypeFloat, t->floats.data());
    if (ok && srgb) {
      const int colour = colour_channels(t->channels);
      for (size_t i = 0; i < values; i += size_t(t->channels))
        for (int c = 0; c < colour; ++c) {
          float& v = t->floats[i + size_t(c)];
          v = srgb_to_linear(v);
        }
    }
  }
  if (!ok) {
    g_texel_bytes -= bytes;
    return nullptr;
  }
  return t;
}

// Texel index i of a row or column of n texels under a wrap mode (OpenImageIO's and OpenGL's
// meanings: periodic, clamped to the edge, mirrored every other period).
inline int64_t wrap_index(int64_t i, int64_t n, TextureWrap wrap) {
  if (uint64_t(i) < uint64_t(n)) return i;  // inside the image: every mode's identity
  switch (wrap) {
    case TextureWrap::Clamp:
      return std::clamp<int64_t>(i, 0, n - 1);
    case TextureWrap::Mirror: {
      const int64_t m = ((i % (2 * n)) + 2 * n) % (2 * n);
      return m < n ? m : 2 * n - 1 - m;
    }
    case TextureWrap::Repeat:
      break;
  }
  return ((i % n) + n) % n;
}

// The texel coordinate s * n, kept finite and within what an int64_t holds (a coordinate
// that far out of [0, 1] is meaningless at float precision anyway).
inline float texel_coordinate(float s, int n) {
  const float x = s * float(n);
  return std::isfinite(x) ? std::clamp(x, -1e15f, 1e15f) : 0.f;
}

// Channels [0, want) of texel (x, y), added with weight w into out.
inline void add_texel(const Texels& t, int64_t x, int64_t y, float w, int want, float* out) {
  const size_t at = (size_t(y) * size_t(t.width) + size_t(x)) * size_t(t.channels);
  if (!t.bytes.empty())
    for (int c = 0; c < want; ++c) out[c] += w * t.table[size_t(c)][t.bytes[at + size_t(c)]];
  else
    for (int c = 0; c < want; ++c) out[c] += w * t.floats[at + size_t(c)];
}

// The bilinear blend of the four texels around uv (texel centres at half-integers, as the
// TextureSystem's), or the closest texel; channels [0, want) into out.
void texel_lookup(const Texels& t, TextureWrap wrap_s, TextureWrap wrap_t, bool nearest,
                  Point2 uv, int want, float* out) {
  for (int c = 0; c < want; ++c) out[c] = 0.f;
  if (nearest) {
    const int64_t x = wrap_index(int64_t(std::floor(texel_coordinate(uv.x, t.width))), t.width,
                                 wrap_s);
    const int64_t y = wrap_index(int64_t(std::floor(texel_coordinate(uv.y, t.height))),
                                 t.height, wrap_t);
    add_texel(t, x, y, 1.f, want, out);
    return;
  }
  const float fx = texel_coordinate(uv.x, t.width) - 0.5f;
  const float fy = texel_coordinate(uv.y, t.height) - 0.5f;
  const float x0f = std::floor(fx), y0f = std::floor(fy);
  const float ax = fx - x0f, ay = fy - y0f;
  const int64_t x0 = wrap_index(int64_t(x0f), t.width, wrap_s);
  const int64_t y0 = wrap_index(int64_t(y0f), t.height, wrap_t);
  // The next texel: periodic, the one after the wrapped first (no second division).
  const int64_t x1 = wrap_s == TextureWrap::Repeat ? (x0 + 1 == t.width ? 0 : x0 + 1)
                                                   : wrap_index(int64_t(x0f) + 1, t.width, wrap_s);
  const int64_t y1 = wrap_t == TextureWrap::Repeat ? (y0 + 1 == t.height ? 0 : y0 + 1)
                                                   : wrap_index(int64_t(y0f) + 1, t.height, wrap_t);
  add_texel(t, x0, y0, (1.f - ax) * (1.f - ay), want, out);
  add_texel(t, x1, y0, ax * (1.f - ay), want, out);
  add_texel(t, x0, y1, (1.f - ax) * ay, want, out);
  add_texel(t, x1, y1, ax * ay, want, out);
}

}  // namespace

struct TextureSet::Entry {
  OIIO::ustring filename;
  OIIO::TextureSystem::TextureHandle* handle = nullptr;
  int channels = 0;
  TextureWrap wrap_s = TextureWrap::Repeat, wrap_t = TextureWrap::Repeat;
  // sRGB textures looked up through the TextureSystem (beyond the texel budget): the linear
  // copy's path, made at the first such lookup (std::call_once), whose handle then replaces
  // the encoded image's. If it cannot be made, lookups decode after
  // filtering (decode_after), as a last resort that keeps the render going.
  bool nearest = false;  // InterpClosest instead of InterpBilinear
  bool srgb = false;
  std::string linear_path;
  mutable std::once_flag linear_once;
  mutable OIIO::TextureSystem::TextureHandle* linear_handle = nullptr;
  mutable bool decode_after = false;
  // The texels in memory (load_texels), read at the first lookup; null: through the
  // TextureSystem.
  mutable std::once_flag texels_once;
  mutable std::unique_ptr<Texels> texels;
  ~Entry() {
    if (texels) g_texel_bytes -= texels->memory();
  }
};

TextureSet::TextureSet() = default;
TextureSet::~TextureSet() = default;

int TextureSet::add_file(const std::string& path, TextureWrap wrap_s, TextureWrap wrap_t,
                         std::string* error, bool srgb, bool nearest) {
  if (srgb) {  // by its bytes: the linear copy is named by their hash
    std::ifstream in(path, std::ios::binary);
    const std::vector<unsigned char> bytes((std::istreambuf_iterator<char>(in)),
                                           std::istreambuf_iterator<char>());
    if (!in.bad() && !bytes.empty())
      return add_encoded(bytes, "", wrap_s, wrap_t, error, true, nearest);
  }
  OIIO::TextureSystem* ts = texture_system();
  auto e = std::make_unique<Entry>();
  e->filename = OIIO::ustring(path);
  e->handle = ts->get_texture_handle(e->filename);
  int channels = 0;
  if (!e->handle ||
      !ts->get_texture_info(e->filename, 0, OIIO::ustring("channels"), OIIO::TypeInt,
                            &channels) ||
      channels <= 0) {
    // The message names no file: the path is this machine's (a cache or temporary file), and
    // the message reaches the user; the caller names the texture.
    if (error) {
      std::string why = ts->geterror();
      for (size_t at = why.find(path); !path.empty() && at != std::string::npos;
           at = why.find(path, at))
        why.replace(at, path.size(), "the image");
      *error = "OpenImageIO cannot read the image: " + why;
    }
    return -1;
  }
  e->channels = channels;
  e->wrap_s = wrap_s;
  e->wrap_t = wrap_t;
  e->nearest = nearest;
  entries_.push_back(std::move(e));
  return int(entries_.size() - 1);
}

int TextureSet::add_encoded(const std::vector<unsigned char>& bytes, const std::string& mime,
                            TextureWrap wrap_s, TextureWrap wrap_t, std::string* error,
                            bool srgb, bool nearest) {
  if (bytes.empty()) {
    if (error) *error = "image has no data";
    return -1;
  }
  const std::string hex =
      sha256_hex(std::string(reinterpret_cast<const char*>(bytes.data()), bytes.size()));
  std::error_code ec;
  const fs::path dir = fs::temp_directory_path(ec) / "renderfarm-textures";
  fs::create_directories(dir, ec);
  const fs::path path = dir / (hex + extension_for(bytes, mime));
  if (!fs::is_regular_file(path, ec) || fs::file_size(path, ec) != bytes.size()) {
    // Write under a unique temporary name, then rename (atomic within one directory), so
    // concurrent loaders never see a partial file.
    static std::mutex counter_mutex;
    static uint64_t counter = 0;
    uint64_t n;
    {
      std::lock_guard<std::mutex> lock(counter_mutex);
      n = ++counter;
    }
    const fs::path tmp =
        dir / ("." + hex + "." + std::to_string(::getpid()) + "." + std::to_string(n) + ".tmp");
    {
      std::ofstream out(tmp, std::ios::binary | std::ios::trunc);
      out.write(reinterpret_cast<const char*>(bytes.data()), std::streamsize(bytes.size()));
      if (!out) {
        if (error) *error = "cannot write the image to the temporary directory";
        return -1;
      }
    }
    fs::rename(tmp, path, ec);
    if (ec) {
      fs::remove(tmp, ec);
      if (error) *error = "cannot write the image to the temporary directory";
      return -1;
    }
  }
  const int index = add_file(path.string(), wrap_s, wrap_t, error, false, nearest);
  if (index >= 0 && srgb) {
    Entry& e = *entries_[size_t(index)];
    e.srgb = true;
    // Named by the source and the conversion (a change of it must not reuse older copies).
    e.linear_path = (dir / (hex + ".linear-f32-t64.exr")).string();
  }
  return index;
}

void TextureSet::set_texel_budget(size_t bytes) { g_texel_budget = bytes; }
size_t TextureSet::texel_bytes() { return g_texel_bytes.load(); }

uint64_t TextureSet::pixels(int texture) const {
  if (texture < 0 || size_t(texture) >= entries_.size()) return 0;
  int resolution[2] = {0, 0};
  OIIO::TextureSystem* ts = texture_system();
  if (!ts->get_texture_info(entries_[size_t(texture)]->filename, 0, OIIO::ustring("resolution"),
                            OIIO::TypeDesc(OIIO::TypeDesc::INT, 2), resolution))
    return 0;
  return uint64_t(std::max(0, resolution[0])) * uint64_t(std::max(0, resolution[1]));
}

// Through the TextureSystem (a texture beyond the texel budget): channels [0, want) at uv
// into result, false if the lookup fails.
bool TextureSet::cache_lookup(const Entry& e, Point2 uv, int want, float* result) {
  OIIO::TextureOpt opt;
  opt.swrap = to_oiio(e.wrap_s);
  opt.twrap = to_oiio(e.wrap_t);
  opt.interpmode = e.nearest ? OIIO::TextureOpt::InterpClosest : OIIO::TextureOpt::InterpBilinear;
  opt.mipmode = OIIO::TextureOpt::MipModeNoMIP;  // no ray differentials: finest level
  OIIO::TextureSystem* ts = texture_system();
  OIIO::TextureSystem::TextureHandle* handle = e.handle;
  if (e.srgb) {
    std::call_once(e.linear_once, [&] {
      std::error_code ec;
      if (fs::is_regular_file(e.linear_path, ec) ||
          write_linear_copy(e.filename.string(), e.linear_path))
        e.linear_handle = ts->get_texture_handle(OIIO::ustring(e.linear_path));
      e.decode_after = e.linear_handle == nullptr;
    });
    if (e.linear_handle) handle = e.linear_handle;
  }
  if (!ts->texture(handle, ts->get_perthread_info(), opt, uv.x, uv.y, 0.f, 0.f, 0.f, 0.f, want,
                   result))
    return false;
  if (e.decode_after)
    for (int c = 0; c < std::min(colour_channels(e.channels), want); ++c)
      result[c] = srgb_to_linear(result[c]);
  return true;
}

bool TextureSet::lookup(int texture, Point2 uv, int n, float* out) const {
  if (texture < 0 || size_t(texture) >= entries_.size()) return false;
  const Entry& e = *entries_[size_t(texture)];
  float result[4] = {1.f, 1.f, 1.f, 1.f};
  // Gray images (one channel, or gray and alpha) give their gray to red, green and blue; the
  // alpha of a gray-and-alpha image is its second channel.
  const bool gray = e.channels <= 2;
  const int want = gray ? (n >= 4 && e.channels == 2 ? 2 : 1)
                        : std::min(4, std::max(1, std::min(n, e.channels)));
  std::call_once(e.texels_once, [&] { e.texels = load_texels(e.filename.string(), e.srgb); });
  if (e.texels)
    texel_lookup(*e.texels, e.wrap_s, e.wrap_t, e.nearest, uv, want, result);
  else if (!cache_lookup(e, uv, want, result))
    return false;
  for (int c = 0; c < n; ++c) {
    if (c == 3) out[c] = gray ? (want == 2 ? result[1] : 1.f) : (want > 3 ? result[3] : 1.f);
    else out[c] = gray ? result[0] : result[std::min(c, want - 1)];
  }
  return true;
}

}  // namespace rf
