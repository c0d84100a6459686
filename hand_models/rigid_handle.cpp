#include "hand_models/rigid_handle.hpp"

#include <algorithm>
#include <cmath>
#include <stdexcept>

namespace hapticd::hand {

Eigen::Matrix3d skew(const Eigen::Vector3d& a) {
  Eigen::Matrix3d m;
  m << 0, -a.z(), a.y(), a.z(), 0, -a.x(), -a.y(), a.x(), 0;
  return m;
}

RigidHandle make_handle(const TetMesh& mesh, const Eigen::VectorXd& node_mass, const Eigen::Vector3d& seed,
                        double radius, const std::vector<int>& nodes, const std::string& name) {
  if (!(radius > 0) || !seed.allFinite())
    throw std::invalid_argument("handle " + name + ": radius must be > 0 and the seed finite");
  RigidHandle h;
  h.name = name;
  Eigen::Vector3d com = Eigen::Vector3d::Zero();
  auto take = [&](int i) {
    h.nodes.push_back(i);
    h.mass_kg += node_mass[i];
    com += node_mass[i] * mesh.X[i];
  };
  if (!nodes.empty()) {
    for (int i : nodes) {
      if (i < 0 || i >= mesh.num_nodes())
        throw std::invalid_argument("handle " + name + ": node " + std::to_string(i) + " is not in the mesh");
      take(i);
    }
  } else {
    for (int i = 0; i < mesh.num_nodes(); ++i)
      if ((mesh.X[i] - seed).norm() <= radius) take(i);
  }
  if (h.nodes.empty())
    throw std::invalid_argument("handle " + name + ": no mesh node within " + std::to_string(radius) +
                                " m of the seed point");
  com /= h.mass_kg;
  h.p_WH_rest = com;
  for (int i : h.nodes) {
    const Eigen::Vector3d r = mesh.X[i] - com;
    h.r_B.push_back(r);
    h.inertia_B += node_mass[i] * (r.squaredNorm() * Eigen::Matrix3d::Identity() - r * r.transpose());
  }
  // A point or line of nodes has a singular inertia: add that of a small sphere (2/5 m r^2, r = radius / 10).
  h.inertia_B += 0.4 * h.mass_kg * std::pow(0.1 * radius, 2) * Eigen::Matrix3d::Identity();
  return h;
}

FrameToHandle frame_to_handle(const Eigen::Vector3d& frame_p_rest, const Eigen::Matrix3d& frame_R_rest,
                              const RigidHandle& handle) {
  FrameToHandle o;
  o.p_F = frame_R_rest.transpose() * (handle.p_WH_rest - frame_p_rest);
  o.q_F = Eigen::Quaterniond(frame_R_rest.transpose()).normalized();
  return o;
}

SpringTerms coupling_spring(const Eigen::Vector3d& x_A, const Eigen::Vector3d& v_A, const HandleState& h,
                            const Eigen::Vector3d& r_B, double k, double d) {
  SpringTerms s;
  s.k = k;
  s.d = d;
  const Eigen::Vector3d rho = h.q_WH * r_B;  // R_h r_B
  const Eigen::Matrix3d rho_x = skew(rho);
  const Eigen::Matrix3d w_x = skew(h.w_WH);
  const Eigen::Vector3d x_B = h.p_WH + rho;
  const Eigen::Vector3d v_B = h.v_WH + h.w_WH.cross(rho);
  // seed 004 eq. 4
  s.F_A = -k * (x_A - x_B) - d * (v_A - v_B);
  const Eigen::Vector3d F_B = -s.F_A;
  s.W_B << F_B, rho.cross(F_B);  // eq. 5
  const Eigen::Matrix3d I = Eigen::Matrix3d::Identity();
  // eq. 11 with d(R r)/d theta = -[rho]x; the damping term carries d(w x rho)/d theta = -[w]x [rho]x.
  s.dFA_dxh << k * I, -k * rho_x - d * w_x * rho_x;
  s.dFA_dvh << d * I, -d * rho_x;
  const Eigen::Matrix<double, 3, 6> dFB_dxh = -s.dFA_dxh;
  const Eigen::Matrix<double, 3, 6> dFB_dvh = -s.dFA_dvh;
  s.dWB_dxA << k * I, k * rho_x;
  s.dWB_dvA << d * I, d * rho_x;
  s.dWB_dxh.topRows<3>() = dFB_dxh;
  s.dWB_dvh.topRows<3>() = dFB_dvh;
  // dT_B = d(rho) x F_B + rho x dF_B, d(rho) = -[rho]x dtheta.
  s.dWB_dxh.bottomRows<3>() = rho_x * dFB_dxh;
  s.dWB_dxh.bottomRightCorner<3, 3>() += skew(F_B) * rho_x;
  s.dWB_dvh.bottomRows<3>() = rho_x * dFB_dvh;
  return s;
}

Eigen::Matrix<double, 3, 4> d_rotated_d_quaternion(const Eigen::Quaterniond& q, const Eigen::Vector3d& r) {
  // R(q) r = q o (r, 0) o q'  =>  d/dq = [right-multiplication by a = (r,0) o q'] + [left by b = q o (r,0)] C.
  const Eigen::Quaterniond a = Eigen::Quaterniond(0, r.x(), r.y(), r.z()) * q.conjugate();
  const Eigen::Quaterniond b = q * Eigen::Quaterniond(0, r.x(), r.y(), r.z());
  // Rows: vector part of p o a and b o p as linear maps of p = (x, y, z, s).
  Eigen::Matrix<double, 3, 4> right, left;
  right << a.w(), a.z(), -a.y(), a.x(),  //
      -a.z(), a.w(), a.x(), a.y(),       //
      a.y(), -a.x(), a.w(), a.z();
  left << b.w(), -b.z(), b.y(), b.x(),  //
      b.z(), b.w(), -b.x(), b.y(),      //
      -b.y(), b.x(), b.w(), b.z();
  Eigen::Matrix4d C = Eigen::Matrix4d::Identity();  // conjugation: d(q') = C dq
  C.topLeftCorner<3, 3>() *= -1;
  return right + left * C;
}

Eigen::Matrix<double, 4, 3> quaternion_rate_matrix(const Eigen::Quaterniond& q) {
  // dq/dt = 1/2 (w, 0) o q
  Eigen::Matrix<double, 4, 3> G;
  G << q.w(), q.z(), -q.y(),  //
      -q.z(), q.w(), q.x(),   //
      q.y(), -q.x(), q.w(),   //
      -q.x(), -q.y(), -q.z();
  return 0.5 * G;
}

double clearance_share(const ClearancePlane* planes, int count, const Eigen::Vector3d& dx,
                       const Eigen::Vector3d& dtheta, const Eigen::Vector3d& move, const Eigen::Vector3d& turn) {
  double share = 1.0;
  for (int k = 0; k < count; ++k) {
    const ClearancePlane& c = planes[k];
    // How much a displacement closes the gap: -n . (dx + dtheta x r).
    const Eigen::Vector3d g_lin = -c.n_W, g_rot = -c.r_W.cross(c.n_W);
    const double closed = g_lin.dot(dx) + g_rot.dot(dtheta);
    const double closing = g_lin.dot(move) + g_rot.dot(turn);
    const double room = std::max(c.gap_m, closed) - closed;
    if (closing > room) share = std::min(share, room / closing);
  }
  return share;
}

double free_travel_share(const Eigen::Vector3d& dx, const Eigen::Vector3d& dtheta, const Eigen::Vector3d& move,
                         const Eigen::Vector3d& turn, double radius_m) {
  const double used = dx.norm() + radius_m * dtheta.norm();
  const double after = (dx + move).norm() + radius_m * (dtheta + turn).norm();
  if (after <= kClearanceLook_m || after <= used) return 1.0;  // within reach, or coming back
  // |dx + s move| + radius |dtheta + s turn| <= used + s (|move| + radius |turn|) (the triangle
  // inequality): the largest s that keeps that bound within reach.
  const double room = kClearanceLook_m - used, rate = move.norm() + radius_m * turn.norm();
  return room > 0 && rate > 0 ? std::min(1.0, room / rate) : 0.0;
}

Eigen::Quaterniond rotate_by(const Eigen::Quaterniond& q, const Eigen::Vector3d& theta) {
  const double angle = theta.norm();
  Eigen::Quaterniond dq = Eigen::Quaterniond::Identity();
  if (angle > 0) dq = Eigen::Quaterniond(Eigen::AngleAxisd(angle, theta / angle));
  return (dq * q).normalized();
}

Eigen::Vector3d rotation_difference(const Eigen::Quaterniond& q_a, const Eigen::Quaterniond& q_b) {
  Eigen::Quaterniond d = q_a * q_b.conjugate();
  if (d.w() < 0) d.coeffs() = -d.coeffs();
  const Eigen::AngleAxisd aa(d.normalized());
  return aa.angle() * aa.axis();
}

}  // namespace hapticd::hand
