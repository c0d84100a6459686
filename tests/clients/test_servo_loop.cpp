#include <gtest/gtest.h>

#include <chrono>
#include <cstdint>
#include <vector>

#include "clients/cpp/client.hpp"
#include "clients/sim/device_simulation.hpp"
#include "clients/sim/servo_loop.hpp"
#include "fake_server.hpp"

// The simulated devices' servo loop (sim::run_servo_loop) as a server sees it: each pose is stamped
// with the time it is of, the start of the servo period the device advanced to, not with when the
// loop got round to sending it. The server takes the device's velocity over the stamps' intervals
// (haptic::ProxyHand::commit_sample); stamped at the send, a servo that woke late gave one interval
// that much too long for a period's motion and the next as much too short, and the coupling's damper
// jerked a stylus lifting through free space on a busy machine (press_hold_lift_busy.sh).

namespace hapticd::client {
namespace {

using namespace std::chrono_literals;

TEST(ServoLoop, EachPoseIsStampedOnTheServoPeriodsItsDeviceAdvancedTo) {
  std::vector<std::uint64_t> stamps, sequences;
  Client client;
  const protocol::Hello hello = test::stylus_hello();
  sim::ServoResult r;
  {
    test::FakeServer server([&](test::FakeServer& s, const protocol::Message& m) {
      if (m.type == protocol::MessageType::kHello) {
        s.reply(test::welcome_for(m.hello, 5));
      } else if (m.type == protocol::MessageType::kPoseSample) {
        stamps.push_back(m.pose_sample.client_timestamp_ns);
        sequences.push_back(m.pose_sample.sequence);
        s.reply(test::force_for(m.pose_sample, 0.0f));
      }
    });
    client.connect("127.0.0.1", server.port(), hello, 2s);
    sim::ServoConfig config;
    config.rate_hz = 1000;
    config.duration_s = 0.3;
    config.frame_id = hello.frames[0].id;
    r = sim::run_servo_loop(client, sim::Trajectory::press(), config);
    client.bye();
  }
  ASSERT_GT(stamps.size(), 200u);
  const std::uint64_t period_ns = 1'000'000;
  for (std::size_t k = 1; k < stamps.size(); ++k) {
    ASSERT_GT(sequences[k], sequences[k - 1]);
    // Consecutive poses' stamps are whole periods apart: one, or more where the servo missed ticks.
    EXPECT_GT(stamps[k], stamps[k - 1]) << k;
    EXPECT_EQ((stamps[k] - stamps[k - 1]) % period_ns, 0u)
        << "pose " << k << ": " << stamps[k] - stamps[k - 1] << " ns";
  }
  // The round trips are the server's, from each send: no longer than the run, never negative.
  ASSERT_EQ(r.rtt_us.size(), r.replies);
  for (const double rtt : r.rtt_us) {
    EXPECT_GT(rtt, 0.0);
    EXPECT_LT(rtt, 3e5);
  }
}

}  // namespace
}  // namespace hapticd::client
