// ResultPacker: results ready while a message is being written share the next message.
#include "farm/result_packer.h"

#include <gtest/gtest.h>

#include <condition_variable>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

namespace pb = renderfarm::v1;

namespace rf {
namespace {

pb::TileResult result(const std::string& id, size_t payload_bytes = 16) {
  pb::TileResult r;
  r.set_task_id(id);
  r.set_rgb_sum(std::string(payload_bytes, 'x'));
  return r;
}

// The task ids of each message written, in order ("result" messages as one id).
using Written = std::vector<std::vector<std::string>>;

std::vector<std::string> ids(const pb::WorkerMessage& m) {
  if (m.has_result()) return {m.result().task_id()};
  std::vector<std::string> out;
  for (const auto& r : m.results().results()) out.push_back(r.task_id());
  return out;
}

// A stream whose first write blocks until released: the results sent meanwhile are ready
// together when it returns.
struct HeldStream {
  std::mutex mutex;
  std::condition_variable cv;
  bool entered = false, released = false;
  Written written;
  std::vector<bool> was_packed;

  bool write(const pb::WorkerMessage& m) {
    std::unique_lock<std::mutex> lock(mutex);
    if (!entered) {
      entered = true;
      cv.notify_all();
      cv.wait(lock, [&] { return released; });
    }
    written.push_back(ids(m));
    was_packed.push_back(m.has_results());
    return true;
  }
};

Written send_while_held(bool packed, const std::vector<std::string>& later,
                        std::vector<bool>* was_packed) {
  HeldStream stream;
  ResultPacker packer(packed, [&](const pb::WorkerMessage& m) { return stream.write(m); });
  std::thread first([&] { packer.send(result("first")); });
  {
    std::unique_lock<std::mutex> lock(stream.mutex);
    stream.cv.wait(lock, [&] { return stream.entered; });
  }
  // The first message is being written: these return at once, their results waiting.
  for (const std::string& id : later) packer.send(result(id));
  {
    std::lock_guard<std::mutex> lock(stream.mutex);
    EXPECT_EQ(stream.written.size(), 0u);
    stream.released = true;
  }
  stream.cv.notify_all();
  first.join();
  *was_packed = stream.was_packed;
  return stream.written;
}

TEST(ResultPacker, ResultsReadyDuringAWriteShareTheNextMessage) {
  std::vector<bool> packed_kind;
  const Written written = send_while_held(true, {"b", "c", "d"}, &packed_kind);
  EXPECT_EQ(written, (Written{{"first"}, {"b", "c", "d"}}));
  EXPECT_EQ(packed_kind, (std::vector<bool>{false, true}));  // a single one goes as result
}

TEST(ResultPacker, AServerThatIsNotPackedGetsOneResultAMessage) {
  std::vector<bool> packed_kind;
  const Written written = send_while_held(false, {"b", "c"}, &packed_kind);
  EXPECT_EQ(written, (Written{{"first"}, {"b"}, {"c"}}));
  EXPECT_EQ(packed_kind, (std::vector<bool>{false, false, false}));
}

TEST(ResultPacker, AMessageHoldsAtMostItsCountAndBytes) {
  std::vector<std::string> many;
  for (int i = 0; i < 70; ++i) many.push_back("r" + std::to_string(i));
  std::vector<bool> packed_kind;
  const Written written = send_while_held(true, many, &packed_kind);
  ASSERT_EQ(written.size(), 3u);
  EXPECT_EQ(written[1].size(), ResultPacker::kMaxResults);
  EXPECT_EQ(written[2].size(), 70u - ResultPacker::kMaxResults);
  EXPECT_EQ(written[1].front(), "r0");
  EXPECT_EQ(written[2].back(), "r69");

  // Results of 20 MB: two would pass the byte limit, so each goes alone.
  HeldStream stream;
  ResultPacker packer(true, [&](const pb::WorkerMessage& m) { return stream.write(m); });
  std::thread first([&] { packer.send(result("first")); });
  {
    std::unique_lock<std::mutex> lock(stream.mutex);
    stream.cv.wait(lock, [&] { return stream.entered; });
  }
  packer.send(result("big1", 20u << 20));
  packer.send(result("big2", 20u << 20));
  packer.send(result("small"));
  {
    std::lock_guard<std::mutex> lock(stream.mutex);
    stream.released = true;
  }
  stream.cv.notify_all();
  first.join();
  EXPECT_EQ(stream.written, (Written{{"first"}, {"big1"}, {"big2", "small"}}));
}

}  // namespace
}  // namespace rf
