#include "clients/sim/glove_model.hpp"

#include <cmath>

namespace hapticd::sim {

std::string glove_frame_name(int frames, int frame) {
  if (frame == 0) return "palm";
  const int phalanx = glove_frame_phalanx(frames, frame);
  if (phalanx < 0) return "?";
  return std::string(hand::finger_name(phalanx / 3)) + "_" + hand::phalanx_name(phalanx % 3);
}

std::array<RigidPose, kMaxGloveFrames> glove_frame_poses(const hand::SkeletonPose& skeleton, const RigidPose& palm,
                                                         int frames) {
  std::array<RigidPose, kMaxGloveFrames> poses{};
  poses[0] = palm;
  for (int id = 1; id < frames && id < kMaxGloveFrames; ++id) {
    const int i = glove_frame_phalanx(frames, id);
    if (i < 0) continue;
    poses[id].p_m = palm.p_m + palm.q * skeleton.centre[i];
    poses[id].q = palm.q * Eigen::Quaterniond(skeleton.R[i]);
  }
  return poses;
}

std::array<PhalanxJacobian, hand::kHandPhalanges> phalanx_jacobians(const hand::HandJointAngles& angles,
                                                              const hand::SkeletonPose& skeleton, bool left) {
  // Every joint of the skeleton turns the segments distal to it rigidly (hand_skeleton.cpp):
  //   abduction: the bone yaw psi, a turn of the whole finger about -z through the base joint
  //              (increasing psi swings the bone from +y toward +x);
  //   flexion k: the bone pitch decreases by it, a turn of segments k-1.. about the horizontal
  //              axis (-cos psi, sin psi, 0) through joint k-1 (so flexion moves the tip palmar, -z).
  // A turn about unit axis a through point o moves point c with a x (c - o) and turns its frame
  // with a. A left hand is the mirror image x -> -x (M = diag(-1, 1, 1)): points map by M, and
  // angular velocities, axial vectors, by det(M) M = -M; then a_L x (M c - M o) = M (a x (c - o))
  // with a_L = -M a, so the same formula holds with the mirrored axes and the mirrored points.
  const Eigen::Vector3d mirror_axial(1.0, -1.0, -1.0);  // -M, diagonal
  std::array<PhalanxJacobian, hand::kHandPhalanges> J;
  for (int f = 0; f < hand::kHandFingers; ++f) {
    const double psi = angles.finger[f][0];
    std::array<Eigen::Vector3d, 4> axis = {
        Eigen::Vector3d(0.0, 0.0, -1.0), Eigen::Vector3d(-std::cos(psi), std::sin(psi), 0.0),
        Eigen::Vector3d(-std::cos(psi), std::sin(psi), 0.0), Eigen::Vector3d(-std::cos(psi), std::sin(psi), 0.0)};
    if (left)
      for (Eigen::Vector3d& a : axis) a = a.cwiseProduct(mirror_axial);
    // Joint k's pivot: the base for abduction and flexion 1, then the 2nd and 3rd joints.
    const std::array<Eigen::Vector3d, 4> pivot = {skeleton.joints[f][0], skeleton.joints[f][0], skeleton.joints[f][1],
                                                  skeleton.joints[f][2]};
    for (int s = 0; s < 3; ++s) {
      PhalanxJacobian& j = J[3 * f + s];
      j.setZero();
      const Eigen::Vector3d& c = skeleton.centre[3 * f + s];
      for (int k = 0; k <= s + 1; ++k) {  // abduction and the flexions proximal to the segment's far end
        j.block<3, 1>(0, k) = axis[k].cross(c - pivot[k]);
        j.block<3, 1>(3, k) = axis[k];
      }
    }
  }
  return J;
}

JointVector joint_torques(const std::array<PhalanxJacobian, hand::kHandPhalanges>& jacobians,
                          const std::array<Wrench6, hand::kHandPhalanges>& wrenches_H) {
  JointVector tau = JointVector::Zero();
  for (int i = 0; i < hand::kHandPhalanges; ++i)
    tau.segment<4>(4 * (i / 3)) += jacobians[i].transpose() * wrenches_H[i];
  return tau;
}

double step_joints(const GloveParams& params, JointState& state, const JointVector& q_C_rad,
                   const JointVector& qd_C_rad_s, const JointVector& tau_ext_n_m, double dt_s) noexcept {
  double work = 0.0;
  for (int j = 0; j < hand::kHandJointDofs; ++j) {
    const JointImpedance& p = params.of_dof(j);
    const double I = p.inertia_kg_m2, k = p.stiffness_n_m_per_rad, b = p.damping_n_m_s_per_rad;
    // I (w1 - w0) = dt [k (q_C - q0 - dt w1) + b (w_C - w1) + tau], solved for w1.
    const double rhs =
        I * state.qd_rad_s[j] + dt_s * (k * (q_C_rad[j] - state.q_rad[j]) + b * qd_C_rad_s[j] + tau_ext_n_m[j]);
    state.qd_rad_s[j] = rhs / (I + dt_s * b + dt_s * dt_s * k);
    const double dq = dt_s * state.qd_rad_s[j];
    state.q_rad[j] += dq;
    work += tau_ext_n_m[j] * dq;
  }
  return work;
}

}  // namespace hapticd::sim
