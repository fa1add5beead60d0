#include "util/isa.h"

#include <gtest/gtest.h>

#include <cstdlib>
#include <stdexcept>
#include <string>
#include <utility>

#include "scene/scene.h"
#include "testing/test_scenes.h"

namespace rf {
namespace {

TEST(Isa, NamesParseBackToTheirCap) {
  for (IsaCap cap : {IsaCap::Sse42, IsaCap::Avx2, IsaCap::Avx512, IsaCap::Native}) {
    IsaCap parsed = IsaCap::Sse42;
    ASSERT_TRUE(parse_isa_cap(isa_cap_name(cap), &parsed)) << isa_cap_name(cap);
    EXPECT_EQ(parsed, cap);
  }
  IsaCap parsed;
  for (const char* bad : {"AVX2", "avx", "avx-512", "sse42", "", "native "})
    EXPECT_FALSE(parse_isa_cap(bad, &parsed)) << bad;
}

TEST(Isa, UnsetMeansAvx2AndABadValueNamesTheVariable) {
  EXPECT_EQ(isa_cap_from(nullptr), IsaCap::Avx2);
  EXPECT_EQ(isa_cap_from(""), IsaCap::Avx2);
  EXPECT_EQ(isa_cap_from("native"), IsaCap::Native);
  EXPECT_EQ(isa_cap_from("sse4.2"), IsaCap::Sse42);
  try {
    isa_cap_from("avx1024");
    FAIL() << "avx1024 accepted";
  } catch (const std::invalid_argument& e) {
    const std::string message = e.what();
    EXPECT_NE(message.find("RENDERFARM_ISA"), std::string::npos) << message;
    EXPECT_NE(message.find("avx1024"), std::string::npos) << message;
  }
}

TEST(Isa, EmbreeIsCappedByTheDeviceConfiguration) {
  EXPECT_EQ(embree_device_config(IsaCap::Avx2), "max_isa=avx2");
  EXPECT_EQ(embree_device_config(IsaCap::Sse42), "max_isa=sse4.2");
  EXPECT_EQ(embree_device_config(IsaCap::Avx512), "max_isa=avx512");
  EXPECT_EQ(embree_device_config(IsaCap::Native), "");
  EXPECT_TRUE(isa_allows(IsaCap::Avx2, IsaCap::Sse42));
  EXPECT_TRUE(isa_allows(IsaCap::Avx2, IsaCap::Avx2));
  EXPECT_FALSE(isa_allows(IsaCap::Avx2, IsaCap::Avx512));
  EXPECT_TRUE(isa_allows(IsaCap::Native, IsaCap::Avx512));
}

TEST(Isa, AScenesEmbreeRunsWithinTheCap) {
  // Under a cap below AVX-512 Embree has no native 16-wide ray packets (its AVX-512 kernels
  // are the only ones with them), so the scene queries 8 lanes at a time: on a CPU with
  // AVX-512 this fails if the cap did not reach Embree's device.
  if (!isa_allows(isa_cap(), IsaCap::Avx512)) {
    SceneDescription desc;
    desc.materials = {Material{}};
    testing::add_quad(&desc, {-1, -1, 0}, {1, -1, 0}, {1, 1, 0}, {-1, 1, 0}, 0);
    const Scene scene(std::move(desc));
    EXPECT_EQ(scene.packet_query_width(), 8);
  } else {
    // RENDERFARM_ISA=avx512 or native in the test's environment: nothing is capped below.
    EXPECT_TRUE(std::getenv("RENDERFARM_ISA") != nullptr);
  }
}

}  // namespace
}  // namespace rf
