// Results of one stream on their way to the server, several to a message when they are ready
// together (workers.proto, TileResults).
#pragma once

#include <cstddef>
#include <functional>
#include <mutex>
#include <vector>

#include "renderfarm/v1/workers.pb.h"

namespace rf {

class ResultPacker {
 public:
  using Write = std::function<bool(const renderfarm::v1::WorkerMessage&)>;
  // At most this many results, or about this many bytes (a single larger result goes alone),
  // in one message.
  static constexpr size_t kMaxResults = 64;
  static constexpr size_t kMaxBytes = size_t(32) << 20;

  // packed: the server reads TileResults (its Welcome said so). write: one message onto the
  // stream (serialised by the caller's own lock with the stream's other writers).
  ResultPacker(bool packed, Write write) : packed_(packed), write_(std::move(write)) {}

  // Sends a result. If another thread is writing, the result goes out with that thread's next
  // message, together with every other one ready by then, and this call returns at once;
  // otherwise this thread writes it, then whatever came meanwhile, until none is left. So no
  // result waits for more than the message before it, and a server whose reading is the
  // bottleneck gets fewer, fuller messages. A result alone (or any to a server that is not
  // packed) goes as WorkerMessage.result.
  void send(renderfarm::v1::TileResult result);

 private:
  const bool packed_;
  const Write write_;
  std::mutex mutex_;
  std::vector<renderfarm::v1::TileResult> waiting_;
  bool writing_ = false;
};

}  // namespace rf
