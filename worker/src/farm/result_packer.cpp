#include "farm/result_packer.h"

#include <iterator>
#include <utility>

namespace pb = renderfarm::v1;

namespace rf {

void ResultPacker::send(pb::TileResult result) {
  std::unique_lock<std::mutex> lock(mutex_);
  waiting_.push_back(std::move(result));
  if (writing_) return;  // the writing thread takes it with its next message
  writing_ = true;
  while (!waiting_.empty()) {
    size_t count = 0, bytes = 0;
    while (count < waiting_.size() && count < kMaxResults) {
      const size_t size = waiting_[count].ByteSizeLong();
      if (count > 0 && bytes + size > kMaxBytes) break;
      bytes += size;
      ++count;
    }
    const auto end = waiting_.begin() + std::ptrdiff_t(count);
    std::vector<pb::TileResult> ready(std::make_move_iterator(waiting_.begin()),
                                      std::make_move_iterator(end));
    waiting_.erase(waiting_.begin(), end);
    lock.unlock();
    if (ready.size() > 1 && packed_) {
      pb::WorkerMessage msg;
      for (pb::TileResult& one : ready) *msg.mutable_results()->add_results() = std::move(one);
      write_(msg);
    } else {
      for (pb::TileResult& one : ready) {
        pb::WorkerMessage msg;
        *msg.mutable_result() = std::move(one);
        write_(msg);
      }
    }
    lock.lock();
  }
  writing_ = false;
}

}  // namespace rf
