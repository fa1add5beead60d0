// Texture lookups from the texels held in memory (TextureSet::lookup) against OpenImageIO's
// own TextureSystem on the same files, which the worker used for every lookup before and still
// uses beyond the memory budget: the same bilinear and closest-texel filters, wrap modes, image
// formats and channel layouts; sRGB textures decoded texel by texel before filtering (glTF
// 3.9.2, the IEC 61966-2-1 formula written out here); and the budget's fallback.
#include <OpenImageIO/imageio.h>
#include <OpenImageIO/texture.h>
#include <gtest/gtest.h>

#include <cmath>
#include <fstream>
#include <random>
#include <string>
#include <vector>

#include "scene/textures.h"
#include "testing/test_scenes.h"

namespace rf {
namespace {

// Writes an image of width x height pixels of `channels` values of `type` (data as floats,
// converted by OpenImageIO on writing).
void write_image(const std::string& path, int width, int height, int channels,
                 OIIO::TypeDesc type, const std::vector<float>& data) {
  auto out = OIIO::ImageOutput::create(path);
  ASSERT_TRUE(out) << path;
  OIIO::ImageSpec spec(width, height, channels, type);
  if (channels == 2 || channels == 4) spec.alpha_channel = channels - 1;
  spec.attribute("oiio:UnassociatedAlpha", 1);
  ASSERT_TRUE(out->open(path, spec)) << out->geterror();
  ASSERT_TRUE(out->write_image(OIIO::TypeFloat, data.data())) << out->geterror();
  ASSERT_TRUE(out->close());
}

struct TestImage {
  std::string path;
  int width, height, channels;
  OIIO::TypeDesc type;
};

// Random texel values for an image of `type` (bytes, 16-bit or float values beyond 1).
std::vector<float> random_texels(const TestImage& im, std::mt19937* rng) {
  std::vector<float> v(size_t(im.width) * size_t(im.height) * size_t(im.channels));
  std::uniform_int_distribution<int> byte(0, 255), word(0, 65535);
  std::uniform_real_distribution<float> real(0.f, 4.f);
  for (float& x : v) {
    if (im.type == OIIO::TypeDesc::UINT8) x = float(byte(*rng)) / 255.f;
    else if (im.type == OIIO::TypeDesc::UINT16) x = float(word(*rng)) / 65535.f;
    else x = real(*rng);
  }
  return v;
}

// OpenImageIO's TextureSystem of this test alone (not the worker's shared one), reading as the
// worker's does.
OIIO::TextureSystem* reference_system() {
  static OIIO::TextureSystem* ts = [] {
    OIIO::TextureSystem* t = OIIO::TextureSystem::create(false);
    t->attribute("unassociatedalpha", 1);
    return t;
  }();
  return ts;
}

OIIO::TextureOpt::Wrap oiio_wrap(TextureWrap w) {
  return w == TextureWrap::Clamp    ? OIIO::TextureOpt::WrapClamp
         : w == TextureWrap::Mirror ? OIIO::TextureOpt::WrapMirror
                                    : OIIO::TextureOpt::WrapPeriodic;
}

// The reference's channels [0, n) at uv.
void reference_lookup(const std::string& path, TextureWrap ws, TextureWrap wt, bool nearest,
                      Point2 uv, int n, float* out) {
  OIIO::TextureOpt opt;
  opt.swrap = oiio_wrap(ws);
  opt.twrap = oiio_wrap(wt);
  opt.interpmode = nearest ? OIIO::TextureOpt::InterpClosest : OIIO::TextureOpt::InterpBilinear;
  opt.mipmode = OIIO::TextureOpt::MipModeNoMIP;
  ASSERT_TRUE(reference_system()->texture(OIIO::ustring(path), opt, uv.x, uv.y, 0.f, 0.f, 0.f,
                                          0.f, n, out))
      << reference_system()->geterror();
}

const TextureWrap kWraps[3][2] = {{TextureWrap::Repeat, TextureWrap::Mirror},
                                  {TextureWrap::Clamp, TextureWrap::Repeat},
                                  {TextureWrap::Mirror, TextureWrap::Clamp}};

TEST(TextureLookup, TexelsInMemoryGiveWhatOpenImageIOsTextureSystemGives) {
  std::mt19937 rng(7);
  const TestImage images[] = {
      {testing::test_path("rgba8.png"), 13, 7, 4, OIIO::TypeDesc::UINT8},
      {testing::test_path("rgb8.png"), 6, 11, 3, OIIO::TypeDesc::UINT8},
      {testing::test_path("gray8.png"), 5, 6, 1, OIIO::TypeDesc::UINT8},
      {testing::test_path("grayalpha8.png"), 3, 4, 2, OIIO::TypeDesc::UINT8},
      {testing::test_path("rgb16.png"), 6, 5, 3, OIIO::TypeDesc::UINT16},
      {testing::test_path("rgb32.exr"), 9, 5, 3, OIIO::TypeDesc::FLOAT},
  };
  std::uniform_real_distribution<float> coord(-2.3f, 3.7f);
  const size_t before = TextureSet::texel_bytes();
  size_t held = 0;
  {
    TextureSet set;
    for (const TestImage& im : images) {
      write_image(im.path, im.width, im.height, im.channels, im.type, random_texels(im, &rng));
      for (const auto& wrap : kWraps)
        for (const bool nearest : {false, true}) {
          std::string error;
          const int tex = set.add_file(im.path, wrap[0], wrap[1], &error, false, nearest);
          ASSERT_GE(tex, 0) << error;
          for (int k = 0; k < 200; ++k) {
            const Point2 uv{coord(rng), coord(rng)};
            float got[4], want[4] = {0.f, 0.f, 0.f, 0.f};
            ASSERT_TRUE(set.lookup(tex, uv, 4, got));
            reference_lookup(im.path, wrap[0], wrap[1], nearest, uv, im.channels, want);
            // Gray images give their gray to red, green and blue, and their alpha (a second
            // channel) to alpha; images without alpha read alpha 1.
            float expect[4] = {want[0], want[0], want[0], 1.f};
            if (im.channels == 2) expect[3] = want[1];
            if (im.channels >= 3)
              for (int c = 0; c < 4; ++c) expect[c] = c < im.channels ? want[c] : 1.f;
            for (int c = 0; c < 4; ++c)
              ASSERT_NEAR(got[c], expect[c], 2e-6f * std::max(1.f, std::abs(expect[c])))
                  << im.path << " channel " << c << " at (" << uv.x << ", " << uv.y
                  << "), wrap " << int(wrap[0]) << "/" << int(wrap[1])
                  << (nearest ? ", closest texel" : ", bilinear");
          }
        }
      // Each image registered six times, each entry holding its own copy.
      const size_t bytes_per_value = im.type == OIIO::TypeDesc::UINT8 ? 1 : 4;
      held += 6 * size_t(im.width) * size_t(im.height) * size_t(im.channels) * bytes_per_value;
    }
    EXPECT_EQ(TextureSet::texel_bytes() - before, held);
  }
  EXPECT_EQ(TextureSet::texel_bytes(), before) << "a set's texels are freed with it";
}

// IEC 61966-2-1's decoding, written here rather than taken from the code under test.
double iec_srgb_to_linear(double c) {
  return c <= 0.04045 ? c / 12.92 : std::pow((c + 0.055) / 1.055, 2.4);
}

TEST(TextureLookup, SrgbTexelsAreDecodedBeforeTheBilinearBlend) {
  // Random 8-bit sRGB texels with alpha: the blend of decoded texels (glTF 3.9.2: colours
  // are linear before filtering; alpha is never encoded), compared with the reference's
  // bilinear lookup of a float image of the decoded colours and the alpha as it is.
  std::mt19937 rng(11);
  const TestImage encoded{testing::test_path("srgb.png"), 7, 6, 4, OIIO::TypeDesc::UINT8};
  const std::vector<float> bytes = random_texels(encoded, &rng);
  write_image(encoded.path, encoded.width, encoded.height, 4, encoded.type, bytes);
  std::vector<float> decoded(bytes);
  for (size_t i = 0; i < bytes.size(); ++i)
    if (i % 4 != 3) decoded[i] = float(iec_srgb_to_linear(std::round(bytes[i] * 255.0) / 255.0));
  const std::string linear = testing::test_path("srgb-decoded.exr");
  write_image(linear, encoded.width, encoded.height, 4, OIIO::TypeDesc::FLOAT, decoded);
  TextureSet set;
  std::string error;
  const int tex =
      set.add_file(encoded.path, TextureWrap::Repeat, TextureWrap::Repeat, &error, true);
  ASSERT_GE(tex, 0) << error;
  std::uniform_real_distribution<float> coord(0.f, 1.f);
  for (int k = 0; k < 300; ++k) {
    const Point2 uv{coord(rng), coord(rng)};
    float got[4], want[4];
    ASSERT_TRUE(set.lookup(tex, uv, 4, got));
    reference_lookup(linear, TextureWrap::Repeat, TextureWrap::Repeat, false, uv, 4, want);
    for (int c = 0; c < 4; ++c)
      ASSERT_NEAR(got[c], want[c], 2e-6f) << "channel " << c << " at (" << uv.x << ", " << uv.y
                                          << ")";
  }
}

TEST(TextureLookup, BeyondTheBudgetLookupsGoThroughTheTextureSystemAndAgree) {
  std::mt19937 rng(3);
  const TestImage im{testing::test_path("budget.png"), 10, 9, 4, OIIO::TypeDesc::UINT8};
  write_image(im.path, im.width, im.height, im.channels, im.type, random_texels(im, &rng));
  std::string error;
  TextureSet in_memory;
  const int a = in_memory.add_file(im.path, TextureWrap::Repeat, TextureWrap::Clamp, &error);
  ASSERT_GE(a, 0) << error;
  float first[4];
  ASSERT_TRUE(in_memory.lookup(a, {0.5f, 0.5f}, 4, first));  // reads its texels
  const size_t held = TextureSet::texel_bytes();
  TextureSet::set_texel_budget(held);  // nothing more fits
  TextureSet paged;
  const int b = paged.add_file(im.path, TextureWrap::Repeat, TextureWrap::Clamp, &error);
  ASSERT_GE(b, 0) << error;
  std::uniform_real_distribution<float> coord(-1.f, 2.f);
  for (int k = 0; k < 200; ++k) {
    const Point2 uv{coord(rng), coord(rng)};
    float x[4], y[4];
    ASSERT_TRUE(in_memory.lookup(a, uv, 4, x));
    ASSERT_TRUE(paged.lookup(b, uv, 4, y));
    for (int c = 0; c < 4; ++c) ASSERT_NEAR(x[c], y[c], 2e-6f) << "channel " << c;
  }
  EXPECT_EQ(TextureSet::texel_bytes(), held) << "the second set's texels stayed on disk";
  TextureSet::set_texel_budget(size_t(2) << 30);
}

}  // namespace
}  // namespace rf
