// A glove's frames on the wire: a pose sample that leaves a frame out (its
// tracking failed: the client library drops a non-finite frame) holds that
// frame and ramps its force to zero while the other frames keep rendering;
// a first sample must carry every frame.
#include <gtest/gtest.h>

#include <array>
#include <chrono>
#include <cmath>
#include <thread>

#include "haptic_server_test_util.hpp"

namespace hapticd {
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
    protocol::Hello h;
    h.client_name.assign("glove");
    h.device_kind = protocol::DeviceKind::kGlove;
    for (int j = 0; j < kFrames; ++j) {
      protocol::TrackedFrame f;
      f.id = static_cast<std::uint16_t>(10 + j);
      f.name.assign("frame");
      h.frames.push_back(f);
    }
    send(h);
    const Message m = receive(1000);
    ASSERT_EQ(m.type, MessageType::kWelcome);
    session = m.welcome.session_id;
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

}  // namespace
}  // namespace hapticd
