// Farm mode: a gRPC client of WorkerService.Connect (proto/renderfarm/v1/workers.proto) that
// renders assigned tile tasks and streams TileResults back, fetching scenes it has not cached
// through SceneService.FetchScene on the same channel.
#pragma once

#include <atomic>
#include <cstdint>
#include <functional>
#include <map>
#include <string>
#include <vector>

#include "scene/scene.h"

namespace rf {

struct FarmOptions {
  // The servers to serve, comma-separated: host:port (a name with several IPv4 addresses is
  // one server per address), [v6]:port or any gRPC target. One stream each; the worker's
  // threads are shared among them.
  std::string server;
  uint32_t threads = 1;    // render threads (Hello.cores)
  uint32_t prefetch = 2;   // extra tasks leased beyond threads (Hello.max_in_flight)
  // The least time between two result messages of a stream (ResultPacker): results that come
  // sooner share the next message. 0: each message as soon as the stream takes it.
  uint32_t result_interval_ms = 50;
  std::string cache_dir;   // scene file cache
  std::string token;       // shared worker token ("" if the server needs none)
  std::string worker_id;   // Hello.worker_id
  std::string hostname;
  std::vector<std::string> tags;  // Hello.tags: what jobs may require of this worker (--tag)
  size_t scenes_in_memory = 4;  // loaded-scene LRU capacity
  size_t scene_memory_budget = 0;  // bytes of loaded scenes kept (SceneCache), 0: no limit
  BvhLayout bvh = BvhLayout::Fast;  // how loaded scenes build their BVH
  SceneLimits limits;               // what a scene may cost (max_memory_bytes: this machine's)
  double task_timeout_s = 600.0;    // a task rendering longer fails (not retryable)
  // TLS (grpc::SslCredentials): the server's CA bundle ("": the system's), the client
  // certificate chain and key for mutual TLS ("": none), and the name to check in the
  // server's certificate ("": the host of `server`).
  bool tls = false;
  std::string tls_ca_pem, tls_cert_pem, tls_key_pem, tls_server_name;
  // Reconnect backoff: initial, doubling up to max; reset after a successful Welcome.
  double backoff_initial_s = 0.5;
  double backoff_max_s = 10.0;
  // How often the names of `server` are resolved again (servers gained or lost).
  double resolve_interval_s = 10.0;
};

// What the worker dials for FarmOptions::server, by dial target: each comma-separated entry as
// given, except a host:port whose host `resolve` gives several addresses ("a.b.c.d:port"),
// which is one server per address, its TLS certificate still checked against the host.
struct ServerTarget {
  std::string name;      // for messages: the entry, and the address if it is one of several
  std::string tls_name;  // the name to check in its certificate ("": the target's)
};
using Resolver =
    std::function<std::vector<std::string>(const std::string& host, const std::string& port)>;
std::map<std::string, ServerTarget> server_targets(const std::string& servers,
                                                   const Resolver& resolve);
// The host's IPv4 addresses now (getaddrinfo), "a.b.c.d:port" each.
std::vector<std::string> resolve_ipv4(const std::string& host, const std::string& port);

// Runs until *stop becomes true (set e.g. by a SIGINT/SIGTERM handler). Then it stops taking
// new tasks, finishes the tasks being rendered, sends their results, closes the stream and
// returns 0. Connection failures are retried with exponential backoff; they never end run().
int run_farm_client(const FarmOptions& options, const std::atomic<bool>& stop);

}  // namespace rf
