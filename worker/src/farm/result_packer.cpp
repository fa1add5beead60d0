#include "farm/result_packer.h"

#include <algorithm>
#include <utility>

namespace pb = renderfarm::v1;

namespace rf {

ResultPacker::ResultPacker(bool packed, Write write, std::chrono::milliseconds interval)
    : packed_(packed), write_(std::move(write)), interval_(interval), thread_([this] { run(); }) {}

ResultPacker::~ResultPacker() {
  {
    std::lock_guard<std::mutex> lock(mutex_);
    stop_ = true;
  }
  cv_.notify_all();
  thread_.join();
}

void ResultPacker::send(pb::TileResult result) {
  {
    std::lock_guard<std::mutex> lock(mutex_);
    const size_t bytes = result.ByteSizeLong();
    waiting_.push_back({std::move(result), bytes});
    waiting_bytes_ += bytes;
  }
  cv_.notify_all();
}

void ResultPacker::drain() {
  std::unique_lock<std::mutex> lock(mutex_);
  ++draining_;
  cv_.notify_all();
  cv_.wait(lock, [&] { return stop_ || (waiting_.empty() && !writing_); });
  --draining_;
}

double ResultPacker::results_per_message() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return per_message_;
}

bool ResultPacker::full() const {
  return waiting_.size() >= kMaxResults || waiting_bytes_ >= kMaxBytes;
}

std::vector<pb::TileResult> ResultPacker::take() {
  size_t count = 0, bytes = 0;
  while (count < waiting_.size() && count < kMaxResults) {
    if (count > 0 && bytes + waiting_[count].bytes > kMaxBytes) break;
    bytes += waiting_[count].bytes;
    ++count;
  }
  std::vector<pb::TileResult> ready;
  ready.reserve(count);
  for (size_t i = 0; i < count; ++i) ready.push_back(std::move(waiting_[i].result));
  waiting_.erase(waiting_.begin(), waiting_.begin() + std::ptrdiff_t(count));
  waiting_bytes_ -= bytes;
  return ready;
}

void ResultPacker::run() {
  std::unique_lock<std::mutex> lock(mutex_);
  for (;;) {
    cv_.wait(lock, [&] { return stop_ || !waiting_.empty(); });
    // The interval from the last message, unless a message is full or a drain waits.
    while (!stop_ && !draining_ && !full() && Clock::now() < next_) cv_.wait_until(lock, next_);
    if (stop_) return;
    std::vector<pb::TileResult> ready = take();
    const auto started = Clock::now();
    writing_ = true;
    lock.unlock();
    const size_t count = ready.size();
    write(std::move(ready));
    lock.lock();
    writing_ = false;
    next_ = started + interval_;
    per_message_ = std::max(1.0, 0.8 * per_message_ + 0.2 * double(count));
    cv_.notify_all();  // drain() may be waiting
  }
}

void ResultPacker::write(std::vector<pb::TileResult> ready) {
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
}

}  // namespace rf
