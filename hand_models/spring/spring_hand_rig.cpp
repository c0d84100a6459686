#include "hand_models/spring/spring_hand_rig.hpp"

#include <Eigen/Eigenvalues>
#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdarg>
#include <cstdio>
#include <limits>
#include <mutex>
#include <stdexcept>
#include <string>

namespace hapticd::hand {

namespace {
std::atomic<long> ode_message_count{0};

void count_ode_message(int, const char*, va_list) { ode_message_count.fetch_add(1, std::memory_order_relaxed); }

[[noreturn]] void throw_ode_error(int errnum, const char* msg, va_list ap) {
  char text[256];
  std::vsnprintf(text, sizeof text, msg, ap);
  throw std::runtime_error("ODE error " + std::to_string(errnum) + ": " + text);
}
}  // namespace

long ode_messages() { return ode_message_count.load(std::memory_order_relaxed); }

void ensure_ode_for_this_thread() {
  static std::once_flag once;
  std::call_once(once, [] {
    dInitODE2(0);
    dSetMessageHandler(&count_ode_message);
    dSetErrorHandler(&throw_ode_error);
    dSetDebugHandler(&throw_ode_error);
  });
  thread_local bool allocated = false;
  if (!allocated) allocated = dAllocateODEDataForThread(dAllocateMaskAll) != 0;
}

}  // namespace hapticd::hand

namespace hapticd::hand::spring {
namespace {

// The point mass joining a base joint's two hinges (section 4.6.1): this share of the proximal
// phalanx's mass, in a sphere of half the base's flesh radius.
constexpr double kBaseMassShare = 0.1;

Eigen::Vector3d vec(const dReal* p) { return {p[0], p[1], p[2]}; }
Eigen::Quaterniond quat(const dReal* q) { return {q[0], q[1], q[2], q[3]}; }  // ODE: w, x, y, z

void set_pose(dBodyID b, const Eigen::Vector3d& p, const Eigen::Matrix3d& R) {
  dBodySetPosition(b, p.x(), p.y(), p.z());
  const Eigen::Quaterniond q(R);
  const dQuaternion dq = {q.w(), q.x(), q.y(), q.z()};
  dBodySetQuaternion(b, dq);
}

// The hinge of DoF `dof` in the hand frame: the axis of the rotation a small change of that angle
// turns the child segment by (R(q + e) R(q - e)^T), so the skeleton's conventions (mirroring,
// the thumb's roll) carry over as they are.
Eigen::Vector3d hinge_axis_in_hand(const HandJointAngles& q, int dof, bool left) {
  constexpr double e = 1e-6;
  const int finger = dof / 4, k = dof % 4;
  const int segment = 3 * finger + std::max(k - 1, 0);
  Eigen::Matrix<double, kHandJointDofs, 1> plus = q.vector(), minus = q.vector();
  plus[dof] += e;
  minus[dof] -= e;
  const Eigen::Matrix3d dR = skeleton_pose(HandJointAngles::from_vector(plus), left).R[segment] *
                             skeleton_pose(HandJointAngles::from_vector(minus), left).R[segment].transpose();
  const Eigen::AngleAxisd aa(dR);
  return aa.axis();
}

// The longest explicit step of a spring-damper (k, b) on inertia I: h^2 k / I + 2 h b / I <= 1.
double stable_step(double k, double b, double I) {
  if (!(I > 0)) return 0;
  const double w2 = k / I, c = b / I;
  if (w2 <= 0) return c > 0 ? 0.5 / c : std::numeric_limits<double>::infinity();
  return (-c + std::sqrt(c * c + w2)) / w2;
}

Eigen::Matrix3d inertia_W(dBodyID b) {
  dMass m;
  dBodyGetMass(b, &m);
  Eigen::Matrix3d I;
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c) I(r, c) = m.I[4 * r + c];
  const Eigen::Matrix3d R = quat(dBodyGetQuaternion(b)).toRotationMatrix();
  return R * I * R.transpose();
}

// Moment of inertia of bodies about the axis through `anchor`.
double inertia_about(std::initializer_list<dBodyID> bodies, const Eigen::Vector3d& anchor, const Eigen::Vector3d& a) {
  double I = 0;
  for (dBodyID b : bodies) {
    dMass m;
    dBodyGetMass(b, &m);
    const Eigen::Vector3d r = vec(dBodyGetPosition(b)) - anchor;
    I += a.dot(inertia_W(b) * a) + m.mass * r.cross(a).squaredNorm();
  }
  return I;
}

}  // namespace

SpringHandRig::SpringHandRig(dWorldID world, dSpaceID space, const SpringHandParams& params, bool left,
                             const TrackedHand& start)
    : params_(params), left_(left), tracked_(start), tracked_before_(start) {
  const SkeletonPose s = skeleton_pose(start.angles, left);
  const Eigen::Matrix3d R_W = start.q_W.normalized().toRotationMatrix();
  const auto to_W = [&](const Eigen::Vector3d& p_H) -> Eigen::Vector3d { return start.p_W + R_W * p_H; };
  const auto set_category = [](dGeomID g) {
    dGeomSetCategoryBits(g, kSpringHandCategory);
    dGeomSetCollideBits(g, ~kSpringHandCategory);
  };

  palm_ = dBodyCreate(world);
  {
    dMass m;
    const double lx = 2 * kPalmHalfWidth_m, ly = 2 * kPalmHalfLength_m, lz = 2 * kPalmHalfThickness_m;
    dMassSetBoxTotal(&m, params.density_kg_m3 * lx * ly * lz + params.palm_extra_mass_kg, lx, ly, lz);
    dBodySetMass(palm_, &m);
    total_mass_kg_ += m.mass;
    palm_geom_ = dCreateBox(space, lx, ly, lz);
    dGeomSetBody(palm_geom_, palm_);
    set_category(palm_geom_);
  }

  // A capsule is along its geom's z; the phalanx's body frame has the bone along y.
  dMatrix3 capsule_offset;
  dRFrom2Axes(capsule_offset, 1, 0, 0, 0, 0, -1);  // columns x = (1,0,0), y = (0,0,-1): z -> body y
  for (int f = 0; f < kHandFingers; ++f) {
    const FingerGeometry& g = finger_geometry()[f];
    for (int k = 0; k < 3; ++k) {
      const int i = 3 * f + k;
      const double r = 0.5 * (g.radius[k] + g.radius[k + 1]);
      const double length = k < 2 ? g.length[k] : g.length[k] - r;  // the distal's round end at the tip
      phalanx_[i] = dBodyCreate(world);
      dMass m;
      dMassSetCapsule(&m, params.density_kg_m3, 2, r, length);
      dBodySetMass(phalanx_[i], &m);
      total_mass_kg_ += m.mass;
      capsule_length_[i] = length;
      phalanx_geom_[i] = dCreateCapsule(space, r, length);
      dGeomSetBody(phalanx_geom_[i], phalanx_[i]);
      dGeomSetOffsetRotation(phalanx_geom_[i], capsule_offset);
      set_category(phalanx_geom_[i]);
      if (k == 0) {
        base_[f] = dBodyCreate(world);
        dMass mb;
        dMassSetSphereTotal(&mb, kBaseMassShare * m.mass, 0.5 * g.radius[0]);
        dBodySetMass(base_[f], &mb);
        total_mass_kg_ += mb.mass;
      }
    }
  }
  set_body_poses(start);
  update_tracked_tips();
  if (!params.gravity) {
    dBodySetGravityMode(palm_, 0);
    for (dBodyID b : base_) dBodySetGravityMode(b, 0);
    for (dBodyID b : phalanx_) dBodySetGravityMode(b, 0);
  }
  for (int f = 0; f < kHandFingers; ++f) {
    const Eigen::Vector3d tip_W = to_W(s.joints[f][3]);
    const Eigen::Isometry3d distal = phalanx_pose(3 * f + 2);
    tip_in_distal_[f] = distal.inverse() * tip_W;
    for (int k = 0; k < 4; ++k) {
      const int dof = 4 * f + k;
      dBodyID child = k == 0 ? base_[f] : phalanx_[3 * f + k - 1];
      dBodyID parent = k == 0 ? palm_ : k == 1 ? base_[f] : phalanx_[3 * f + k - 2];
      const Eigen::Vector3d anchor = to_W(s.joints[f][std::max(k - 1, 0)]);
      const Eigen::Vector3d axis = R_W * hinge_axis_in_hand(start.angles, dof, left);
      hinge_[dof] = dJointCreateHinge(world, nullptr);
      dJointAttach(hinge_[dof], child, parent);  // the angle and its torque: the child's about the axis
      dJointSetHingeAnchor(hinge_[dof], anchor.x(), anchor.y(), anchor.z());
      dJointSetHingeAxis(hinge_[dof], axis.x(), axis.y(), axis.z());
      angle_at_build_[dof] = start.angles.vector()[dof];
    }
  }
  for (Eigen::Vector3d& f : f_ls_) f.setZero();

  // Stability: each joint spring on what it turns with its parent held (the rest of the finger as
  // one body), each fingertip spring on the distal phalanx alone, the palm's on the palm alone.
  double h = std::numeric_limits<double>::infinity();
  for (int f = 0; f < kHandFingers; ++f) {
    const dBodyID p0 = phalanx_[3 * f], p1 = phalanx_[3 * f + 1], p2 = phalanx_[3 * f + 2];
    for (int k = 0; k < 4; ++k) {
      const int dof = 4 * f + k;
      const Eigen::Vector3d a = joint_axis_W(dof), c = joint_anchor_W(dof);
      const double I = k == 0   ? inertia_about({base_[f], p0, p1, p2}, c, a)
                       : k == 1 ? inertia_about({p0, p1, p2}, c, a)
                       : k == 2 ? inertia_about({p1, p2}, c, a)
                                : inertia_about({p2}, c, a);
      h = std::min(h, stable_step(params.joint.k, params.joint.b, I));
    }
    // The tip spring turns the distal phalanx about its joint with lever |d| (worst: d normal to it).
    const Eigen::Vector3d c = joint_anchor_W(4 * f + 3);
    const double d2 = (tip_W(f) - c).squaredNorm();
    const double I_tip = inertia_about({p2}, c, joint_axis_W(4 * f + 3));
    h = std::min(h, stable_step(params.tip.k * d2, params.tip.b * d2, I_tip));
  }
  dMass palm_mass;
  dBodyGetMass(palm_, &palm_mass);
  h = std::min(h, stable_step(params.palm_linear.k, params.palm_linear.b, palm_mass.mass));
  const Eigen::Matrix3d I_palm =
      Eigen::Map<const Eigen::Matrix<dReal, 3, 4, Eigen::RowMajor>>(palm_mass.I).leftCols<3>();
  h = std::min(h, stable_step(params.palm_torsional.k, params.palm_torsional.b,
                              Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d>(I_palm).eigenvalues().minCoeff()));
  max_stable_step_s_ = h;
}

void SpringHandRig::set_body_poses(const TrackedHand& t) {
  const SkeletonPose s = skeleton_pose(t.angles, left_);
  const Eigen::Matrix3d R_W = t.q_W.normalized().toRotationMatrix();
  set_pose(palm_, t.p_W, R_W);
  for (int f = 0; f < kHandFingers; ++f) {
    set_pose(base_[f], t.p_W + R_W * s.joints[f][0], R_W);
    for (int k = 0; k < 3; ++k) {
      const int i = 3 * f + k;
      const Eigen::Vector3d axis_H = (s.joints[f][k + 1] - s.joints[f][k]).normalized();
      set_pose(phalanx_[i], t.p_W + R_W * (s.joints[f][k] + 0.5 * capsule_length_[i] * axis_H), R_W * s.R[i]);
    }
  }
}

void SpringHandRig::place(const TrackedHand& t) {
  set_body_poses(t);
  reaction_sum_.setZero();
  const auto rest = [](dBodyID b) {
    dBodySetLinearVel(b, 0, 0, 0);
    dBodySetAngularVel(b, 0, 0, 0);
  };
  rest(palm_);
  for (dBodyID b : base_) rest(b);
  for (dBodyID b : phalanx_) rest(b);
  tracked_ = tracked_before_ = t;
  tracked_.q_W.normalize();
  tracked_before_.q_W.normalize();
  update_tracked_tips();
  steps_since_reading_ = 0;
  steps_between_readings_ = 1;
}

bool SpringHandRig::sane(double max_speed_m_s, double max_distance_m) const {
  const auto ok = [&](dBodyID b) {
    const Eigen::Vector3d p = vec(dBodyGetPosition(b)), v = vec(dBodyGetLinearVel(b)), w = vec(dBodyGetAngularVel(b));
    const Eigen::Quaterniond q = quat(dBodyGetQuaternion(b));
    return p.allFinite() && v.allFinite() && w.allFinite() && q.coeffs().allFinite() && v.norm() <= max_speed_m_s &&
           (p - tracked_.p_W).norm() <= max_distance_m;
  };
  bool all = ok(palm_);
  for (dBodyID b : base_) all = all && ok(b);
  for (dBodyID b : phalanx_) all = all && ok(b);
  return all;
}

SpringHandRig::~SpringHandRig() {
  for (dJointID j : hinge_)
    if (j) dJointDestroy(j);
  for (dGeomID g : phalanx_geom_)
    if (g) dGeomDestroy(g);
  if (palm_geom_) dGeomDestroy(palm_geom_);
  for (dBodyID b : phalanx_)
    if (b) dBodyDestroy(b);
  for (dBodyID b : base_)
    if (b) dBodyDestroy(b);
  if (palm_) dBodyDestroy(palm_);
}

void SpringHandRig::set_tracked(const TrackedHand& reading) {
  tracked_before_ = steps_since_reading_ > 0 ? tracked_ : reading;
  tracked_ = reading;
  tracked_.q_W.normalize();
  steps_between_readings_ = std::max(steps_since_reading_, 1);
  steps_since_reading_ = 0;
  reaction_sum_.setZero();
  update_tracked_tips();
}

void SpringHandRig::update_tracked_tips() {
  const SkeletonPose now = skeleton_pose(tracked_.angles, left_), before = skeleton_pose(tracked_before_.angles, left_);
  for (int f = 0; f < kHandFingers; ++f) tips_H_[f] = now.joints[f][3], tips_before_H_[f] = before.joints[f][3];
}

void SpringHandRig::apply_springs(double h) {
  const double interval = steps_between_readings_ * h;  // between the last two tracker readings, s
  const Eigen::Matrix<double, kHandJointDofs, 1> theta_t = tracked_.angles.vector(),
                                                 omega_t = (theta_t - tracked_before_.angles.vector()) / interval;
  const HandJointAngles theta_s = joint_angles();
  const Eigen::Matrix<double, kHandJointDofs, 1> omega_s = joint_rates(), theta_s_v = theta_s.vector();
  for (int dof = 0; dof < kHandJointDofs; ++dof) {
    torque_[dof] = joint_spring_torque(params_.joint, theta_t[dof], theta_s_v[dof], omega_s[dof], omega_t[dof]);
    dJointAddHingeTorque(hinge_[dof], torque_[dof]);
  }

  // The palm (section 4.3).
  const Eigen::Vector3d p_s = palm_position(), v_s = vec(dBodyGetLinearVel(palm_)),
                        w_s = vec(dBodyGetAngularVel(palm_));
  const Eigen::Quaterniond q_s = palm_orientation();
  const Eigen::Vector3d v_t = tracked_.has_velocity ? tracked_.v_W : (tracked_.p_W - tracked_before_.p_W) / interval;
  palm_force_ = linear_spring_force(params_.palm_linear, tracked_.p_W, p_s, v_s, v_t);
  // The spring palm's rotation over this step from its angular velocity (section 4.3's suggestion
  // for a simulator that has one), the tracked palm's between its readings.
  const Eigen::Quaterniond q_ws(
      Eigen::AngleAxisd(w_s.norm() * h, w_s.norm() > 0 ? Eigen::Vector3d(w_s.normalized()) : Eigen::Vector3d::UnitX()));
  const double w_t = tracked_.w_W.norm();
  const Eigen::Quaterniond q_wt =
      tracked_.has_velocity ? Eigen::Quaterniond(Eigen::AngleAxisd(
                                  w_t * h, w_t > 0 ? Eigen::Vector3d(tracked_.w_W / w_t) : Eigen::Vector3d::UnitX()))
                            : Eigen::Quaterniond(tracked_.q_W * tracked_before_.q_W.conjugate());
  palm_torque_ =
      palm_restoring_torque(params_.palm_torsional.k, q_s, tracked_.q_W) +
      palm_damping_torque(params_.palm_torsional.b, q_ws, q_wt, tracked_.has_velocity ? 1 : steps_between_readings_, h);
  reaction_sum_.head<3>() -= palm_force_;
  reaction_sum_.tail<3>() -= palm_torque_;
  dBodyAddForce(palm_, palm_force_.x(), palm_force_.y(), palm_force_.z());
  dBodyAddTorque(palm_, palm_torque_.x(), palm_torque_.y(), palm_torque_.z());

  // The fingertips (section 4.4), and f_ls of section 4.5: the same spring in the palm's frame.
  const Eigen::Matrix3d R_s = q_s.toRotationMatrix();
  for (int f = 0; f < kHandFingers; ++f) {
    const Eigen::Vector3d &tip_t_H = tips_H_[f], &tip_t0_H = tips_before_H_[f];
    const Eigen::Vector3d tip_t = tracked_.p_W + tracked_.q_W * tip_t_H,
                          tip_t0 = tracked_before_.p_W + tracked_before_.q_W * tip_t0_H;
    const Eigen::Vector3d tip_s = tip_W(f);
    dVector3 v;
    dBodyGetPointVel(phalanx_[3 * f + 2], tip_s.x(), tip_s.y(), tip_s.z(), v);
    const Eigen::Vector3d v_tip = vec(v);
    // With a measured palm velocity, the tracked tip moves with the palm, plus its fingers' motion.
    const Eigen::Vector3d v_tip_t = tracked_.has_velocity
                                        ? Eigen::Vector3d(tracked_.v_W + tracked_.w_W.cross(tip_t - tracked_.p_W) +
                                                          tracked_.q_W * ((tip_t_H - tip_t0_H) / interval))
                                        : Eigen::Vector3d((tip_t - tip_t0) / interval);
    const Eigen::Vector3d f_tip = linear_spring_force(params_.tip, tip_t, tip_s, v_tip, v_tip_t);
    dBodyAddForceAtPos(phalanx_[3 * f + 2], f_tip.x(), f_tip.y(), f_tip.z(), tip_s.x(), tip_s.y(), tip_s.z());
    reaction_sum_.head<3>() -= f_tip;
    reaction_sum_.tail<3>() -= (tip_t - tracked_.p_W).cross(f_tip);
    const Eigen::Vector3d v_rel_H = R_s.transpose() * (v_tip - v_s - w_s.cross(tip_s - p_s));
    f_ls_[f] = R_s * linear_spring_force(params_.tip, tip_t_H, R_s.transpose() * (tip_s - p_s), v_rel_H,
                                         (tip_t_H - tip_t0_H) / interval);
  }
  ++steps_since_reading_;
}

HandJointAngles SpringHandRig::joint_angles() const {
  Eigen::Matrix<double, kHandJointDofs, 1> q;
  for (int dof = 0; dof < kHandJointDofs; ++dof) q[dof] = angle_at_build_[dof] + dJointGetHingeAngle(hinge_[dof]);
  return HandJointAngles::from_vector(q);
}

Eigen::Matrix<double, kHandJointDofs, 1> SpringHandRig::joint_rates() const {
  Eigen::Matrix<double, kHandJointDofs, 1> w;
  for (int dof = 0; dof < kHandJointDofs; ++dof) w[dof] = dJointGetHingeAngleRate(hinge_[dof]);
  return w;
}

Eigen::Vector3d SpringHandRig::palm_position() const { return vec(dBodyGetPosition(palm_)); }
Eigen::Quaterniond SpringHandRig::palm_orientation() const { return quat(dBodyGetQuaternion(palm_)); }

Eigen::Isometry3d SpringHandRig::phalanx_pose(int phalanx) const {
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  T.linear() = quat(dBodyGetQuaternion(phalanx_[phalanx])).toRotationMatrix();
  T.translation() = vec(dBodyGetPosition(phalanx_[phalanx]));
  return T;
}

Eigen::Vector3d SpringHandRig::tip_W(int finger) const { return phalanx_pose(3 * finger + 2) * tip_in_distal_[finger]; }

Eigen::Matrix<double, 6, 6> SpringHandRig::composite_inertia(Eigen::Vector3d& com_offset_W) const {
  const Eigen::Vector3d o = palm_position();
  double m_total = 0;
  Eigen::Vector3d first_moment = Eigen::Vector3d::Zero();
  Eigen::Matrix3d I_o = Eigen::Matrix3d::Zero();
  const auto add = [&](dBodyID b) {
    dMass m;
    dBodyGetMass(b, &m);
    const Eigen::Vector3d r = vec(dBodyGetPosition(b)) - o;
    m_total += m.mass;
    first_moment += m.mass * r;
    I_o += inertia_W(b) + m.mass * (r.squaredNorm() * Eigen::Matrix3d::Identity() - r * r.transpose());
  };
  add(palm_);
  for (dBodyID b : base_) add(b);
  for (dBodyID b : phalanx_) add(b);
  com_offset_W = first_moment / m_total;
  Eigen::Matrix3d cx;
  cx << 0, -first_moment.z(), first_moment.y(), first_moment.z(), 0, -first_moment.x(), -first_moment.y(),
      first_moment.x(), 0;
  Eigen::Matrix<double, 6, 6> M;
  M << m_total * Eigen::Matrix3d::Identity(), -cx, cx, I_o;
  return M;
}

Eigen::Vector3d SpringHandRig::tip_velocity_W(int finger) const {
  const Eigen::Vector3d p = tip_W(finger);
  dVector3 v;
  dBodyGetPointVel(phalanx_[3 * finger + 2], p.x(), p.y(), p.z(), v);
  return vec(v);
}

Eigen::Vector3d SpringHandRig::joint_axis_W(int dof) const {
  dVector3 a;
  dJointGetHingeAxis(hinge_[dof], a);
  return vec(a);
}

Eigen::Vector3d SpringHandRig::joint_anchor_W(int dof) const {
  dVector3 a;
  dJointGetHingeAnchor(hinge_[dof], a);
  return vec(a);
}

double SpringHandRig::feedback(int finger, bool touching, const Eigen::Vector3d& n_W) const {
  if (!touching) return 0.0;
  const Eigen::Vector3d n = n_W.squaredNorm() > 0 ? Eigen::Vector3d(n_W.normalized())
                                                  : Eigen::Vector3d(phalanx_pose(3 * finger + 2).linear().col(2));
  const Eigen::Vector3d tip = tip_W(finger);
  std::array<Eigen::Vector3d, 3> f_tau;
  for (int k = 0; k < 3; ++k) {
    const int dof = 4 * finger + 1 + k;
    f_tau[k] = flexion_torque_force(joint_axis_W(dof), joint_anchor_W(dof), tip, torque_[dof]);
  }
  return glove_feedback(params_.feedback_a, f_tau, f_ls_[finger], n);
}

}  // namespace hapticd::hand::spring
