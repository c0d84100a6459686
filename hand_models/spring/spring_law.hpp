#pragma once
// The spring-damper laws of the articulated spring hand of seed 002 (Borst and Indugula, sections
// 4.2-4.5), as pure functions: what couples the simulated ("spring") hand to the tracked hand, and
// how its forces become one scalar per finger of a force-feedback glove. SpringHandRig applies them
// to ODE bodies; these are kept apart so that each is tested against its formula.
//
// Units: N, m, s, rad. Where the paper measures an angular velocity as a rotation per simulation
// step (its quaternion differences), these functions take the step length h and use rad/s, so a
// gain keeps its meaning when the step changes: the paper's b_R is b_R / h here.
#include <Eigen/Core>
#include <Eigen/Geometry>
#include <array>

namespace hapticd::hand::spring {

struct SpringGains {
  double k = 0;  // stiffness: N/m, or N m/rad
  double b = 0;  // damping: N s/m, or N m s/rad
};

// Seed 002 section 4.2: the torque of a finger joint's torsional spring-damper about its joint axis,
// tau = k (theta_t - theta_s) - b (omega_s - omega_t); t tracked, s the spring hand.
double joint_spring_torque(const SpringGains& g, double theta_t, double theta_s, double omega_s, double omega_t);

// Seed 002 sections 4.3 (palm) and 4.4 (fingertips): f = k (p_t - p_s) - b (v_s - v_t).
Eigen::Vector3d linear_spring_force(const SpringGains& g, const Eigen::Vector3d& p_t, const Eigen::Vector3d& p_s,
                                    const Eigen::Vector3d& v_s, const Eigen::Vector3d& v_t);

// The paper's modified quaternion product (section 4.3): a result with a negative scalar part is
// negated, so it describes the same orientation change by the rotation of angle <= pi.
Eigen::Quaterniond smaller_rotation(const Eigen::Quaterniond& q);

// Axis (unit) and angle in [0, 2 pi) of a unit quaternion; the x axis for the identity.
void axis_angle(const Eigen::Quaterniond& q, Eigen::Vector3d& axis, double& angle);

// Section 4.3, restoring part: q = q_s^* q_t (the smaller rotation), torque k_R theta_q about its
// axis a_q, which is in the spring palm's frame; returned in the world frame (R_s k_R theta_q a_q).
Eigen::Vector3d palm_restoring_torque(double k_R, const Eigen::Quaterniond& q_s, const Eigen::Quaterniond& q_t);

// Section 4.3, damping part, world frame. q_ws: the spring palm's rotation over one simulation step
// of length h (q_s1 q_s0^*, the smaller rotation); q_wt: the tracked palm's rotation between its last
// two readings (q_t1 q_t0^*, the smaller rotation), `steps` simulation steps apart, whose angle is
// divided by `steps` (the paper's correction for a simulation faster than the tracker). The relative
// rotation q_w = q_ws q_wt,adjusted^* (the plain product, as in the paper), and the torque
// -b_R theta_qw / h about its axis a_qw.
Eigen::Vector3d palm_damping_torque(double b_R, const Eigen::Quaterniond& q_ws, const Eigen::Quaterniond& q_wt,
                                    int steps, double h);

// Section 4.5: the force a flexion torque tau contributes, with direction axis x d and magnitude
// tau / |d|, d from the joint centre to the fingertip point (zero when d vanishes).
Eigen::Vector3d flexion_torque_force(const Eigen::Vector3d& axis, const Eigen::Vector3d& joint_centre,
                                     const Eigen::Vector3d& tip, double tau);

// Section 4.5: the scalar force of a 1-DoF-per-finger glove actuator,
// f = -(a1 f_tau1 + a2 f_tau2 + a3 f_tau3 + a4 f_ls) . n, n the actuator's unit line of action.
double glove_feedback(const std::array<double, 4>& a, const std::array<Eigen::Vector3d, 3>& f_tau,
                      const Eigen::Vector3d& f_ls, const Eigen::Vector3d& n);

}  // namespace hapticd::hand::spring
