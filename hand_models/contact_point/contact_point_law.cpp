#include "hand_models/contact_point/contact_point_law.hpp"

#include <cmath>

namespace hapticd::hand::contact_point {

ContactForce contact_force(double gamma_n_m, double mu_static, double mu_dynamic, const Eigen::Vector3d& C_W,
                           const Eigen::Vector3d& n_W, const Eigen::Vector3d& p_W) {
  ContactForce out;
  const Eigen::Vector3d f = gamma_n_m * (C_W - p_W);  // eq. 1
  const double fn = f.dot(n_W);
  if (!(fn > 0)) return out;                // separated (and nothing non-finite passes)
  out.f_n = fn * n_W;                       // eq. 2
  const Eigen::Vector3d f_t = f - out.f_n;  // eq. 3
  const double ft = f_t.norm();
  if (ft <= mu_static * fn) {  // eq. 4
    out.state = ContactState::stuck;
    out.f_T = f_t;  // eq. 5, inside
  } else {
    out.state = ContactState::sliding;
    out.f_T = (mu_dynamic * fn / ft) * f_t;  // eq. 5, outside (Coulomb's reading, see the header)
  }
  return out;
}

Eigen::Vector3d slide_target(double mu_dynamic, const Eigen::Vector3d& C_W, const Eigen::Vector3d& n_W,
                             const Eigen::Vector3d& p_W) {
  const Eigen::Vector3d d = C_W - p_W;
  const double depth = d.dot(n_W);
  const Eigen::Vector3d d_t = d - depth * n_W;
  const double dt = d_t.norm();
  const double keep = mu_dynamic * depth;  // the tangential offset whose spring is the kinetic force
  if (!(depth > 0) || !(dt > keep)) return C_W;
  return C_W - (dt - keep) / dt * d_t;
}

}  // namespace hapticd::hand::contact_point
