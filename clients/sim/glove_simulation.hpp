#pragma once

// The simulated glove over a run: the trajectory, the hand's joints and palm (glove_model.hpp), the
// wrenches last received per frame, and the figures a report needs, for the hand as a whole (as the
// stylus's DeviceSimulation) and per finger. Network-free, so the physics and the bookkeeping are
// tested without a server; the servo loop drives it tick by tick (glove_servo.hpp).

#include <array>
#include <cstdint>

#include "clients/sim/force_figures.hpp"
#include "clients/sim/glove_model.hpp"
#include "clients/sim/glove_trajectory.hpp"

namespace hapticd::sim {

// Figures of one finger (the sum of its tracked frames' forces) or of the palm, over a run.
struct GloveGroupFigures {
  double force_max_n = 0.0;       // largest |sum of the group's frame forces| over steps
  double force_rms_n = 0.0;       // RMS of it over steps
  double contact_fraction = 0.0;  // recorded ticks in which any of its frames reported InContact
  // Largest |q_C - q| over the finger's four joints and the recorded ticks: how far the finger
  // trailed (or was pushed from) the commanded posture, rad. 0 for the palm.
  double joint_lag_max_rad = 0.0;
};

class GloveSimulation {
 public:
  // frames: 16 or 6 (glove_model.hpp); throws std::invalid_argument otherwise. The joints and the
  // palm start at rest at the trajectory's command at t = 0.
  GloveSimulation(GloveTrajectory trajectory, const GloveParams& params, int frames, bool left, double dt_s);

  // One tick: t += dt; the held wrenches become joint torques through the Jacobians of the posture
  // at the start of the step, the joints and the palm take one implicit step toward the trajectory;
  // accumulates the wrenches' work and the force figures.
  void advance() noexcept;
  // The newest wrench on frame `frame` (force at its origin in N and torque in N m, both in D) and
  // whether it reported contact; held until the next. Unknown frame ids are ignored.
  void set_wrench(int frame, Vec3d f_N, Vec3d t_Nm, bool in_contact) noexcept;
  // The share of the held wrenches the glove renders from the next advance() on (client::ReplyWatchdog).
  void set_output_scale(double scale) noexcept { output_scale_ = scale; }
  // End of a tick: contact, penetration and joint-lag bookkeeping for the current state.
  void record_tick() noexcept;

  [[nodiscard]] double time_s() const noexcept { return static_cast<double>(steps_) * dt_s_; }
  [[nodiscard]] int frames() const noexcept { return frames_; }
  [[nodiscard]] bool left() const noexcept { return left_; }
  [[nodiscard]] const GloveTrajectory& trajectory() const noexcept { return trajectory_; }
  [[nodiscard]] const GloveParams& params() const noexcept { return params_; }
  [[nodiscard]] const JointState& joints() const noexcept { return joints_; }
  [[nodiscard]] const DeviceState& palm() const noexcept { return palm_; }
  [[nodiscard]] const hand::SkeletonPose& skeleton() const noexcept { return skeleton_; }
  [[nodiscard]] JointVector commanded_angles() const noexcept { return trajectory_.angles(time_s()); }
  [[nodiscard]] RigidPose palm_pose() const noexcept;
  // Poses of frames 0 .. frames()-1 in D, for the current state.
  [[nodiscard]] std::array<RigidPose, kMaxGloveFrames> frame_poses() const noexcept;
  // The wrench rendered on a frame: the held one times the output scale.
  [[nodiscard]] Vec3d force(int frame) const noexcept { return output_scale_ * f_N_[static_cast<unsigned>(frame)]; }
  [[nodiscard]] Vec3d torque(int frame) const noexcept { return output_scale_ * t_Nm_[static_cast<unsigned>(frame)]; }
  [[nodiscard]] bool in_contact() const noexcept;
  // The joint torques the held wrenches apply at the current posture, N m.
  [[nodiscard]] JointVector external_joint_torques() const noexcept;

  // Whole hand, as DeviceSimulation: work of the wrenches on the hand (J, sum over steps of
  // tau_ext . dq + f_palm . dp_palm, the frames' f . dp + t . dtheta to first order in the step;
  // > 0: the rendering put energy in), |sum of every frame's force| max and RMS over steps, and the
  // largest distance between a frame in contact and where the commanded posture would put it.
  [[nodiscard]] double passivity_energy_j() const noexcept { return energy_j_; }
  [[nodiscard]] double force_max_n() const noexcept { return force_.max_n; }
  [[nodiscard]] double force_rms_n() const noexcept;
  [[nodiscard]] double penetration_max_m() const noexcept { return penetration_max_m_; }
  // group: a finger 0..4, or kPalmGroup.
  [[nodiscard]] GloveGroupFigures group_figures(int group) const noexcept;
  [[nodiscard]] std::uint64_t steps() const noexcept { return steps_; }
  [[nodiscard]] std::uint64_t recorded_ticks() const noexcept { return recorded_ticks_; }
  [[nodiscard]] std::uint64_t contact_ticks() const noexcept { return contact_ticks_; }

 private:
  static constexpr int kGroups = hand::kHandFingers + 1;

  GloveTrajectory trajectory_;
  GloveParams params_;
  int frames_;
  bool left_;
  double dt_s_;
  JointState joints_;
  DeviceState palm_;
  hand::SkeletonPose skeleton_;  // skeleton_pose(joints_.q_rad, left_)
  std::array<Vec3d, kMaxGloveFrames> f_N_{};
  std::array<Vec3d, kMaxGloveFrames> t_Nm_{};
  std::array<bool, kMaxGloveFrames> contact_{};
  double output_scale_ = 1.0;
  std::uint64_t steps_ = 0;
  std::uint64_t recorded_ticks_ = 0;
  std::uint64_t contact_ticks_ = 0;
  double energy_j_ = 0.0;
  ForceFigures force_;
  double penetration_max_m_ = 0.0;
  std::array<ForceFigures, kGroups> group_force_{};
  std::array<std::uint64_t, kGroups> group_contact_ticks_{};
  std::array<double, kGroups> group_lag_max_rad_{};
};

}  // namespace hapticd::sim
