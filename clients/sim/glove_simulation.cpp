#include "clients/sim/glove_simulation.hpp"

#include <algorithm>
#include <cmath>
#include <stdexcept>
#include <string>
#include <utility>

namespace hapticd::sim {
namespace {

Eigen::Vector3d to_eigen(Vec3d v) noexcept { return {v.x, v.y, v.z}; }

}  // namespace

GloveSimulation::GloveSimulation(GloveTrajectory trajectory, const GloveParams& params, int frames, bool left,
                                 double dt_s)
    : trajectory_(std::move(trajectory)), params_(params), frames_(frames), left_(left), dt_s_(dt_s) {
  if (!valid_glove_frame_count(frames))
    throw std::invalid_argument("a glove tracks 16 or 6 frames, not " + std::to_string(frames));
  joints_.q_rad = trajectory_.angles(0.0);
  palm_.p_DT_m = trajectory_.palm_position(0.0);
  skeleton_ = skeleton_pose(hand::HandJointAngles::from_vector(joints_.q_rad), left_);
}

RigidPose GloveSimulation::palm_pose() const noexcept {
  return {to_eigen(palm_.p_DT_m), trajectory_.palm_orientation()};
}

std::array<RigidPose, kMaxGloveFrames> GloveSimulation::frame_poses() const noexcept {
  return glove_frame_poses(skeleton_, palm_pose(), frames_);
}

bool GloveSimulation::in_contact() const noexcept {
  return std::any_of(contact_.begin(), contact_.begin() + frames_, [](bool c) { return c; });
}

JointVector GloveSimulation::external_joint_torques() const noexcept {
  // The wrenches arrive in D; the Jacobians are in the hand frame: rotate by the palm's R^T.
  const Eigen::Matrix3d R_T = trajectory_.palm_orientation().toRotationMatrix().transpose();
  std::array<Wrench6, hand::kHandPhalanges> wrenches_H;
  for (Wrench6& w : wrenches_H) w.setZero();
  for (int id = 1; id < frames_; ++id) {
    const int i = glove_frame_phalanx(frames_, id);
    wrenches_H[i].head<3>() = R_T * to_eigen(force(id));
    wrenches_H[i].tail<3>() = R_T * to_eigen(torque(id));
  }
  return joint_torques(phalanx_jacobians(hand::HandJointAngles::from_vector(joints_.q_rad), skeleton_, left_),
                       wrenches_H);
}

void GloveSimulation::advance() noexcept {
  ++steps_;
  const double t = time_s();
  Vec3d total;
  std::array<Vec3d, kGroups> group{};
  for (int id = 0; id < frames_; ++id) {
    total += force(id);
    group[glove_frame_group(frames_, id)] += force(id);
  }
  force_.add(norm(total));
  for (int g = 0; g < kGroups; ++g) group_force_[g].add(norm(group[g]));
  const JointVector tau = external_joint_torques();
  energy_j_ += step_joints(params_, joints_, trajectory_.angles(t), trajectory_.angle_rates(t), tau, dt_s_);
  energy_j_ += step(params_.palm, palm_, trajectory_.palm_position(t), trajectory_.palm_velocity(t), force(0), dt_s_);
  skeleton_ = skeleton_pose(hand::HandJointAngles::from_vector(joints_.q_rad), left_);
}

void GloveSimulation::set_wrench(int frame, Vec3d f_N, Vec3d t_Nm, bool in_contact) noexcept {
  if (frame < 0 || frame >= frames_) return;
  f_N_[frame] = f_N;
  t_Nm_[frame] = t_Nm;
  contact_[frame] = in_contact;
}

void GloveSimulation::record_tick() noexcept {
  ++recorded_ticks_;
  const JointVector q_C = commanded_angles();
  for (int f = 0; f < hand::kHandFingers; ++f)
    group_lag_max_rad_[f] = std::max(group_lag_max_rad_[f],
                                     (q_C.segment<4>(4 * f) - joints_.q_rad.segment<4>(4 * f)).cwiseAbs().maxCoeff());
  std::array<bool, kGroups> group_contact{};
  for (int id = 0; id < frames_; ++id) group_contact[glove_frame_group(frames_, id)] |= contact_[id];
  for (int g = 0; g < kGroups; ++g) group_contact_ticks_[g] += group_contact[g];
  if (!in_contact()) return;
  ++contact_ticks_;
  // Where the frames in contact would be at the commanded posture and palm position.
  const RigidPose palm_C{to_eigen(trajectory_.palm_position(time_s())), trajectory_.palm_orientation()};
  const auto commanded =
      glove_frame_poses(skeleton_pose(hand::HandJointAngles::from_vector(q_C), left_), palm_C, frames_);
  const auto actual = frame_poses();
  for (int id = 0; id < frames_; ++id)
    if (contact_[id]) penetration_max_m_ = std::max(penetration_max_m_, (commanded[id].p_m - actual[id].p_m).norm());
}

double GloveSimulation::force_rms_n() const noexcept {
  return force_.rms_n(steps_);
}

GloveGroupFigures GloveSimulation::group_figures(int group) const noexcept {
  GloveGroupFigures g;
  if (group < 0 || group >= kGroups) return g;
  g.force_max_n = group_force_[group].max_n;
  g.force_rms_n = group_force_[group].rms_n(steps_);
  g.contact_fraction = recorded_ticks_ == 0
                           ? 0.0
                           : static_cast<double>(group_contact_ticks_[group]) / static_cast<double>(recorded_ticks_);
  g.joint_lag_max_rad = group_lag_max_rad_[group];
  return g;
}

}  // namespace hapticd::sim
