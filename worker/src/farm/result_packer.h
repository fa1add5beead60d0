// Results of one stream on their way to the server, several to a message when they are ready
// together (workers.proto, TileResults), sent by a thread of their own so that render threads
// never wait for the stream.
#pragma once

#include <chrono>
#include <condition_variable>
#include <cstddef>
#include <functional>
#include <mutex>
#include <thread>
#include <vector>

#include "renderfarm/v1/workers.pb.h"

namespace rf {

class ResultPacker {
 public:
  using Write = std::function<bool(const renderfarm::v1::WorkerMessage&)>;
  using Clock = std::chrono::steady_clock;
  // At most this many results, or about this many bytes (a single larger result goes alone),
  // in one message.
  static constexpr size_t kMaxResults = 64;
  static constexpr size_t kMaxBytes = size_t(32) << 20;

  // packed: the server reads TileResults (its Welcome said so). write: one message onto the
  // stream (serialised by the caller's own lock with the stream's other writers). interval:
  // the least time from one message to the next (`renderfarm-worker connect
  // --result-interval-ms`): results that come sooner wait and share the next message, so a
  // worker with many threads sends a few full messages rather than many of one result each
  // (a server's cost is mostly per message). A result that comes after the interval has
  // passed goes at once, as does a full message; 0: every message as soon as the stream takes
  // it (results ready while one is written share the next).
  ResultPacker(bool packed, Write write,
               std::chrono::milliseconds interval = std::chrono::milliseconds(0));
  // Stops the sending thread after the message it is writing; results still waiting are
  // dropped (the stream is over: drain() first on a graceful end).
  ~ResultPacker();
  ResultPacker(const ResultPacker&) = delete;
  ResultPacker& operator=(const ResultPacker&) = delete;

  // Queues a result for the sending thread and returns at once. A result alone (or any to a
  // server that is not packed) goes as WorkerMessage.result.
  void send(renderfarm::v1::TileResult result);
  // Returns once every result queued before the call has been written, sending what waits
  // without waiting for the interval (a graceful end, before WritesDone).
  void drain();
  // Results a message has carried lately (a moving average, at least 1): about how many
  // results wait for the next message at its fullest, which the worker adds to the tasks it
  // asks for so that its threads do not run dry while their results wait.
  double results_per_message() const;

 private:
  struct Waiting {
    renderfarm::v1::TileResult result;
    size_t bytes;
  };
  void run();
  // The results of the next message, from the front of waiting_ (mutex_ held).
  std::vector<renderfarm::v1::TileResult> take();
  bool full() const;  // waiting_ fills a message (mutex_ held)
  void write(std::vector<renderfarm::v1::TileResult> ready);

  const bool packed_;
  const Write write_;
  const std::chrono::milliseconds interval_;
  mutable std::mutex mutex_;
  std::condition_variable cv_;
  std::vector<Waiting> waiting_;
  size_t waiting_bytes_ = 0;
  bool writing_ = false, stop_ = false;
  unsigned draining_ = 0;
  Clock::time_point next_ = Clock::time_point::min();  // the next message may go from then
  double per_message_ = 1.0;
  std::thread thread_;  // last: starts once the rest is set
};

}  // namespace rf
