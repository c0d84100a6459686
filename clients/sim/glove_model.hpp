#pragma once

// The simulated glove's hand: which tracked frames it sends, their poses through the standard hand
// skeleton (hand_models/skeleton/hand_skeleton.hpp), the Jacobian that turns the server's wrenches
// on those frames into joint torques, and the impedance with which each of the 20 finger joints
// follows the angle the user commands.
//
// Tracked frames (the server drives the hand's handles with them in this order; keep it exact):
//   16 frames  id 0 = palm (the hand frame itself), id 1 + i = phalanx i of SkeletonPose
//              (finger-major: thumb, index, middle, ring, little; proximal, middle, distal)
//    6 frames  id 0 = palm, id 1 + f = the distal phalanx of finger f (phalanx 3 f + 2)
// The pose of phalanx frame i in the device base frame D, with the palm at (p_palm, q_palm):
//   p_DF = p_palm + q_palm * centre_i,   q_DF = q_palm * R_i
// (centre_i, R_i: the segment's midpoint and frame in the hand frame, y along the bone, z dorsal).
//
// The joints (the user's fingers), each of the 20 DoF of HandJointAngles on its own:
//
//   I q'' = k (q_C - q) + b (q_C' - q') + tau_ext
//
// q_C: the angle the user commands (the glove trajectory); tau_ext: the server's wrenches on the
// phalanx frames mapped to joint torques, tau_ext = sum_i J_i^T [f_i; t_i], J_i the geometric
// Jacobian of frame i (linear velocity of its origin and angular velocity per joint rate). The
// muscles hold the commanded posture like a spring-damper, so a rendered contact force deflects a
// finger against k and slows its motion, as a real finger is slowed when it meets an object.
//
// Parameter choices (GloveParams defaults; the same for the five fingers, whose differences, a
// factor ~2 in inertia from little finger to middle, are within the spread of the measurements):
//   joint            I kg m^2   k N m/rad   b N m s/rad   f_n Hz   damping ratio
//   abduction        1.0e-4     1.0         0.014         15.9     0.70
//   flexion 1 (MCP)  1.0e-4     2.0         0.020         22.5     0.71
//   flexion 2 (PIP)  2.0e-5     1.0         0.006         35.6     0.67
//   flexion 3 (DIP)  5.0e-6     0.5         0.0022        50.3     0.70
//   I: the segments distal to the joint about it: an index finger of ~45 g with a radius of
//      gyration of ~4.5 cm about the MCP gives ~1e-4; the middle and distal phalanges (~20 g at
//      ~3 cm) ~2e-5 about the PIP; the distal phalanx (~8 g at ~1.2 cm, plus the flexor tendon's
//      share) ~5e-6 about the DIP.
//   k: the co-contracted finger of a relaxed hand: 0.5-3 N m/rad at the MCP, less distally. With
//      these, the tip of a straight index is held with ~155 N/m (1 / sum over its flexion joints
//      of r_j^2 / k_j), the low end of the 100-1000 N/m measured at fingertips, like the stylus's
//      arm.
//   b: a well damped finger (damping ratio ~0.7): a released finger settles in ~2 / (zeta w_n) =
//      10-30 ms without ringing. Joint damping of 0.01-0.05 N m s/rad is measured at the MCP.
//      At a 1 kHz servo rate implicit Euler damps the fast distal joints a little more (w dt up to
//      0.32): a step overshoots 3.7 % (PIP) and 2.5 % (DIP) instead of 5.8 % and 4.8 %.
//   The palm follows its trajectory with the stylus's arm model (device_model.hpp) driven by the
//   palm frame's force only (the fingers' reactions at their bases are not passed to the arm):
//   m = 0.4 kg (a hand is ~0.6 % of a 70 kg body), k_arm = 200 N/m as the stylus, b_arm = 10 N s/m
//   (damping ratio 0.56, the stylus's 0.58 for the larger mass), no device damping (a glove has no
//   linkage). The palm's orientation is the trajectory's; the palm torque is not simulated.
// No joint limits: the server's force limit (Welcome) bounds a deflection to a few tenths of a
// radian.

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <array>
#include <string>

#include "clients/sim/device_model.hpp"
#include "hand_models/skeleton/hand_skeleton.hpp"

namespace hapticd::sim {

// The 20 joint values in HandJointAngles::vector() order (abduction, flexion 1, 2, 3 per finger).
using JointVector = Eigen::Matrix<double, hand::kHandJointDofs, 1>;

inline constexpr int kGloveFramesAll = 16;  // palm + 15 phalanges
inline constexpr int kGloveFramesTips = 6;  // palm + 5 distal phalanges
inline constexpr int kMaxGloveFrames = 16;
inline constexpr int kPalmGroup = hand::kHandFingers;  // the palm after the five fingers in per-group figures

// --- Tracked frames ------------------------------------------------------------------------------

[[nodiscard]] constexpr bool valid_glove_frame_count(int frames) noexcept {
  return frames == kGloveFramesAll || frames == kGloveFramesTips;
}
// The phalanx tracked as frame id `frame` of a glove with `frames` frames, -1 for the palm (id 0)
// and for ids the glove does not have.
[[nodiscard]] constexpr int glove_frame_phalanx(int frames, int frame) noexcept {
  if (frame <= 0 || frame >= frames || !valid_glove_frame_count(frames)) return -1;
  return frames == kGloveFramesAll ? frame - 1 : 3 * (frame - 1) + 2;
}
// The finger (0 thumb .. 4 little) a frame belongs to, kPalmGroup for the palm.
[[nodiscard]] constexpr int glove_frame_group(int frames, int frame) noexcept {
  const int phalanx = glove_frame_phalanx(frames, frame);
  return phalanx < 0 ? kPalmGroup : phalanx / 3;
}
// "palm", "thumb_proximal", ..., "little_distal": the names the server maps to handles.
std::string glove_frame_name(int frames, int frame);

// --- Forward kinematics --------------------------------------------------------------------------

struct RigidPose {
  Eigen::Vector3d p_m = Eigen::Vector3d::Zero();
  Eigen::Quaterniond q = Eigen::Quaterniond::Identity();
};

// The poses in D of frames 0 .. frames-1 (the rest of the array is left as the identity), for the
// skeleton posture `skeleton` (skeleton_pose() of the joint angles) and the palm pose `palm`.
std::array<RigidPose, kMaxGloveFrames> glove_frame_poses(const hand::SkeletonPose& skeleton, const RigidPose& palm,
                                                         int frames);

// Geometric Jacobian of each phalanx frame's origin (its segment centre) with respect to its own
// finger's four joints (abduction, flexion 1, 2, 3), in the hand frame: rows 0-2 the linear
// velocity (m/s per rad/s), rows 3-5 the angular velocity (rad/s per rad/s). A phalanx does not
// move with the other fingers' joints, nor with the joints distal to it (those columns are zero).
// `skeleton` must be skeleton_pose(angles, left).
using PhalanxJacobian = Eigen::Matrix<double, 6, 4>;
std::array<PhalanxJacobian, hand::kHandPhalanges> phalanx_jacobians(const hand::HandJointAngles& angles,
                                                              const hand::SkeletonPose& skeleton, bool left);

// Joint torques (N m) of wrenches on the phalanx frames: tau = sum_i J_i^T [f_i; t_i], each wrench
// = force at the frame's origin (N) and torque (N m), both in the hand frame.
using Wrench6 = Eigen::Matrix<double, 6, 1>;
JointVector joint_torques(const std::array<PhalanxJacobian, hand::kHandPhalanges>& jacobians,
                          const std::array<Wrench6, hand::kHandPhalanges>& wrenches_H);

// --- Joint impedance -----------------------------------------------------------------------------

struct JointImpedance {
  double inertia_kg_m2 = 1e-4;
  double stiffness_n_m_per_rad = 1.0;
  double damping_n_m_s_per_rad = 0.01;
};

struct GloveParams {
  // Per joint of a finger: abduction, flexion 1 (MCP; the thumb's CMC), flexion 2 (PIP; thumb MCP),
  // flexion 3 (DIP; thumb IP). The same for every finger.
  std::array<JointImpedance, 4> joint = {
      {{1.0e-4, 1.0, 0.014}, {1.0e-4, 2.0, 0.020}, {2.0e-5, 1.0, 0.006}, {5.0e-6, 0.5, 0.0022}}};
  DeviceParams palm{0.4, 200.0, 10.0, 0.0};

  [[nodiscard]] const JointImpedance& of_dof(int dof) const noexcept { return joint[static_cast<unsigned>(dof % 4)]; }
};

struct JointState {
  JointVector q_rad = JointVector::Zero();
  JointVector qd_rad_s = JointVector::Zero();
};

// One step of dt for the 20 joints: implicit Euler in the spring and damper (linear, solved exactly
// per joint, stable for any stiffness and step, as step() in device_model.hpp), explicit in the held
// external torque. q_C / qd_C: the commanded angles and rates at the end of the step. Returns the
// work of tau_ext over the step, tau_ext . (q_new - q_old) in J.
double step_joints(const GloveParams& params, JointState& state, const JointVector& q_C_rad,
                   const JointVector& qd_C_rad_s, const JointVector& tau_ext_n_m, double dt_s) noexcept;

}  // namespace hapticd::sim
