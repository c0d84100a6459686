#include "hand_models/spring/spring_hand.hpp"

#include <Eigen/Cholesky>
#include <algorithm>
#include <cmath>
#include <stdexcept>
#include <string>

#include "hand_models/contact_pgs.hpp"
#include "hand_models/hand_model.hpp"

namespace hapticd::hand::spring {

SpringHand::SpringHand(dWorldID world, dSpaceID space, const SpringHandConfig& config, const Eigen::Vector3d& p_W,
                       const Eigen::Quaterniond& q_W)
    : config_(config), handles_(static_cast<std::size_t>(std::max(config.handles, 1))) {
  if (config.handles != 1 && config.handles != 1 + kHandFingers && config.handles != 1 + kHandPhalanges)
    throw std::invalid_argument(
        "the spring hand is driven by its palm (1 handle, a stylus) or by a glove's palm and 5 distal "
        "phalanges (6) or 15 phalanges (16), not " +
        std::to_string(config.handles) + " handles");
  place_handles(p_W, q_W.normalized());
  rig_ = std::make_unique<SpringHandRig>(world, space, config.params, config.left, tracked());
}

void SpringHand::place_handles(const Eigen::Vector3d& p_W, const Eigen::Quaterniond& q_W) {
  const SkeletonPose pose = skeleton_pose(angles_, config_.left);
  for (int f = 0; f < kHandFingers; ++f) tips_H_[f] = pose.joints[f][3];
  tracked_frames::place(handles_, p_W, q_W, pose);
}

HandJointAngles SpringHand::tracked_angles(const std::vector<HandleState>& h) const {
  if (h.size() == 1) return angles_;
  const Eigen::Matrix3d palm_T = h[0].q_WH.toRotationMatrix().transpose();
  if (h.size() == 1 + kHandFingers) {
    std::array<Eigen::Matrix3d, kHandFingers> R_distal;
    for (int f = 0; f < kHandFingers; ++f) R_distal[f] = palm_T * h[1 + f].q_WH.toRotationMatrix();
    return joint_angles_from_distal(R_distal, config_.left, &angles_);
  }
  std::array<Eigen::Matrix3d, kHandPhalanges> R;
  for (int i = 0; i < kHandPhalanges; ++i) R[i] = palm_T * h[i + 1].q_WH.toRotationMatrix();
  return joint_angles_from_segments(R, config_.left);
}

TrackedHand SpringHand::tracked() const {
  TrackedHand t;
  t.p_W = handles_[0].p_WH;
  t.q_W = handles_[0].q_WH;
  t.angles = tracked_angles(handles_);
  t.has_velocity = true;
  t.v_W = handles_[0].v_WH;
  t.w_W = handles_[0].w_WH;
  return t;
}

HandleInfo SpringHand::handle_info(int, int) const { return tracked_frames::info(config_.handle_mass_kg); }

bool SpringHand::set_target(int j, const HandleTarget& target) { return tracked_frames::set(handles_, j, target); }

void SpringHand::place(const Eigen::Vector3d& p_W, const Eigen::Quaterniond& q_W) {
  place_handles(p_W, q_W.normalized());
  rig_->place(tracked());
}

void SpringHand::step(HandleLinearization*) {
  angles_ = tracked_angles(handles_);
  rig_->set_tracked(tracked());
}

void SpringHand::after_ode_steps() {
  if (rig_->sane(config_.max_speed_m_s, config_.max_distance_m)) return;
  ++resets_;
  rig_->place(tracked());
}

void SpringHand::recover(const Eigen::Vector3d& fallback_p_W, const Eigen::Quaterniond& fallback_q_W) {
  ++resets_;
  bool whole = true;
  for (const HandleState& h : handles_) whole = whole && h.p_WH.allFinite() && h.q_WH.coeffs().allFinite();
  if (whole) {
    rig_->place(tracked());
  } else if (fallback_p_W.allFinite() && fallback_q_W.coeffs().allFinite()) {
    place(fallback_p_W, fallback_q_W);
  } else {
    place(Eigen::Vector3d::Zero(), Eigen::Quaterniond::Identity());
  }
}

Eigen::VectorXd SpringHand::reaction(const std::vector<HandleState>& h) const {
  const SpringHandParams& p = config_.params;
  const int n = static_cast<int>(h.size());
  Eigen::VectorXd out = Eigen::VectorXd::Zero(6 * n);
  const dBodyID palm = rig_->palm_body();
  const Eigen::Vector3d p_s = rig_->palm_position();
  const dReal* v = dBodyGetLinearVel(palm);
  const dReal* w = dBodyGetAngularVel(palm);
  const Eigen::Vector3d v_s(v[0], v[1], v[2]), w_s(w[0], w[1], w[2]);
  // The palm's springs, on the palm's handle (section 4.3).
  out.segment<3>(0) = -p.palm_linear.k * (h[0].p_WH - p_s) - p.palm_linear.b * (h[0].v_WH - v_s);
  out.segment<3>(3) = -palm_restoring_torque(p.palm_torsional.k, rig_->palm_orientation(), h[0].q_WH) -
                      p.palm_torsional.b * (h[0].w_WH - w_s);
  // The fingertips' springs (4.4), on the handle their tracked tip moves with: the palm's, or the
  // distal phalanx's of a glove, about that handle's origin.
  const HandJointAngles angles = tracked_angles(h);
  const SkeletonPose pose = skeleton_pose(angles, config_.left);
  for (int f = 0; f < kHandFingers; ++f) {
    const int j = phalanx_frame(3 * f + 2);
    const Eigen::Vector3d tip = h[0].p_WH + h[0].q_WH * pose.joints[f][3];
    const Eigen::Vector3d r = tip - h[j].p_WH;
    const Eigen::Vector3d f_tip =
        linear_spring_force(p.tip, tip, rig_->tip_W(f), rig_->tip_velocity_W(f), h[j].v_WH + h[j].w_WH.cross(r));
    out.segment<3>(6 * j) -= f_tip;
    out.segment<3>(6 * j + 3) -= r.cross(f_tip);
  }
  if (n == 1) return out;  // a stylus's tracked hand is rigid: the joint springs' reactions cancel on it
  // The joint springs (4.2): the tracked child segment feels -tau about the spring joint's axis, its
  // parent (the palm, for a base joint) +tau; the tracked angular rate is the frames' relative one.
  const Eigen::Matrix<double, kHandJointDofs, 1> theta_t = angles.vector(), theta_s = rig_->joint_angles().vector(),
                                                 omega_s = rig_->joint_rates();
  // A 6-frame glove tracks each finger's distal frame alone, and its joints through it
  // (joint_angles_from_distal): a joint's angle is its share of the distal's turn from the palm (all
  // of the abduction, 3/8, 3/8 and 2/8 of the flexion), so its spring's reaction, by virtual work,
  // is that share of tau on the distal frame and on the palm.
  for (int dof = 0; dof < kHandJointDofs; ++dof) {
    const int f = dof / 4, k = dof % 4;
    const bool six = n == 1 + kHandFingers;
    const int child = six ? 1 + f : phalanx_frame(3 * f + std::max(k - 1, 0));
    const int parent = six || k <= 1 ? 0 : phalanx_frame(3 * f + k - 2);
    const double share = !six || k == 0 ? 1.0 : k == 3 ? 2.0 / 8.0 : 3.0 / 8.0;
    const Eigen::Vector3d a = rig_->joint_axis_W(dof);
    const double omega_t = share * a.dot(h[child].w_WH - h[parent].w_WH);
    const double tau = joint_spring_torque(p.joint, theta_t[dof], theta_s[dof], omega_s[dof], omega_t);
    out.segment<3>(6 * child + 3) -= share * tau * a;
    out.segment<3>(6 * parent + 3) += share * tau * a;
  }
  return out;
}

void SpringHand::set_contacts(const std::vector<OdeHandContact>& contacts) {
  contacts_ = contacts;
  if (static_cast<int>(contacts_.size()) > kMaxLinearizedContacts) {
    std::partial_sort(contacts_.begin(), contacts_.begin() + kMaxLinearizedContacts, contacts_.end(),
                      [](const OdeHandContact& a, const OdeHandContact& b) { return a.depth_m > b.depth_m; });
    contacts_.resize(kMaxLinearizedContacts);
  }
}

bool SpringHand::linearize_rigid_body(HandleLinearization& out) const {
  const double h = dt_s_;
  // The world steps the hand in ODE steps no longer than the rig's stable step (RigidWorld::step):
  // the model takes the same substeps, ODE's semi-implicit Euler, on the hand as one body.
  const int substeps = std::max(1, static_cast<int>(std::ceil(h / rig_->max_stable_step() - 1e-9)));
  const double hs = h / substeps;
  const Eigen::MatrixXd K = out.K, D = out.D;
  Eigen::Vector3d c;
  const Eigen::Matrix<double, 6, 6> M = rig_->composite_inertia(c);
  const Eigen::LLT<Eigen::Matrix<double, 6, 6>> M_llt(M);
  if (M_llt.info() != Eigen::Success) return false;
  Eigen::Matrix<double, 6, 1> v_s;
  const dReal* v = dBodyGetLinearVel(rig_->palm_body());
  const dReal* w = dBodyGetAngularVel(rig_->palm_body());
  v_s << v[0], v[1], v[2], w[0], w[1], w[2];
  Eigen::Matrix<double, 6, 1> f_g;
  f_g << M(0, 0) * config_.gravity_m_s2, M(0, 0) * c.cross(config_.gravity_m_s2);
  // Rows in contact frames (n, t1, t2) at each point, on the body's velocity (v of the palm's centre, w).
  const int n = static_cast<int>(contacts_.size());
  Eigen::MatrixXd J(3 * n, 6);
  const Eigen::Vector3d o = rig_->palm_position();
  HandleContactModel& m = out.contacts;
  m = HandleContactModel{};
  m.bias.resize(n);
  m.mu.resize(n);
  for (int i = 0; i < n; ++i) {
    const OdeHandContact& k = contacts_[i];
    const Eigen::Vector3d t1 = k.n_W.unitOrthogonal(), t2 = k.n_W.cross(t1), r = k.p_W - o;
    const Eigen::Vector3d dirs[3] = {k.n_W, t1, t2};
    for (int a = 0; a < 3; ++a) J.row(3 * i + a) << dirs[a].transpose(), r.cross(dirs[a]).transpose();
    // A penetrating point is pushed out by a share of its depth per step, as the hands' constraint
    // contacts are (kContactDepthRecovery); ODE reports only touching points, none with a gap.
    m.bias[i] = kContactDepthRecovery * std::max(k.depth_m, 0.0) / h;
    m.mu[i] = k.mu;
  }
  // The body's displacement dp and velocity change dv_s over the step, linear in the inputs
  // u = (handle displacement dx, handle velocity change dv, row impulses lambda, 1): columns of S.
  // Each substep: the reaction on the handle is F0 + K (dx - dp) + D (dv - dv_s), the body takes its
  // opposite, its weight and the impulses spread over the step.
  const int cols = 12 + 3 * n + 1, one = cols - 1;
  Eigen::MatrixXd E = Eigen::MatrixXd::Zero(6, cols);  // the body's force, less its state's part
  E.leftCols(6) = -K;
  E.middleCols(6, 6) = -D;
  if (n > 0) E.middleCols(12, 3 * n) = J.transpose() / h;
  E.col(one) = f_g - out.F0;
  // The reaction on the handle after each substep, F0 + K (dx - dp) + D (dv - dv_s), averaged over
  // the step: the impulse the hand exchanges with a handle held at (x, v), over h.
  Eigen::MatrixXd S_p = Eigen::MatrixXd::Zero(6, cols), S_v = Eigen::MatrixXd::Zero(6, cols);
  Eigen::MatrixXd F_u = Eigen::MatrixXd::Zero(6, cols);
  for (int k = 0; k < substeps; ++k) {
    S_v += hs * M_llt.solve(K * S_p + D * S_v + E);
    S_p += hs * S_v;
    S_p.col(one) += hs * v_s;
    F_u -= (K * S_p + D * S_v) / substeps;
  }
  F_u.leftCols(6) += K;
  F_u.middleCols(6, 6) += D;
  out.F0 += F_u.col(one);
  out.K = F_u.leftCols(6);
  out.D = F_u.middleCols(6, 6);
  if (n == 0) return out.F0.allFinite() && out.K.allFinite() && out.D.allFinite();
  m.G = F_u.middleCols(12, 3 * n);
  const Eigen::MatrixXd JS = J * S_v;
  m.W = JS.middleCols(12, 3 * n);
  m.W = 0.5 * (m.W + m.W.transpose());
  m.u0 = J * v_s + JS.col(one);
  m.U_K = JS.leftCols(6);
  m.U_D = JS.middleCols(6, 6);
  ContactProblem problem{m.W, m.u0, m.bias, m.mu};
  const PgsResult solved = solve_contacts_pgs(problem);
  if (!solved.lambda.allFinite()) return false;
  m.lambda0 = solved.lambda;
  return true;
}

bool SpringHand::linearize_next_step(HandleLinearization& out, ContactLinearization) {
  out = HandleLinearization{};
  out.x0 = handles_;
  out.F0 = reaction(handles_);
  const int m = 6 * num_handles();
  out.K = Eigen::MatrixXd::Zero(m, m);
  out.D = Eigen::MatrixXd::Zero(m, m);
  // Central differences: the reaction is linear in the velocities and in the positions, and smooth
  // in the rotations (the model's rotation coordinate: a world rotation vector applied to q0).
  constexpr double e = 1e-6;
  std::vector<HandleState> a = handles_, b = handles_;
  for (int j = 0; j < num_handles(); ++j) {
    const HandleState& x0 = handles_[static_cast<std::size_t>(j)];
    HandleState& ha = a[static_cast<std::size_t>(j)];
    HandleState& hb = b[static_cast<std::size_t>(j)];
    for (int i = 0; i < 3; ++i) {
      ha.p_WH[i] += e, hb.p_WH[i] -= e;
      out.K.col(6 * j + i) = (reaction(a) - reaction(b)) / (2 * e);
      ha = hb = x0;
      ha.q_WH = Eigen::Quaterniond(Eigen::AngleAxisd(e, Eigen::Vector3d::Unit(i))) * x0.q_WH;
      hb.q_WH = Eigen::Quaterniond(Eigen::AngleAxisd(-e, Eigen::Vector3d::Unit(i))) * x0.q_WH;
      out.K.col(6 * j + 3 + i) = (reaction(a) - reaction(b)) / (2 * e);
      ha = hb = x0;
      ha.v_WH[i] += e, hb.v_WH[i] -= e;
      out.D.col(6 * j + i) = (reaction(a) - reaction(b)) / (2 * e);
      ha = hb = x0;
      ha.w_WH[i] += e, hb.w_WH[i] -= e;
      out.D.col(6 * j + 3 + i) = (reaction(a) - reaction(b)) / (2 * e);
      ha = hb = x0;
    }
  }
  if (config_.body_step_model && num_handles() == 1 && !linearize_rigid_body(out)) return false;
  return out.F0.allFinite() && out.K.allFinite() && out.D.allFinite();
}

Eigen::VectorXd SpringHand::coupling_wrench() const { return reaction(handles_); }

int SpringHand::phalanx_frame(int i) const {
  if (num_handles() == 1) return 0;
  return num_handles() == 1 + kHandFingers ? 1 + i / 3 : 1 + i;
}

double SpringHand::glove_feedback(int finger, const Eigen::Vector3d& n_W) const {
  if (num_handles() == 1 || finger < 0 || finger >= kHandFingers) return 0.0;
  const bool touching = std::any_of(contacts_.begin(), contacts_.end(), [&](const OdeHandContact& c) {
    for (int k = 0; k < 3; ++k)
      if (c.handle == phalanx_frame(3 * finger + k)) return true;
    return false;
  });
  return rig_->feedback(finger, touching, n_W);
}

Eigen::Vector3d SpringHand::skin_point(int i) const {
  if (i <= 0) return rig_->palm_position();
  if (i <= kHandPhalanges) return rig_->phalanx_pose(i - 1).translation();
  return rig_->tip_W(i - 1 - kHandPhalanges);
}

int SpringHand::skin_handle(int i) const {
  if (i < 0 || i >= num_skin_points()) return -1;
  if (i == 0) return 0;
  if (i <= kHandPhalanges) return phalanx_frame(i - 1);
  return phalanx_frame(3 * (i - 1 - kHandPhalanges) + 2);  // a fingertip: its distal phalanx's
}

}  // namespace hapticd::hand::spring
