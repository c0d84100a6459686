#include "hand_models/spring/spring_law.hpp"

#include <algorithm>
#include <cmath>

namespace hapticd::hand::spring {

double joint_spring_torque(const SpringGains& g, double theta_t, double theta_s, double omega_s, double omega_t) {
  return g.k * (theta_t - theta_s) - g.b * (omega_s - omega_t);
}

Eigen::Vector3d linear_spring_force(const SpringGains& g, const Eigen::Vector3d& p_t, const Eigen::Vector3d& p_s,
                                    const Eigen::Vector3d& v_s, const Eigen::Vector3d& v_t) {
  return g.k * (p_t - p_s) - g.b * (v_s - v_t);
}

Eigen::Quaterniond smaller_rotation(const Eigen::Quaterniond& q) {
  return q.w() < 0 ? Eigen::Quaterniond(-q.w(), -q.x(), -q.y(), -q.z()) : q;
}

void axis_angle(const Eigen::Quaterniond& q, Eigen::Vector3d& axis, double& angle) {
  const double s = q.vec().norm();
  // atan2 keeps the small angles accurate, where acos(w) loses half the digits.
  angle = 2.0 * std::atan2(s, q.w());
  if (angle < 0) angle += 2.0 * M_PI;
  axis = s > 0 ? Eigen::Vector3d(q.vec() / s) : Eigen::Vector3d::UnitX();
}

Eigen::Vector3d palm_restoring_torque(double k_R, const Eigen::Quaterniond& q_s, const Eigen::Quaterniond& q_t) {
  Eigen::Vector3d a;
  double theta;
  axis_angle(smaller_rotation(q_s.conjugate() * q_t), a, theta);
  return q_s * (k_R * theta * a);
}

Eigen::Vector3d palm_damping_torque(double b_R, const Eigen::Quaterniond& q_ws, const Eigen::Quaterniond& q_wt,
                                    int steps, double h) {
  Eigen::Vector3d a;
  double theta;
  axis_angle(smaller_rotation(q_wt), a, theta);
  const Eigen::Quaterniond q_wt_adjusted(Eigen::AngleAxisd(theta / std::max(steps, 1), a));
  axis_angle(smaller_rotation(q_ws) * q_wt_adjusted.conjugate(), a, theta);
  return -b_R * theta / h * a;
}

Eigen::Vector3d flexion_torque_force(const Eigen::Vector3d& axis, const Eigen::Vector3d& joint_centre,
                                     const Eigen::Vector3d& tip, double tau) {
  const Eigen::Vector3d d = tip - joint_centre;
  const Eigen::Vector3d dir = axis.cross(d);
  const double dn = d.norm(), n = dir.norm();
  if (!(dn > 0) || !(n > 0)) return Eigen::Vector3d::Zero();
  return tau / dn * dir / n;
}

double glove_feedback(const std::array<double, 4>& a, const std::array<Eigen::Vector3d, 3>& f_tau,
                      const Eigen::Vector3d& f_ls, const Eigen::Vector3d& n) {
  return -(a[0] * f_tau[0] + a[1] * f_tau[1] + a[2] * f_tau[2] + a[3] * f_ls).dot(n);
}

}  // namespace hapticd::hand::spring
