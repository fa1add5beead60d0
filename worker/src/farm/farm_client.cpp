#include "farm/farm_client.h"

#include <arpa/inet.h>
#include <grpcpp/grpcpp.h>
#include <netdb.h>
#include <netinet/in.h>
#include <sys/socket.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <condition_variable>
#include <cstdio>
#include <deque>
#include <filesystem>
#include <fstream>
#include <functional>
#include <iostream>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <set>
#include <sstream>
#include <thread>
#include <vector>

#include "render/channels.h"
#include "render/guiding.h"
#include "render/integrators.h"
#include "render/light_groups.h"
#include "render/motion.h"
#include "renderfarm/v1/scenes.grpc.pb.h"
#include "renderfarm/v1/workers.grpc.pb.h"
#include "farm/frames.h"
#include "farm/result_packer.h"
#include "farm/scene_cache.h"
#include "util/sha256.h"

namespace fs = std::filesystem;
namespace pb = renderfarm::v1;

namespace rf {
namespace {

using Clock = std::chrono::steady_clock;

// Path guiding's fields a worker keeps (one per frame of a job; a job's frames are leased
// mostly in order, a few at a time per worker; each field a few MB at most).
constexpr size_t kGuideFields = 4;

// Pixels a Task.active_pixels mask renders (its set bits).
uint64_t active_count(const std::string& mask) {
  uint64_t n = 0;
  for (const char c : mask) n += uint64_t(__builtin_popcount(static_cast<unsigned char>(c)));
  return n;
}

std::mutex g_log_mutex;
void log_line(const std::string& message) {
  std::lock_guard<std::mutex> lock(g_log_mutex);
  std::cerr << "renderfarm-worker: " << message << std::endl;
}

// A task failure: retryable unless the scene itself (or the request) cannot be rendered.
struct TaskError {
  std::string message;
  bool retryable;
};

// A message that reaches the user (a task's error) names no file of this machine: every
// occurrence of `path` becomes `name`.
std::string without_path(std::string message, const std::string& path, const std::string& name) {
  if (path.empty()) return message;
  for (size_t at = message.find(path); at != std::string::npos; at = message.find(path, at))
    message.replace(at, path.size(), name);
  return message;
}

// A render in progress: its cancel flag (set by a Cancel from the server, the end of the
// stream or the time budget), and whether the time budget set it.
struct RunningTask {
  std::shared_ptr<std::atomic<bool>> cancel = std::make_shared<std::atomic<bool>>(false);
  std::shared_ptr<std::atomic<bool>> timed_out = std::make_shared<std::atomic<bool>>(false);
  std::chrono::steady_clock::time_point started = std::chrono::steady_clock::now();
};

// Maps the protocol's settings onto the renderer's; zero/empty fields take the documented
// defaults (the server normally fills them in).
// The part of a scene's cache and warnings key that names its material variant ("" for the
// default materials).
std::string variant_key(const std::string& variant) {
  return variant.empty() ? std::string() : " variant=" + variant;
}

// The part of a scene's cache key that names the image height its points and lines are one
// pixel wide at (LoadOptions::image_height).
std::string height_key(uint32_t height) { return " height=" + std::to_string(height); }

// The task's settings. The server sends every field set (server/renderfarm/domain/jobspec.py holds
// their defaults, in one place): an unset or unknown one fails the task rather than taking a
// default of the worker's own. *animation: the glTF animations an animated task's pose uses
// (resolve_animation_selection; frames and fps are the server's, which sends the frame and its
// time with the task).
bool settings_from_proto(const pb::RenderSettings& in, RenderSettings* out, std::string* animation,
                         std::string* err) {
  if (!in.has_width() || !in.has_height() || !in.has_max_depth() || !in.has_seed()) {
    *err = "width, height, max_depth and seed must be set";
    return false;
  }
  out->width = in.width();
  out->height = in.height();
  out->seed = in.seed();
  out->max_depth = in.max_depth();
  switch (in.sampler()) {
    case pb::SAMPLER_SOBOL: out->sampler = SamplerType::Sobol; break;
    case pb::SAMPLER_HALTON: out->sampler = SamplerType::Halton; break;
    case pb::SAMPLER_STRATIFIED: out->sampler = SamplerType::Stratified; break;
    case pb::SAMPLER_INDEPENDENT: out->sampler = SamplerType::Independent; break;
    default:
      *err = "unknown sampler " + std::to_string(int(in.sampler())) +
             " (expected sobol, halton, stratified or independent)";
      return false;
  }
  switch (in.integrator()) {
    case pb::INTEGRATOR_PATH: out->integrator = IntegratorType::Path; break;
    case pb::INTEGRATOR_DIRECT: out->integrator = IntegratorType::Direct; break;
    case pb::INTEGRATOR_AO: out->integrator = IntegratorType::AmbientOcclusion; break;
    default:
      *err = "unknown integrator " + std::to_string(int(in.integrator())) +
             " (expected path, direct or ao)";
      return false;
  }
  out->guiding = in.guiding();
  out->aperture_radius = float(in.aperture_radius());
  out->focus_distance = float(in.focus_distance());
  *animation = in.animation();
  return true;
}

// One server the worker serves (an address of --server): its channel and stubs, the id this
// worker gives itself there, and whether it has left the address list (a name that resolves to
// several addresses no longer gives this one).
struct Connection {
  std::string name;  // for messages
  std::string worker_id;
  std::unique_ptr<pb::WorkerService::Stub> workers;  // both on one channel to the server
  std::unique_ptr<pb::SceneService::Stub> scenes;
  std::atomic<bool> retired{false};
  std::atomic<bool> done{false};  // its thread has returned
};

class Worker {
 public:
  explicit Worker(const FarmOptions& options)
      : options_(options), scenes_(options.scenes_in_memory, options.scene_memory_budget) {}

  // One Connect stream to `c` from Hello to its end. Returns true if a Welcome was received.
  // Sessions with several servers run at once (a thread each); they share this worker's
  // threads, scene cache and environments.
  bool run_session(Connection& c, const std::atomic<bool>& stop);

 private:
  // State of one stream. Guarded by mutex_ unless atomic.
  struct Session {
    Connection* conn = nullptr;
    // Heartbeat.max_in_flight last sent (Hello's at first), and when.
    uint32_t want_sent = 0;
    Clock::time_point want_sent_at;
    grpc::ClientContext context;
    std::unique_ptr<grpc::ClientReaderWriter<pb::WorkerMessage, pb::ServerMessage>> stream;
    std::mutex write_mutex;
    std::deque<pb::Task> queue;
    std::map<std::string, RunningTask> running;  // by task id
    bool closing = false;      // graceful stop: take no new tasks
    bool over = false;         // stream ended: render threads and supervisor exit
    bool reader_done = false;
    bool welcomed = false;
    bool packed = false;       // the server's Welcome said packed: results may share a message
    uint32_t heartbeat_ms = 5000;
    std::atomic<uint64_t> samples{0}, rays{0};
    // Results on their way (send_result), made once Welcome has said whether packed (before
    // the render threads start).
    std::unique_ptr<ResultPacker> packer;
  };

  bool write(Session& s, const pb::WorkerMessage& message) {
    std::lock_guard<std::mutex> lock(s.write_mutex);
    return s.stream->Write(message);
  }
  // Sends a result through the session's ResultPacker: results ready together share a message
  // to a server whose Welcome said packed.
  void send_result(Session& s, pb::TileResult result);
  void render_loop(Session& s);
  void supervise(Session& s, const std::atomic<bool>& stop);
  void run_task(Session& s, const pb::Task& task, const RunningTask& running);
  // A still task's scene with the materials of KHR_materials_variants' `variant` ("" for the
  // default ones).
  std::shared_ptr<const Scene> scene_for(Connection& from, const std::string& sha256,
                                         const std::string& variant, uint32_t height);
  // An animated task's scene: sha256 posed at time_s by the animations `animation` selects,
  // moving during the shutter if it is open (motion blur).
  std::shared_ptr<const Scene> posed_scene_for(Connection& from, const std::string& sha256,
                                               const std::string& animation, double time_s,
                                               const Shutter& shutter,
                                               const std::string& variant, uint32_t height);
  // load(path, fetched) on the cached file of sha256, fetched first if there is none; a cached
  // file whose load fails with a SceneError and whose content no longer matches its name is
  // fetched again and loaded once more.
  template <typename T>
  T load_scene_file(Connection& from, const std::string& sha256,
                    const std::function<T(const std::string& path)>& load);
  LoadOptions farm_load_options(const std::string& sha256) const;
  std::shared_ptr<const Environment> environment_for(Connection& from,
                                                     const pb::RenderSettings& settings);
  // Fetches a scene (or environment) file into the cache from the server `from`.
  std::string fetch_scene(Connection& from, const std::string& sha256);

  // The tasks a session wants leased at once (mutex_ held): the worker's threads plus prefetch,
  // less what the other sessions hold (queued or rendering), at least 1 so that each server
  // can still hand over work. With one server: threads plus prefetch, always.
  uint32_t want(const Session& s) const;

  const FarmOptions& options_;
  SceneCache scenes_;
  std::vector<Session*> sessions_;  // the live sessions (mutex_)
  uint32_t busy_ = 0;                // tasks rendering over every session (mutex_)
  std::mutex warned_mutex_;
  std::set<std::string> warned_;  // scenes whose loader warnings were logged (posed scenes)
  // The task log (TileResult.warnings): the loader's warnings of each loaded scene, by scene
  // key (the sha256, and for animated tasks the animation selection after it), and the
  // (job, scene key) pairs whose warnings went out with a result already.
  void remember_warnings(const std::string& scene_key, const std::vector<std::string>& warnings,
                         bool append = false);
  std::vector<std::string> warnings_to_send(const std::string& job_id,
                                            const std::string& scene_key);
  std::mutex warnings_mutex_;
  std::map<std::string, std::vector<std::string>> scene_warnings_;
  std::set<std::string> warnings_sent_;
  // Path guiding's fields by job and frame (settings.guiding): each trained once by the first
  // task of its frame while the frame's other tasks wait, the last few kept.
  SceneCache guides_{kGuideFields};
  // Loaded environment maps by (sha256, intensity, rotation); a handful at most.
  std::mutex env_mutex_;
  std::map<std::string, std::shared_ptr<const Environment>> environments_;
  std::mutex mutex_;
  std::condition_variable cv_;
};

uint32_t Worker::want(const Session& s) const {
  uint64_t others = 0;
  for (const Session* o : sessions_)
    if (o != &s) others += o->queue.size() + o->running.size();
  // Results waiting for their message (--result-interval-ms) still hold their leases: ask for
  // as many more as a message has lately carried beyond one, so threads never run dry.
  const uint64_t waiting =
      s.packer ? uint64_t(std::max(0.0, s.packer->results_per_message() - 0.5)) : 0;
  const uint64_t capacity = uint64_t(options_.threads) + options_.prefetch + waiting;
  return uint32_t(std::max<uint64_t>(1, capacity > others ? capacity - others : 0));
}

bool Worker::run_session(Connection& c, const std::atomic<bool>& stop) {
  Session s;
  s.conn = &c;
  s.stream = c.workers->Connect(&s.context);
  pb::WorkerMessage hello_msg;
  pb::Hello* hello = hello_msg.mutable_hello();
  hello->set_worker_id(c.worker_id);
  hello->set_hostname(options_.hostname);
  hello->set_cores(options_.threads);
  {
    std::lock_guard<std::mutex> lock(mutex_);
    sessions_.push_back(&s);
    s.want_sent = want(s);
    s.want_sent_at = Clock::now();
  }
  hello->set_max_in_flight(s.want_sent);
  for (const std::string& sha : list_cached_scenes(options_.cache_dir))
    hello->add_cached_scenes(sha);
  hello->set_version(RENDERFARM_VERSION);
  hello->set_token(options_.token);
  hello->set_packed(true);  // reads ServerMessage.assigns
  // Every row of the channel table it renders: the server leases it tasks that name them.
  for (const channels::Spec& row : channels::kSpecs) hello->add_channels(row.name);
  for (const std::string& tag : options_.tags) hello->add_tags(tag);

  // The supervisor runs from the start so that a stop request also interrupts the wait for
  // Welcome; it sends heartbeats once welcomed.
  std::thread supervisor([&] { supervise(s, stop); });
  std::vector<std::thread> renderers;
  bool welcomed = false;
  if (write(s, hello_msg)) {
    pb::ServerMessage msg;
    if (s.stream->Read(&msg)) {
      if (msg.has_welcome()) {
        welcomed = true;
        log_line("connected to " + c.name + " as '" + msg.welcome().worker_id() +
                 "' (heartbeat " + std::to_string(msg.welcome().heartbeat_interval_ms()) +
                 " ms, lease " + std::to_string(msg.welcome().lease_ms()) + " ms)");
        {
          std::lock_guard<std::mutex> lock(mutex_);
          s.welcomed = true;
          s.packed = msg.welcome().packed();
          s.packer = std::make_unique<ResultPacker>(
              s.packed, [&s, this](const pb::WorkerMessage& m) { return write(s, m); },
              std::chrono::milliseconds(options_.result_interval_ms));
          if (msg.welcome().heartbeat_interval_ms())
            s.heartbeat_ms = msg.welcome().heartbeat_interval_ms();
        }
        cv_.notify_all();
        for (uint32_t i = 0; i < options_.threads; ++i)
          renderers.emplace_back([&] { render_loop(s); });
        while (s.stream->Read(&msg)) {
          std::lock_guard<std::mutex> lock(mutex_);
          if (msg.has_assign()) {
            if (!s.closing) s.queue.push_back(msg.assign().task());
          } else if (msg.has_assigns()) {
            if (!s.closing)
              for (const pb::Assign& a : msg.assigns().assigns()) s.queue.push_back(a.task());
          } else if (msg.has_cancel()) {
            for (const std::string& id : msg.cancel().task_ids()) {
              for (auto it = s.queue.begin(); it != s.queue.end();)
                it = it->task_id() == id ? s.queue.erase(it) : it + 1;
              auto r = s.running.find(id);
              if (r != s.running.end()) r->second.cancel->store(true);
            }
          }
          cv_.notify_all();
        }
      } else {
        log_line("protocol error: the server's first message is not Welcome");
        s.context.TryCancel();
      }
    }
  }
  {
    // The stream has ended: queued tasks go back to the server with the lease, and renders
    // in progress stop (their results could not be delivered any more).
    std::lock_guard<std::mutex> lock(mutex_);
    s.reader_done = true;
    s.over = true;
    s.queue.clear();
    for (auto& r : s.running) r.second.cancel->store(true);
  }
  cv_.notify_all();
  for (auto& t : renderers) t.join();
  supervisor.join();
  // Results still waiting can no longer go (a graceful end drained them before WritesDone).
  s.packer.reset();
  {
    std::lock_guard<std::mutex> lock(mutex_);
    sessions_.erase(std::find(sessions_.begin(), sessions_.end(), &s));
  }
  cv_.notify_all();  // the other sessions may want more now
  const grpc::Status status = s.stream->Finish();
  if (!status.ok() && !stop)
    log_line("stream to " + c.name + " ended: " + status.error_message() + " (code " +
             std::to_string(int(status.error_code())) + ")");
  return welcomed;
}

void Worker::supervise(Session& s, const std::atomic<bool>& stop) {
  auto last_beat = Clock::now();
  uint64_t last_samples = 0, last_rays = 0;
  std::unique_lock<std::mutex> lock(mutex_);
  for (;;) {
    cv_.wait_for(lock, std::chrono::milliseconds(50));
    if (s.over) return;
    if (stop && !s.closing) {
      if (!s.welcomed) {
        s.context.TryCancel();
        return;
      }
      // Graceful stop: drop queued tasks (the server re-leases them when the stream closes),
      // let the running ones finish and send their results, then close our side.
      log_line("stopping: finishing " + std::to_string(s.running.size()) + " task(s)");
      s.closing = true;
      s.queue.clear();
      cv_.notify_all();
      while (!s.running.empty() && !s.over) cv_.wait(lock);
      if (s.over) return;
      lock.unlock();
      s.packer->drain();  // the last results, without waiting for --result-interval-ms
      {
        std::lock_guard<std::mutex> wlock(s.write_mutex);
        s.stream->WritesDone();
      }
      lock.lock();
      // The server normally ends the stream when we end ours; don't wait forever.
      if (!cv_.wait_for(lock, std::chrono::seconds(5), [&] { return s.reader_done; }))
        s.context.TryCancel();
      return;
    }
    if (!s.welcomed) continue;
    const auto now = Clock::now();
    // The time budget: a render past it stops now and fails (run_task reports it).
    for (auto& r : s.running)
      if (!r.second.cancel->load() &&
          std::chrono::duration<double>(now - r.second.started).count() >
              options_.task_timeout_s) {
        r.second.timed_out->store(true);
        r.second.cancel->store(true);
      }
    const double elapsed = std::chrono::duration<double>(now - last_beat).count();
    // A heartbeat goes out on time, or early (at most every 100 ms) when the tasks this
    // stream should ask for changed because the other servers' tasks came or went.
    const uint32_t wanted = want(s);
    const bool want_changed =
        wanted != s.want_sent && now - s.want_sent_at >= std::chrono::milliseconds(100);
    if (elapsed * 1000.0 < double(s.heartbeat_ms) && !want_changed) continue;
    pb::WorkerMessage msg;
    pb::Heartbeat* hb = msg.mutable_heartbeat();
    for (const auto& r : s.running) hb->add_task_ids(r.first);
    for (const auto& t : s.queue) hb->add_task_ids(t.task_id());
    const uint64_t samples = s.samples, rays = s.rays;
    hb->set_samples_per_s(double(samples - last_samples) / elapsed);
    hb->set_rays_per_s(double(rays - last_rays) / elapsed);
    hb->set_busy_threads(uint32_t(s.running.size()));
    hb->set_max_in_flight(wanted);
    s.want_sent = wanted;
    s.want_sent_at = now;
    last_samples = samples;
    last_rays = rays;
    last_beat = now;
    lock.unlock();
    if (!write(s, msg)) s.context.TryCancel();  // broken stream: let the reader see it
    lock.lock();
  }
}

void Worker::render_loop(Session& s) {
  std::unique_lock<std::mutex> lock(mutex_);
  for (;;) {
    // The worker's threads are shared by its sessions: a task starts when one is free.
    cv_.wait(lock, [&] {
      return s.over || s.closing || (!s.queue.empty() && busy_ < options_.threads);
    });
    if (s.over || s.queue.empty()) return;  // closing with nothing queued: done
    pb::Task task = std::move(s.queue.front());
    s.queue.pop_front();
    const RunningTask running = s.running[task.task_id()];  // shares the flags
    ++busy_;
    lock.unlock();
    run_task(s, task, running);
    lock.lock();
    --busy_;
    s.running.erase(task.task_id());
    cv_.notify_all();
  }
}

void Worker::run_task(Session& s, const pb::Task& task, const RunningTask& running) {
  const auto t0 = Clock::now();
  const std::atomic<bool>& cancel = *running.cancel;
  auto fail = [&](const TaskError& e) {
    log_line("task " + task.task_id() + " failed: " + e.message);
    pb::WorkerMessage msg;
    pb::TaskFailed* f = msg.mutable_failed();
    f->set_task_id(task.task_id());
    f->set_error(e.message);
    f->set_retryable(e.retryable);
    write(s, msg);
  };
  RenderSettings settings;
  std::string animation, err;
  if (!settings_from_proto(task.settings(), &settings, &animation, &err))
    return fail({"settings: " + err, false});
  Shutter shutter;
  if (task.animated()) {
    if (!std::isfinite(task.time_s()))
      return fail({"task: time_s of frame " + std::to_string(task.frame()) + " is not finite",
                   false});
    // Motion blur: the shutter in seconds from the frame's time (fractions of a frame of
    // 1 / fps seconds).
    if (!parse_shutter(task.settings().shutter(), task.settings().fps(), &shutter, &err))
      return fail({err, false});
    // docs/architecture.md, "Determinism": the frame enters every random number.
    settings.seed = frame_seed(settings.seed, task.frame());
  }
  const PixelRect rect{task.rect().x0(), task.rect().y0(), task.rect().width(),
                       task.rect().height()};
  err = validate_render_request(settings, rect, task.sample_start(), task.sample_count());
  if (!err.empty()) return fail({"task: " + err, false});
  // Per-pixel adaptive sampling: the pixels this batch renders (workers.proto).
  const std::string& active = task.active_pixels();
  if (!active.empty() && active.size() != (size_t(rect.pixel_count()) + 7) / 8)
    return fail({"task: active_pixels has " + std::to_string(active.size()) +
                     " bytes, the rect's " + std::to_string(rect.pixel_count()) +
                     " pixels need " + std::to_string((size_t(rect.pixel_count()) + 7) / 8),
                 false});
  std::shared_ptr<const Scene> scene;
  const std::string& variant = task.settings().variant();
  try {
    scene = task.animated() ? posed_scene_for(*s.conn, task.scene_sha256(), animation,
                                              task.time_s(),
                                              shutter, variant, settings.height)
                            : scene_for(*s.conn, task.scene_sha256(), variant, settings.height);
  } catch (const TaskError& e) {
    return fail(e);
  } catch (const AnimationSelectionError& e) {
    return fail({e.what(), false});
  } catch (const SceneError& e) {
    return fail({std::string("scene load: ") + e.what(), false});
  } catch (const std::exception& e) {
    return fail({std::string("scene: ") + e.what(), true});
  }
  try {
    settings.environment = environment_for(*s.conn, task.settings());
  } catch (const TaskError& e) {
    return fail(e);
  } catch (const std::exception& e) {
    return fail({without_path(std::string("environment: ") + e.what(),
                              find_cached_scene(options_.cache_dir, task.settings().environment_sha256()),
                              "environment " + task.settings().environment_sha256().substr(0, 12)),
                 false});
  }
  // The rows of the channel table the result carries (Task.channels, in its order); a server
  // from before the table names none and reads the TileResult's own fields (no ranked rows:
  // their labels are not counted, nor the lobe rows or light groups traced).
  std::vector<channels::Id> wanted;
  uint32_t rows = channels::kAll & ~channels::kRanked & ~channels::bit(channels::Id::Motion) &
                  ~channels::kLobes & ~channels::bit(channels::Id::LightGroups);
  if (task.channels_size() > 0) {
    rows = 0;
    for (const std::string& name : task.channels()) {
      const channels::Spec* found = nullptr;
      for (const channels::Spec& row : channels::kSpecs)
        if (name == row.name) found = &row;
      if (!found)
        return fail({"task: channel '" + name.substr(0, 40) + "' is not one this worker " +
                         "renders (channel table version " +
                         std::to_string(channels::kTableVersion) + "): upgrade the worker",
                     false});
      wanted.push_back(found->id);
      rows |= channels::bit(found->id);
    }
  }
  // The light groups (settings.light_groups), read only for a task that asks for their row;
  // a value that is not a JSON object of group name -> node indices, or has no group, and a
  // scene with an emitting node in no group are refused (the groups would not sum to the
  // image).
  if (rows & channels::bit(channels::Id::LightGroups)) {
    auto groups = std::make_shared<LightGroups>();
    err = parse_light_groups(task.settings().light_groups(), groups.get());
    if (err.empty()) err = check_light_groups(*scene, *groups);
    if (!err.empty()) return fail({err, false});
    settings.light_groups = std::move(groups);
  }
  // Path guiding: the field of the task's frame, trained by the first task that needs it
  // (with all of the worker's threads) and shared by the frame's other tasks. Its key names
  // everything it is learned from that a job's tasks can differ in: the frame (scene pose,
  // seed) and the variant.
  if (settings.guiding) {
    char time[32];
    std::snprintf(time, sizeof time, "%.17g", task.animated() ? task.time_s() : 0.0);
    const std::string key = task.job_id() + "/" + task.scene_sha256() + "/" +
                            std::to_string(task.frame()) + "/" + time + "/" + variant + "/" +
                            std::to_string(settings.seed);
    try {
      settings.guide = guides_.get_derived<GuideField>(key, [&] {
        GuideStats stats;
        auto field = train_guide(*scene, settings, options_.threads, &stats);
        char line[160];
        std::snprintf(line, sizeof line,
                      " frame %u: path guiding trained in %.2f s (%llu paths, %u regions)",
                      task.frame(), stats.seconds, static_cast<unsigned long long>(stats.paths),
                      stats.distributions);
        log_line("job " + task.job_id() + line);
        return field;
      });
    } catch (const std::exception& e) {
      return fail({std::string("path guiding: ") + e.what(), true});
    }
  }
  // The Motion row of an animated task: the scene posed (plain, no shutter) at the frames
  // before and after, t -+ 1 / fps, through the pose cache like the frame's own pose; only
  // for a task that asks for the row (the first-sample batch), so no other task poses more.
  // A still has no motion: its row is 0 (no poses).
  std::shared_ptr<const Scene> previous, next;
  std::optional<MotionPoses> motion;
  if ((rows & channels::bit(channels::Id::Motion)) && task.animated()) {
    const double fps = task.settings().fps();
    if (!(fps > 0.0) || !std::isfinite(fps))
      return fail({"task: the motion row needs fps > 0 (frames 1 / fps apart)", false});
    try {
      previous = posed_scene_for(*s.conn, task.scene_sha256(), animation,
                                 task.time_s() - 1.0 / fps, Shutter{}, variant,
                                 settings.height);
      next = posed_scene_for(*s.conn, task.scene_sha256(), animation,
                             task.time_s() + 1.0 / fps, Shutter{}, variant, settings.height);
    } catch (const TaskError& e) {
      return fail(e);
    } catch (const SceneError& e) {
      return fail({std::string("scene load: ") + e.what(), false});
    } catch (const std::exception& e) {
      return fail({std::string("scene: ") + e.what(), true});
    }
    motion.emplace(*scene, frame_shutter_time(shutter), *previous, *next, settings.width,
                   settings.height);
  }
  TileBuffer tile;
  const bool rendered =
      !cancel && render_rect(*scene, settings, rect, task.sample_start(), task.sample_count(),
                             &tile, &cancel, rows, motion ? &*motion : nullptr,
                             active.empty() ? nullptr
                                            : reinterpret_cast<const uint8_t*>(active.data()));
  if (running.timed_out->load()) {
    char budget[32];
    std::snprintf(budget, sizeof budget, "%g", options_.task_timeout_s);
    return fail({std::string("task: rendering one batch took longer than the worker's time "
                             "budget of ") + budget + " s (--task-timeout-s); the scene is too " +
                     "costly per sample for this farm",
                 false});
  }
  if (!rendered || cancel) return;  // cancelled: send nothing
  pb::TileResult result;
  pb::TileResult* r = &result;
  r->set_task_id(task.task_id());
  r->set_job_id(task.job_id());
  r->set_tile_index(task.tile_index());
  r->set_batch_index(task.batch_index());
  r->set_sample_start(task.sample_start());
  r->set_sample_count(task.sample_count());
  *r->mutable_rect() = task.rect();
  // float32 on the wire: the radiance's batch sums (at most 64 samples, summed in double)
  // rounded once; the other rows as render_rect summed them, those of type U32 (ids) as the
  // integers their sums hold; the ranked rows as their (label, count) pairs, uint32.
  if (!wanted.empty()) {
    r->set_table_version(channels::kTableVersion);
    for (const channels::Id id : wanted) {
      const channels::Spec& row = channels::spec(id);
      pb::ChannelBlock* block = r->add_channels();
      block->set_name(row.name);
      block->set_type(pb::ValueType(int(row.type)));
      // The per-group row: 3 components per light group of the task.
      block->set_components(channels::components(id, tile.groups));
      if (id == channels::Id::Rgb)
        block->set_data(pack_f64_as_f32_le(tile.rgb_sum));
      else if (id == channels::Id::Luminance)
        block->set_data(pack_f64_as_f32_le(tile.luminance_m2));
      else if (row.ranked)
        block->set_data(pack_u32_le(tile.ranked(id)));  // (label, count) pairs
      else if (row.type == channels::Type::U32)
        block->set_data(pack_f32_as_u32_le(tile.sum(id)));  // ids, exact in the float sums
      else
        block->set_data(pack_f32_le(tile.sum(id)));
    }
  } else {  // a server from before the channel table
    r->set_rgb_sum(pack_f64_as_f32_le(tile.rgb_sum));
    r->set_luminance_m2(pack_f64_as_f32_le(tile.luminance_m2));
    if (!task.skip_aovs()) {
      r->set_albedo_sum(pack_f32_le(tile.sum(channels::Id::Albedo)));
      r->set_normal_sum(pack_f32_le(tile.sum(channels::Id::Normal)));
    }
    r->set_coverage_sum(pack_f32_le(tile.sum(channels::Id::Coverage)));
  }
  r->set_nonfinite_samples(tile.nonfinite_samples);
  r->set_render_seconds(std::chrono::duration<double>(Clock::now() - t0).count());
  r->set_rays(tile.rays);
  const std::string scene_key =
      (task.animated() ? task.scene_sha256() + " " + animation : task.scene_sha256()) +
      variant_key(variant);
  for (const std::string& w : warnings_to_send(task.job_id(), scene_key)) r->add_warnings(w);
  s.samples += uint64_t(active.empty() ? rect.pixel_count() : active_count(active)) *
               task.sample_count();
  s.rays += tile.rays;
  send_result(s, std::move(result));
}

void Worker::send_result(Session& s, pb::TileResult result) {
  s.packer->send(std::move(result));
}

void Worker::remember_warnings(const std::string& scene_key,
                               const std::vector<std::string>& warnings, bool append) {
  std::lock_guard<std::mutex> lock(warnings_mutex_);
  std::vector<std::string>& kept = scene_warnings_[scene_key];
  if (!append) kept.clear();
  for (const std::string& w : warnings) {
    // The server reads at most 50 messages of 1000 characters (workers.proto).
    if (kept.size() >= 50) break;
    if (std::find(kept.begin(), kept.end(), w) == kept.end()) kept.push_back(w.substr(0, 1000));
  }
}

std::vector<std::string> Worker::warnings_to_send(const std::string& job_id,
                                                  const std::string& scene_key) {
  std::lock_guard<std::mutex> lock(warnings_mutex_);
  auto it = scene_warnings_.find(scene_key);
  if (it == scene_warnings_.end() || it->second.empty()) return {};
  if (warnings_sent_.size() > 100000) warnings_sent_.clear();  // a long-lived worker's memory
  if (!warnings_sent_.insert(job_id + "\n" + scene_key).second) return {};
  return it->second;
}

// Farm scenes are uploads: self-contained, within the limits, and named by their hash in
// messages (which reach the user) rather than by this machine's cache path.
LoadOptions Worker::farm_load_options(const std::string& sha256) const {
  LoadOptions load;
  load.display_name = "scene " + sha256.substr(0, 12);
  load.allow_external_files = false;
  load.limits = options_.limits;
  load.bvh = options_.bvh;
  return load;
}

template <typename T>
T Worker::load_scene_file(Connection& from, const std::string& sha256,
                          const std::function<T(const std::string& path)>& load) {
  std::string path = find_cached_scene(options_.cache_dir, sha256);
  bool fetched = false;
  if (path.empty()) {
    path = fetch_scene(from, sha256);
    fetched = true;
  }
  try {
    return load(path);
  } catch (const SceneError&) {
    // A cached file that no longer matches its name was damaged on disk: fetch it again.
    if (fetched || sha256_file_hex(path) == sha256) throw;
    log_line("cached scene " + path + " is corrupt; fetching it again");
    fs::remove(path);
    return load(fetch_scene(from, sha256));
  }
}

std::shared_ptr<const Scene> Worker::scene_for(Connection& from, const std::string& sha256,
                                               const std::string& variant, uint32_t height) {
  if (!is_sha256_hex(sha256)) throw TaskError{"scene: invalid sha256 '" + sha256 + "'", false};
  const std::string key = sha256 + variant_key(variant);
  const auto loader = [&]() -> std::shared_ptr<const Scene> {
    LoadOptions load = farm_load_options(sha256);
    load.variant = variant;
    load.image_height = height;
    return load_scene_file<std::shared_ptr<const Scene>>(
        from, sha256, [&](const std::string& path) -> std::shared_ptr<const Scene> {
          std::vector<std::string> warnings;
          std::unique_ptr<Scene> scene = load_scene(path, &warnings, load);
          for (const auto& w : warnings) log_line("warning: " + w);
          remember_warnings(key, warnings);
          log_line("scene " + sha256.substr(0, 12) + ": " +
                   std::to_string(scene->world_triangle_count()) + " triangles, " +
                   format_bytes(scene->memory_bytes()) + " in memory (" +
                   bvh_layout_name(options_.bvh) + " BVH)");
          return scene;
        });
  };
  // Loaded once for every image height, unless it has points and lines, which are made for
  // one height (Scene::thin_height): another height then has a copy of its own.
  std::shared_ptr<const Scene> scene = scenes_.get(key, loader);
  if (scene->thin_height() == 0 || scene->thin_height() == height) return scene;
  return scenes_.get(key + height_key(height), loader);
}

std::shared_ptr<const Scene> Worker::posed_scene_for(Connection& from,
                                                     const std::string& sha256,
                                                     const std::string& animation_selection,
                                                     double time_s, const Shutter& shutter,
                                                     const std::string& variant,
                                                     uint32_t height) {
  if (!is_sha256_hex(sha256)) throw TaskError{"scene: invalid sha256 '" + sha256 + "'", false};
  // The variant is part of the selection: an AnimatedScene (and its poses) per variant.
  const std::string animation = animation_selection + variant_key(variant);
  // The exact time (hexadecimal floating point) and the selection as sent: the tasks of one
  // frame of one job share a key.
  char time_key[128];
  std::snprintf(time_key, sizeof time_key, "%a [%a %a]", time_s,
                shutter.is_open() ? shutter.open_s : 0.0, shutter.is_open() ? shutter.close_s : 0.0);
  // The height sizes a pose's points and lines: a pose per height (the animated scene, its
  // static part, is the same for every height).
  const std::string pose_key = std::string(time_key) + " " + animation + height_key(height);
  const SceneCache::AnimatedLoader prepare = [&]() -> std::shared_ptr<const AnimatedScene> {
    const LoadOptions load = farm_load_options(sha256);
    return load_scene_file<std::shared_ptr<const AnimatedScene>>(
        from, sha256, [&](const std::string& path) -> std::shared_ptr<const AnimatedScene> {
          std::vector<std::string> warnings;
          std::shared_ptr<const GltfDocument> document = parse_gltf(path, &warnings, load);
          LoadOptions split = load;
          split.animations =
              resolve_animation_selection(animation_selection, gltf_animation_names(*document));
          split.variant = variant;
          auto animated = std::make_shared<const AnimatedScene>(document, split, &warnings);
          for (const auto& w : warnings) log_line("warning: " + w);
          remember_warnings(sha256 + " " + animation, warnings);
          const Scene& part = animated->static_part();
          log_line("scene " + sha256.substr(0, 12) + ": loaded for animation (" +
                   format_bytes(gltf_document_bytes(*document)) + " of buffers and images; " +
                   "static part " + std::to_string(part.world_triangle_count()) + " + " +
                   std::to_string(animated->moving_nodes()) + " moving and " +
                   std::to_string(animated->deformed_nodes()) + " deformed mesh nodes, " +
                   format_bytes(part.memory_bytes()) + ")");
          return animated;
        });
  };
  const SceneCache::Poser pose = [&](const AnimatedScene& animated) -> std::shared_ptr<const Scene> {
    std::vector<std::string> warnings;
    const auto start = Clock::now();
    std::shared_ptr<const Scene> scene = animated.pose(time_s, &warnings, shutter, height);
    const double seconds = std::chrono::duration<double>(Clock::now() - start).count();
    // The loader warns of the same things at every time: once per scene and selection.
    bool first;
    {
      std::lock_guard<std::mutex> lock(warned_mutex_);
      first = warned_.insert(sha256 + " " + animation).second;
    }
    if (first) {
      for (const auto& w : warnings) log_line("warning: " + w);
      remember_warnings(sha256 + " " + animation, warnings, true);
      char at[96];
      std::snprintf(at, sizeof at, "%g s in %.3f s", time_s, seconds);
      log_line("scene " + sha256.substr(0, 12) + " posed at " + at + ": " +
               std::to_string(scene->world_triangle_count()) + " triangles, " +
               format_bytes(scene->memory_bytes()) + " of its own in memory (" +
               bvh_layout_name(options_.bvh) + " BVH)");
    }
    return scene;
  };
  return scenes_.get_posed(sha256, animation, pose_key, prepare, pose);
}

std::shared_ptr<const Environment> Worker::environment_for(Connection& from,
                                                           const pb::RenderSettings& settings) {
  const std::string& sha256 = settings.environment_sha256();
  if (sha256.empty()) return nullptr;
  if (!is_sha256_hex(sha256))
    throw TaskError{"environment: invalid sha256 '" + sha256 + "'", false};
  const float intensity =
      settings.environment_intensity() != 0.0 ? float(settings.environment_intensity()) : 1.f;
  const float rotation = float(settings.environment_rotation_deg());
  if (!(intensity > 0.f) || !std::isfinite(intensity) || !std::isfinite(rotation))
    throw TaskError{"environment: intensity must be > 0 and rotation finite", false};
  const std::string key = sha256 + "/" + std::to_string(intensity) + "/" + std::to_string(rotation);
  // One lock around lookup and load: environments change rarely, and loading one twice in
  // parallel would only waste memory.
  std::lock_guard<std::mutex> lock(env_mutex_);
  auto it = environments_.find(key);
  if (it != environments_.end()) return it->second;
  std::string path = find_cached_scene(options_.cache_dir, sha256);
  const bool cached = !path.empty();
  if (!cached) path = fetch_scene(from, sha256);
  std::shared_ptr<const Environment> env;
  try {
    env = Environment::load(path, intensity, rotation);
  } catch (const std::runtime_error&) {
    // A cached file that no longer matches its name was damaged on disk: fetch it again.
    if (!cached || sha256_file_hex(path) == sha256) throw;
    log_line("cached environment " + path + " is corrupt; fetching it again");
    fs::remove(path);
    path = fetch_scene(from, sha256);
    env = Environment::load(path, intensity, rotation);
  }
  if (environments_.size() >= 4) environments_.erase(environments_.begin());
  environments_[key] = env;
  log_line("loaded environment " + sha256 + " (" + std::to_string(env->width()) + "x" +
           std::to_string(env->height()) + ")");
  return env;
}

std::string Worker::fetch_scene(Connection& from, const std::string& sha256) {
  std::error_code ec;
  fs::create_directories(options_.cache_dir, ec);
  std::ostringstream tmp_name;
  tmp_name << "." << sha256 << "." << ::getpid() << "." << std::this_thread::get_id() << ".tmp";
  const fs::path tmp = fs::path(options_.cache_dir) / tmp_name.str();
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() + std::chrono::minutes(10));
  pb::FetchSceneRequest request;
  request.set_sha256(sha256);
  auto reader = from.scenes->FetchScene(&context, request);
  std::ofstream out(tmp, std::ios::binary | std::ios::trunc);
  if (!out) throw TaskError{"scene fetch: cannot write to the worker's scene cache", true};
  Sha256 hash;
  uint64_t offset = 0;
  pb::SceneFormat format = pb::SCENE_FORMAT_UNSPECIFIED;
  std::string filename;
  std::string first_bytes;
  pb::SceneChunk chunk;
  bool ordered = true;
  while (reader->Read(&chunk)) {
    if (chunk.has_info()) {
      format = chunk.info().format();
      filename = chunk.info().filename();
    }
    if (chunk.offset() != offset) ordered = false;
    const std::string& data = chunk.data();
    if (first_bytes.size() < 4) first_bytes += data.substr(0, 4 - first_bytes.size());
    out.write(data.data(), std::streamsize(data.size()));
    hash.update(data.data(), data.size());
    offset += data.size();
  }
  out.close();
  const grpc::Status status = reader->Finish();
  auto discard = [&](const std::string& why, bool retryable) {
    fs::remove(tmp, ec);
    throw TaskError{"scene fetch " + sha256 + ": " + why, retryable};
  };
  if (!status.ok())
    discard(status.error_message() + " (code " + std::to_string(int(status.error_code())) + ")",
            true);
  if (!out) discard("cannot write to the worker's scene cache", true);
  if (!ordered) discard("chunks arrived out of order", true);
  const std::string got = hash.final_hex();
  if (got != sha256) discard("SHA-256 mismatch (received " + got + ")", true);
  std::string ext;
  if (format == pb::SCENE_FORMAT_GLB) ext = ".glb";
  else if (format == pb::SCENE_FORMAT_GLTF) ext = ".gltf";
  else if (format == pb::SCENE_FORMAT_HDR) ext = ".hdr";
  else if (format == pb::SCENE_FORMAT_EXR) ext = ".exr";
  else if (first_bytes == "glTF") ext = ".glb";  // unspecified: sniff the magic
  else if (first_bytes.compare(0, 2, "#?") == 0) ext = ".hdr";
  else if (first_bytes == std::string("\x76\x2f\x31\x01", 4)) ext = ".exr";
  else ext = ".gltf";
  const fs::path final_path = fs::path(options_.cache_dir) / (sha256 + ext);
  fs::rename(tmp, final_path, ec);  // atomic within one directory
  if (ec) discard("cannot move into the cache: " + ec.message(), true);
  log_line("fetched scene " + sha256 + " ('" + filename + "', " + std::to_string(offset) +
           " bytes)");
  return final_path.string();
}

}  // namespace

namespace {

// "host:port" or "[v6]:port" into its parts; false for other gRPC targets (dns:///..., unix:...).
bool split_host_port(const std::string& target, std::string* host, std::string* port) {
  if (target.find("://") != std::string::npos || target.rfind("unix:", 0) == 0) return false;
  const size_t colon = target.rfind(':');
  if (colon == std::string::npos || colon == 0 || colon + 1 == target.size()) return false;
  *host = target.substr(0, colon);
  *port = target.substr(colon + 1);
  if (host->front() == '[') return false;  // an IPv6 literal: one address
  return host->find(':') == std::string::npos;
}

}  // namespace

std::vector<std::string> resolve_ipv4(const std::string& host, const std::string& port) {
  addrinfo hints{};
  hints.ai_family = AF_INET;
  hints.ai_socktype = SOCK_STREAM;
  addrinfo* found = nullptr;
  std::set<std::string> out;
  if (getaddrinfo(host.c_str(), port.c_str(), &hints, &found) != 0) return {};
  for (addrinfo* a = found; a; a = a->ai_next) {
    char text[INET_ADDRSTRLEN] = {};
    const auto* in = reinterpret_cast<const sockaddr_in*>(a->ai_addr);
    if (inet_ntop(AF_INET, &in->sin_addr, text, sizeof text)) out.insert(std::string(text));
  }
  freeaddrinfo(found);
  std::vector<std::string> addresses;
  for (const std::string& a : out) addresses.push_back(a + ":" + port);
  return addresses;
}

std::map<std::string, ServerTarget> server_targets(const std::string& servers,
                                                   const Resolver& resolve) {
  std::map<std::string, ServerTarget> targets;
  std::stringstream list(servers);
  for (std::string entry; std::getline(list, entry, ',');) {
    entry.erase(0, entry.find_first_not_of(" \t"));
    entry.erase(entry.find_last_not_of(" \t") + 1);
    if (entry.empty()) continue;
    std::string host, port;
    std::vector<std::string> addresses;
    if (split_host_port(entry, &host, &port)) addresses = resolve(host, port);
    std::sort(addresses.begin(), addresses.end());
    addresses.erase(std::unique(addresses.begin(), addresses.end()), addresses.end());
    if (addresses.size() < 2) {
      targets.emplace(entry, ServerTarget{entry, ""});
      continue;
    }
    for (const std::string& a : addresses)
      targets.emplace(a, ServerTarget{entry + " (" + a + ")", host});
  }
  return targets;
}

int run_farm_client(const FarmOptions& options, const std::atomic<bool>& stop) {
  grpc::ChannelArguments base_args;
  base_args.SetMaxReceiveMessageSize(64 << 20);
  std::shared_ptr<grpc::ChannelCredentials> credentials;
  if (options.tls) {
    grpc::SslCredentialsOptions ssl;
    ssl.pem_root_certs = options.tls_ca_pem;  // "": gRPC's default roots (the system's)
    ssl.pem_cert_chain = options.tls_cert_pem;
    ssl.pem_private_key = options.tls_key_pem;
    credentials = grpc::SslCredentials(ssl);
  } else {
    credentials = grpc::InsecureChannelCredentials();
  }
  Worker worker(options);
  log_line(std::string("serving ") + options.server +
           (options.tls ? " over TLS" + std::string(options.tls_cert_pem.empty() ? "" : " (client "
                                                                                  "certificate)")
                        : " without TLS"));
  log_line("loaded scenes kept in memory: up to " + std::to_string(options.scenes_in_memory) +
           " scenes" +
           (options.scene_memory_budget
                ? " or " + format_bytes(options.scene_memory_budget) + " (--scene-memory-mb)"
                : std::string()) +
           ", " + bvh_layout_name(options.bvh) + " BVH");
  // One thread per server, each reconnecting with its own backoff; the address list is
  // resolved again every resolve_interval_s, so that servers a name gains are served and those
  // it loses are left once their stream ends.
  struct Served {
    std::unique_ptr<Connection> connection;
    std::thread thread;
  };
  std::map<std::string, Served> served;
  auto serve = [&](Connection& c) {
    double backoff = options.backoff_initial_s;
    while (!stop && !c.retired) {
      if (worker.run_session(c, stop)) backoff = options.backoff_initial_s;
      if (stop || c.retired) break;
      log_line("reconnecting to " + c.name + " in " + std::to_string(backoff) + " s");
      const auto until = Clock::now() + std::chrono::duration<double>(backoff);
      while (!stop && !c.retired && Clock::now() < until)
        std::this_thread::sleep_for(std::chrono::milliseconds(20));
      backoff = std::min(options.backoff_max_s, 2.0 * backoff);
    }
  };
  const bool several_entries = options.server.find(',') != std::string::npos;
  for (auto next_resolve = Clock::now(); !stop;
       std::this_thread::sleep_for(std::chrono::milliseconds(20))) {
    if (Clock::now() < next_resolve) continue;
    next_resolve = Clock::now() + std::chrono::duration_cast<Clock::duration>(
                                      std::chrono::duration<double>(options.resolve_interval_s));
    const auto targets = server_targets(options.server, resolve_ipv4);
    // A server that left and whose stream has ended is forgotten (and served afresh if it
    // comes back).
    for (auto it = served.begin(); it != served.end();) {
      if (it->second.connection->done) {
        it->second.thread.join();
        it = served.erase(it);
      } else {
        ++it;
      }
    }
    for (auto& [target, entry] : served)
      if (!targets.count(target) && !entry.connection->retired) {
        log_line("leaving " + entry.connection->name + ": no longer an address of --server");
        entry.connection->retired = true;
      }
    for (const auto& [target, names] : targets) {
      if (served.count(target)) {
        served[target].connection->retired = false;  // back before its stream ended
        continue;
      }
      auto c = std::make_unique<Connection>();
      c->name = names.name;
      // Several servers see this process as one worker each: the address tells them apart
      // (in a farm of replicas they share one table of workers).
      c->worker_id = several_entries || target != names.name
                         ? (options.worker_id + "@" + target).substr(0, 100)
                         : options.worker_id;
      grpc::ChannelArguments args = base_args;
      const std::string tls_name =
          !options.tls_server_name.empty() ? options.tls_server_name : names.tls_name;
      if (options.tls && !tls_name.empty()) args.SetSslTargetNameOverride(tls_name);
      const auto channel = grpc::CreateCustomChannel(target, credentials, args);
      c->workers = pb::WorkerService::NewStub(channel);
      c->scenes = pb::SceneService::NewStub(channel);
      log_line("connecting to " + c->name);
      Served& entry = served[target];
      entry.connection = std::move(c);
      Connection* conn = entry.connection.get();
      entry.thread = std::thread([&serve, conn] {
        serve(*conn);
        conn->done = true;
      });
    }
  }
  for (auto& [target, entry] : served)
    if (entry.thread.joinable()) entry.thread.join();
  log_line("stopped");
  return 0;
}

}  // namespace rf
