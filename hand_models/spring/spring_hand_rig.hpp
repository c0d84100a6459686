#pragma once
// The articulated spring hand of seed 002 (Borst and Indugula) as ODE bodies and joints: a palm and
// 15 phalanges on the shared skeleton (hand_skeleton.hpp), 20 finger DoF as hinge joints, pulled
// toward the tracked hand by the spring-dampers of spring_law.hpp:
//  - a torsional spring per finger DoF (section 4.2), applied about its hinge;
//  - a linear and a torsional spring on the palm (4.3);
//  - a linear spring per fingertip (4.4);
// and the per-finger glove force of section 4.5.
//
// Bodies (section 4.6.1, 4.6.2): the palm a box (9 x 7.4 x 2.5 cm) with extra mass, there being no
// arm to carry it; each phalanx a capsule (a line-swept sphere) from joint to joint, its radius
// the mean of the skeleton's flesh radii at its ends, its mass from its volume; a 2-DoF base joint
// (abduction, then flexion) is two hinges joined by a small sphere, the paper's point mass. Hinges
// join bodies so their geoms do not collide with each other; the geoms carry kSpringHandCategory
// and do not collide with that category (a hand's fingers pass through each other, as the FEM
// hand's do; self-collision is issue 19's). Restitution zero on hand geoms is the world's near
// callback's to apply (4.6.2).
//
// The springs are forces added to the bodies, which ODE integrates explicitly: a step longer than
// max_stable_step() makes the hand oscillate and diverge. The owner steps the ODE world in steps no
// longer than that, calling apply_springs() before each.
//
// The rig owns its bodies, joints and geoms in the ODE world and space it is given (which must
// outlive it) and touches nothing else. Not thread-safe; ODE must be initialized on the calling
// thread (ensure_ode_for_this_thread).
#include <ode/ode.h>

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <array>

#include "hand_models/skeleton/hand_skeleton.hpp"
#include "hand_models/spring/spring_law.hpp"

namespace hapticd::hand {
// Calls dInitODE2 once per process and dAllocateODEDataForThread for the calling thread (the world's
// rigid bodies and the rigid hands share it). It also takes ODE's handlers: its messages (warnings
// such as "LCP internal error, s <= 0", which its LCP solver recovers from; a spring hand pressing
// the bunny raised a few a second) are counted, not printed (ode_messages); its fatal errors and
// debug traps, which would abort the process (ODE's defaults), throw std::runtime_error naming
// them, for the visual step to catch as any failed step.
void ensure_ode_for_this_thread();
// ODE's messages since the process started (all threads).
long ode_messages();
}  // namespace hapticd::hand

namespace hapticd::hand::spring {

inline constexpr unsigned long kSpringHandCategory = 1ul << 20;

struct SpringHandParams {
  SpringGains joint{0.5, 3e-4};                          // every finger DoF (4.2): N m/rad, N m s/rad
  SpringGains palm_linear{2000.0, 60.0};                 // k_T, b_T (4.3)
  SpringGains palm_torsional{10.0, 0.3};                 // k_R, b_R (4.3)
  SpringGains tip{40.0, 0.02};                           // every fingertip (4.4)
  double density_kg_m3 = 1100.0;                         // phalanx masses proportional to their volume (4.6.2)
  double palm_extra_mass_kg = 0.3;                       // on top of the palm box's own (4.6.2)
  std::array<double, 4> feedback_a{1.0, 1.0, 1.0, 1.0};  // a1 .. a4 of the glove force (4.5)
  bool gravity = true;                                   // false: the world's gravity leaves the hand alone
};

// A tracker reading: the palm's pose (the hand frame's) in the world and the 20 joint angles.
struct TrackedHand {
  Eigen::Vector3d p_W = Eigen::Vector3d::Zero();
  Eigen::Quaterniond q_W = Eigen::Quaterniond::Identity();
  HandJointAngles angles;
  // The palm's velocity and angular velocity when the tracker measures them (a device's proxy does);
  // without them, the difference of the last two readings (section 4.3).
  bool has_velocity = false;
  Eigen::Vector3d v_W = Eigen::Vector3d::Zero(), w_W = Eigen::Vector3d::Zero();
};

class SpringHandRig {
 public:
  // Builds the hand at `start` (the tracked hand becomes `start` too), at rest.
  SpringHandRig(dWorldID world, dSpaceID space, const SpringHandParams& params, bool left, const TrackedHand& start);
  ~SpringHandRig();
  SpringHandRig(const SpringHandRig&) = delete;
  SpringHandRig& operator=(const SpringHandRig&) = delete;

  // Moves every body rigidly to the pose `t` gives them (its joint angles too), at rest; the tracked
  // hand becomes `t` (a re-synced device, a reset).
  void place(const TrackedHand& t);
  // Every body's position, orientation and velocities finite, its speed below max_speed_m_s and its
  // distance from the tracked palm below max_distance_m.
  bool sane(double max_speed_m_s, double max_distance_m) const;
  // A new tracker reading. Tracked velocities are its difference from the previous reading over
  // the simulation steps taken since (apply_springs calls), as in section 4.2; the first reading
  // after the rig was built or placed, with no step since, has none (zero).
  void set_tracked(const TrackedHand& reading);
  // Adds every spring's force and torque to the bodies for one ODE step of length h.
  void apply_springs(double h);
  // The longest step at which the explicitly integrated springs stay stable (a margin of 2 below the
  // limit of each spring on the body it moves, its parent held: h^2 w^2 + 2 h c <= 1 with
  // w^2 = k / I, c = b / I).
  double max_stable_step() const { return max_stable_step_s_; }

  // The spring hand now.
  HandJointAngles joint_angles() const;
  Eigen::Matrix<double, kHandJointDofs, 1> joint_rates() const;
  Eigen::Vector3d palm_position() const;
  Eigen::Quaterniond palm_orientation() const;
  Eigen::Vector3d tip_W(int finger) const;
  Eigen::Vector3d tip_velocity_W(int finger) const;
  const SpringHandParams& params() const { return params_; }
  // A phalanx's pose (the skeleton's segment frame: y along the bone, z dorsal), world.
  Eigen::Isometry3d phalanx_pose(int phalanx) const;
  // The hinge of finger DoF `dof` (4 per finger: abduction, flexion 1-3): axis and anchor, world.
  Eigen::Vector3d joint_axis_W(int dof) const;
  Eigen::Vector3d joint_anchor_W(int dof) const;

  // What the last apply_springs() applied: the joint torques, the palm's force and torque (on the
  // spring hand; a device driving the palm feels their opposite), and per finger the fingertip
  // force without the palm's configuration (f_ls of section 4.5).
  double joint_torque(int dof) const { return torque_[dof]; }
  const Eigen::Vector3d& palm_force() const { return palm_force_; }
  const Eigen::Vector3d& palm_torque() const { return palm_torque_; }
  const Eigen::Vector3d& tip_force_without_palm(int finger) const { return f_ls_[finger]; }
  // The palm's and fingertips' springs' reaction on the tracked hand (force, torque about the tracked
  // palm), averaged over the apply_springs() calls since the last reading: what a device holding the
  // tracked palm felt over that time.
  Eigen::Matrix<double, 6, 1> mean_reaction_since_reading() const {
    return steps_since_reading_ > 0 ? Eigen::Matrix<double, 6, 1>(reaction_sum_ / steps_since_reading_)
                                    : Eigen::Matrix<double, 6, 1>::Zero();
  }
  // Section 4.5: the glove actuator's scalar force for `finger` along its unit line of action n_W
  // (the distal phalanx's dorsal axis when n_W is zero), from the last apply_springs(); zero for a
  // finger that touches nothing (section 4.6.2).
  double feedback(int finger, bool touching, const Eigen::Vector3d& n_W = Eigen::Vector3d::Zero()) const;

  dBodyID palm_body() const { return palm_; }
  dBodyID phalanx_body(int phalanx) const { return phalanx_[phalanx]; }
  dGeomID palm_geom() const { return palm_geom_; }
  dGeomID phalanx_geom(int phalanx) const { return phalanx_geom_[phalanx]; }
  double total_mass_kg() const { return total_mass_kg_; }
  // The whole hand as one rigid body moving with the palm (its joints locked): its 6x6 spatial
  // inertia about the palm's centre, for velocities (v of the palm's centre, w), and the offset of
  // its centre of mass from the palm's centre, world frame.
  Eigen::Matrix<double, 6, 6> composite_inertia(Eigen::Vector3d& com_offset_W) const;

 private:
  // The bodies' poses for tracked hand `t` (the skeleton's forward kinematics).
  void set_body_poses(const TrackedHand& t);
  // The tracked fingertips in the hand frame, of the last reading and of the one before.
  void update_tracked_tips();

  SpringHandParams params_;
  bool left_;
  dBodyID palm_ = nullptr;
  std::array<dBodyID, kHandFingers> base_{};  // the point mass between a base joint's two hinges
  std::array<dBodyID, kHandPhalanges> phalanx_{};
  std::array<dJointID, kHandJointDofs> hinge_{};
  dGeomID palm_geom_ = nullptr;
  std::array<dGeomID, kHandPhalanges> phalanx_geom_{};
  // Per finger DoF: the skeleton's angle where the hinge reads 0 (the angle at build).
  std::array<double, kHandJointDofs> angle_at_build_{};
  std::array<double, kHandPhalanges> capsule_length_{};  // the cylinder's, between the round ends
  // Per finger: the fingertip in the distal phalanx's body frame.
  std::array<Eigen::Vector3d, kHandFingers> tip_in_distal_;
  TrackedHand tracked_, tracked_before_;
  std::array<Eigen::Vector3d, kHandFingers> tips_H_, tips_before_H_;  // update_tracked_tips()
  int steps_since_reading_ = 0, steps_between_readings_ = 1;
  std::array<double, kHandJointDofs> torque_{};
  Eigen::Vector3d palm_force_ = Eigen::Vector3d::Zero(), palm_torque_ = Eigen::Vector3d::Zero();
  std::array<Eigen::Vector3d, kHandFingers> f_ls_;
  Eigen::Matrix<double, 6, 1> reaction_sum_ = Eigen::Matrix<double, 6, 1>::Zero();
  double max_stable_step_s_ = 0;
  double total_mass_kg_ = 0;
};

}  // namespace hapticd::hand::spring
