// End-to-end test of farm mode against an in-process fake server.
#include "farm/farm_client.h"

#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <condition_variable>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <string>
#include <thread>
#include <vector>

#include "render/channel_table.h"
#include "render/channels.h"
#include "render/integrators.h"
#include "render/light_groups.h"
#include "render/motion.h"
#include "scene/animated_scene.h"
#include "renderfarm/v1/scenes.grpc.pb.h"
#include "renderfarm/v1/workers.grpc.pb.h"
#include "util/sha256.h"
#include "testing/test_scenes.h"
// Last: OpenImageIO defines byte-swap macros that break protobuf headers included after it.
#include <OpenImageIO/imageio.h>

namespace pb = renderfarm::v1;
namespace fs = std::filesystem;

namespace rf {
namespace {

// Loads at the tasks' image height, which sets the width of the test scene's lines.
LoadOptions at_height(uint32_t height) {
  LoadOptions load;
  load.image_height = height;
  return load;
}

struct FakeFarm {
  std::mutex mutex;
  std::condition_variable cv;
  std::vector<pb::WorkerMessage> received;
  grpc::ServerReaderWriter<pb::ServerMessage, pb::WorkerMessage>* stream = nullptr;
  bool stream_ended = false;
  std::string scene_bytes, scene_sha;
  int fetches = 0;
  // Environment maps, stored and served like scenes.
  std::string env_bytes, env_sha;
  int env_fetches = 0;
  // While true, FetchScene waits (a task that fetches stays in flight).
  bool hold_fetches = false;

  template <typename Pred>
  bool wait_for(Pred pred, int seconds = 60) {
    std::unique_lock<std::mutex> lock(mutex);
    return cv.wait_for(lock, std::chrono::seconds(seconds), [&] { return pred(); });
  }
  bool send(const pb::ServerMessage& m) {
    std::lock_guard<std::mutex> lock(mutex);
    return stream && stream->Write(m);
  }
  bool assign(const pb::Task& t) {
    pb::ServerMessage m;
    *m.mutable_assign()->mutable_task() = t;
    return send(m);
  }
  // With mutex held (wait_for's predicates): whether a heartbeat listed task `id` in flight,
  // and whether its result came.
  bool in_heartbeat(const std::string& id) const {
    for (const auto& m : received)
      if (m.has_heartbeat())
        for (const auto& t : m.heartbeat().task_ids())
          if (t == id) return true;
    return false;
  }
  bool has_result(const std::string& id) const {
    for (const auto& m : received)
      if (m.has_result() && m.result().task_id() == id) return true;
    return false;
  }
};

class FakeWorkerService final : public pb::WorkerService::Service {
 public:
  explicit FakeWorkerService(FakeFarm* farm) : farm_(farm) {}
  grpc::Status Connect(grpc::ServerContext*,
                       grpc::ServerReaderWriter<pb::ServerMessage, pb::WorkerMessage>* stream) override {
    pb::WorkerMessage m;
    if (!stream->Read(&m) || !m.has_hello())
      return grpc::Status(grpc::StatusCode::INVALID_ARGUMENT, "expected Hello");
    pb::ServerMessage welcome;
    welcome.mutable_welcome()->set_worker_id("fake-1");
    welcome.mutable_welcome()->set_heartbeat_interval_ms(100);
    welcome.mutable_welcome()->set_lease_ms(10000);
    stream->Write(welcome);
    {
      std::lock_guard<std::mutex> lock(farm_->mutex);
      farm_->received.push_back(m);
      farm_->stream = stream;
    }
    farm_->cv.notify_all();
    while (stream->Read(&m)) {
      std::lock_guard<std::mutex> lock(farm_->mutex);
      farm_->received.push_back(m);
      farm_->cv.notify_all();
    }
    std::lock_guard<std::mutex> lock(farm_->mutex);
    farm_->stream = nullptr;
    farm_->stream_ended = true;
    farm_->cv.notify_all();
    return grpc::Status::OK;
  }

 private:
  FakeFarm* farm_;
};

class FakeSceneService final : public pb::SceneService::Service {
 public:
  explicit FakeSceneService(FakeFarm* farm) : farm_(farm) {}
  grpc::Status FetchScene(grpc::ServerContext*, const pb::FetchSceneRequest* request,
                          grpc::ServerWriter<pb::SceneChunk>* writer) override {
    {
      std::unique_lock<std::mutex> lock(farm_->mutex);
      farm_->cv.wait(lock, [&] { return !farm_->hold_fetches; });
    }
    const bool env = !farm_->env_sha.empty() && request->sha256() == farm_->env_sha;
    if (request->sha256() != farm_->scene_sha && !env)
      return grpc::Status(grpc::StatusCode::NOT_FOUND, "unknown scene");
    {
      std::lock_guard<std::mutex> lock(farm_->mutex);
      ++(env ? farm_->env_fetches : farm_->fetches);
    }
    const std::string& bytes = env ? farm_->env_bytes : farm_->scene_bytes;
    const size_t chunk = 500;  // several chunks to exercise reassembly
    for (size_t off = 0; off < bytes.size(); off += chunk) {
      pb::SceneChunk c;
      if (off == 0) {
        c.mutable_info()->set_sha256(request->sha256());
        c.mutable_info()->set_size_bytes(bytes.size());
        c.mutable_info()->set_format(env ? pb::SCENE_FORMAT_HDR : pb::SCENE_FORMAT_GLTF);
        c.mutable_info()->set_filename(env ? "sky.hdr" : "small.gltf");
      }
      c.set_offset(off);
      c.set_data(bytes.substr(off, chunk));
      writer->Write(c);
    }
    return grpc::Status::OK;
  }

 private:
  FakeFarm* farm_;
};

std::vector<float> as_floats(const std::vector<double>& v) { return {v.begin(), v.end()}; }

pb::Task make_task(const std::string& id, const std::string& sha, uint32_t spp,
                   pb::Sampler sampler = pb::SAMPLER_SOBOL) {
  pb::Task t;
  t.set_task_id(id);
  t.set_job_id("job-1");
  t.set_scene_sha256(sha);
  t.set_tile_index(1);
  t.set_batch_index(2);
  t.mutable_rect()->set_x0(8);
  t.mutable_rect()->set_y0(0);
  t.mutable_rect()->set_width(8);
  t.mutable_rect()->set_height(6);
  t.set_sample_start(8);
  t.set_sample_count(spp);
  pb::RenderSettings* s = t.mutable_settings();
  s->set_width(16);
  s->set_height(12);
  s->set_sampler(sampler);
  s->set_integrator(pb::INTEGRATOR_PATH);
  s->set_max_depth(4);
  s->set_seed(77);
  return t;
}

// The task's rect and samples of the small scene rendered here, with make_task's settings
// (what the worker's result must equal).
TileBuffer render_locally(const std::string& scene_bytes, const pb::Task& t) {
  Scene scene(load_gltf_from_string(scene_bytes, ".", "small.gltf", nullptr, at_height(12)));
  RenderSettings settings;
  settings.width = 16;
  settings.height = 12;
  settings.seed = 77;
  settings.max_depth = 4;
  TileBuffer local;
  EXPECT_TRUE(render_rect(scene, settings,
                          {t.rect().x0(), t.rect().y0(), t.rect().width(), t.rect().height()},
                          t.sample_start(), t.sample_count(), &local));
  return local;
}

TEST(FarmClient, RendersFetchesCancelsAndStopsGracefully) {
  FakeFarm farm;
  farm.scene_bytes = testing::small_gltf_json();
  farm.scene_sha = sha256_hex(farm.scene_bytes);
  // A small HDR environment map (Radiance RGBE), written with OpenImageIO.
  const std::string env_path = testing::test_path("farm_env_test.hdr");
  {
    auto out = OIIO::ImageOutput::create(env_path);
    ASSERT_TRUE(out);
    OIIO::ImageSpec spec(8, 4, 3, OIIO::TypeDesc::FLOAT);
    std::vector<float> px(8 * 4 * 3);
    for (size_t i = 0; i < px.size(); ++i) px[i] = 0.1f + 0.05f * float(i % 7);
    ASSERT_TRUE(out->open(env_path, spec) && out->write_image(OIIO::TypeDesc::FLOAT, px.data()) &&
                out->close());
    std::ifstream in(env_path, std::ios::binary);
    farm.env_bytes.assign(std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>());
    farm.env_sha = sha256_hex(farm.env_bytes);
  }
  FakeWorkerService worker_service(&farm);
  FakeSceneService scene_service(&farm);
  grpc::ServerBuilder builder;
  int port = 0;
  builder.AddListeningPort("127.0.0.1:0", grpc::InsecureServerCredentials(), &port);
  builder.RegisterService(&worker_service);
  builder.RegisterService(&scene_service);
  std::unique_ptr<grpc::Server> server = builder.BuildAndStart();
  ASSERT_TRUE(server);
  ASSERT_GT(port, 0);

  const fs::path cache = fs::path(testing::test_path("rf-farm-test-cache"));
  fs::remove_all(cache);
  FarmOptions options;
  options.server = "127.0.0.1:" + std::to_string(port);
  options.threads = 2;
  options.prefetch = 1;
  options.cache_dir = cache.string();
  options.worker_id = "test-worker";
  options.hostname = "test-host";
  std::atomic<bool> stop{false};
  int exit_code = -1;
  std::thread client([&] { exit_code = run_farm_client(options, stop); });

  ASSERT_TRUE(farm.wait_for([&] { return farm.stream != nullptr; }));
  {
    std::lock_guard<std::mutex> lock(farm.mutex);
    const pb::Hello& hello = farm.received.at(0).hello();
    EXPECT_EQ(hello.worker_id(), "test-worker");
    EXPECT_EQ(hello.cores(), 2u);
    EXPECT_EQ(hello.max_in_flight(), 3u);
    // Every row of the channel table, each once: the server leases a task naming a row only
    // to a worker that lists it (the Cryptomatte rows among them).
    const std::vector<std::string> listed(hello.channels().begin(), hello.channels().end());
    EXPECT_EQ(listed.size(), size_t(channels::kCount));
    for (const channels::Spec& row : channels::kSpecs)
      EXPECT_EQ(std::count(listed.begin(), listed.end(), row.name), 1) << row.name;
    for (const char* name : {"rgb", "coverage", "depth", "instance", "material",
                             "crypto_object", "crypto_material", "diffuse_direct",
                             "diffuse_indirect", "glossy_direct", "glossy_indirect",
                             "transmission_direct", "transmission_indirect", "emission",
                             "background"})
      EXPECT_EQ(std::count(listed.begin(), listed.end(), name), 1) << name;
  }
  // A long task that we cancel, a good one, and one with an unknown sampler.
  auto assign = [&](const pb::Task& t) { ASSERT_TRUE(farm.assign(t)); };
  assign(make_task("long", farm.scene_sha, 1u << 20));
  assign(make_task("good", farm.scene_sha, 8));
  assign(make_task("bad", farm.scene_sha, 8, pb::Sampler(99)));  // a number the enum lacks
  auto has = [&](const std::string& id, bool result) {
    for (const auto& m : farm.received)
      if ((result && m.has_result() && m.result().task_id() == id) ||
          (!result && m.has_failed() && m.failed().task_id() == id))
        return true;
    return false;
  };
  ASSERT_TRUE(farm.wait_for([&] { return has("good", true) && has("bad", false); }));
  // The long task is in flight now (or queued): heartbeats list it; cancel it.
  ASSERT_TRUE(farm.wait_for([&] { return farm.in_heartbeat("long"); }));
  pb::ServerMessage cancel;
  cancel.mutable_cancel()->add_task_ids("long");
  cancel.mutable_cancel()->set_reason("test");
  ASSERT_TRUE(farm.send(cancel));
  // After the cancel, a later task still gets rendered.
  assign(make_task("after", farm.scene_sha, 4, pb::SAMPLER_INDEPENDENT));
  ASSERT_TRUE(farm.wait_for([&] { return has("after", true); }));
  // Tasks that name their channels (the channel table's rows): the result carries one
  // ChannelBlock each, in the task's order, and none of the old fields; a channel the worker
  // does not know fails the task for good, naming it.
  pb::Task blocks = make_task("blocks", farm.scene_sha, 8);
  for (const char* name : {"coverage", "rgb", "luminance", "albedo"}) blocks.add_channels(name);
  assign(blocks);
  pb::Task unknown = make_task("unknown", farm.scene_sha, 4);
  unknown.add_channels("rgb");
  unknown.add_channels("no-such-row");
  assign(unknown);
  ASSERT_TRUE(farm.wait_for([&] { return has("blocks", true) && has("unknown", false); }));
  {
    std::lock_guard<std::mutex> lock(farm.mutex);
    for (const auto& m : farm.received) {
      if (m.has_failed() && m.failed().task_id() == "unknown") {
        EXPECT_NE(m.failed().error().find("channel 'no-such-row'"), std::string::npos)
            << m.failed().error();
        EXPECT_FALSE(m.failed().retryable());
      }
      if (!m.has_result() || m.result().task_id() != "blocks") continue;
      const pb::TileResult& r = m.result();
      EXPECT_TRUE(r.rgb_sum().empty() && r.coverage_sum().empty() && r.albedo_sum().empty());
      EXPECT_EQ(r.table_version(), channels::kTableVersion);
      ASSERT_EQ(r.channels_size(), 4);
      const TileBuffer local = render_locally(farm.scene_bytes, blocks);
      const std::vector<std::vector<float>> want = {
          local.sum(channels::Id::Coverage), as_floats(local.rgb_sum),
          as_floats(local.luminance_m2), local.sum(channels::Id::Albedo)};
      const uint32_t components[] = {1, 3, 1, 3};
      for (int k = 0; k < 4; ++k) {
        const pb::ChannelBlock& b = r.channels(k);
        EXPECT_EQ(b.name(), blocks.channels(k));
        EXPECT_EQ(b.type(), pb::VALUE_TYPE_F32);
        EXPECT_EQ(b.components(), components[k]);
        EXPECT_EQ(unpack_f32_le(b.data()), want[size_t(k)]) << b.name();
      }
    }
  }
  // Two tasks with the environment map, a thin lens and the new samplers: the map is
  // fetched once (cached by hash as <sha>.hdr) and the results equal local renders.
  auto env_task = [&](const std::string& id, pb::Sampler sampler) {
    pb::Task t = make_task(id, farm.scene_sha, 4, sampler);
    t.mutable_settings()->set_environment_sha256(farm.env_sha);
    t.mutable_settings()->set_environment_intensity(2.0);
    t.mutable_settings()->set_environment_rotation_deg(30.0);
    t.mutable_settings()->set_aperture_radius(0.05);
    t.mutable_settings()->set_focus_distance(5.0);
    t.mutable_settings()->set_integrator(pb::INTEGRATOR_DIRECT);
    return t;
  };
  assign(env_task("env1", pb::SAMPLER_HALTON));
  assign(env_task("env2", pb::SAMPLER_STRATIFIED));
  ASSERT_TRUE(farm.wait_for([&] { return has("env1", true) && has("env2", true); }));
  // A task past the AOV samples: the result carries no albedo or normal sums.
  pb::Task late = make_task("late", farm.scene_sha, 4);
  late.set_skip_aovs(true);
  assign(late);
  ASSERT_TRUE(farm.wait_for([&] { return has("late", true); }));
  // Per-pixel adaptive sampling: a task naming its pixels renders only those (the 8x6 rect's
  // pixels 0, 5 and 47: bits of bytes 0 and 5); a mask of the wrong length fails for good.
  pb::Task masked = make_task("masked", farm.scene_sha, 4);
  std::string mask(6, '\0');
  mask[0] = char(0x21);
  mask[5] = char(0x80);
  masked.set_active_pixels(mask);
  assign(masked);
  pb::Task bad_mask = make_task("badmask", farm.scene_sha, 4);
  bad_mask.set_active_pixels(std::string(5, '\xff'));
  assign(bad_mask);
  ASSERT_TRUE(farm.wait_for([&] { return has("masked", true) && has("badmask", false); }));

  stop = true;
  client.join();
  EXPECT_EQ(exit_code, 0);
  ASSERT_TRUE(farm.wait_for([&] { return farm.stream_ended; }));
  server->Shutdown();

  std::lock_guard<std::mutex> lock(farm.mutex);
  EXPECT_FALSE(has("long", true)) << "a cancelled task must send nothing";
  for (const auto& m : farm.received)
    if (m.has_result() && m.result().task_id() != "blocks") {  // the old fields
      const bool skipped = m.result().task_id() == "late";
      EXPECT_EQ(m.result().albedo_sum().empty(), skipped) << m.result().task_id();
      EXPECT_EQ(m.result().normal_sum().empty(), skipped) << m.result().task_id();
      EXPECT_FALSE(m.result().rgb_sum().empty());
    }
  EXPECT_EQ(farm.fetches, 1) << "the scene is fetched once and then cached";
  EXPECT_TRUE(fs::exists(cache / (farm.scene_sha + ".gltf")));
  EXPECT_EQ(farm.env_fetches, 1) << "the environment is fetched once and then cached";
  EXPECT_TRUE(fs::exists(cache / (farm.env_sha + ".hdr")));
  for (const auto& m : farm.received) {
    if (!m.has_result() || m.result().task_id() != "env1") continue;
    Scene scene(load_gltf_from_string(farm.scene_bytes, ".", "small.gltf", nullptr, at_height(12)));
    RenderSettings settings;
    settings.width = 16;
    settings.height = 12;
    settings.seed = 77;
    settings.max_depth = 4;
    settings.sampler = SamplerType::Halton;
    settings.integrator = IntegratorType::Direct;
    settings.aperture_radius = 0.05f;
    settings.focus_distance = 5.f;
    settings.environment = Environment::load(env_path, 2.f, 30.f);
    TileBuffer local;
    ASSERT_TRUE(render_rect(scene, settings, {8, 0, 8, 6}, 8, 4, &local));
    EXPECT_EQ(unpack_f32_le(m.result().rgb_sum()), as_floats(local.rgb_sum));
    double total = 0.0;
    for (double v : local.rgb_sum) total += v;
    EXPECT_GT(total, 0.0);
  }
  for (const auto& m : farm.received) {
    if (m.has_failed() && m.failed().task_id() == "badmask") {
      EXPECT_FALSE(m.failed().retryable());
      EXPECT_NE(m.failed().error().find("active_pixels has 5 bytes"), std::string::npos)
          << m.failed().error();
      continue;
    }
    if (m.has_result() && m.result().task_id() == "masked") {
      const TileBuffer local = render_locally(farm.scene_bytes, masked);
      const std::vector<float> got = unpack_f32_le(m.result().rgb_sum());
      const std::vector<float> whole = as_floats(local.rgb_sum);
      ASSERT_EQ(got.size(), whole.size());
      for (size_t i = 0; i < got.size(); ++i) {
        const size_t pixel = i / 3;
        const bool on = pixel == 0 || pixel == 5 || pixel == 47;
        EXPECT_EQ(got[i], on ? whole[i] : 0.f) << "pixel " << pixel;
      }
    }
    if (m.has_failed() && m.failed().task_id() != "unknown") {
      EXPECT_EQ(m.failed().task_id(), "bad");
      EXPECT_FALSE(m.failed().retryable());
      EXPECT_NE(m.failed().error().find("unknown sampler 99"), std::string::npos);
    }
    if (!m.has_result() || m.result().task_id() != "good") continue;
    // The result equals rendering the same rect and samples locally.
    const pb::TileResult& r = m.result();
    EXPECT_EQ(r.job_id(), "job-1");
    EXPECT_EQ(r.tile_index(), 1u);
    EXPECT_EQ(r.batch_index(), 2u);
    EXPECT_EQ(r.sample_start(), 8u);
    EXPECT_EQ(r.sample_count(), 8u);
    const TileBuffer local = render_locally(farm.scene_bytes, make_task("good", "", 8));
    // float32 on the wire: the double batch sums rounded once.
    EXPECT_EQ(unpack_f32_le(r.rgb_sum()), as_floats(local.rgb_sum));
    EXPECT_EQ(unpack_f32_le(r.luminance_m2()), as_floats(local.luminance_m2));
    EXPECT_EQ(unpack_f32_le(r.albedo_sum()), local.sum(channels::Id::Albedo));
    EXPECT_EQ(unpack_f32_le(r.normal_sum()), local.sum(channels::Id::Normal));
    EXPECT_EQ(r.rays(), local.rays);
    EXPECT_GT(r.render_seconds(), 0.0);
  }
}

// The batch at sample 0 (one sample long) carries every row whose window holds it, the
// first-sample rows depth and position among them: one ChannelBlock each, float32, of one and
// three components a pixel, equal to the local render's rows. Where the first sample hit the
// floor, its depth is the hit's distance from the camera along the viewing axis (the small
// scene's camera: at (0, 1, 5), turned 0.2 rad down about x); where it missed, 1e10 and 0.
TEST(FarmClient, SendsTheFirstSampleDepthAndPositionRows) {
  FakeFarm farm;
  farm.scene_bytes = testing::small_gltf_json();
  farm.scene_sha = sha256_hex(farm.scene_bytes);
  FakeWorkerService worker_service(&farm);
  FakeSceneService scene_service(&farm);
  grpc::ServerBuilder builder;
  int port = 0;
  builder.AddListeningPort("127.0.0.1:0", grpc::InsecureServerCredentials(), &port);
  builder.RegisterService(&worker_service);
  builder.RegisterService(&scene_service);
  std::unique_ptr<grpc::Server> server = builder.BuildAndStart();
  ASSERT_TRUE(server);
  FarmOptions options;
  options.server = "127.0.0.1:" + std::to_string(port);
  options.threads = 1;
  options.prefetch = 0;
  options.cache_dir = testing::test_path("cache");
  options.worker_id = "first-sample";
  std::atomic<bool> stop{false};
  std::thread client([&] { run_farm_client(options, stop); });
  ASSERT_TRUE(farm.wait_for([&] { return farm.stream != nullptr; }));
  // The whole image: the floor below the horizon, nothing above it.
  pb::Task first = make_task("first", farm.scene_sha, 1);
  first.set_sample_start(0);
  first.mutable_rect()->set_x0(0);
  first.mutable_rect()->set_width(16);
  first.mutable_rect()->set_height(12);
  const char* const names[] = {"rgb", "luminance", "albedo", "normal", "coverage", "depth",
                               "position"};
  for (const char* name : names) first.add_channels(name);
  ASSERT_TRUE(farm.assign(first));
  ASSERT_TRUE(farm.wait_for([&] { return farm.has_result("first"); }));
  stop = true;
  client.join();
  server->Shutdown();

  std::lock_guard<std::mutex> lock(farm.mutex);
  const pb::TileResult* r = nullptr;
  for (const auto& m : farm.received)
    if (m.has_result() && m.result().task_id() == "first") r = &m.result();
  ASSERT_NE(r, nullptr);
  ASSERT_EQ(r->channels_size(), 7);
  const size_t pixels = 16 * 12;
  const uint32_t components[] = {3, 1, 3, 3, 1, 1, 3};
  for (int k = 0; k < 7; ++k) {
    const pb::ChannelBlock& b = r->channels(k);
    EXPECT_EQ(b.name(), names[k]);
    EXPECT_EQ(b.type(), pb::VALUE_TYPE_F32) << b.name();
    EXPECT_EQ(b.components(), components[k]) << b.name();
    EXPECT_EQ(b.data().size(), 4 * components[k] * pixels) << b.name();
  }
  const std::vector<float> coverage = unpack_f32_le(r->channels(4).data());
  const std::vector<float> depth = unpack_f32_le(r->channels(5).data());
  const std::vector<float> position = unpack_f32_le(r->channels(6).data());
  ASSERT_EQ(depth.size(), pixels);
  ASSERT_EQ(position.size(), 3 * pixels);
  const TileBuffer local = render_locally(farm.scene_bytes, first);
  EXPECT_EQ(depth, local.sum(channels::Id::Depth));
  EXPECT_EQ(position, local.sum(channels::Id::Position));
  const Vec3 eye(0.f, 1.f, 5.f), forward(0.f, -std::sin(0.2f), -std::cos(0.2f));
  int hits = 0, misses = 0;
  for (size_t i = 0; i < pixels; ++i) {
    const Vec3 p(position[3 * i], position[3 * i + 1], position[3 * i + 2]);
    if (coverage[i] == 0.f) {
      ++misses;
      EXPECT_EQ(depth[i], 1e10f) << "pixel " << i;
      EXPECT_TRUE(p.x == 0.f && p.y == 0.f && p.z == 0.f) << "pixel " << i;
      continue;
    }
    ++hits;
    EXPECT_NEAR(depth[i], dot(p - eye, forward), 1e-5f * depth[i]) << "pixel " << i;
    // On the floor (|x|, |z| <= 1 at y = 0), give or take its lines' width.
    EXPECT_LE(std::fabs(p.x), 1.2f) << "pixel " << i;
    EXPECT_LE(std::fabs(p.y), 0.2f) << "pixel " << i;
    EXPECT_LE(std::fabs(p.z), 1.2f) << "pixel " << i;
  }
  EXPECT_GT(hits, 10);
  EXPECT_GT(misses, 10);
}

// The first-sample rows instance and material travel as ChannelBlocks of type U32: one
// component, four bytes a pixel, little-endian uint32, each pixel's first sample's glTF node
// and glTF material plus one. In the inner pixels of testing::ids_gltf_json's cells they are
// the cells' (the scene's construction), 0 wherever the camera ray hit nothing (coverage 0),
// and everywhere the local render's float32 sums as integers.
TEST(FarmClient, SendsTheInstanceAndMaterialRowsAsU32) {
  FakeFarm farm;
  farm.scene_bytes = testing::ids_gltf_json();
  farm.scene_sha = sha256_hex(farm.scene_bytes);
  FakeWorkerService worker_service(&farm);
  FakeSceneService scene_service(&farm);
  grpc::ServerBuilder builder;
  int port = 0;
  builder.AddListeningPort("127.0.0.1:0", grpc::InsecureServerCredentials(), &port);
  builder.RegisterService(&worker_service);
  builder.RegisterService(&scene_service);
  std::unique_ptr<grpc::Server> server = builder.BuildAndStart();
  ASSERT_TRUE(server);
  FarmOptions options;
  options.server = "127.0.0.1:" + std::to_string(port);
  options.threads = 1;
  options.prefetch = 0;
  options.cache_dir = testing::test_path("cache");
  options.worker_id = "ids";
  std::atomic<bool> stop{false};
  std::thread client([&] { run_farm_client(options, stop); });
  ASSERT_TRUE(farm.wait_for([&] { return farm.stream != nullptr; }));
  pb::Task first = make_task("ids", farm.scene_sha, 1);
  first.set_sample_start(0);
  first.mutable_rect()->set_x0(0);
  first.mutable_rect()->set_width(16);
  first.mutable_rect()->set_height(12);
  const char* const names[] = {"rgb", "luminance", "coverage", "depth", "instance", "material"};
  for (const char* name : names) first.add_channels(name);
  ASSERT_TRUE(farm.assign(first));
  ASSERT_TRUE(farm.wait_for([&] { return farm.has_result("ids"); }));
  stop = true;
  client.join();
  server->Shutdown();

  std::lock_guard<std::mutex> lock(farm.mutex);
  const pb::TileResult* r = nullptr;
  for (const auto& m : farm.received)
    if (m.has_result() && m.result().task_id() == "ids") r = &m.result();
  ASSERT_NE(r, nullptr);
  ASSERT_EQ(r->channels_size(), 6);
  const size_t pixels = 16 * 12;
  for (int k = 0; k < 6; ++k) EXPECT_EQ(r->channels(k).name(), names[k]);
  EXPECT_EQ(r->channels(3).type(), pb::VALUE_TYPE_F32);
  for (int k : {4, 5}) {
    const pb::ChannelBlock& b = r->channels(k);
    EXPECT_EQ(b.type(), pb::VALUE_TYPE_U32) << b.name();
    EXPECT_EQ(b.components(), 1u) << b.name();
    ASSERT_EQ(b.data().size(), 4 * pixels) << b.name();
  }
  // Pixel (1, 1), in the cell of nodes[7] and materials[0]: 8 and 1, little-endian.
  const std::string& instance_bytes = r->channels(4).data();
  const std::string& material_bytes = r->channels(5).data();
  const size_t at = 4 * (16 + 1);
  EXPECT_EQ(instance_bytes.substr(at, 4), std::string("\x08\0\0\0", 4));
  EXPECT_EQ(material_bytes.substr(at, 4), std::string("\x01\0\0\0", 4));
  const std::vector<float> coverage = unpack_f32_le(r->channels(2).data());
  const std::vector<uint32_t> instance = unpack_u32_le(instance_bytes);
  const std::vector<uint32_t> material = unpack_u32_le(material_bytes);
  int checked = 0;
  for (const testing::IdCell& cell : testing::ids_gltf_cells())
    for (uint32_t y = cell.y0 + 1; y <= cell.y0 + 2; ++y)
      for (uint32_t x = cell.x0 + 1; x <= cell.x0 + 2; ++x) {
        const size_t i = size_t(y) * 16 + x;
        EXPECT_EQ(instance[i], cell.instance) << x << ", " << y << ": " << cell.what;
        EXPECT_EQ(material[i], cell.material) << x << ", " << y << ": " << cell.what;
        ++checked;
      }
  EXPECT_EQ(checked, 48);
  const TileBuffer local = render_locally(farm.scene_bytes, first);
  int misses = 0;
  for (size_t i = 0; i < pixels; ++i) {
    EXPECT_EQ(float(instance[i]), local.sum(channels::Id::Instance)[i]) << "pixel " << i;
    EXPECT_EQ(float(material[i]), local.sum(channels::Id::Material)[i]) << "pixel " << i;
    if (coverage[i] != 0.f) continue;
    ++misses;
    EXPECT_EQ(instance[i], 0u) << "pixel " << i;
    EXPECT_EQ(material[i], 0u) << "pixel " << i;
  }
  EXPECT_GT(misses, 8);
}

// The ranked rows crypto_object and crypto_material travel as ChannelBlocks of type U32: 12
// components, 48 bytes a pixel, little-endian uint32 (label, count) pairs, largest count first,
// (0, 0) in the slots no label fills. In the inner pixels of testing::ids_gltf_json's cells,
// a task of 8 samples from sample 4 gives one pair: the cell's node plus one (its material
// plus one, or 0xFFFFFFFF for the primitive without a material) and 8; nothing where no
// sample hit anything; everywhere counts adding up to the coverage and the local render's
// pairs.
TEST(FarmClient, SendsTheCryptomatteRowsAsRankedU32Pairs) {
  FakeFarm farm;
  farm.scene_bytes = testing::ids_gltf_json();
  farm.scene_sha = sha256_hex(farm.scene_bytes);
  FakeWorkerService worker_service(&farm);
  FakeSceneService scene_service(&farm);
  grpc::ServerBuilder builder;
  int port = 0;
  builder.AddListeningPort("127.0.0.1:0", grpc::InsecureServerCredentials(), &port);
  builder.RegisterService(&worker_service);
  builder.RegisterService(&scene_service);
  std::unique_ptr<grpc::Server> server = builder.BuildAndStart();
  ASSERT_TRUE(server);
  FarmOptions options;
  options.server = "127.0.0.1:" + std::to_string(port);
  options.threads = 1;
  options.prefetch = 0;
  options.cache_dir = testing::test_path("cache");
  options.worker_id = "crypto";
  std::atomic<bool> stop{false};
  std::thread client([&] { run_farm_client(options, stop); });
  ASSERT_TRUE(farm.wait_for([&] { return farm.stream != nullptr; }));
  pb::Task task = make_task("crypto", farm.scene_sha, 8);
  task.set_sample_start(4);
  task.mutable_rect()->set_x0(0);
  task.mutable_rect()->set_width(16);
  task.mutable_rect()->set_height(12);
  const char* const names[] = {"rgb", "luminance", "coverage", "crypto_object",
                               "crypto_material"};
  for (const char* name : names) task.add_channels(name);
  ASSERT_TRUE(farm.assign(task));
  ASSERT_TRUE(farm.wait_for([&] { return farm.has_result("crypto"); }));
  stop = true;
  client.join();
  server->Shutdown();

  std::lock_guard<std::mutex> lock(farm.mutex);
  const pb::TileResult* r = nullptr;
  for (const auto& m : farm.received)
    if (m.has_result() && m.result().task_id() == "crypto") r = &m.result();
  ASSERT_NE(r, nullptr);
  ASSERT_EQ(r->channels_size(), 5);
  const size_t pixels = 16 * 12;
  for (int k = 0; k < 5; ++k) EXPECT_EQ(r->channels(k).name(), names[k]);
  for (int k : {3, 4}) {
    const pb::ChannelBlock& b = r->channels(k);
    EXPECT_EQ(b.type(), pb::VALUE_TYPE_U32) << b.name();
    EXPECT_EQ(b.components(), 12u) << b.name();
    ASSERT_EQ(b.data().size(), 48 * pixels) << b.name();
  }
  const std::string& object_bytes = r->channels(3).data();
  const std::string& material_bytes = r->channels(4).data();
  // Pixel (1, 1), in the cell of nodes[7] and materials[0]: (8, 8) and (1, 8), then zeros.
  const size_t at = 48 * (16 + 1);
  EXPECT_EQ(object_bytes.substr(at, 48), std::string("\x08\0\0\0\x08\0\0\0", 8) +
                                              std::string(40, '\0'));
  EXPECT_EQ(material_bytes.substr(at, 48), std::string("\x01\0\0\0\x08\0\0\0", 8) +
                                                std::string(40, '\0'));
  // Pixel (13, 1), nodes[9] without a material: (10, 8) and (0xFFFFFFFF, 8).
  const size_t plain = 48 * (16 + 13);
  EXPECT_EQ(object_bytes.substr(plain, 8), std::string("\x0a\0\0\0\x08\0\0\0", 8));
  EXPECT_EQ(material_bytes.substr(plain, 8), std::string("\xff\xff\xff\xff\x08\0\0\0", 8));
  // Pixel (9, 5), in the cell of nothing: every slot (0, 0).
  EXPECT_EQ(object_bytes.substr(48 * (5 * 16 + 9), 48), std::string(48, '\0'));
  EXPECT_EQ(material_bytes.substr(48 * (5 * 16 + 9), 48), std::string(48, '\0'));

  const std::vector<float> coverage = unpack_f32_le(r->channels(2).data());
  const std::vector<uint32_t> object = unpack_u32_le(object_bytes);
  const std::vector<uint32_t> material = unpack_u32_le(material_bytes);
  int checked = 0;
  for (const testing::IdCell& cell : testing::ids_gltf_cells())
    for (uint32_t y = cell.y0 + 1; y <= cell.y0 + 2; ++y)
      for (uint32_t x = cell.x0 + 1; x <= cell.x0 + 2; ++x) {
        const size_t i = size_t(y) * 16 + x;
        std::vector<uint32_t> want_object(12, 0u), want_material(12, 0u);
        if (cell.instance != 0) {
          want_object[0] = cell.instance;
          want_material[0] = cell.material ? cell.material : 0xFFFFFFFFu;
          want_object[1] = want_material[1] = 8;
        }
        EXPECT_EQ(std::vector<uint32_t>(object.begin() + 12 * i, object.begin() + 12 * i + 12),
                  want_object) << x << ", " << y << ": " << cell.what;
        EXPECT_EQ(
            std::vector<uint32_t>(material.begin() + 12 * i, material.begin() + 12 * i + 12),
            want_material) << x << ", " << y << ": " << cell.what;
        ++checked;
      }
  EXPECT_EQ(checked, 48);
  const TileBuffer local = render_locally(farm.scene_bytes, task);
  EXPECT_EQ(object, local.ranked(channels::Id::CryptoObject));
  EXPECT_EQ(material, local.ranked(channels::Id::CryptoMaterial));
  for (size_t i = 0; i < pixels; ++i) {
    uint32_t objects = 0, materials = 0;
    for (size_t k = 0; k < 6; ++k) {
      objects += object[12 * i + 2 * k + 1];
      materials += material[12 * i + 2 * k + 1];
    }
    EXPECT_EQ(float(objects), coverage[i]) << "pixel " << i;
    EXPECT_EQ(float(materials), coverage[i]) << "pixel " << i;
  }
}

// The lobe rows (aovs `lobes`) travel as ChannelBlocks of three float32 components a pixel,
// over every sample of the batch like the radiance: equal to the local render's sums, and per
// pixel summing to the radiance (the rgb block, the double sums rounded once to float32).
// The small scene's emitter and unlit lines are seen directly (emission), and the emitter
// lights the floor, a metal (glTF's default metallicFactor 1: glossy).
TEST(FarmClient, SendsTheLobeRows) {
  FakeFarm farm;
  farm.scene_bytes = testing::small_gltf_json();
  farm.scene_sha = sha256_hex(farm.scene_bytes);
  FakeWorkerService worker_service(&farm);
  FakeSceneService scene_service(&farm);
  grpc::ServerBuilder builder;
  int port = 0;
  builder.AddListeningPort("127.0.0.1:0", grpc::InsecureServerCredentials(), &port);
  builder.RegisterService(&worker_service);
  builder.RegisterService(&scene_service);
  std::unique_ptr<grpc::Server> server = builder.BuildAndStart();
  ASSERT_TRUE(server);
  FarmOptions options;
  options.server = "127.0.0.1:" + std::to_string(port);
  options.threads = 1;
  options.prefetch = 0;
  options.cache_dir = testing::test_path("cache");
  options.worker_id = "lobes";
  std::atomic<bool> stop{false};
  std::thread client([&] { run_farm_client(options, stop); });
  ASSERT_TRUE(farm.wait_for([&] { return farm.stream != nullptr; }));
  pb::Task task = make_task("lobes", farm.scene_sha, 8);
  task.set_sample_start(4);
  task.mutable_rect()->set_x0(0);
  task.mutable_rect()->set_width(16);
  task.mutable_rect()->set_height(12);
  const char* const names[] = {"rgb",           "luminance",        "coverage",
                               "diffuse_direct", "diffuse_indirect", "glossy_direct",
                               "glossy_indirect", "transmission_direct",
                               "transmission_indirect", "emission", "background"};
  constexpr int kBlocks = 11;
  for (const char* name : names) task.add_channels(name);
  ASSERT_TRUE(farm.assign(task));
  ASSERT_TRUE(farm.wait_for([&] { return farm.has_result("lobes"); }));
  stop = true;
  client.join();
  server->Shutdown();

  std::lock_guard<std::mutex> lock(farm.mutex);
  const pb::TileResult* r = nullptr;
  for (const auto& m : farm.received)
    if (m.has_result() && m.result().task_id() == "lobes") r = &m.result();
  ASSERT_NE(r, nullptr);
  ASSERT_EQ(r->channels_size(), kBlocks);
  const size_t pixels = 16 * 12;
  const TileBuffer local = render_locally(farm.scene_bytes, task);
  std::vector<std::vector<float>> lobes;
  for (int k = 3; k < kBlocks; ++k) {
    const pb::ChannelBlock& b = r->channels(k);
    EXPECT_EQ(b.name(), names[k]);
    EXPECT_EQ(b.type(), pb::VALUE_TYPE_F32) << b.name();
    EXPECT_EQ(b.components(), 3u) << b.name();
    ASSERT_EQ(b.data().size(), 12 * pixels) << b.name();
    lobes.push_back(unpack_f32_le(b.data()));
    for (const channels::Spec& row : channels::kSpecs) {
      if (b.name() == row.name) {
        EXPECT_EQ(lobes.back(), local.sum(row.id)) << b.name();
      }
    }
  }
  const std::vector<float> rgb = unpack_f32_le(r->channels(0).data());
  double emission = 0.0, glossy = 0.0;
  for (size_t i = 0; i < 3 * pixels; ++i) {
    double sum = 0.0, magnitude = std::abs(double(rgb[i]));
    for (const std::vector<float>& v : lobes) {
      sum += v[i];
      magnitude += std::abs(double(v[i]));
    }
    EXPECT_NEAR(sum, rgb[i], 1e-5 * magnitude + 1e-5) << "value " << i;
    glossy += lobes[2][i];
    emission += lobes[6][i];
  }
  EXPECT_GT(emission, 0.0);
  EXPECT_GT(glossy, 0.0);
}

// The light groups (aovs `light_groups`) travel as one ChannelBlock of 3 float32 components
// per group a pixel (the groups in settings.light_groups' order), over every sample of the
// batch: equal to a local render with the same groups, and per pixel summing to the radiance.
// The small scene's emitter (node 2) lights the floor; the floor's node (0) has unlit lines.
TEST(FarmClient, SendsTheLightGroupsRow) {
  FakeFarm farm;
  farm.scene_bytes = testing::small_gltf_json();
  farm.scene_sha = sha256_hex(farm.scene_bytes);
  FakeWorkerService worker_service(&farm);
  FakeSceneService scene_service(&farm);
  grpc::ServerBuilder builder;
  int port = 0;
  builder.AddListeningPort("127.0.0.1:0", grpc::InsecureServerCredentials(), &port);
  builder.RegisterService(&worker_service);
  builder.RegisterService(&scene_service);
  std::unique_ptr<grpc::Server> server = builder.BuildAndStart();
  ASSERT_TRUE(server);
  FarmOptions options;
  options.server = "127.0.0.1:" + std::to_string(port);
  options.threads = 1;
  options.prefetch = 0;
  options.cache_dir = testing::test_path("cache");
  options.worker_id = "groups";
  std::atomic<bool> stop{false};
  std::thread client([&] { run_farm_client(options, stop); });
  ASSERT_TRUE(farm.wait_for([&] { return farm.stream != nullptr; }));
  {
    std::lock_guard<std::mutex> lock(farm.mutex);
    const auto& listed = farm.received.at(0).hello().channels();
    EXPECT_EQ(std::count(listed.begin(), listed.end(), "light_groups"), 1);
  }
  const std::string json = R"({"light":[2],"floor":[0],"environment":[]})";
  pb::Task task = make_task("groups", farm.scene_sha, 8);
  task.set_sample_start(4);
  task.mutable_rect()->set_x0(0);
  task.mutable_rect()->set_width(16);
  task.mutable_rect()->set_height(12);
  task.mutable_settings()->set_light_groups(json);
  for (const char* name : {"rgb", "luminance", "coverage", "light_groups"})
    task.add_channels(name);
  ASSERT_TRUE(farm.assign(task));
  ASSERT_TRUE(farm.wait_for([&] { return farm.has_result("groups"); }));
  stop = true;
  client.join();
  server->Shutdown();

  std::lock_guard<std::mutex> lock(farm.mutex);
  const pb::TileResult* r = nullptr;
  for (const auto& m : farm.received)
    if (m.has_result() && m.result().task_id() == "groups") r = &m.result();
  ASSERT_NE(r, nullptr);
  ASSERT_EQ(r->channels_size(), 4);
  const pb::ChannelBlock& b = r->channels(3);
  EXPECT_EQ(b.name(), "light_groups");
  EXPECT_EQ(b.type(), pb::VALUE_TYPE_F32);
  constexpr uint32_t kGroups = 3;
  EXPECT_EQ(b.components(), 3 * kGroups);
  const size_t pixels = 16 * 12;
  ASSERT_EQ(b.data().size(), 4 * 3 * kGroups * pixels);
  const std::vector<float> groups = unpack_f32_le(b.data());
  // The same render here.
  Scene scene(load_gltf_from_string(farm.scene_bytes, ".", "small.gltf", nullptr, at_height(12)));
  RenderSettings settings;
  settings.width = 16;
  settings.height = 12;
  settings.seed = 77;
  settings.max_depth = 4;
  auto parsed = std::make_shared<LightGroups>();
  ASSERT_EQ(parse_light_groups(json, parsed.get()), "");
  settings.light_groups = parsed;
  TileBuffer local;
  ASSERT_TRUE(render_rect(scene, settings, {0, 0, 16, 12}, 4, 8, &local, nullptr,
                          channels::bit(channels::Id::Rgb) |
                              channels::bit(channels::Id::LightGroups)));
  EXPECT_EQ(groups, local.sum(channels::Id::LightGroups));
  const std::vector<float> rgb = unpack_f32_le(r->channels(0).data());
  double total[kGroups] = {0.0, 0.0, 0.0};
  for (size_t i = 0; i < pixels; ++i)
    for (size_t c = 0; c < 3; ++c) {
      double sum = 0.0, magnitude = std::abs(double(rgb[3 * i + c]));
      for (size_t g = 0; g < kGroups; ++g) {
        const double v = groups[3 * (kGroups * i + g) + c];
        sum += v;
        magnitude += std::abs(v);
        total[g] += v;
      }
      EXPECT_NEAR(sum, rgb[3 * i + c], 1e-5 * magnitude + 1e-5) << "pixel " << i;
    }
  EXPECT_GT(total[0], 0.0);    // the emitter
  EXPECT_GT(total[1], 0.0);    // the lines
  EXPECT_EQ(total[2], 0.0);    // no environment
}

// A task whose light groups cannot sum to its image fails, not retryable, with a message that
// says why: settings.light_groups without an emitting node of the scene (the floor's lines),
// not a JSON object, empty. A task that does not ask for the row ignores the setting, as does
// one of a server from before the channel table (no Task.channels), which never traces it.
TEST(FarmClient, RefusesLightGroupsThatCannotSumToTheImage) {
  FakeFarm farm;
  farm.scene_bytes = testing::small_gltf_json();
  farm.scene_sha = sha256_hex(farm.scene_bytes);
  FakeWorkerService worker_service(&farm);
  FakeSceneService scene_service(&farm);
  grpc::ServerBuilder builder;
  int port = 0;
  builder.AddListeningPort("127.0.0.1:0", grpc::InsecureServerCredentials(), &port);
  builder.RegisterService(&worker_service);
  builder.RegisterService(&scene_service);
  std::unique_ptr<grpc::Server> server = builder.BuildAndStart();
  ASSERT_TRUE(server);
  FarmOptions options;
  options.server = "127.0.0.1:" + std::to_string(port);
  options.threads = 1;
  options.prefetch = 0;
  options.cache_dir = testing::test_path("cache");
  options.worker_id = "refusals";
  std::atomic<bool> stop{false};
  std::thread client([&] { run_farm_client(options, stop); });
  ASSERT_TRUE(farm.wait_for([&] { return farm.stream != nullptr; }));
  struct Case {
    const char* id;
    const char* light_groups;
    bool row;       // the task names the light_groups row
    bool channels;  // the task names rows at all
    const char* error;  // "": it renders
  };
  const Case cases[] = {
      {"missing", R"({"light":[2],"environment":[]})", true, true,
       "settings.light_groups: node 0 (\"floor\") emits light but is in no light group"},
      {"array", "[0, 2]", true, true,
       "settings.light_groups: not a JSON object: it must be a JSON object of group name -> "
       "a list of glTF node indices"},
      {"empty", "", true, true,
       "settings.light_groups: empty, while the task asks for the light_groups row"},
      {"unasked", "[0, 2]", false, true, ""},
      {"old-server", "[0, 2]", false, false, ""},
  };
  for (const Case& c : cases) {
    pb::Task task = make_task(c.id, farm.scene_sha, 2);
    task.mutable_settings()->set_light_groups(c.light_groups);
    if (c.channels)
      for (const char* name : {"rgb", "luminance", "coverage"}) task.add_channels(name);
    if (c.row) task.add_channels("light_groups");
    ASSERT_TRUE(farm.assign(task));
  }
  for (const Case& c : cases) {
    const std::string id = c.id;
    ASSERT_TRUE(farm.wait_for([&] {
      for (const auto& m : farm.received)
        if ((m.has_result() && m.result().task_id() == id) ||
            (m.has_failed() && m.failed().task_id() == id))
          return true;
      return false;
    })) << id;
  }
  stop = true;
  client.join();
  server->Shutdown();

  std::lock_guard<std::mutex> lock(farm.mutex);
  for (const Case& c : cases) {
    SCOPED_TRACE(c.id);
    const pb::TaskFailed* failed = nullptr;
    const pb::TileResult* result = nullptr;
    for (const auto& m : farm.received) {
      if (m.has_failed() && m.failed().task_id() == c.id) failed = &m.failed();
      if (m.has_result() && m.result().task_id() == c.id) result = &m.result();
    }
    const std::string error = c.error;
    if (error.empty()) {
      ASSERT_NE(result, nullptr) << (failed ? failed->error() : "");
      EXPECT_EQ(failed, nullptr);
      for (const pb::ChannelBlock& b : result->channels()) EXPECT_NE(b.name(), "light_groups");
      if (!c.channels) {
        EXPECT_EQ(result->channels_size(), 0);
        EXPECT_FALSE(result->rgb_sum().empty());
      }
    } else {
      ASSERT_NE(failed, nullptr);
      EXPECT_EQ(result, nullptr);
      EXPECT_EQ(failed->error().substr(0, error.size()), error) << failed->error();
      EXPECT_FALSE(failed->retryable());
    }
  }
}

// The seed of frame f of a job of seed s, written out from docs/architecture.md,
// "Determinism" (SplitMix64's output function, applied twice), not taken from the worker.
// A worker given two servers (--server A,B) serves both: a stream each, under an id each, its
// threads shared (one thread: a task of B waits while A's renders), scenes fetched from the
// server whose task needs them, and each stream asks for what the other does not hold.
TEST(FarmClient, ServesSeveralServersWithSharedThreadsAndCredit) {
  FakeFarm a, b;
  a.scene_bytes = testing::small_gltf_json();
  a.scene_sha = sha256_hex(a.scene_bytes);
  b.scene_bytes = testing::animated_gltf_json();  // another scene: B's own
  b.scene_sha = sha256_hex(b.scene_bytes);
  FakeWorkerService a_workers(&a), b_workers(&b);
  FakeSceneService a_scenes(&a), b_scenes(&b);
  int a_port = 0, b_port = 0;
  grpc::ServerBuilder a_builder, b_builder;
  a_builder.AddListeningPort("127.0.0.1:0", grpc::InsecureServerCredentials(), &a_port);
  a_builder.RegisterService(&a_workers);
  a_builder.RegisterService(&a_scenes);
  b_builder.AddListeningPort("127.0.0.1:0", grpc::InsecureServerCredentials(), &b_port);
  b_builder.RegisterService(&b_workers);
  b_builder.RegisterService(&b_scenes);
  std::unique_ptr<grpc::Server> a_server = a_builder.BuildAndStart();
  std::unique_ptr<grpc::Server> b_server = b_builder.BuildAndStart();
  ASSERT_TRUE(a_server && b_server);

  const fs::path cache = fs::path(testing::test_path("rf-farm-two-servers"));
  fs::remove_all(cache);
  FarmOptions options;
  const std::string a_addr = "127.0.0.1:" + std::to_string(a_port);
  const std::string b_addr = "127.0.0.1:" + std::to_string(b_port);
  options.server = a_addr + ", " + b_addr;
  options.threads = 1;
  options.prefetch = 1;
  options.cache_dir = cache.string();
  options.worker_id = "two";
  std::atomic<bool> stop{false};
  std::thread client([&] { run_farm_client(options, stop); });
  ASSERT_TRUE(a.wait_for([&] { return a.stream != nullptr; }));
  ASSERT_TRUE(b.wait_for([&] { return b.stream != nullptr; }));
  {
    std::lock_guard<std::mutex> la(a.mutex), lb(b.mutex);
    EXPECT_EQ(a.received.at(0).hello().worker_id(), "two@" + a_addr);
    EXPECT_EQ(b.received.at(0).hello().worker_id(), "two@" + b_addr);
    EXPECT_EQ(a.received.at(0).hello().max_in_flight(), 2u);
    EXPECT_EQ(b.received.at(0).hello().max_in_flight(), 2u);
  }
  // The last max_in_flight a farm heard from the worker (Hello's, then its heartbeats').
  auto wanted = [](FakeFarm& farm) {
    uint32_t w = 0;
    for (const auto& m : farm.received) {
      if (m.has_hello()) w = m.hello().max_in_flight();
      if (m.has_heartbeat() && m.heartbeat().max_in_flight()) w = m.heartbeat().max_in_flight();
    }
    return w;
  };
  {
    std::lock_guard<std::mutex> lock(a.mutex);
    a.hold_fetches = true;  // A's first task stays in flight, fetching its scene
  }
  ASSERT_TRUE(a.assign(make_task("a1", a.scene_sha, 4)));
  ASSERT_TRUE(a.assign(make_task("a2", a.scene_sha, 4)));
  // A holds the worker's two slots: B is asked for one task only.
  ASSERT_TRUE(b.wait_for([&] { return wanted(b) == 1; }, 30));
  pb::Task b1 = make_task("b1", b.scene_sha, 4);
  b1.set_job_id("job-b");
  ASSERT_TRUE(b.assign(b1));
  // One thread, busy with A's task: B's waits (its heartbeats list it, no result yet).
  ASSERT_TRUE(b.wait_for([&] { return b.in_heartbeat("b1"); }, 30));
  {
    std::lock_guard<std::mutex> lock(b.mutex);
    EXPECT_FALSE(b.has_result("b1"));
    EXPECT_EQ(b.fetches, 0);
  }
  {
    std::lock_guard<std::mutex> lock(a.mutex);
    a.hold_fetches = false;
  }
  a.cv.notify_all();
  ASSERT_TRUE(a.wait_for([&] { return a.has_result("a1") && a.has_result("a2"); }));
  ASSERT_TRUE(b.wait_for([&] { return b.has_result("b1"); }));
  // Each scene came from its own server, once; with nothing held, each stream wants two again.
  ASSERT_TRUE(b.wait_for([&] { return wanted(b) == 2; }, 30));
  ASSERT_TRUE(a.wait_for([&] { return wanted(a) == 2; }, 30));
  {
    std::lock_guard<std::mutex> la(a.mutex), lb(b.mutex);
    EXPECT_EQ(a.fetches, 1);
    EXPECT_EQ(b.fetches, 1);
  }
  stop = true;
  client.join();
  a_server->Shutdown();
  b_server->Shutdown();
}

// --server's entries: as given, except a name with several addresses, one server per address
// with its certificate checked against the name; other gRPC targets and IP literals as given.
TEST(FarmClient, ServerTargetsExpandANameWithSeveralAddresses) {
  const Resolver fake = [](const std::string& host, const std::string& port) {
    if (host == "farm-headless") return std::vector<std::string>{"10.0.0.3:" + port,
                                                                 "10.0.0.1:" + port,
                                                                 "10.0.0.3:" + port};
    if (host == "one") return std::vector<std::string>{"10.0.0.9:" + port};
    return std::vector<std::string>{};
  };
  const auto t = server_targets(" one:50051 ,farm-headless:50051,,dns:///x:1,[::1]:7", fake);
  ASSERT_EQ(t.size(), 5u);
  EXPECT_EQ(t.at("one:50051").name, "one:50051");  // one address: dialed by name
  EXPECT_EQ(t.at("one:50051").tls_name, "");
  EXPECT_EQ(t.at("10.0.0.1:50051").name, "farm-headless:50051 (10.0.0.1:50051)");
  EXPECT_EQ(t.at("10.0.0.1:50051").tls_name, "farm-headless");
  EXPECT_EQ(t.at("10.0.0.3:50051").tls_name, "farm-headless");
  EXPECT_TRUE(t.count("dns:///x:1"));
  EXPECT_TRUE(t.count("[::1]:7"));
  // The real resolver (/etc/hosts): localhost has one IPv4 address.
  EXPECT_EQ(resolve_ipv4("localhost", "80"), std::vector<std::string>{"127.0.0.1:80"});
}

uint64_t spec_splitmix64(uint64_t x) {
  uint64_t z = x + 0x9E3779B97F4A7C15ull;
  z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ull;
  z = (z ^ (z >> 27)) * 0x94D049BB133111EBull;
  return z ^ (z >> 31);
}
uint64_t spec_frame_seed(uint64_t seed, int32_t frame) {
  return spec_splitmix64(seed ^ spec_splitmix64(uint64_t(int64_t(frame))));
}

TEST(FarmClient, RendersAnimatedFramesPosedAndSeededByTheirFrame) {
  FakeFarm farm;
  farm.scene_bytes = testing::animated_gltf_json();
  farm.scene_sha = sha256_hex(farm.scene_bytes);
  FakeWorkerService worker_service(&farm);
  FakeSceneService scene_service(&farm);
  grpc::ServerBuilder builder;
  int port = 0;
  builder.AddListeningPort("127.0.0.1:0", grpc::InsecureServerCredentials(), &port);
  builder.RegisterService(&worker_service);
  builder.RegisterService(&scene_service);
  std::unique_ptr<grpc::Server> server = builder.BuildAndStart();
  ASSERT_TRUE(server);
  const fs::path cache = fs::path(testing::test_path("rf-farm-frames-cache"));
  fs::remove_all(cache);
  FarmOptions options;
  options.server = "127.0.0.1:" + std::to_string(port);
  options.threads = 1;
  options.prefetch = 0;
  options.cache_dir = cache.string();
  options.worker_id = "frames-worker";
  std::atomic<bool> stop{false};
  int exit_code = -1;
  std::thread client([&] { exit_code = run_farm_client(options, stop); });
  ASSERT_TRUE(farm.wait_for([&] { return farm.stream != nullptr; }));

  auto frame_task = [&](const std::string& id, int32_t frame, double time_s,
                        const std::string& animation, uint32_t spp = 4) {
    pb::Task t = make_task(id, farm.scene_sha, spp);
    t.set_animated(true);
    t.set_frame(frame);
    t.set_time_s(time_s);
    t.mutable_settings()->set_animation(animation);
    return t;
  };
  auto find = [&](const std::string& id) -> const pb::WorkerMessage* {
    for (const auto& m : farm.received)
      if ((m.has_result() && m.result().task_id() == id) ||
          (m.has_failed() && m.failed().task_id() == id))
        return &m;
    return nullptr;
  };
  // One task at a time, in this order: frame 5, frame 9, frame 5 again (its pose rebuilt or
  // found in the cache), an index selection, two frames of one pose (a static scene), a still
  // and an unknown animation name.
  auto run = [&](const pb::Task& t) {
    pb::ServerMessage m;
    *m.mutable_assign()->mutable_task() = t;
    ASSERT_TRUE(farm.send(m));
    ASSERT_TRUE(farm.wait_for([&] { return find(t.task_id()) != nullptr; }));
  };
  run(frame_task("f5", 5, 0.5, "slide"));
  run(frame_task("f9", 9, 1.5, "slide"));
  run(frame_task("f5-again", 5, 0.5, "slide"));
  run(frame_task("by-index", 7, 1.0, " 1"));
  run(frame_task("static-3", 3, 0.0, "slide", 16));
  run(frame_task("static-4", 4, 0.0, "slide", 16));
  run(make_task("still", farm.scene_sha, 4));
  run(frame_task("unknown", 6, 0.25, "slide,Slide"));
  pb::Task blurred = frame_task("blurred", 5, 0.5, "slide");
  blurred.mutable_settings()->set_shutter("0,0.5");
  blurred.mutable_settings()->set_fps(2.0);
  run(blurred);
  pb::Task bad_shutter = frame_task("bad-shutter", 5, 0.5, "slide");
  bad_shutter.mutable_settings()->set_shutter("0.5,0");
  bad_shutter.mutable_settings()->set_fps(2.0);
  run(bad_shutter);
  stop = true;
  client.join();
  EXPECT_EQ(exit_code, 0);
  server->Shutdown();

  std::lock_guard<std::mutex> lock(farm.mutex);
  EXPECT_EQ(farm.fetches, 1);
  for (const char* id :
       {"f5", "f9", "f5-again", "by-index", "static-3", "static-4", "still", "blurred"})
    ASSERT_TRUE(find(id)->has_result()) << id << ": " << find(id)->failed().error();
  // Each result is the local render of the scene loaded at the frame's time with the chosen
  // animations (`render --time`: a fresh AnimatedScene's pose), with the frame's seed, bit for
  // bit.
  const std::string scene_path = testing::test_path("rf-farm-frames.gltf");
  {
    std::ofstream out(scene_path);
    out << farm.scene_bytes;
  }
  auto local = [&](double time, std::vector<int> animations, uint64_t seed, uint32_t spp,
                   Shutter shutter = {}) {
    LoadOptions load;
    load.time = time;
    load.animations = std::move(animations);
    load.image_height = 12;  // the tasks' (the width of the scene's lines)
    const AnimatedScene animated(parse_gltf(scene_path, nullptr, load), load);
    const std::shared_ptr<const Scene> posed = animated.pose(time, nullptr, shutter);
    const Scene& scene = *posed;
    RenderSettings settings;
    settings.width = 16;
    settings.height = 12;
    settings.seed = seed;
    settings.max_depth = 4;
    TileBuffer tile;
    EXPECT_TRUE(render_rect(scene, settings, {8, 0, 8, 6}, 8, spp, &tile));
    return tile;
  };
  auto rgb = [&](const std::string& id) { return unpack_f32_le(find(id)->result().rgb_sum()); };
  const TileBuffer f5 = local(0.5, {0}, spec_frame_seed(77, 5), 4);
  EXPECT_EQ(rgb("f5"), as_floats(f5.rgb_sum));
  EXPECT_EQ(unpack_f32_le(find("f5")->result().luminance_m2()), as_floats(f5.luminance_m2));
  EXPECT_EQ(rgb("f9"), as_floats(local(1.5, {0}, spec_frame_seed(77, 9), 4).rgb_sum));
  EXPECT_EQ(rgb("f5-again"), rgb("f5"));
  EXPECT_NE(rgb("f9"), rgb("f5"));
  EXPECT_EQ(rgb("by-index"), as_floats(local(1.0, {1}, spec_frame_seed(77, 7), 4).rgb_sum));
  // Motion blur: the shutter of half a frame at 2 fps, [0.5, 0.75] s, which the light crosses
  // moving; the task renders what the scene posed over that shutter renders.
  EXPECT_EQ(rgb("blurred"),
            as_floats(local(0.5, {0}, spec_frame_seed(77, 5), 4, Shutter{0.0, 0.25}).rgb_sum));
  EXPECT_NE(rgb("blurred"), rgb("f5"));
  const pb::WorkerMessage* bad = find("bad-shutter");
  ASSERT_TRUE(bad->has_failed());
  EXPECT_FALSE(bad->failed().retryable());
  EXPECT_NE(bad->failed().error().find("settings.shutter"), std::string::npos)
      << bad->failed().error();
  // A still keeps the job's seed and the scene as stored (no animation).
  {
    LoadOptions load;
    load.image_height = 12;
    Scene scene(load_gltf_from_string(farm.scene_bytes, ".", "animated.gltf", nullptr, load));
    RenderSettings settings;
    settings.width = 16;
    settings.height = 12;
    settings.seed = 77;
    settings.max_depth = 4;
    TileBuffer tile;
    ASSERT_TRUE(render_rect(scene, settings, {8, 0, 8, 6}, 8, 4, &tile));
    EXPECT_EQ(rgb("still"), as_floats(tile.rgb_sum));
  }
  // Two frames of one pose: different noise, the same mean within it. The tile's mean
  // luminance per frame, and its standard error from the per-pixel luminance M2.
  auto tile_mean = [&](const std::string& id, double* variance) {
    const std::vector<float> sums = rgb(id);
    const std::vector<float> m2 = unpack_f32_le(find(id)->result().luminance_m2());
    const double n = 16.0, pixels = double(m2.size());
    double mean = 0.0;
    *variance = 0.0;
    for (size_t p = 0; p < m2.size(); ++p) {
      mean += (0.2126 * sums[3 * p] + 0.7152 * sums[3 * p + 1] + 0.0722 * sums[3 * p + 2]) / n;
      *variance += double(m2[p]) / (n - 1.0) / n;
    }
    *variance /= pixels * pixels;
    return mean / pixels;
  };
  EXPECT_NE(rgb("static-3"), rgb("static-4"));
  double v3 = 0.0, v4 = 0.0;
  const double m3 = tile_mean("static-3", &v3), m4 = tile_mean("static-4", &v4);
  EXPECT_GT(m3, 0.0);
  EXPECT_LT(std::fabs(m3 - m4), 5.0 * std::sqrt(v3 + v4)) << m3 << " vs " << m4;
  // An unknown name fails the task for good, naming the setting and the name.
  const pb::WorkerMessage* unknown = find("unknown");
  ASSERT_TRUE(unknown->has_failed());
  EXPECT_FALSE(unknown->failed().retryable());
  EXPECT_NE(unknown->failed().error().find("settings.animation"), std::string::npos)
      << unknown->failed().error();
  EXPECT_NE(unknown->failed().error().find("\"Slide\""), std::string::npos)
      << unknown->failed().error();
}

// The Motion row (a first-sample row of 4 float32 components): a batch-0 task of an animated
// job that asks for it gets a ChannelBlock "motion", F32, 4 components, 16 bytes a pixel,
// equal to the local render of the frame's pose with the poses of the frames before and after
// (t -+ 1 / fps, testing::animated_gltf_json's "shrink" scaling the floor towards its centre
// at 2 fps: its points off the centre move), 0 where the camera ray hit nothing; a task that
// does not ask gets no such block, and a still's row is 0 everywhere.
TEST(FarmClient, SendsTheMotionRowOnlyWhenAskedFor) {
  FakeFarm farm;
  farm.scene_bytes = testing::animated_gltf_json();
  farm.scene_sha = sha256_hex(farm.scene_bytes);
  FakeWorkerService worker_service(&farm);
  FakeSceneService scene_service(&farm);
  grpc::ServerBuilder builder;
  int port = 0;
  builder.AddListeningPort("127.0.0.1:0", grpc::InsecureServerCredentials(), &port);
  builder.RegisterService(&worker_service);
  builder.RegisterService(&scene_service);
  std::unique_ptr<grpc::Server> server = builder.BuildAndStart();
  ASSERT_TRUE(server);
  FarmOptions options;
  options.server = "127.0.0.1:" + std::to_string(port);
  options.threads = 1;
  options.prefetch = 0;
  options.cache_dir = testing::test_path("cache");
  options.worker_id = "motion-worker";
  std::atomic<bool> stop{false};
  std::thread client([&] { run_farm_client(options, stop); });
  ASSERT_TRUE(farm.wait_for([&] { return farm.stream != nullptr; }));
  auto task = [&](const std::string& id, bool animated, bool motion) {
    pb::Task t = make_task(id, farm.scene_sha, 1);
    t.set_sample_start(0);
    t.mutable_rect()->set_x0(0);
    t.mutable_rect()->set_width(16);
    t.mutable_rect()->set_height(12);
    if (animated) {
      t.set_animated(true);
      t.set_frame(2);
      t.set_time_s(1.0);
      t.mutable_settings()->set_animation("shrink");
      t.mutable_settings()->set_fps(2.0);
    }
    for (const char* name : {"rgb", "coverage"}) t.add_channels(name);
    if (motion) t.add_channels("motion");
    return t;
  };
  for (const pb::Task& t : {task("moving", true, true), task("without", true, false),
                            task("still", false, true)}) {
    ASSERT_TRUE(farm.assign(t));
    ASSERT_TRUE(farm.wait_for([&] { return farm.has_result(t.task_id()); }));
  }
  stop = true;
  client.join();
  server->Shutdown();

  std::lock_guard<std::mutex> lock(farm.mutex);
  auto result = [&](const std::string& id) -> const pb::TileResult* {
    for (const auto& m : farm.received)
      if (m.has_result() && m.result().task_id() == id) return &m.result();
    return nullptr;
  };
  const size_t pixels = 16 * 12;
  auto motion_of = [&](const pb::TileResult* r) -> std::vector<float> {
    EXPECT_EQ(r->channels_size(), 3);
    if (r->channels_size() != 3) return {};
    const pb::ChannelBlock& b = r->channels(2);
    EXPECT_EQ(b.name(), "motion");
    EXPECT_EQ(b.type(), pb::VALUE_TYPE_F32);
    EXPECT_EQ(b.components(), 4u);
    EXPECT_EQ(b.data().size(), 16 * pixels);
    return unpack_f32_le(b.data());
  };
  const pb::TileResult* moving = result("moving");
  const pb::TileResult* without = result("without");
  const pb::TileResult* still = result("still");
  ASSERT_TRUE(moving && without && still);
  ASSERT_EQ(without->channels_size(), 2);
  for (const pb::ChannelBlock& b : without->channels()) EXPECT_NE(b.name(), "motion");
  const std::vector<float> still_motion = motion_of(still);
  ASSERT_EQ(still_motion.size(), 4 * pixels);
  for (float v : still_motion) EXPECT_EQ(v, 0.f);
  const std::vector<float> motion = motion_of(moving);
  ASSERT_EQ(motion.size(), 4 * pixels);
  const std::vector<float> coverage = unpack_f32_le(moving->channels(1).data());
  // The local render: the frame's pose and its neighbours', with the frame's seed.
  const std::string scene_path = testing::test_path("rf-farm-motion.gltf");
  {
    std::ofstream out(scene_path);
    out << farm.scene_bytes;
  }
  LoadOptions load;
  load.animations = {1};
  load.image_height = 12;
  const AnimatedScene animated(parse_gltf(scene_path, nullptr, load), load);
  const auto previous = animated.pose(0.5), current = animated.pose(1.0),
             next = animated.pose(1.5);
  const MotionPoses poses(*current, 0.f, *previous, *next, 16, 12);
  RenderSettings settings;
  settings.width = 16;
  settings.height = 12;
  settings.seed = spec_frame_seed(77, 2);
  settings.max_depth = 4;
  TileBuffer local;
  ASSERT_TRUE(render_rect(*current, settings, {0, 0, 16, 12}, 0, 1, &local, nullptr,
                          channels::bit(channels::Id::Motion), &poses));
  EXPECT_EQ(motion, local.sum(channels::Id::Motion));
  int moved = 0;
  for (size_t i = 0; i < pixels; ++i) {
    if (coverage[i] == 0.f) {
      for (int c = 0; c < 4; ++c) EXPECT_EQ(motion[4 * i + size_t(c)], 0.f) << "pixel " << i;
    }
    moved += motion[4 * i] != 0.f;
  }
  EXPECT_GT(moved, 10);  // the floor's pixels
}

}  // namespace
}  // namespace rf
