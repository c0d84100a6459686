#include <gtest/gtest.h>

#include <cstring>

#include "allocation_counter.hpp"
#include "protocol/codec.hpp"
#include "protocol_test_util.hpp"

// The hot path (encode and decode of PoseSample and ForceSample) must not touch
// the heap after warm-up: a measured loop asserts the count did not move.

namespace hapticd::protocol {
namespace {

// This thread's allocations so far (counting starts at the first call).
std::size_t allocations() {
  testing_util::count_allocations_on_this_thread(true);
  return static_cast<std::size_t>(testing_util::allocations_on_this_thread());
}

TEST(CodecNoAllocation, TheCounterSeesAllocations) {
  const std::size_t before = allocations();
  // A direct call: a new-expression paired with its delete may be elided.
  ::operator delete(::operator new(sizeof(int)));
  EXPECT_EQ(allocations() - before, 1u) << "otherwise the zero below proves nothing";
}

TEST(CodecNoAllocation, PoseAndForceRoundTripsAllocateNothingAfterWarmUp) {
  Encoder encoder;  // allocates its builder memory here, once
  // Static: a ReceiveBuffer and a Message belong to the receiving thread, made once.
  static ReceiveBuffer rx;
  static Message decoded;
  PoseSample pose = test::sample_pose(kMaxFrames);
  ForceSample force = test::sample_force(kMaxFrames);

  const std::size_t before = allocations();
  std::size_t decoded_ok = 0;
  for (int i = 0; i < 10000; ++i) {
    pose.sequence = static_cast<std::uint64_t>(i);
    const EncodeResult p = encoder.encode(pose);
    std::memcpy(rx.bytes.data(), p.bytes.data(), p.bytes.size());  // what recvfrom would do
    decoded_ok += decode({rx.bytes.data(), p.bytes.size()}, decoded).ok();

    force.sequence = decoded.pose_sample.sequence;
    const EncodeResult f = encoder.encode(force);
    std::memcpy(rx.bytes.data(), f.bytes.data(), f.bytes.size());
    decoded_ok += decode({rx.bytes.data(), f.bytes.size()}, decoded).ok();
  }
  const std::size_t during = allocations() - before;
  EXPECT_EQ(during, 0u);
  EXPECT_EQ(decoded_ok, 20000u);
  EXPECT_EQ(decoded.force_sample.sequence, 9999u);
}

// Stronger than the hot path needs: after construction no message type allocates, including the
// largest Hello and rejected datagrams.
TEST(CodecNoAllocation, NoMessageTypeAllocatesAfterConstruction) {
  const std::vector<Message> samples = test::sample_messages();
  Hello largest = test::sample_hello(kMaxFrames);
  largest.client_name.assign(std::string(kMaxClientName, 'c'));
  for (TrackedFrame& f : largest.frames) f.name.assign(std::string(kMaxFrameName, 'n'));
  static Message decoded;
  Encoder encoder;

  const std::size_t before = allocations();
  std::size_t ok = 0;
  for (int round = 0; round < 100; ++round) {
    for (const Message& m : samples) ok += decode(encoder.encode(m).bytes, decoded).ok();
    ok += decode(encoder.encode(largest).bytes, decoded).ok();
    PoseSample bad = samples[3].pose_sample;
    bad.poses[0].position_m.x = std::numeric_limits<float>::quiet_NaN();
    ok += encoder.encode(bad).ok();                                                     // refused, not allocated
    ok += decode(std::span(encoder.encode(samples[8]).bytes).first(40), decoded).ok();  // rejected
  }
  EXPECT_EQ(allocations() - before, 0u);
  EXPECT_EQ(ok, 100u * 10u);
}

}  // namespace
}  // namespace hapticd::protocol
