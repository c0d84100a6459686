// The haptic loop's server on loopback: handshake, every pose answered, bad
// datagrams rejected and counted while a good client is served, silence and
// timeouts, and a thread that never allocates.
#include <gtest/gtest.h>
#include <poll.h>

#include <atomic>
#include <boost/asio/io_context.hpp>
#include <boost/asio/ip/udp.hpp>
#include <chrono>
#include <cmath>
#include <cstring>
#include <limits>
#include <thread>
#include <utility>

#include "haptic_server_test_util.hpp"

namespace hapticd::haptic {
namespace {

using protocol::Message;
using protocol::MessageType;
using test::RunningServer;
using test::TestClient;

TEST(HapticServer, AnswersEveryPoseWithTheEchoedSequenceAndTheWallForce) {
  RunningServer s;
  TestClient c(s.server.port());
  ASSERT_NE(c.hello(), 0u);
  int answered = 0;
  double f = 0;
  for (std::uint64_t k = 1; k <= 300; ++k) {
    // A client time stamp the server cannot derive from anything else: it must come back as sent.
    protocol::PoseSample p = c.pose_at(-0.004, k);
    p.client_timestamp_ns = 7'000'000'000ull + 1'000'003ull * k;
    c.send(p);
    const Message m = c.receive();
    f = NAN;
    if (m.type == MessageType::kForceSample && m.force_sample.sequence == k) {
      c.last = m.force_sample;
      f = m.force_sample.wrenches[0].wrench.force_n.z;
      EXPECT_EQ(m.force_sample.client_timestamp_ns, p.client_timestamp_ns);
    }
    answered += !std::isnan(f);
    std::this_thread::sleep_for(std::chrono::microseconds(500));
  }
  EXPECT_EQ(answered, 300);
  // Steady: the coupling (1000 N/m) in series with the wall (3000 N/m), 4 mm deep.
  EXPECT_NEAR(f, 750.0 * 0.004, 0.05 * 3.0);
  EXPECT_TRUE(c.last.flags & protocol::ForceFlags::kInContact);
  EXPECT_GE(c.last.server_send_ns, c.last.server_receive_ns);
  s.halt();
  EXPECT_EQ(s.server.stats().replies, 300u);
  EXPECT_GT(s.server.stats().ticks, 100u);
}

// A stylus on the wall's surface (z = 0, where the wall pulls nothing) sliding along x, each pose
// stamped 1 ms after the last whenever it is sent (a device's own clock), as a queue would carry them;
// `gap` moves that clock on by a gap in the device's samples.
struct SlidingStylus {
  TestClient& c;
  std::uint64_t seq = 0;
  std::uint64_t t0 = protocol::now_ns();
  void gap(std::chrono::nanoseconds d) { t0 += static_cast<std::uint64_t>(d.count()); }
  void send(double x) {
    protocol::PoseSample p = c.pose_at(0.0, ++seq);
    p.client_timestamp_ns = t0 + 1'000'000ull * seq;
    p.poses[0].position_m.x = static_cast<float>(x);
    c.send(p);
  }
  // The largest force of the next `replies` replies (0 for those that do not come).
  double largest_force(int replies) {
    double f = 0;
    for (int k = 0; k < replies; ++k) {
      const Message m = c.receive();
      if (m.type != MessageType::kForceSample) continue;
      const protocol::Vec3& v = m.force_sample.wrenches[0].wrench.force_n;
      f = std::max(f, std::sqrt(static_cast<double>(v.x * v.x + v.y * v.y + v.z * v.z)));
    }
    return f;
  }
  // `n` poses at x, each answered before the next, 0.5 ms apart: the largest force.
  double paced(double x, int n) {
    double f = 0;
    for (int k = 0; k < n; ++k) {
      send(x);
      f = std::max(f, largest_force(1));
      std::this_thread::sleep_for(std::chrono::microseconds(500));
    }
    return f;
  }
};

TEST(HapticServer, PosesReadInABurstMoveTheCouplingByTheDevicesOwnVelocity) {
  // A stylus resting on the wall's surface, then 40 poses
  // of a slide along x at 10 mm/s, stamped 1 ms apart but sent at once (what a stalled server
  // finds queued), then held at the slide's end. The proxy trails the device by at most the
  // slide, 0.4 mm: the coupling (1000 N/m) gives at most 0.4 N, plus its damper (0.75 N s/m) on
  // 10 mm/s (0.405 N measured). Taken over how far apart the poses were read (microseconds), the
  // velocity was 1-2 m/s, and that damper alone gave 0.75-1.5 N; without the device's stamps it
  // is taken over kMinSampleInterval_s at least (0.475 N here).
  RunningServer s;
  TestClient c(s.server.port());
  ASSERT_NE(c.hello(), 0u);
  SlidingStylus stylus{c};
  stylus.paced(0.0, 200);
  const double v = 0.01, slide = 40 * 1e-3 * v;
  for (int k = 1; k <= 40; ++k) stylus.send(k * 1e-3 * v);
  const double f_max = std::max(stylus.largest_force(40), stylus.paced(slide, 100));
  EXPECT_LE(f_max, 1000.0 * slide + 0.75 * v + 0.05) << "the burst's velocity reached the damper";
  EXPECT_GT(f_max, 0.5 * 1000.0 * slide) << "the slide was felt";
  s.halt();
  EXPECT_EQ(s.server.stats().resets, 0u);
}

struct QueuedSlide {
  double f_max;
  std::uint64_t resyncs, bridged_gaps;
};

// A stylus at rest on the wall's surface, then a 200 ms gap in its samples (in their time stamps too)
// across which it moves `away` along x, then 30 poses of a 15 mm slide along x from there sent at once
// (a queue its driver or link held), the last ten 5 ms after the first twenty if `interrupted`, then
// held at the slide's end: the largest force, the re-syncs and the bridged gaps counted.
QueuedSlide slide_queued_after_a_gap(bool interrupted, double away) {
  RunningServer s;
  TestClient c(s.server.port());
  if (c.hello() == 0) return {std::numeric_limits<double>::infinity(), 0, 0};
  SlidingStylus stylus{c};
  stylus.paced(0.0, 100);
  const std::uint64_t resyncs_before = s.server.stats().resyncs;
  std::this_thread::sleep_for(std::chrono::milliseconds(200));
  stylus.gap(std::chrono::milliseconds(200));
  for (int k = 0; k < 30; ++k) {
    if (interrupted && k == 20) std::this_thread::sleep_for(std::chrono::milliseconds(5));
    stylus.send(away + 5e-4 * k);
  }
  const double f_max = std::max(stylus.largest_force(30), stylus.paced(away + 5e-4 * 29, 50));
  s.halt();
  return {f_max, s.server.stats().resyncs - resyncs_before, s.server.stats().bridged_gaps};
}

// How far the stylus moves across the gap: farther than a gap is bridged over (re-synced), or not at
// all (bridged: ProxyHand::commit_sample).
constexpr double kAways[] = {2 * haptic::kMaxBridgedStretch_m, 0.0};

TEST(HapticServer, AQueueReadAfterAGapResyncsOnceOntoItsNewestPose) {
  // Back from afar, the first pose of the queue re-syncs (counted once); the rest carry the proxy
  // with them, so the device feels nothing of the slide: without that, the proxy waited 14.5 mm
  // behind and the coupling pulled the device back with up to 2.3 N. Back where it was, the gap is
  // bridged instead: the queue's slide joins the clutch, and is not felt either.
  for (const double away : kAways) {
    const QueuedSlide r = slide_queued_after_a_gap(false, away);
    EXPECT_EQ(r.resyncs, away > 0 ? 1u : 0u) << away;
    EXPECT_EQ(r.bridged_gaps, away > 0 ? 0u : 1u) << away;
    EXPECT_LT(r.f_max, 0.5) << "the proxy stayed behind the queue's oldest pose; away " << away;
  }
}

TEST(HapticServer, AQueueWhoseReadingIsInterruptedCarriesTheProxyToItsNewestPose) {
  // The last ten poses of the queue come 5 ms after the first twenty (as when the server is
  // descheduled while it reads them, a busy machine): they waited longer than the device's poses
  // before the gap, and carry the proxy with them too (or join the clutch of a bridged gap). Taken by
  // read times alone, the queue ended with the first of them, the proxy was left behind, and the
  // device was pulled back with 0.94 N.
  for (const double away : kAways) {
    const QueuedSlide r = slide_queued_after_a_gap(true, away);
    EXPECT_EQ(r.resyncs, away > 0 ? 1u : 0u) << away;
    EXPECT_EQ(r.bridged_gaps, away > 0 ? 0u : 1u) << away;
    EXPECT_LT(r.f_max, 0.5) << "the proxy stayed behind the queue's first part; away " << away;
  }
}

// A float's bytes in a datagram, replaced (the codec refuses to encode a NaN).
void patch_float(std::span<std::uint8_t> bytes, float from, float to) {
  for (std::size_t i = 0; i + 4 <= bytes.size(); ++i)
    if (std::memcmp(bytes.data() + i, &from, 4) == 0) std::memcpy(bytes.data() + i, &to, 4);
}

TEST(HapticServer, RejectsAndCountsBadDatagramsWhileServingAWellBehavedClient) {
  RunningServer s;
  TestClient good(s.server.port()), bad(s.server.port());
  good.hello();
  bad.hello();
  int answered = 0;
  std::array<std::uint8_t, 3000> junk{};
  for (std::size_t i = 0; i < junk.size(); ++i) junk[i] = static_cast<std::uint8_t>(i * 37 + 11);
  for (std::uint64_t k = 1; k <= 100; ++k) {
    switch (k % 6) {
      case 0: bad.send_bytes(junk.data(), 8); break;      // truncated
      case 1: bad.send_bytes(junk.data(), 3000); break;   // oversized
      case 2: bad.send_bytes(junk.data(), 256); break;    // garbage
      case 3: {                                           // NaN position
        const auto r = bad.encoder.encode(bad.pose_at(0.123, 1000 + k));
        std::vector<std::uint8_t> copy(r.bytes.begin(), r.bytes.end());
        patch_float(copy, 0.123f, NAN);
        bad.send_bytes(copy.data(), copy.size());
        break;
      }
      case 4: {  // unknown session
        protocol::PoseSample p = bad.pose_at(0.0, k);
        p.session_id = 12345;
        bad.send(p);
        break;
      }
      case 5: bad.send(bad.pose_at(0.0, 1)); break;  // replayed sequence
    }
    answered += !std::isnan(good.press(-0.002, k));
  }
  EXPECT_EQ(answered, 100);
  // The bad client's replayed sequence 1 was answered once, and its NaN sample never.
  int bad_replies = 0;
  while (bad.receive(50).type == MessageType::kForceSample) ++bad_replies;
  EXPECT_EQ(bad_replies, 1);
  s.halt();
  const ServerStats& st = s.server.stats();
  using R = protocol::RejectReason;
  EXPECT_EQ(st.rejected[static_cast<int>(R::kTooShort)], 16u);
  EXPECT_EQ(st.rejected[static_cast<int>(R::kTooLong)], 17u);
  EXPECT_EQ(st.rejected[static_cast<int>(R::kNonFinite)], 17u);
  EXPECT_GE(st.rejected[static_cast<int>(R::kBadIdentifier)] + st.rejected[static_cast<int>(R::kVerifyFailed)], 1u);
  EXPECT_EQ(st.unknown_session, 17u);
  EXPECT_EQ(st.duplicates, 15u);
  EXPECT_EQ(st.replies, 101u);
}

TEST(HapticServer, SilentSessionFadesToZeroForceThenTimesOut) {
  ServerOptions o;
  o.silence_s = 0.05;
  o.ramp_s = 0.1;
  o.resync_gap_s = 10;  // no resync: the fade alone must bring the force down
  o.session_timeout_s = 0.5;
  RunningServer s(o);
  TestClient c(s.server.port());
  c.hello();
  double pressed = 0;
  std::uint64_t seq = 0;
  for (int k = 0; k < 300; ++k) {
    pressed = c.press(-0.004, ++seq);
    std::this_thread::sleep_for(std::chrono::microseconds(500));
  }
  ASSERT_NEAR(pressed, 3.0, 0.15);
  std::this_thread::sleep_for(std::chrono::milliseconds(250));  // silent: faded out by 0.15 s
  const double after_silence = c.press(-0.004, ++seq);
  EXPECT_LT(std::abs(after_silence), 0.05 * pressed);
  // Poses again: the force comes back over the ramp, not in one step.
  double halfway = 0;
  const std::uint64_t t0 = protocol::now_ns();
  while (protocol::now_ns() - t0 < 50'000'000ull) {
    halfway = c.press(-0.004, ++seq);
    std::this_thread::sleep_for(std::chrono::microseconds(500));
  }
  EXPECT_GT(halfway, 0.2 * pressed);
  EXPECT_LT(halfway, 0.8 * pressed);
  std::this_thread::sleep_for(std::chrono::milliseconds(700));  // past the session timeout
  EXPECT_TRUE(std::isnan(c.press(-0.004, ++seq)));
  s.halt();
  EXPECT_EQ(s.server.stats().sessions_timed_out, 1u);
  EXPECT_EQ(s.server.stats().unknown_session, 1u);
}

TEST(HapticServer, AModelFromBeforeTheSessionsResyncIsNotRendered) {
  // No visual loop acknowledges the re-sync of the first pose: the model (the wall)
  // describes the hand where it was, so the proxy feels only its device.
  RunningServer s({}, false);
  TestClient c(s.server.port());
  c.hello();
  double f = 0;
  for (std::uint64_t k = 1; k <= 100; ++k) {
    f = std::max(f, std::abs(c.press(-0.004, k)));
    std::this_thread::sleep_for(std::chrono::microseconds(500));
  }
  EXPECT_LT(f, 0.01);  // 3 N with the model (the test above)
  EXPECT_TRUE(c.last.flags & protocol::ForceFlags::kInContact);
}

TEST(HapticServer, TheHapticThreadNeverAllocates) {
  RunningServer s;
  TestClient c(s.server.port());
  c.hello();
  for (std::uint64_t k = 1; k <= 200; ++k) c.press(k < 100 ? 0.01 : -0.004, k);
  protocol::Heartbeat hb{c.session, protocol::now_ns(), 0};
  c.send(hb);
  EXPECT_EQ(c.receive().type, MessageType::kHeartbeat);
  c.send(protocol::StatsRequest{c.session});
  const Message stats = c.receive();
  ASSERT_EQ(stats.type, MessageType::kStats);
  EXPECT_EQ(stats.stats.sessions_active, 1u);
  EXPECT_GE(stats.stats.packets_in, 202u);
  c.send_bytes("garbage!", 8);
  c.send(protocol::Bye{c.session});
  std::this_thread::sleep_for(std::chrono::milliseconds(20));
  s.halt();
  EXPECT_EQ(s.allocations.load(), 0);
  EXPECT_EQ(s.server.stats().sessions_closed, 1u);
}

}  // namespace
}  // namespace hapticd::haptic
