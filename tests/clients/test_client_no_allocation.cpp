#include <gtest/gtest.h>

#include <chrono>

#include "allocation_counter.hpp"
#include "clients/cpp/client.hpp"
#include "fake_server.hpp"

namespace hapticd::client {
namespace {

using namespace std::chrono_literals;

using testing_util::allocations_in;

TEST(ClientNoAllocation, TheCounterSeesAllocations) {
  EXPECT_EQ(allocations_in([] { ::operator delete(::operator new(sizeof(int))); }), 1) << "otherwise the zero below proves nothing";
}

TEST(ClientNoAllocation, SendPosePollForceAndHeartbeatAllocateNothingAfterConnect) {
  test::FakeServer server([](test::FakeServer& s, const protocol::Message& m) {
    if (m.type == protocol::MessageType::kHello) s.reply(test::welcome_for(m.hello, 42));
    if (m.type == protocol::MessageType::kPoseSample) {
      s.reply(test::force_for(m.pose_sample, 0.5f));
      // A stale duplicate too, so the dropping path is measured as well.
      s.reply(test::force_for(m.pose_sample, 0.5f));
    }
  });
  Client client;
  client.connect("127.0.0.1", server.port(), test::stylus_hello(), 2s);
  protocol::PoseSample pose = test::stylus_pose();

  std::size_t replies = 0;
  const std::size_t during = allocations_in([&] {
    for (int i = 0; i < 1000; ++i) {
      pose.client_timestamp_ns = 0;
      if (client.send_pose(pose) != SendResult::kSent) continue;
      // Until the reply to this pose: duplicates of the previous one are read and dropped first.
      while (const auto reply = client.poll_force(1s)) {
        ++replies;
        if (reply->sample.sequence == pose.sequence) break;
      }
      if (i % 100 == 0) (void)client.heartbeat();
    }
    (void)client.poll_force(0ns);
  });
  EXPECT_EQ(during, 0u);
  EXPECT_EQ(replies, 1000u);
  EXPECT_GE(client.counters().forces_stale, 900u) << "the duplicates were received and dropped";
}

}  // namespace
}  // namespace hapticd::client
