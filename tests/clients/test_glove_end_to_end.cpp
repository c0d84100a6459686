#include <gtest/gtest.h>

#include <chrono>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "clients/sim/child_process.hpp"
#include "clients/sim/glove_model.hpp"
#include "device_cli.hpp"
#include "fake_server.hpp"

// haptic-device --device glove as built, against the in-test fake server on loopback: the Hello,
// the per-frame poses, and the server's per-frame forces showing up in the per-finger report.

namespace hapticd::sim {
namespace {

using namespace std::chrono_literals;

std::string temp_path(const std::string& name) { return testing_util::temp_path("haptic_glove_", name); }

constexpr float kIndexForceZ = 0.5f;  // N on every index frame, reported in contact
constexpr float kPalmForceX = 1.0f;   // N on the palm, not in contact

// The fake server's rendering: every frame of the index finger pushed dorsally (+z, the rest
// posture's dorsal direction) and in contact, the palm pushed along +x, the rest free.
void serve_glove(client::test::FakeServer& server, const protocol::Message& m) {
  if (m.type == protocol::MessageType::kHello) {
    server.reply(client::test::welcome_for(m.hello, 77));
  } else if (m.type == protocol::MessageType::kPoseSample) {
    const protocol::PoseSample& pose = m.pose_sample;
    const int frames = static_cast<int>(pose.poses.size());
    protocol::ForceSample f;
    f.session_id = pose.session_id;
    f.sequence = pose.sequence;
    f.client_timestamp_ns = pose.client_timestamp_ns;
    f.server_receive_ns = 1;
    f.server_send_ns = 2;
    for (const protocol::FramePose& p : pose.poses) {
      protocol::FrameWrench w;
      w.frame = p.frame;
      const int group = glove_frame_group(frames, p.frame);
      if (group == 1) {
        w.wrench.force_n = {0.0f, 0.0f, kIndexForceZ};
        w.flags = protocol::ForceFlags::kInContact;
      } else if (group == kPalmGroup) {
        w.wrench.force_n = {kPalmForceX, 0.0f, 0.0f};
      }
      f.flags |= w.flags;
      f.wrenches.push_back(w);
    }
    server.reply(f);
  } else if (m.type == protocol::MessageType::kStatsRequest) {
    protocol::Stats s;
    s.session_id = m.stats_request.session_id;
    s.sessions_active = 1;
    server.reply(s);
  }
}

void run_glove(int frames, bool left) {
  SCOPED_TRACE(std::to_string(frames) + " frames, " + (left ? "left" : "right") + " hand");
  client::test::FakeServer server(serve_glove);
  const std::string report = temp_path(std::to_string(frames) + "_report.json");
  ChildProcess device(HAPTICD_DEVICE_BIN,
                      {"--server", "127.0.0.1:" + std::to_string(server.port()), "--device", "glove", "--frames",
                       std::to_string(frames), "--hand", left ? "left" : "right", "--trajectory", "grasp", "--origin",
                       "0.1,0.2,0.3", "--duration", "1", "--report", report});
  ASSERT_EQ(device.wait(30s), 0) << device.output();
  const std::vector<protocol::Message> received = server.received();

  // The Hello: a glove with every frame, ids 0 .. frames-1, named by the skeleton.
  ASSERT_FALSE(received.empty());
  ASSERT_EQ(received.front().type, protocol::MessageType::kHello);
  const protocol::Hello& hello = received.front().hello;
  EXPECT_EQ(hello.device_kind, protocol::DeviceKind::kGlove);
  ASSERT_EQ(hello.frames.size(), static_cast<std::size_t>(frames));
  for (int id = 0; id < frames; ++id) {
    EXPECT_EQ(hello.frames[id].id, id);
    EXPECT_EQ(hello.frames[id].dof, 6);
    EXPECT_EQ(hello.frames[id].name.view(), glove_frame_name(frames, id));
  }

  // Every sample carries every frame in id order; the first is the rest posture (grasp at t = 0)
  // with the palm at --origin.
  std::size_t samples = 0;
  const auto rest = glove_frame_poses(hand::skeleton_pose(hand::rest_joint_angles(), left),
                                      {Eigen::Vector3d(0.1, 0.2, 0.3), Eigen::Quaterniond::Identity()}, frames);
  for (const protocol::Message& m : received) {
    if (m.type != protocol::MessageType::kPoseSample) continue;
    const protocol::PoseSample& pose = m.pose_sample;
    ASSERT_EQ(pose.poses.size(), static_cast<std::size_t>(frames)) << "sample " << pose.sequence;
    for (int id = 0; id < frames; ++id) ASSERT_EQ(pose.poses[id].frame, id) << "sample " << pose.sequence;
    if (samples++ == 0)
      for (int id = 0; id < frames; ++id) {
        const protocol::FramePose& p = pose.poses[id];
        EXPECT_EQ(p.position_m.x, static_cast<float>(rest[id].p_m.x())) << id;
        EXPECT_EQ(p.position_m.y, static_cast<float>(rest[id].p_m.y())) << id;
        EXPECT_EQ(p.position_m.z, static_cast<float>(rest[id].p_m.z())) << id;
        // Decode normalizes quaternions: compare as rotations.
        const Eigen::Quaterniond q(p.orientation.w, p.orientation.x, p.orientation.y, p.orientation.z);
        EXPECT_GT(std::abs(q.dot(rest[id].q)), 1.0 - 1e-6) << id;
      }
  }

  std::ifstream in(report);
  ASSERT_TRUE(in) << "no report at " << report;
  const nlohmann::json r = nlohmann::json::parse(in);
  std::filesystem::remove(report);
  EXPECT_EQ(r["device"], "glove");
  EXPECT_EQ(r["frames"], frames);
  EXPECT_EQ(r["hand"], left ? "left" : "right");
  EXPECT_EQ(r["trajectory"], "grasp");
  const auto sent = r["samples_sent"].get<std::uint64_t>();
  EXPECT_EQ(sent, samples);
  EXPECT_EQ(r["ticks"].get<std::uint64_t>(), 1000u);
  EXPECT_EQ(sent + r["missed_ticks"].get<std::uint64_t>(), 1000u);
  // Most ticks are sent even on a loaded or instrumented build (an ASan run sent 862); the rate a
  // quiet machine keeps is the latency bench's figure.
  EXPECT_GE(sent, 500u);
  EXPECT_EQ(r["lost"].get<std::uint64_t>(), 0u) << "loopback loses nothing";
  for (const char* key : {"late_fraction", "loss_fraction", "passivity_energy_j", "penetration_mm_max",
                          "rate_hz_achieved", "contact_fraction"})
    EXPECT_TRUE(r[key].is_number() && std::isfinite(r[key].get<double>())) << key;
  EXPECT_EQ(r["server_stats"]["sessions_active"], 1);

  // The index's frames' forces sum to 3 x 0.5 N (16 frames) or the distal's 0.5 N (6 frames),
  // from the first reply on; in contact whenever a reply had arrived.
  const double index_force = (frames == 16 ? 3.0 : 1.0) * kIndexForceZ;
  const nlohmann::json& index = r["fingers"]["index"];
  EXPECT_DOUBLE_EQ(index["force_n"]["max"].get<double>(), index_force);
  EXPECT_LE(index["force_n"]["rms"].get<double>(), index_force);
  EXPECT_GT(index["force_n"]["rms"].get<double>(), 0.95 * index_force);
  EXPECT_GT(index["contact_fraction"].get<double>(), 0.9);
  EXPECT_LE(index["contact_fraction"].get<double>(), 1.0);
  EXPECT_DOUBLE_EQ(r["contact_fraction"].get<double>(), index["contact_fraction"].get<double>())
      << "the hand is in contact when its index is";
  // Pushed dorsally, the index trails its commanded flexion by about the static deflection: with
  // 16 frames ~2.1 degrees at the MCP (0.5 N x (2 + 5.25 + 7.5) cm / 2 N m/rad), with 6 ~1.1;
  // the free fingers follow the grasp within hundredths of a degree (I q_C'' / k).
  const double index_lag = index["joint_lag_deg_max"].get<double>();
  EXPECT_GT(index_lag, frames == 16 ? 1.8 : 0.9);
  EXPECT_LT(index_lag, frames == 16 ? 3.0 : 1.6);
  for (const char* name : {"thumb", "middle", "ring", "little"}) {
    const nlohmann::json& finger = r["fingers"][name];
    EXPECT_EQ(finger["force_n"]["max"].get<double>(), 0.0) << name;
    EXPECT_EQ(finger["force_n"]["rms"].get<double>(), 0.0) << name;
    EXPECT_EQ(finger["contact_fraction"].get<double>(), 0.0) << name;
    EXPECT_LT(finger["joint_lag_deg_max"].get<double>(), 0.1) << name;
  }
  EXPECT_DOUBLE_EQ(r["palm"]["force_n"]["max"].get<double>(), kPalmForceX);
  EXPECT_EQ(r["palm"]["contact_fraction"].get<double>(), 0.0);
  EXPECT_FALSE(r["palm"].contains("joint_lag_deg_max"));
  // The whole hand: |(1, 0, index_force)|; the index frames held a few mm from their commanded
  // places while in contact.
  EXPECT_DOUBLE_EQ(r["force_n"]["max"].get<double>(), std::hypot(kPalmForceX, index_force));
  EXPECT_GT(r["penetration_mm_max"].get<double>(), 0.5);
  EXPECT_LT(r["penetration_mm_max"].get<double>(), 10.0);
  EXPECT_EQ(r["glove_model"]["joints"]["flexion1"]["stiffness_n_m_per_rad"], 2.0);
  EXPECT_EQ(r["glove_model"]["palm"]["mass_kg"], 0.4);
  EXPECT_NE(device.output().find("index  force N: max"), std::string::npos) << device.output();
}

TEST(HapticDeviceGloveEndToEnd, SixteenFramesRightHand) { run_glove(16, false); }

TEST(HapticDeviceGloveEndToEnd, SixFramesLeftHand) { run_glove(6, true); }

TEST(HapticDeviceGloveEndToEnd, BadGloveFlagsAreRefusedWithTheReason) {
  const std::string bad_csv = temp_path("bad_glove.csv");
  {
    std::ofstream out(bad_csv);
    out << "0";
    for (int i = 0; i < 20; ++i) out << ",0";
    out << "\n1";
    for (int i = 0; i < 20; ++i) out << (i == 5 ? ",ten" : ",10");
    out << "\n";
  }
  const std::string server = "127.0.0.1:7000";
  const std::vector<testing_util::RefusedCase> cases = {
      {{"--server", server, "--device", "glove", "--frames", "5"}, "--frames"},
      {{"--server", server, "--device", "glove", "--hand", "both"}, "--hand"},
      {{"--server", server, "--device", "stylus", "--frames", "6"}, "--frames: is for --device glove"},
      {{"--server", server, "--hand", "left"}, "--hand: is for --device glove"},
      {{"--server", server, "--device", "glove", "--frame-name", "x"}, "--frame-name: is for --device stylus"},
      {{"--server", server, "--device", "glove", "--trajectory", "press"},
       "cannot read glove trajectory file 'press' (expected grasp, pinch, release, fist, spread, tap"},
      {{"--server", server, "--device", "glove", "--trajectory", bad_csv},
       bad_csv + ":2:7: index_flexion1_deg: 'ten' is not a number"},
      {{"--server", server, "--device", "gauntlet"}, "--device"},
  };
  testing_util::expect_refused(HAPTICD_DEVICE_BIN, cases);
  std::filesystem::remove(bad_csv);
}

}  // namespace
}  // namespace hapticd::sim
