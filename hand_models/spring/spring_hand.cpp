#include "hand_models/spring/spring_hand.hpp"

#include <Eigen/Cholesky>
#include <algorithm>
#include <array>
#include <cmath>
#include <stdexcept>
#include <string>

#include "hand_models/contact_pgs.hpp"
#include "hand_models/hand_model.hpp"
#include "hand_models/shape_probes.hpp"

namespace hapticd::hand::spring {
namespace {

// A contact's rows in its frame (n, t1, t2) at `arm` from an origin: the velocity along each of a point
// moving with a body's twist (v at the origin, w).
Eigen::Matrix<double, 3, 6> contact_rows(const Eigen::Vector3d& n, const Eigen::Vector3d& arm) {
  const Eigen::Vector3d t1 = n.unitOrthogonal(), t2 = n.cross(t1);
  Eigen::Matrix<double, 3, 6> J;
  J.row(0) << n.transpose(), arm.cross(n).transpose();
  J.row(1) << t1.transpose(), arm.cross(t1).transpose();
  J.row(2) << t2.transpose(), arm.cross(t2).transpose();
  return J;
}

}  // namespace

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
  // Where the stylus model looks for objects, in each geom's frame: the palm box's faces on 7 x 7 grids
  // (1 cm apart at most), and spheres of each capsule's radius along its axis (ODE's z) half a radius
  // apart, whose union leaves at most 3 % of the radius between them.
  probes_G_.resize(static_cast<std::size_t>(num_geoms()));
  dVector3 lengths;
  dGeomBoxGetLengths(geom(0), lengths);
  palm_half_ = 0.5 * Eigen::Vector3d(lengths[0], lengths[1], lengths[2]);
  for (const Eigen::Vector3d& q : box_probes(palm_half_, kPalmGrid)) {
    int face = 0;  // the axis the point lies on a face of, and the side (box_probes' order)
    for (int a = 0; a < 3; ++a)
      if (std::abs(std::abs(q[a]) - palm_half_[a]) < 1e-12) face = 2 * a + (q[a] > 0);
    probes_G_[0].push_back({q, 0.0, face});
  }
  for (int g = 1; g < num_geoms(); ++g) {
    dReal radius, length;
    dGeomCapsuleGetParams(geom(g), &radius, &length);
    const int stations = 1 + static_cast<int>(std::ceil(length / (0.5 * radius)));
    for (int k = 0; k <= stations; ++k)
      probes_G_[g].push_back({Eigen::Vector3d(0, 0, length * (static_cast<double>(k) / stations - 0.5)), radius, -1});
  }
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
  place_rig();
}

void SpringHand::place_rig() {
  rig_->place(tracked());
  // Its contacts were where it was.
  contacts_.clear();
  contacts_G_.clear();
  previous_.clear();
}

void SpringHand::step(HandleLinearization*) {
  angles_ = tracked_angles(handles_);
  rig_->set_tracked(tracked());
}

void SpringHand::after_ode_steps() {
  if (rig_->sane(config_.max_speed_m_s, config_.max_distance_m)) return;
  ++resets_;
  place_rig();
}

void SpringHand::recover(const Eigen::Vector3d& fallback_p_W, const Eigen::Quaterniond& fallback_q_W) {
  ++resets_;
  bool whole = true;
  for (const HandleState& h : handles_) whole = whole && h.p_WH.allFinite() && h.q_WH.coeffs().allFinite();
  if (whole) {
    place_rig();
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
  // The contacts of the last kHeldSteps steps, each with its point in its geom's frame when ODE found
  // it (the geoms had not moved since): the last step's, and the older ones that step did not renew.
  std::vector<Held> held;
  for (std::size_t k = 0; k < contacts_.size(); ++k)
    if (contacts_[k].geom >= 0) held.push_back({contacts_[k], contacts_G_[k], 1});
  const std::size_t renewed = held.size();
  for (const Held& h : previous_) {
    if (h.age >= kHeldSteps) continue;
    const Eigen::Vector3d p = geom_pose(h.contact.geom) * h.p_G;
    const bool superseded =
        std::any_of(held.begin(), held.begin() + static_cast<std::ptrdiff_t>(renewed), [&](const Held& o) {
          return o.contact.geom == h.contact.geom && (o.contact.p_W - p).squaredNorm() < kHeldApart_m * kHeldApart_m;
        });
    if (!superseded) held.push_back({h.contact, h.p_G, h.age + 1});
  }
  previous_ = std::move(held);
  contacts_ = contacts;
  if (static_cast<int>(contacts_.size()) > kMaxLinearizedContacts) {
    std::partial_sort(contacts_.begin(), contacts_.begin() + kMaxLinearizedContacts, contacts_.end(),
                      [](const OdeHandContact& a, const OdeHandContact& b) { return a.depth_m > b.depth_m; });
    contacts_.resize(kMaxLinearizedContacts);
  }
  contacts_G_.clear();
  for (const OdeHandContact& c : contacts_)
    contacts_G_.push_back(c.geom >= 0 ? geom_pose(c.geom).inverse() * c.p_W : c.p_W);
}

Eigen::Isometry3d SpringHand::geom_pose(int g) const {
  const dReal* pos = dGeomGetPosition(geom(g));
  const dReal* R = dGeomGetRotation(geom(g));
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  T.linear() << R[0], R[1], R[2], R[4], R[5], R[6], R[8], R[9], R[10];
  T.translation() << pos[0], pos[1], pos[2];
  return T;
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
    J.middleRows<3>(3 * i) = contact_rows(k.n_W, k.p_W - o);
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

bool SpringHand::deepest_on_face(int face, const Eigen::Vector3d& o, const Eigen::Matrix3d& R_W, int object,
                                 double reach, Eigen::Vector3d& q, double& depth, Eigen::Vector3d& n) const {
  // Descent of the object's distance over the face (a flat palm on a round bump touches between the
  // grid's points, 2 mm from the nearest): step against the normal's part along the face, halved
  // whenever it does not go deeper.
  const int axis = face / 2;
  if (!objects_->surface_near(object, o + R_W * q, reach, depth, n)) return false;
  double step = palm_half_.maxCoeff() / (kPalmGrid - 1);
  for (int it = 0; it < 12 && step > 1e-4; ++it) {
    Eigen::Vector3d along = R_W.transpose() * n;
    along[axis] = 0;
    if (along.norm() < 1e-9) break;
    Eigen::Vector3d next = q - step * along.normalized();
    for (int a = 0; a < 3; ++a)
      if (a != axis) next[a] = std::clamp(next[a], -palm_half_[a], palm_half_[a]);
    double d;
    Eigen::Vector3d m;
    if (objects_->surface_near(object, o + R_W * next, reach, d, m) && d > depth) {
      q = next, depth = d, n = m;
    } else {
      step *= 0.5;
    }
  }
  return true;
}

void SpringHand::probe_rows(double reach, bool touching, std::vector<Row>& rows) const {
  for (int g = 0; g < num_geoms(); ++g) {
    const Eigen::Isometry3d T = geom_pose(g);
    const Eigen::Matrix3d R_W = T.linear();
    const Eigen::Vector3d o = T.translation();
    for (int i = 0; i < objects_->object_count(); ++i) {
      const double mu =
          std::sqrt(std::max(config_.friction_static, 0.0) * std::max(objects_->object_friction_static(i), 0.0));
      auto add = [&](const Eigen::Vector3d& p, const Eigen::Vector3d& n, double depth) {
        if (!(touching && depth > 0)) rows.push_back({p, n, depth, mu, g});  // ODE's contacts have the touching parts
      };
      // A point inside one of the palm's flat faces, outside the object, is held apart along the face's
      // normal by its gap along it (ODE's ray from the point): a flat face meets a peak, a ridge or a
      // curved flank there as ODE's box contacts take it once it touches, along the face's normal,
      // whatever the object's own normal at the point's nearest. That one, at a grid point beside the
      // bunny's top peak, stood 56 degrees from ODE's: the model let the stylus slide down the flank,
      // 5 mm deeper at a third of the force, and ODE's contact then pushed it back out (+8.5e-4 J,
      // LateModelsPressHoldLift spring_movable_bunny). Nothing under the point within reach: no row
      // (the face's point over what it would meet has it). A point inside the object, or on the
      // face's border (the palm's edge), is held along the object's normal.
      const auto add_on_face = [&](int face, const Eigen::Vector3d& p, const Eigen::Vector3d& n, double depth) {
        if (depth > 0) return add(p, n, depth);
        const Eigen::Vector3d n_face = (face % 2 ? -1.0 : 1.0) * R_W.col(face / 2);
        Eigen::Vector3d hit, m;
        if (objects_->ray_hit(i, p, p - reach * n_face, hit, m)) add(p, n_face, -(hit - p).norm());
      };
      std::array<int, 6> best_on_face;
      std::array<double, 6> best_depth{};
      best_on_face.fill(-1);
      for (std::size_t k = 0; k < probes_G_[g].size(); ++k) {
        const Probe& probe = probes_G_[g][k];
        const Eigen::Vector3d centre = o + R_W * probe.q_G;
        double depth;
        Eigen::Vector3d n;
        if (!objects_->surface_near(i, centre, reach + probe.radius, depth, n)) continue;
        // A sphere's point nearest the surface, and how deep that is; a face's point (its grid lies
        // inside it).
        if (probe.face >= 0)
          add_on_face(probe.face, centre, n, depth);
        else
          add(centre - probe.radius * n, n, depth + probe.radius);
        if (probe.face >= 0 && (best_on_face[probe.face] < 0 || depth > best_depth[probe.face]))
          best_on_face[probe.face] = static_cast<int>(k), best_depth[probe.face] = depth;
      }
      for (int f = 0; f < 6; ++f) {
        if (best_on_face[f] < 0) continue;
        Eigen::Vector3d q = probes_G_[g][best_on_face[f]].q_G, n;
        double depth;
        if (!deepest_on_face(f, o, R_W, i, reach, q, depth, n)) continue;
        bool inside = true;
        for (int a = 0; a < 3; ++a)
          if (a != f / 2 && std::abs(q[a]) >= palm_half_[a]) inside = false;
        if (inside)
          add_on_face(f, o + R_W * q, n, depth);
        else
          add(o + R_W * q, n, depth);
      }
    }
  }
}

void SpringHand::finger_joints(const std::vector<Row>& rows, Eigen::MatrixXd& J_q, Eigen::MatrixXd& C_q) const {
  const int c = static_cast<int>(rows.size());
  const SpringHandParams& prm = rig_->params();
  // Per row, its three directions' motion per joint angle of its finger (the joints between the palm
  // and its phalanx), and per finger the joints' stiffness: their springs and, through the distal's
  // end, the fingertip's.
  J_q = Eigen::MatrixXd::Zero(3 * c, kHandJointDofs);
  std::array<bool, kHandFingers> touched{};
  for (int i = 0; i < c; ++i) {
    const Row& r = rows[i];
    if (r.geom < 1) continue;
    const int phalanx = r.geom - 1, f = phalanx / 3, segment = phalanx % 3;
    touched[f] = true;
    const Eigen::Matrix<double, 3, 6> rows_i = contact_rows(r.n, Eigen::Vector3d::Zero());
    for (int k = 0; k <= segment + 1; ++k) {  // abduction and flexion at the base, then one per segment
      const int dof = 4 * f + k;
      J_q.block<3, 1>(3 * i, dof) =
          rows_i.leftCols<3>() * rig_->joint_axis_W(dof).cross(r.p - rig_->joint_anchor_W(dof));
    }
  }
  C_q = Eigen::MatrixXd::Zero(kHandJointDofs, kHandJointDofs);
  for (int f = 0; f < kHandFingers; ++f) {
    if (!touched[f]) continue;
    Eigen::Matrix<double, 3, 4> J_tip;
    for (int k = 0; k < 4; ++k)
      J_tip.col(k) = rig_->joint_axis_W(4 * f + k).cross(rig_->tip_W(f) - rig_->joint_anchor_W(4 * f + k));
    const Eigen::Matrix4d K_q = prm.joint.k * Eigen::Matrix4d::Identity() + prm.tip.k * J_tip.transpose() * J_tip;
    C_q.block<4, 4>(4 * f, 4 * f) = K_q.inverse();
  }
}

bool SpringHand::linearize_through_springs(HandleLinearization& out) const {
  // The springs' stiffness on the hand, K_s = -dF/dx (the palm's and the fingertips'), in the handles'
  // coordinates (translation, rotation vector about the handle's origin).
  Eigen::Matrix<double, 6, 6> K_s = -out.K;
  K_s = 0.5 * (K_s + K_s.transpose()).eval();
  const Eigen::LLT<Eigen::Matrix<double, 6, 6>> K_llt(K_s);
  if (K_llt.info() != Eigen::Success) return false;
  // How far the handle stands from the spring hand, delta: the springs' stretch, F = -K_s delta, with
  // the handle moving as the hand does (with the dampers' part the rows moved b/k times the hand's
  // velocity, 3 mm at 0.1 m/s, as the hand rocked on the bunny).
  const Eigen::Vector3d x0 = handles_[0].p_WH;
  std::vector<HandleState> moving = handles_;
  const dReal* v_s = dBodyGetLinearVel(rig_->palm_body());
  const dReal* w_s = dBodyGetAngularVel(rig_->palm_body());
  moving[0].w_WH = Eigen::Vector3d(w_s[0], w_s[1], w_s[2]);
  moving[0].v_WH = Eigen::Vector3d(v_s[0], v_s[1], v_s[2]) + moving[0].w_WH.cross(x0 - rig_->palm_position());
  const Eigen::Matrix<double, 6, 1> delta = -K_llt.solve(reaction(moving));
  // The dampers beside the springs, D_s = -dF/dv, and the handle's velocity they see against a hand
  // the rows hold still.
  Eigen::Matrix<double, 6, 6> D_s = -out.D;
  D_s = 0.5 * (D_s + D_s.transpose()).eval();
  Eigen::Matrix<double, 6, 1> v0;
  v0 << handles_[0].v_WH, handles_[0].w_WH;
  const Eigen::Matrix<double, 6, 1> offset = delta + K_llt.solve(D_s * v0);
  if (!offset.allFinite()) return false;
  out.F0.setZero();
  out.K.setZero();
  out.D.setZero();
  HandleContactModel& m = out.contacts;
  m = HandleContactModel{};
  // The rows: the last ODE step's contacts (once per point and normal: ODE repeats them), the world's
  // law; then the hand's probes within reach of the handle outside the objects, the nearest first
  // (probe_rows). The probes alone (the objects' distance fields) missed ODE's contacts by 0.6 mm and
  // 50 degrees on the bunny, and gave half the law.
  std::vector<Row> rows;
  auto add_contact = [&](const OdeHandContact& k, const Eigen::Vector3d& p, double depth, double apart) {
    const bool repeated = std::any_of(rows.begin(), rows.end(), [&](const Row& r) {
      return r.geom == std::max(k.geom, 0) && (r.p - p).squaredNorm() < apart * apart && r.n.dot(k.n_W) > 0.99;
    });
    if (!repeated) rows.push_back({p, k.n_W, depth, k.mu, std::max(k.geom, 0)});
  };
  for (const OdeHandContact& k : contacts_) add_contact(k, k.p_W, k.depth_m, 1e-3);
  // A contact of the last kHeldSteps steps that this one lacks, carried with its geom (its depth by how
  // far its point moved along the normal): a hand resting on the bunny loses a contact for a step now
  // and then, and the probes' rows that took its place there (the distance field's, 0.6 mm and 50
  // degrees off ODE's) kicked the stylus 0.5 mm each time, +1e-4 J.
  for (const Held& held : previous_) {
    const Eigen::Vector3d p = geom_pose(held.contact.geom) * held.p_G;
    add_contact(held.contact, p, held.contact.depth_m - held.contact.n_W.dot(p - held.contact.p_W), kHeldApart_m);
  }
  const std::ptrdiff_t touching =
      std::min<std::ptrdiff_t>(static_cast<std::ptrdiff_t>(rows.size()), kMaxLinearizedContacts);
  if (objects_)
    probe_rows(kLookahead_m + delta.head<3>().norm() + kHandReach_m * delta.tail<3>().norm(), touching > 0, rows);
  if (rows.size() > static_cast<std::size_t>(kMaxLinearizedContacts)) {
    std::partial_sort(rows.begin() + touching, rows.begin() + kMaxLinearizedContacts, rows.end(),
                      [](const Row& a, const Row& b) { return a.depth > b.depth; });
    rows.resize(kMaxLinearizedContacts);
  }
  const int c = static_cast<int>(rows.size());
  if (c == 0) return true;
  const double h = dt_s_;
  Eigen::MatrixXd J(3 * c, 6);
  m.u0.resize(3 * c);
  m.bias = Eigen::VectorXd::Zero(c);
  m.mu.resize(c);
  for (int i = 0; i < c; ++i) {
    const Row& r = rows[i];
    J.middleRows<3>(3 * i) = contact_rows(r.n, r.p - x0);
    // The point on the massless hand held at the handle (moved by the offset from the spring hand):
    // its gap, which the step may close by at most u h.
    m.u0.segment<3>(3 * i) = J.middleRows<3>(3 * i) * offset / h;
    m.u0[3 * i] -= r.depth / h;
    m.mu[i] = r.mu;
  }
  // A finger's joints give way too, from where their springs would hold them (the tracked angles).
  Eigen::MatrixXd J_q, C_q;
  finger_joints(rows, J_q, C_q);
  m.u0 += J_q * (tracked_angles(handles_).vector() - rig_->joint_angles().vector()) / h;
  // Row impulses lambda over the step: the massless hand takes J^T lambda / h and gives way
  // K_s^-1 J^T lambda / h, and the handle feels what the rows push (G = J^T / h). The dampers add
  // K_s^-1 D_s (v - v0) to the hand's way in. The small diagonal is the rows' own stiffness, far above
  // the springs': it keeps W definite with more rows than six.
  m.G = J.transpose() / h;
  m.U_K = J / h;
  m.U_D = J * K_llt.solve(D_s) / h;
  m.W = J * K_llt.solve(J.transpose()) / (h * h);
  m.W = 0.5 * (m.W + m.W.transpose());
  m.W += J_q * C_q * J_q.transpose() / (h * h);
  m.W.diagonal().array() += 1.0 / (kContactStiffness * h * h);
  const PgsResult solved = solve_contacts_pgs(ContactProblem{m.W, m.u0, m.bias, m.mu});
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
  if (num_handles() == 1 && !config_.body_step_model) return linearize_through_springs(out);
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
