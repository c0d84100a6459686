// The standard hand skeleton: its rest posture is the procedural hand's, bones
// keep their lengths in any posture, frames stay rotations, a left hand is the
// mirror image, and flexion turns a finger toward palmar about its joint.
#include <gtest/gtest.h>

#include <Eigen/Geometry>
#include <numbers>
#include <random>

#include "hand_models/hand_model.hpp"
#include "hand_models/press_scenario.hpp"
#include "hand_models/procedural_hand.hpp"
#include "hand_models/skeleton/hand_skeleton.hpp"

namespace hapticd::hand {
namespace {

TEST(HandSkeleton, RestPostureGivesTheProceduralHandsBonesAndFrames) {
  for (bool left : {false, true}) {
    ProceduralHandOptions o;
    o.target_tets = 350;
    o.left = left;
    const ProceduralHand hand = make_procedural_hand(o);
    const SkeletonPose pose = skeleton_pose(rest_joint_angles(), left);
    for (int i = 0; i < kHandPhalanges; ++i) {
      EXPECT_LT((hand.phalanges[i].p - pose.centre[i]).norm(), 1e-12) << i;
      EXPECT_LT((hand.phalanges[i].R - pose.R[i]).norm(), 1e-12) << i;
      EXPECT_EQ(hand.phalanges[i].name, std::string(finger_name(i / 3)) + "_" + phalanx_name(i % 3));
    }
    for (int f = 0; f < kHandFingers; ++f)
      for (int k = 0; k < 4; ++k) EXPECT_LT((hand.joints[f][k] - pose.joints[f][k]).norm(), 1e-12);
  }
}

TEST(HandSkeleton, AnyPostureKeepsBoneLengthsRotationsAndTheMirror) {
  std::mt19937 rng(7);
  std::uniform_real_distribution<double> angle(-2.0, 2.0);
  for (int trial = 0; trial < 50; ++trial) {
    Eigen::Matrix<double, kHandJointDofs, 1> q;
    for (int i = 0; i < kHandJointDofs; ++i) q[i] = angle(rng);
    const HandJointAngles a = HandJointAngles::from_vector(q);
    EXPECT_EQ(a.vector(), q);
    const SkeletonPose right = skeleton_pose(a), left = skeleton_pose(a, true);
    for (int f = 0; f < kHandFingers; ++f) {
      EXPECT_LT((right.joints[f][0] - finger_geometry()[f].base).norm(), 1e-15);
      for (int k = 0; k < 3; ++k) {
        const int i = 3 * f + k;
        EXPECT_NEAR((right.joints[f][k + 1] - right.joints[f][k]).norm(), finger_geometry()[f].length[k], 1e-12);
        EXPECT_LT((right.R[i].transpose() * right.R[i] - Eigen::Matrix3d::Identity()).norm(), 1e-12);
        EXPECT_NEAR(right.R[i].determinant(), 1.0, 1e-12);
        EXPECT_NEAR(left.R[i].determinant(), 1.0, 1e-12);
        EXPECT_LT((left.centre[i] - Eigen::Vector3d(-right.centre[i].x(), right.centre[i].y(), right.centre[i].z()))
                      .norm(),
                  1e-15);
        // The segment's y axis runs along the bone.
        EXPECT_LT((right.R[i].col(1) * finger_geometry()[f].length[k] - (right.joints[f][k + 1] - right.joints[f][k]))
                      .norm(),
                  1e-12);
      }
    }
  }
}

TEST(HandSkeleton, FlexingTheIndexBaseJointBy90DegreesPointsItPalmar) {
  HandJointAngles a;  // straight, unspread
  a.finger[1][1] = std::numbers::pi / 2;
  const SkeletonPose pose = skeleton_pose(a);
  EXPECT_LT((pose.R[3].col(1) - Eigen::Vector3d(0, 0, -1)).norm(), 1e-12);  // proximal bone points palmar (-z)
  EXPECT_LT((pose.R[3].col(2) - Eigen::Vector3d(0, 1, 0)).norm(), 1e-12);   // its dorsal side faces the fingertips' way
  const Eigen::Vector3d tip = pose.joints[1][3];
  const double total = finger_geometry()[1].length[0] + finger_geometry()[1].length[1] + finger_geometry()[1].length[2];
  EXPECT_NEAR(tip.z(), finger_geometry()[1].base.z() - total, 1e-12);  // the straight finger hangs below its knuckle
}

// A glove's tracked frames, carried through frame_to_handle, land on the handles
// of a hand placed anywhere: the rest relation frame -> handle is kept.
TEST(HandSkeleton, TheJointAnglesComeBackFromTheSegmentFramesAtAnyFlexion) {
  std::mt19937 rng(11);
  std::uniform_real_distribution<double> abduction(-1.0, 0.5),
      flexion(-0.3, 1.9);  // up to 109 degrees: curls past a half turn
  for (int trial = 0; trial < 200; ++trial) {
    const bool left = trial % 2 == 1;
    HandJointAngles a;
    for (int f = 0; f < kHandFingers; ++f) a.finger[f] = {abduction(rng), flexion(rng), flexion(rng), flexion(rng)};
    const HandJointAngles back = joint_angles_from_segments(skeleton_pose(a, left).R, left);
    EXPECT_LT((back.vector() - a.vector()).cwiseAbs().maxCoeff(), 1e-9) << trial;
  }
  // A fist: every flexion 90 degrees, the proximal bones pointing straight palmar; the abduction
  // still comes back (read from the side axis, not the bone).
  HandJointAngles fist = rest_joint_angles();
  for (int f = 0; f < kHandFingers; ++f)
    fist.finger[f][1] = fist.finger[f][2] = fist.finger[f][3] = std::numbers::pi / 2;
  EXPECT_LT((joint_angles_from_segments(skeleton_pose(fist).R).vector() - fist.vector()).cwiseAbs().maxCoeff(), 1e-9);
}

// A 6-frame glove's distal frames give back a posture whose flexions are shared 3 : 3 : 2 (left and
// right, abducted, from a slight extension to a whole flexion of 3 rad), and of any other posture the
// abduction and the whole flexion; past a half turn (a fist: 4.5 rad) from the last posture, 1 rad off.
TEST(HandSkeleton, TheDistalFramesGiveBackThePostureWithFlexionSharedThreeThreeTwo) {
  std::mt19937 rng(12);
  std::uniform_real_distribution<double> abduction(-1.0, 0.5), whole(-0.3, 3.0), flexion(-0.2, 1.0), off(-1.0, 1.0);
  for (int trial = 0; trial < 200; ++trial) {
    const bool left = trial % 2 == 1;
    HandJointAngles shared, any;
    for (int f = 0; f < kHandFingers; ++f) {
      const double a = abduction(rng), t = whole(rng);
      shared.finger[f] = {a, 3.0 / 8 * t, 3.0 / 8 * t, 2.0 / 8 * t};
      any.finger[f] = {a, flexion(rng), flexion(rng), flexion(rng)};
    }
    auto distal = [&](const HandJointAngles& angles) {
      const SkeletonPose pose = skeleton_pose(angles, left);
      std::array<Eigen::Matrix3d, kHandFingers> R;
      for (int f = 0; f < kHandFingers; ++f) R[f] = pose.R[3 * f + 2];
      return R;
    };
    const HandJointAngles back = joint_angles_from_distal(distal(shared), left);
    EXPECT_LT((back.vector() - shared.vector()).cwiseAbs().maxCoeff(), 1e-9) << trial;
    HandJointAngles fist = shared, last = shared;
    for (int f = 0; f < kHandFingers; ++f) {
      fist.finger[f] = {shared.finger[f][0], 3.0 / 8 * 4.5, 3.0 / 8 * 4.5, 2.0 / 8 * 4.5};
      last.finger[f] = {shared.finger[f][0], 3.0 / 8 * (4.5 + off(rng)), 3.0 / 8 * 4.5, 2.0 / 8 * 4.5};
    }
    const HandJointAngles curled = joint_angles_from_distal(distal(fist), left, &last);
    EXPECT_LT((curled.vector() - fist.vector()).cwiseAbs().maxCoeff(), 1e-9) << trial;
    const HandJointAngles other = joint_angles_from_distal(distal(any), left);
    for (int f = 0; f < kHandFingers; ++f) {
      EXPECT_NEAR(other.finger[f][0], any.finger[f][0], 1e-9) << trial;
      EXPECT_NEAR(other.finger[f][1] + other.finger[f][2] + other.finger[f][3],
                  any.finger[f][1] + any.finger[f][2] + any.finger[f][3], 1e-9)
          << trial;
    }
  }
}

TEST(HandSkeleton, TrackedFramesMapOntoTheHandlesOfAPlacedHand) {
  ProceduralHandOptions o;
  o.target_tets = 350;
  const ProceduralHand hand = make_procedural_hand(o);
  for (int m : {1, 6, 16}) {
    HandConfig config;
    config.handles = procedural_handles(hand, m);
    const HandModel model(hand.mesh, config);
    const std::vector<HandFrame> frames = procedural_handle_frames(hand, m);
    ASSERT_EQ(static_cast<int>(frames.size()), m);
    HandState s = make_rest_state(model);
    const Eigen::Quaterniond q_hand(Eigen::AngleAxisd(0.7, Eigen::Vector3d(1, 2, 3).normalized()));
    const Eigen::Vector3d p_hand(0.3, -0.2, 0.9);
    // Handle 0 placed where the hand frame at (p_hand, q_hand) puts it.
    place_hand(model, s, p_hand + q_hand * model.handles()[0].p_WH_rest, q_hand, 0);
    for (int j = 0; j < m; ++j) {
      const FrameToHandle off = frame_to_handle(frames[j].p, frames[j].R, model.handles()[j]);
      const Eigen::Vector3d p_frame = p_hand + q_hand * frames[j].p;
      const Eigen::Quaterniond q_frame = q_hand * Eigen::Quaterniond(frames[j].R);
      EXPECT_LT((p_frame + q_frame * off.p_F - s.handles[j].p_WH).norm(), 1e-12) << m << " " << j;
      EXPECT_LT((q_frame * off.q_F).angularDistance(s.handles[j].q_WH), 1e-12) << m << " " << j;
    }
  }
}

// At rest the posture's targets are the handles' rest poses, wherever the hand is.
TEST(HandSkeleton, RestPostureTargetsAreTheHandlesRestPoses) {
  for (bool left : {false, true}) {
    ProceduralHandOptions o;
    o.target_tets = 350;
    o.left = left;
    const ProceduralHand hand = make_procedural_hand(o);
    HandConfig config;
    config.handles = procedural_handles(hand, 16);
    const HandModel model(hand.mesh, config);
    HandState s = make_rest_state(model);
    const Eigen::Quaterniond q(Eigen::AngleAxisd(-1.1, Eigen::Vector3d(0.2, 0.1, 1).normalized()));
    const Eigen::Vector3d p(-0.4, 0.1, 0.7);
    place_hand(model, s, p + q * model.handles()[0].p_WH_rest, q, 0);
    const std::vector<HandleTarget> t = posture_targets(hand, model, rest_joint_angles(), p, q, left);
    for (int j = 0; j < 16; ++j) {
      EXPECT_LT((t[j].p_W - s.handles[j].p_WH).norm(), 1e-12) << j;
      EXPECT_LT(t[j].q_W.angularDistance(s.handles[j].q_WH), 1e-12) << j;
    }
  }
}

// Skin vertices belong to the handle of their part: a fingertip's skin to its
// distal phalanx (16 handles) or its finger (6), the palm's centre to the palm.
TEST(HandSkeleton, SkinVerticesBelongToTheirPartsHandle) {
  ProceduralHandOptions o;
  o.target_tets = 350;
  const ProceduralHand hand = make_procedural_hand(o);
  auto nearest_skin = [&](const Eigen::Vector3d& p) {
    size_t best = 0;
    for (size_t v = 0; v < hand.skin_vertices.size(); ++v)
      if ((hand.skin_vertices[v] - p).norm() < (hand.skin_vertices[best] - p).norm()) best = v;
    return best;
  };
  const std::vector<int> h16 = procedural_skin_handles(hand, 16), h6 = procedural_skin_handles(hand, 6),
                         h1 = procedural_skin_handles(hand, 1);
  ASSERT_EQ(h16.size(), hand.skin_vertices.size());
  for (int f = 0; f < kHandFingers; ++f) {
    const size_t tip = nearest_skin(hand.joints[f][3]);
    EXPECT_EQ(h16[tip], 3 + 3 * f) << f;
    EXPECT_EQ(h6[tip], 1 + f) << f;
    // The middle of the proximal phalanx: its own handle, or the finger's with fingertip handles.
    const size_t proximal = nearest_skin(0.5 * (hand.joints[f][0] + hand.joints[f][1]));
    EXPECT_EQ(h16[proximal], 1 + 3 * f) << f;
    EXPECT_EQ(h6[proximal], 1 + f) << f;
  }
  const size_t palm = nearest_skin(Eigen::Vector3d(0.005, 0.0, -0.02));  // palmar side of the palm's centre
  EXPECT_EQ(h16[palm], 0);
  EXPECT_EQ(h6[palm], 0);
  for (int j : h1) EXPECT_EQ(j, 0);
  std::vector<int> count(16, 0);
  for (int j : h16) ++count[j];
  for (int j = 0; j < 16; ++j) EXPECT_GT(count[j], 10) << j;  // every part has skin
}

}  // namespace
}  // namespace hapticd::hand
