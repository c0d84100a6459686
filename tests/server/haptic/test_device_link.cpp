// Device links: a glove's tracked frames (the standard skeleton's palm and
// phalanx frames) land on the handles built on them, and the reply's torque is
// taken about the frame's origin.
#include <gtest/gtest.h>

#include <Eigen/Geometry>

#include "allocation_counter.hpp"
#include "hand_models/fem_hand.hpp"
#include "hand_models/skeleton/hand_skeleton.hpp"
#include "hand_models/spring/spring_law.hpp"
#include "server/haptic/device_link.hpp"
#include "server/world/world.hpp"

namespace hapticd::haptic {
namespace {

world::SceneDesc glove_scene(world::HandleSet handles, const world::Pose& hand_pose) {
  world::SceneDesc scene;
  world::HandDesc hand;
  hand.name = "right";
  hand.resolution_tets = 350;
  hand.handles = handles;
  hand.pose = hand_pose;
  scene.hands.push_back(hand);
  world::DeviceDesc glove;
  glove.name = "glove";
  glove.kind = world::DeviceKind::glove;
  glove.hand = "right";
  // Device space is the glove's tracker space: the hand frame at the device origin maps onto the scene's hand.
  glove.workspace.offset_W = hand_pose.p_W;
  glove.workspace.R_WD = hand_pose.q_W;
  scene.devices.push_back(glove);
  return scene;
}

TEST(DeviceLink, GloveFramesAtRestLandOnTheHandles) {
  world::Pose pose;
  pose.p_W = {0.1, -0.2, 0.8};
  pose.q_W = Eigen::Quaterniond(Eigen::AngleAxisd(0.6, Eigen::Vector3d(0.3, 1, 0.2).normalized()));
  for (world::HandleSet set : {world::HandleSet::fingertips, world::HandleSet::phalanges}) {
    const world::SceneDesc scene = glove_scene(set, pose);
    world::WorldOptions options;
    options.hand_gravity = false;
    const world::World world(scene, options);
    const DeviceLink link = make_device_link(world, scene.devices[0], 1000);
    const hand::HandState& s = hand::as_fem(world.hand(0)).state;
    ASSERT_EQ(link.handles, static_cast<int>(s.handles.size()));
    // The glove at rest: palm = hand frame at the device origin, phalanges from the skeleton.
    const hand::SkeletonPose skeleton = hand::skeleton_pose(hand::rest_joint_angles());
    for (int j = 0; j < link.handles; ++j) {
      Eigen::Vector3d p_D = Eigen::Vector3d::Zero();
      Eigen::Quaterniond q_D = Eigen::Quaterniond::Identity();
      if (j > 0) {
        const int phalanx = link.handles == 6 ? 3 * (j - 1) + 2 : j - 1;
        p_D = skeleton.centre[phalanx];
        q_D = Eigen::Quaterniond(skeleton.R[phalanx]);
      }
      const HapticPose h = link.map.to_world(j, p_D, q_D);
      EXPECT_LT((h.p_W - s.handles[j].p_WH).norm(), 1e-9) << j;
      EXPECT_LT(h.q_W.angularDistance(s.handles[j].q_WH), 1e-9) << j;
    }
  }
}

TEST(DeviceLink, ReplyTorqueIsTakenAboutTheTrackedFrame) {
  DeviceMap map;
  map.handle_p_F[0] = {0.02, 0.0, 0.0};  // the handle 2 cm along the frame's x
  const double mass[1] = {0.05};
  const Eigen::Matrix3d inertia[1] = {1e-5 * Eigen::Matrix3d::Identity()};
  CouplingGains gains;
  gains.k_nm_rad = 0;  // no rotational spring: only the force's moment
  gains.b_nms_rad = 0;
  DeviceLimits limits{100.0, 100.0, 1e9};
  ProxyHand proxy;
  proxy.configure(1, mass, inertia, gains, limits, map);
  proxy.set_device_pose(0, Eigen::Vector3d::Zero(), Eigen::Quaterniond::Identity());
  proxy.commit_sample(0.0, 0.05);
  // Move the device 1 mm along y; the proxy stays (no integration): f_W = k * 1 mm on the proxy.
  proxy.set_device_pose(0, Eigen::Vector3d(0, 0.001, 0), Eigen::Quaterniond::Identity());
  proxy.commit_sample(0.001, 0.05);
  const ReplyWrench r = proxy.reply(0, 1.0, 0.001);
  const double f = gains.k_n_m * 0.001;
  const double f_damp = gains.b_ns_m * 0.6 * 1.0;  // the filtered device velocity (first sample of 1 m/s)
  EXPECT_NEAR(r.f_D.y(), -(f + f_damp), 1e-9);
  // The device feels -f at the handle, 2 cm along x from the frame: torque 0.02 x (-f y) = -0.02 f z.
  EXPECT_NEAR(r.tau_D.z(), -0.02 * (f + f_damp), 1e-9);
  EXPECT_NEAR(r.tau_D.x(), 0.0, 1e-12);
}

TEST(DeviceLink, FramesBelongToTheirFingers) {
  EXPECT_EQ(finger_of_frame(16, 0), -1);
  EXPECT_EQ(finger_of_frame(16, 1), 0);
  EXPECT_EQ(finger_of_frame(16, 3), 0);
  EXPECT_EQ(finger_of_frame(16, 4), 1);
  EXPECT_EQ(finger_of_frame(16, 15), 4);
  EXPECT_EQ(finger_of_frame(6, 2), 1);
  EXPECT_EQ(distal_frame(16, 1), 6);
  EXPECT_EQ(distal_frame(6, 4), 5);
}

// seed 002 section 4.5 with a4 = 1: a finger's frame forces summed and projected
// on its actuator line, pull only, on the distal frame.
TEST(DeviceLink, FingerLinesProjectEachFingersForcesOntoItsActuator) {
  DeviceLink link;
  link.handles = 6;
  link.output = ForceOutput::finger_lines;
  link.limits.max_force_n = 5.0;
  link.actuator_line_F = Eigen::Vector3d(0, -0.6, 0.8);
  link.map.R_WD = Eigen::Quaterniond(Eigen::AngleAxisd(0.5, Eigen::Vector3d::UnitZ()));  // device turned about z
  HapticPose device_W[6];
  ReplyWrench w[6];
  for (int j = 0; j < 6; ++j) {
    device_W[j].p_W.setZero();
    device_W[j].q_W = Eigen::Quaterniond(Eigen::AngleAxisd(0.3 * j, Eigen::Vector3d::UnitX()));
  }
  w[0].f_D = {1, 2, 3};   // the palm: no actuator
  w[1].f_D = {0, 0, 2};   // thumb pushed dorsally
  w[2].f_D = {0, 0, -2};  // index pushed palmar: a cable cannot push
  w[1].tau_D = {1, 1, 1};
  const Eigen::Matrix3d R_DW = link.map.R_WD.toRotationMatrix().transpose();
  auto line = [&](int j) -> Eigen::Vector3d { return R_DW * (device_W[j].q_W * link.actuator_line_F); };
  w[3].f_D = 50 * line(3);  // middle: along its line, beyond the limit
  const double thumb = std::max(0.0, Eigen::Vector3d(0, 0, 2).dot(line(1)));
  const double index = std::max(0.0, Eigen::Vector3d(0, 0, -2).dot(line(2)));
  ReplyWrench out[6];
  std::copy(w, w + 6, out);
  project_onto_finger_lines(link, device_W, out);
  EXPECT_EQ(out[0].f_D, Eigen::Vector3d::Zero());
  EXPECT_LT((out[1].f_D - thumb * line(1)).norm(), 1e-12);
  EXPECT_GT(thumb, 0.5);
  EXPECT_EQ(out[1].tau_D, Eigen::Vector3d::Zero());
  EXPECT_EQ(index, 0.0);  // the index's force is against its line: the cable's pull-only case is the one checked
  EXPECT_EQ(out[2].f_D, Eigen::Vector3d::Zero());
  EXPECT_NEAR(out[3].f_D.norm(), 5.0, 1e-12);  // clamped
  EXPECT_TRUE(out[3].clamped);
  EXPECT_EQ(out[4].f_D, Eigen::Vector3d::Zero());
}

// Seed 002 section 4.5 with its joint torques (a 16-frame glove): the spring hand's frames get each
// flexion joint's torque reversed on its child segment and back on its parent, the abduction's on the
// proximal one, and the fingertip spring's force at the fingertip on the distal one (SpringHand's
// reaction). From those wrenches the output rebuilds the torques: against the paper's formula
// (spring_law's glove_feedback) on the torques they were made of.
TEST(DeviceLink, FingerLinesWithJointTorqueCoefficientsRenderSeed002sGloveForce) {
  DeviceLink link;
  link.handles = 16;
  link.output = ForceOutput::finger_lines;
  link.limits.max_force_n = 100.0;
  link.map.scale = 2.0;
  link.feedback_a = {0.7, 1.3, 0.5, 0.9};
  hand::HandJointAngles posture = hand::rest_joint_angles();
  for (int f = 0; f < hand::kHandFingers; ++f)
    for (int k = 1; k < 4; ++k) posture.finger[f][k] = 0.15 + 0.1 * k + 0.03 * f;
  const hand::SkeletonPose pose = hand::skeleton_pose(posture);
  const Eigen::Vector3d palm(0.1, -0.2, 0.9);
  const Eigen::Quaterniond q_palm(Eigen::AngleAxisd(0.4, Eigen::Vector3d(1, 2, 3).normalized()));
  HapticPose device_W[16];
  ReplyWrench w[16];
  device_W[0].p_W = palm;
  device_W[0].q_W = q_palm;
  for (int i = 0; i < hand::kHandPhalanges; ++i) {
    device_W[1 + i].p_W = palm + q_palm * pose.centre[i];
    device_W[1 + i].q_W = q_palm * Eigen::Quaterniond(pose.R[i]);
  }
  double expected[5];
  for (int f = 0; f < hand::kHandFingers; ++f) {
    // Flexion torques on the spring hand (the tracked frames get them reversed), an abduction torque
    // and the fingertip spring's force.
    const int d = 3 + 3 * f;
    const double tau[3] = {-0.04 - 0.01 * f, -0.03, 0.02};  // the last against the others
    const Eigen::Vector3d f_tip = device_W[d].q_W * Eigen::Vector3d(0.1, -0.3, -0.8 - 0.1 * f);  // palmar
    // Each flexion joint's axis: across its bone in the palm's plane (hand_skeleton.hpp: the bone's
    // pitch turns about it; the thumb's segment frames are rolled about the bone, not its joints).
    auto x = [&](int k) -> Eigen::Vector3d {
      const Eigen::Vector3d bone = device_W[1 + 3 * f + k].q_W * Eigen::Vector3d::UnitY();
      return bone.cross(q_palm * Eigen::Vector3d::UnitZ()).normalized();
    };
    auto joint = [&](int k) -> Eigen::Vector3d { return palm + q_palm * pose.joints[f][k]; };
    const Eigen::Vector3d tip = palm + q_palm * pose.joints[f][3];
    Eigen::Vector3d T[3] = {Eigen::Vector3d::Zero(), Eigen::Vector3d::Zero(), Eigen::Vector3d::Zero()};
    for (int k = 0; k < 3; ++k) {
      T[k] -= tau[k] * x(k);
      if (k > 0) T[k - 1] += tau[k] * x(k);
    }
    T[0] += 0.05 * (q_palm * Eigen::Vector3d::UnitZ());  // the abduction's, about the palm's normal
    T[2] += (tip - device_W[d].p_W).cross(-f_tip);
    for (int k = 0; k < 3; ++k) w[1 + 3 * f + k].tau_D = T[k];
    w[d].f_D = link.map.scale * -f_tip;
    const Eigen::Vector3d n = device_W[d].q_W * link.actuator_line_F;
    std::array<Eigen::Vector3d, 3> f_tau;
    for (int k = 0; k < 3; ++k) f_tau[k] = hand::spring::flexion_torque_force(x(k), joint(k), tip, tau[k]);
    expected[f] = link.map.scale * hand::spring::glove_feedback(link.feedback_a, f_tau, f_tip, n);
    EXPECT_GT(expected[f], 0.1) << "a pull, for the check to see it";
  }
  w[0].f_D = {1, 2, 3};  // the palm's: no actuator
  EXPECT_EQ(testing_util::allocations_in([&] { project_onto_finger_lines(link, device_W, w); }), 0)
      << "the haptic tick calls it";
  for (int f = 0; f < hand::kHandFingers; ++f) {
    const int d = 3 + 3 * f;
    const Eigen::Vector3d n = device_W[d].q_W * link.actuator_line_F;
    EXPECT_LT((w[d].f_D - expected[f] * n).norm(), 1e-9) << "finger " << f << ": " << w[d].f_D.dot(n) << " N, the "
                                                         << "formula " << expected[f] << " N";
    EXPECT_EQ(w[d - 1].f_D, Eigen::Vector3d::Zero());
  }
}

}  // namespace
}  // namespace hapticd::haptic
