#include <gtest/gtest.h>

#include <chrono>
#include <cmath>
#include <cstdint>
#include <vector>

#include "clients/cpp/client.hpp"
#include "clients/cpp/reply_watchdog.hpp"
#include "clients/sim/device_simulation.hpp"
#include "clients/sim/servo_loop.hpp"
#include "fake_server.hpp"

// The device's guard against a silent server (client::ReplyWatchdog): the share of the held wrench
// it renders, against the ramp worked out by hand, and the servo loop's device fading out while a
// fake server stops answering and coming back without a step when it answers again.

namespace hapticd::client {
namespace {

using namespace std::chrono_literals;
constexpr std::uint64_t kMs = 1'000'000;

TEST(ReplyWatchdog, HoldsTheFullWrenchWhileRepliesComeThenRampsToZeroAndBack) {
  ReplyWatchdog w({20ms, 50ms});
  EXPECT_EQ(w.scale(1 * kMs), 1.0);  // nothing received yet: nothing held to fade
  // Replies every millisecond up to t = 100 ms.
  for (std::uint64_t t = 2; t <= 100; ++t) {
    w.on_reply(t * kMs);
    EXPECT_EQ(w.scale(t * kMs), 1.0) << t;
  }
  // Silent from then on: full until 120 ms (the hold), then down by 1/50 per ms.
  EXPECT_EQ(w.scale(110 * kMs), 1.0);
  EXPECT_EQ(w.scale(120 * kMs), 1.0);
  EXPECT_NEAR(w.scale(130 * kMs), 1.0 - 10.0 / 50.0, 1e-12);
  EXPECT_NEAR(w.scale(145 * kMs), 1.0 - 25.0 / 50.0, 1e-12);
  EXPECT_EQ(w.scale(170 * kMs), 0.0);
  EXPECT_EQ(w.scale(500 * kMs), 0.0);
  // Replies again from 500 ms, every millisecond: back up by 1/50 per ms, never in a step.
  for (std::uint64_t t = 500; t <= 560; ++t) {
    w.on_reply(t * kMs);
    EXPECT_NEAR(w.scale(t * kMs), std::min(1.0, static_cast<double>(t - 500) / 50.0), 1e-12) << t;
  }
  EXPECT_GT(w.faded(), 0u);
}

TEST(ReplyWatchdog, AShortSilenceFadesPartlyAndComesBackFromWhereItWas) {
  ReplyWatchdog w({20ms, 50ms});
  w.on_reply(1 * kMs);
  EXPECT_EQ(w.scale(1 * kMs), 1.0);
  // 35 ms without a reply: 14 ms past the hold, down to 1 - 14/50.
  EXPECT_NEAR(w.scale(35 * kMs), 1.0 - 14.0 / 50.0, 1e-12);
  w.on_reply(35 * kMs);
  EXPECT_NEAR(w.scale(40 * kMs), 1.0 - 9.0 / 50.0, 1e-12);
}

TEST(ReplyWatchdog, WithoutARampTheWrenchGoesAtOnceAndAClockThatStepsBackChangesNothing) {
  ReplyWatchdog w({10ms, 0ms});
  w.on_reply(100 * kMs);
  EXPECT_EQ(w.scale(110 * kMs), 1.0);
  EXPECT_EQ(w.scale(111 * kMs), 0.0);
  w.on_reply(112 * kMs);
  EXPECT_EQ(w.scale(112 * kMs), 1.0);
  // A time before the last reply or the last call: still fresh, no negative elapsed time.
  ReplyWatchdog v({10ms, 50ms});
  v.on_reply(100 * kMs);
  EXPECT_NEAR(v.scale(130 * kMs), 1.0 - 20.0 / 50.0, 1e-12);
  EXPECT_NEAR(v.scale(90 * kMs), 1.0 - 20.0 / 50.0, 1e-12);
  EXPECT_TRUE(std::isfinite(v.scale(0)));
}

TEST(ReplyWatchdog, TheSimulatedStylusRendersTheHeldForceTimesTheScale) {
  // The same tick under a held 4 N at scale 0.5 and under 2 N at scale 1: the same state and the
  // same work done on the device; at scale 0 no work at all.
  const sim::DeviceParams params;
  sim::DeviceSimulation half(sim::Trajectory::press(), params, 1e-3), full(sim::Trajectory::press(), params, 1e-3),
      none(sim::Trajectory::press(), params, 1e-3);
  half.set_force({0.0, 0.0, 4.0}, true);
  half.set_output_scale(0.5);
  full.set_force({0.0, 0.0, 2.0}, true);
  none.set_force({0.0, 0.0, 4.0}, true);
  none.set_output_scale(0.0);
  for (int k = 0; k < 200; ++k) half.advance(), full.advance(), none.advance();
  EXPECT_EQ(half.state().p_DT_m, full.state().p_DT_m);
  EXPECT_EQ(half.passivity_energy_j(), full.passivity_energy_j());
  EXPECT_NE(full.passivity_energy_j(), 0.0);
  EXPECT_EQ(none.passivity_energy_j(), 0.0);
  EXPECT_EQ(half.force().z, 2.0);
  EXPECT_EQ(none.force().z, 0.0);
}

// A server that answers every pose with 4 N along x, except the poses of sequences [301, 450]:
// 150 ms of silence at 1 kHz, then it answers again.
constexpr float kForce = 4.0f;
constexpr std::uint64_t kSilentFirst = 301, kSilentLast = 450;
void serve_with_a_silence(test::FakeServer& server, const protocol::Message& m) {
  if (m.type == protocol::MessageType::kHello) {
    server.reply(test::welcome_for(m.hello, 5));
  } else if (m.type == protocol::MessageType::kPoseSample) {
    const std::uint64_t s = m.pose_sample.sequence;
    if (s < kSilentFirst || s > kSilentLast) server.reply(test::force_for(m.pose_sample, kForce));
  }
}

TEST(ReplyWatchdog, TheServoLoopFadesAHeldForceOutWhileTheServerIsSilentAndBackWithoutAStep) {
  test::FakeServer server(serve_with_a_silence);
  Client client;
  const protocol::Hello hello = test::stylus_hello();
  client.connect("127.0.0.1", server.port(), hello, 2s);
  sim::ServoConfig config;
  config.rate_hz = 1000;
  config.duration_s = 0.8;
  config.frame_id = hello.frames[0].id;
  config.watchdog = {20ms, 50ms};
  std::vector<sim::TraceRow> trace;
  config.trace = &trace;
  const sim::ServoResult r = sim::run_servo_loop(client, sim::Trajectory::press(), config);
  client.bye();
  ASSERT_EQ(trace.size(), r.ticks);

  // Each row's pose sequence (the sent rows counted); the first row a reply had arrived by, the
  // row of the last pose answered before the silence, and of the first answered after it.
  std::vector<std::uint64_t> sequence(trace.size());
  std::uint64_t sent = 0;
  for (std::size_t k = 0; k < trace.size(); ++k) sequence[k] = sent += trace[k].sent;
  std::size_t first_force = trace.size(), last_before = 0, first_after = trace.size();
  for (std::size_t k = 0; k < trace.size(); ++k) {
    if (first_force == trace.size() && trace[k].f_DT_N.x != 0) first_force = k;
    if (sequence[k] < kSilentFirst) last_before = k;
    if (first_after == trace.size() && sequence[k] > kSilentLast) first_after = k;
  }
  ASSERT_LT(first_force, last_before);
  ASSERT_LT(first_after + 150, trace.size()) << "the run ended too soon after the silence";

  // The force never steps once held: a tick changes it by at most kForce / 50 (1 ms of a 50 ms ramp).
  const double max_step = kForce / 50.0 + 1e-6;
  for (std::size_t k = first_force + 1; k < trace.size(); ++k) {
    EXPECT_LE(std::abs(trace[k].f_DT_N.x - trace[k - 1].f_DT_N.x), max_step) << "tick " << k;
    EXPECT_GE(trace[k].f_DT_N.x, 0.0) << "tick " << k;
    EXPECT_LE(trace[k].f_DT_N.x, kForce) << "tick " << k;
  }
  // The last reply before the silence came by the end of its pose's period (or later): 20 ms on,
  // the fade began, and 50 ms after that the device renders nothing, to the end of the silence.
  std::size_t zero_rows = 0;
  for (std::size_t k = last_before + 1 + 20 + 50 + 2; k < first_after; ++k, ++zero_rows)
    EXPECT_EQ(trace[k].f_DT_N.x, 0.0) << "tick " << k << ", " << k - last_before << " after the last reply";
  EXPECT_GT(zero_rows, 50u);
  // Answered again, it comes back to the full force.
  double largest_after = 0;
  for (std::size_t k = first_after; k < trace.size(); ++k) largest_after = std::max(largest_after, trace[k].f_DT_N.x);
  EXPECT_EQ(largest_after, kForce);
  EXPECT_GE(r.faded_ticks, 100u);  // at least the 50 ticks down and the 50 back up
}

}  // namespace
}  // namespace hapticd::client
