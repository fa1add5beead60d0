#include "render/render.h"

#include <gtest/gtest.h>
#include <OpenImageIO/imageio.h>

#include <cstdio>
#include <cstring>

#include "testing/test_scenes.h"

namespace rf {
namespace {

TEST(RenderImage, OneAndTwoThreadsAreBitwiseIdentical) {
  Scene scene(testing::plane_under_emitter(0.6f, 5.f, 1.f, 1.f, 1.f, {0.5f, -2.5f, 1.5f}, 1.f));
  RenderSettings settings;
  settings.width = 70;  // not a multiple of the tile size
  settings.height = 40;
  settings.seed = 5;
  RenderStats s1, s2;
  const Image a = render_image(scene, settings, 8, 1, &s1);
  const Image b = render_image(scene, settings, 8, 2, &s2);
  ASSERT_EQ(a.rgb.size(), b.rgb.size());
  EXPECT_EQ(std::memcmp(a.rgb.data(), b.rgb.data(), a.rgb.size() * sizeof(float)), 0);
  EXPECT_EQ(std::memcmp(a.albedo.data(), b.albedo.data(), a.albedo.size() * sizeof(float)), 0);
  EXPECT_EQ(std::memcmp(a.normal.data(), b.normal.data(), a.normal.size() * sizeof(float)), 0);
  EXPECT_EQ(s1.rays, s2.rays);
  EXPECT_EQ(s1.samples, 70u * 40u * 8u);
  float max_value = 0.f;
  for (float v : a.rgb) max_value = std::max(max_value, v);
  EXPECT_GT(max_value, 0.f);
}

TEST(RenderImage, WritesExrWithAllChannels) {
  Scene scene(testing::plane_under_emitter(0.6f, 5.f, 1.f, 1.f, 1.f, {0.5f, -2.5f, 1.5f}, 1.f));
  RenderSettings settings;
  settings.width = 20;
  settings.height = 10;
  const Image image = render_image(scene, settings, 4, 2, nullptr);
  const std::string path = testing::test_path("render_test.exr");
  write_exr(path, image);
  auto in = OIIO::ImageInput::open(path);
  ASSERT_TRUE(in);
  const OIIO::ImageSpec& spec = in->spec();
  EXPECT_EQ(spec.width, 20);
  EXPECT_EQ(spec.height, 10);
  ASSERT_EQ(spec.nchannels, 11);
  EXPECT_EQ(spec.alpha_channel, 3);
  std::vector<float> pixels(20 * 10 * 11);
  ASSERT_TRUE(in->read_image(0, 0, 0, 11, OIIO::TypeDesc::FLOAT, pixels.data()));
  bool saw_depth = false, saw_alpha = false;
  for (int c = 0; c < 11; ++c) {
    const std::string name = spec.channelnames[size_t(c)];
    if (name == "depth" || name == "A") {
      const std::vector<float>& plane = name == "A" ? image.alpha : image.depth;
      (name == "A" ? saw_alpha : saw_depth) = true;
      float top = 0.f;
      for (size_t i = 0; i < 200; ++i) {
        ASSERT_EQ(pixels[11 * i + size_t(c)], plane[i]) << name;
        top = std::max(top, plane[i]);
      }
      // The plane is ~3 units from the camera; alpha is a share of samples, at most 1.
      if (name == "depth") {
        EXPECT_GT(top, 1.f);
      } else {
        EXPECT_LE(top, 1.f);
      }
      continue;
    }
    const std::vector<float>* plane = name.rfind("albedo.", 0) == 0   ? &image.albedo
                                      : name.rfind("normal.", 0) == 0 ? &image.normal
                                                                      : &image.rgb;
    const char last = name.back();
    const int k = (last == 'R' || last == 'X') ? 0 : (last == 'G' || last == 'Y') ? 1 : 2;
    for (size_t i = 0; i < 200; ++i)
      ASSERT_EQ(pixels[11 * i + size_t(c)], (*plane)[3 * i + size_t(k)]) << name;
  }
  EXPECT_TRUE(saw_alpha);
  EXPECT_TRUE(saw_depth);
  in->close();
  std::remove(path.c_str());
}

TEST(Film, PackingIsLittleEndian) {
  const std::string bytes = pack_f64_le({1.0});
  ASSERT_EQ(bytes.size(), 8u);
  EXPECT_EQ(static_cast<unsigned char>(bytes[7]), 0x3f);  // 1.0 = 0x3ff0000000000000
  EXPECT_EQ(static_cast<unsigned char>(bytes[6]), 0xf0);
  EXPECT_EQ(unpack_f32_le(pack_f32_le({1.5f, -2.f})), (std::vector<float>{1.5f, -2.f}));
}

}  // namespace
}  // namespace rf
