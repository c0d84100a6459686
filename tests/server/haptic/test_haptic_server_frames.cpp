// A glove's frames on the wire: a pose sample that leaves a frame out (its
// tracking failed: the client library drops a non-finite frame) holds that
// frame and ramps its force to zero while the other frames keep rendering;
// a first sample must carry every frame. A glove Hello that names its hand binds to a device on a
// hand of that side.
#include <gtest/gtest.h>

#include <array>
#include <atomic>
#include <chrono>
#include <cmath>
#include <memory>
#include <thread>

#include "haptic_server_test_util.hpp"

namespace hapticd::haptic {
namespace {

using protocol::Message;
using protocol::MessageType;
using test::TestClient;

constexpr int kFrames = 3;

// Every handle of a 3-handle hand on the wall z <= 0 (3000 N/m each), in contact.
HapticSnapshot glove_wall() {
  HapticSnapshot s;
  s.hands = 1;
  HapticModel& m = s.model[0];
  m.handles = kFrames;
  m.F0 = HapticVector::Zero(6 * kFrames);
  m.K = HapticMatrix::Zero(6 * kFrames, 6 * kFrames);
  m.D = HapticMatrix::Zero(6 * kFrames, 6 * kFrames);
  for (int j = 0; j < kFrames; ++j) {
    m.K(6 * j + 2, 6 * j + 2) = -3000.0;
    m.x0[j].p_W = Eigen::Vector3d(0.05 * j, 0, 0);
    m.v0[j].setZero();
    m.w0[j].setZero();
    m.handle_in_contact[j] = true;
  }
  m.in_contact = true;
  return s;
}

DeviceLink glove_link() {
  DeviceLink l;
  l.name = "glove";
  l.kind = protocol::DeviceKind::kGlove;
  l.handles = kFrames;
  for (int j = 0; j < kFrames; ++j) l.mass_kg[j] = 0.02, l.inertia_B[j] = 1e-6 * Eigen::Matrix3d::Identity();
  l.gains = coupling_gains_for(1000.0, 1.0, 1e-3);
  l.limits = {8.0, 0.5, 1000.0};
  l.contact_gated = true;
  return l;
}

struct GloveClient : TestClient {
  using TestClient::TestClient;
  void hello_glove() {
    const Message m = say_hello(protocol::Hand::kUnspecified);
    ASSERT_EQ(m.type, MessageType::kWelcome);
    session = m.welcome.session_id;
  }
  // A glove Hello naming `hand`; the server's answer.
  Message say_hello(protocol::Hand hand) {
    protocol::Hello h;
    h.client_name.assign("glove");
    h.device_kind = protocol::DeviceKind::kGlove;
    h.hand = hand;
    for (int j = 0; j < kFrames; ++j) {
      protocol::TrackedFrame f;
      f.id = static_cast<std::uint16_t>(10 + j);
      f.name.assign("frame");
      h.frames.push_back(f);
    }
    send(h);
    return receive(1000);
  }
  // Every frame 4 mm into the wall, except `lost` (left out); the z forces of the reply per
  // frame (NaN: no reply, or the frame not in it).
  std::array<double, kFrames> press(int lost, std::uint64_t seq) {
    protocol::PoseSample p;
    p.session_id = session;
    p.sequence = seq;
    p.client_timestamp_ns = protocol::now_ns();
    for (int j = 0; j < kFrames; ++j) {
      if (j == lost) continue;
      protocol::FramePose f;
      f.frame = static_cast<std::uint16_t>(10 + j);
      f.position_m = {static_cast<float>(0.05 * j), 0.0f, -0.004f};
      p.poses.push_back(f);
    }
    send(p);
    std::array<double, kFrames> out;
    out.fill(NAN);
    const Message m = receive();
    if (m.type != MessageType::kForceSample || m.force_sample.sequence != seq) return out;
    for (const protocol::FrameWrench& w : m.force_sample.wrenches)
      if (w.frame >= 10 && w.frame < 10 + kFrames) out[w.frame - 10] = w.wrench.force_n.z;
    return out;
  }
};

TEST(HapticServerFrames, ALostFrameRampsToZeroWhileTheOthersKeepRendering) {
  test::RunningServer s(ServerOptions{}, true, glove_wall, glove_link());
  GloveClient c(s.server.port());
  c.hello_glove();
  std::uint64_t seq = 0;
  // A first sample without every frame has nothing to hold: refused, unanswered.
  EXPECT_TRUE(std::isnan(c.press(1, ++seq)[0]));
  std::array<double, kFrames> f{};
  for (int k = 0; k < 300; ++k, std::this_thread::sleep_for(std::chrono::microseconds(500))) f = c.press(-1, ++seq);
  // Steady on the wall: the coupling (1000 N/m) in series with the wall (3000 N/m), 4 mm deep.
  for (int j = 0; j < kFrames; ++j) EXPECT_NEAR(f[j], 3.0, 0.15) << "frame " << j;
  // Frame 1's tracking fails for 0.15 s: its force ramps to zero within 8 N / 1000 N/s, the others keep theirs.
  double lost_max_late = 0, others_min = 1e9;
  for (int k = 0; k < 300; ++k, std::this_thread::sleep_for(std::chrono::microseconds(500))) {
    f = c.press(1, ++seq);
    ASSERT_FALSE(std::isnan(f[1])) << "the lost frame is still answered";
    if (k > 100) lost_max_late = std::max(lost_max_late, std::abs(f[1]));
    others_min = std::min({others_min, f[0], f[2]});
  }
  EXPECT_LT(lost_max_late, 1e-6);
  EXPECT_GT(others_min, 2.8);
  // Tracking back: the frame renders the wall again.
  for (int k = 0; k < 300; ++k, std::this_thread::sleep_for(std::chrono::microseconds(500))) f = c.press(-1, ++seq);
  EXPECT_NEAR(f[1], 3.0, 0.15);
  s.halt();
  EXPECT_EQ(s.server.stats().frames_lost, 300u);
  EXPECT_EQ(s.server.stats().resets, 0u);
}

TEST(HapticServerFrames, AGloveThatNamesItsHandBindsToADeviceOnAHandOfThatSide) {
  // The right glove's device is listed first: a left glove used to take it when it was free.
  DeviceLink right = glove_link(), left = glove_link();
  right.hand = 0, right.left = false;
  left.hand = 1, left.left = true;
  auto snapshots = std::make_unique<TripleBuffer<HapticSnapshot>>();
  TripleBuffer<ProxyTargets> targets;
  HapticServer server({right, left}, ServerOptions{}, *snapshots, targets);
  std::atomic<bool> stop{false};
  std::thread haptic([&] { server.run(stop); });
  // Which hands the sessions drive once they have sent a pose, as the visual loop reads it.
  auto driven_after_a_pose = [&](GloveClient& c, std::uint64_t seq) {
    (void)c.press(-1, seq);
    std::this_thread::sleep_for(std::chrono::milliseconds(20));  // ticks publish the targets
    targets.update();
    return std::array<bool, 2>{targets.front().driven[0], targets.front().driven[1]};
  };
  GloveClient left_glove(server.port());
  Message m = left_glove.say_hello(protocol::Hand::kLeft);
  ASSERT_EQ(m.type, MessageType::kWelcome);
  left_glove.session = m.welcome.session_id;
  EXPECT_EQ(driven_after_a_pose(left_glove, 1), (std::array<bool, 2>{false, true}));
  GloveClient right_glove(server.port());
  m = right_glove.say_hello(protocol::Hand::kRight);
  ASSERT_EQ(m.type, MessageType::kWelcome);
  right_glove.session = m.welcome.session_id;
  EXPECT_EQ(driven_after_a_pose(right_glove, 1), (std::array<bool, 2>{true, true}));
  stop = true;
  haptic.join();
}

TEST(HapticServerFrames, AGloveOfASideTheSceneDoesNotHaveIsRefusedWithTheReason) {
  auto snapshots = std::make_unique<TripleBuffer<HapticSnapshot>>();
  TripleBuffer<ProxyTargets> targets;
  HapticServer server({glove_link()}, ServerOptions{}, *snapshots, targets);  // a right hand's
  std::atomic<bool> stop{false};
  std::thread haptic([&] { server.run(stop); });
  GloveClient c(server.port());
  const Message m = c.say_hello(protocol::Hand::kLeft);
  ASSERT_EQ(m.type, MessageType::kError);
  EXPECT_EQ(m.error.code, protocol::ErrorCode::kUnsupportedDevice);
  EXPECT_NE(m.error.message.view().find("left hand"), std::string_view::npos) << m.error.message.view();
  EXPECT_EQ(c.say_hello(protocol::Hand::kRight).type, MessageType::kWelcome);
  EXPECT_EQ(c.say_hello(protocol::Hand::kUnspecified).type, MessageType::kWelcome) << "a glove that does not say";
  stop = true;
  haptic.join();
}

}  // namespace
}  // namespace hapticd::haptic
