// ResultPacker: results ready while a message is being written, or within the interval after
// it, share the next message; render threads never write.
#include "farm/result_packer.h"

#include <gtest/gtest.h>

#include <chrono>
#include <condition_variable>
#include <memory>
#include <mutex>
#include <string>
#include <vector>

namespace pb = renderfarm::v1;
using namespace std::chrono_literals;

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

// A stream whose first write blocks until released (held: the results sent meanwhile are
// ready together when it returns), and that records what it was given.
struct Stream {
  std::mutex mutex;
  std::condition_variable cv;
  bool hold_first = true, entered = false, released = false;
  Written written;
  std::vector<bool> was_packed;

  bool write(const pb::WorkerMessage& m) {
    std::unique_lock<std::mutex> lock(mutex);
    if (hold_first && !entered) {
      entered = true;
      cv.notify_all();
      cv.wait(lock, [&] { return released; });
    }
    written.push_back(ids(m));
    was_packed.push_back(m.has_results());
    cv.notify_all();
    return true;
  }
  // Waits (at most 60 s) until `messages` messages are written.
  void wait_for(size_t messages) {
    std::unique_lock<std::mutex> lock(mutex);
    ASSERT_TRUE(cv.wait_for(lock, 60s, [&] { return written.size() >= messages; }))
        << written.size() << " of " << messages << " messages written";
  }
  void wait_entered() {
    std::unique_lock<std::mutex> lock(mutex);
    ASSERT_TRUE(cv.wait_for(lock, 60s, [&] { return entered; }));
  }
  void release() {
    {
      std::lock_guard<std::mutex> lock(mutex);
      released = true;
    }
    cv.notify_all();
  }
  Written snapshot() {
    std::lock_guard<std::mutex> lock(mutex);
    return written;
  }
};

ResultPacker::Write writer(Stream& stream) {
  return [&stream](const pb::WorkerMessage& m) { return stream.write(m); };
}

Written send_while_held(bool packed, const std::vector<std::string>& later,
                        std::vector<bool>* was_packed) {
  Stream stream;
  ResultPacker packer(packed, writer(stream));
  packer.send(result("first"));
  stream.wait_entered();
  // The first message is being written: these wait for the next one.
  for (const std::string& id : later) packer.send(result(id));
  EXPECT_EQ(stream.snapshot().size(), 0u);
  stream.release();
  packer.drain();
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
  Stream stream;
  ResultPacker packer(true, writer(stream));
  packer.send(result("first"));
  stream.wait_entered();
  packer.send(result("big1", 20u << 20));
  packer.send(result("big2", 20u << 20));
  packer.send(result("small"));
  stream.release();
  packer.drain();
  EXPECT_EQ(stream.written, (Written{{"first"}, {"big1"}, {"big2", "small"}}));
}

TEST(ResultPacker, ResultsWithinTheIntervalWaitForTheNextMessage) {
  Stream stream;
  stream.hold_first = false;
  ResultPacker packer(true, writer(stream), std::chrono::hours(1));
  // The first message goes at once: no message went before it.
  packer.send(result("a"));
  stream.wait_for(1);
  // These come within the hour after it: they wait, however long the stream is free.
  packer.send(result("b"));
  packer.send(result("c"));
  EXPECT_EQ(stream.snapshot(), (Written{{"a"}}));
  // A drain (a graceful end) sends them at once, together.
  packer.drain();
  EXPECT_EQ(stream.snapshot(), (Written{{"a"}, {"b", "c"}}));
  // Messages of 1 and 2 results, averaged from 1 with weight 0.2 each.
  EXPECT_NEAR(packer.results_per_message(), 0.8 * 1.0 + 0.2 * 2.0, 1e-9);
}

TEST(ResultPacker, AFullMessageDoesNotWaitForTheInterval) {
  Stream stream;
  stream.hold_first = false;
  ResultPacker packer(true, writer(stream), std::chrono::hours(1));
  packer.send(result("a"));
  stream.wait_for(1);
  for (size_t i = 0; i <= ResultPacker::kMaxResults; ++i)
    packer.send(result("r" + std::to_string(i)));
  // kMaxResults fill a message, which goes within the hour; the one after them waits.
  stream.wait_for(2);
  const Written written = stream.snapshot();
  ASSERT_EQ(written.size(), 2u);
  EXPECT_EQ(written[1].size(), ResultPacker::kMaxResults);
  EXPECT_EQ(written[1].front(), "r0");
}

TEST(ResultPacker, ResultsStillWaitingWhenTheStreamEndsAreDropped) {
  Stream stream;
  stream.hold_first = false;
  {
    ResultPacker packer(true, writer(stream), std::chrono::hours(1));
    packer.send(result("a"));
    stream.wait_for(1);
    packer.send(result("b"));
  }  // the stream is over (no drain): b is not written to it
  EXPECT_EQ(stream.written, (Written{{"a"}}));
}

}  // namespace
}  // namespace rf
