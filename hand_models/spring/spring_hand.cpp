#include "hand_models/spring/spring_hand.hpp"

#include <stdexcept>
#include <string>

namespace hapticd::hand::spring {

SpringHand::SpringHand(dWorldID world, dSpaceID space, const SpringHandConfig& config, const Eigen::Vector3d& p_W,
                       const Eigen::Quaterniond& q_W)
    : config_(config), handles_(1) {
  if (config.handles != 1)
    throw std::invalid_argument("the spring hand is driven by its palm only (1 handle), not " +
                                std::to_string(config.handles) + ": a glove's frames are not built yet");
  handles_[0].p_WH = p_W;
  handles_[0].q_WH = q_W.normalized();
  const SkeletonPose pose = skeleton_pose(angles_, config.left);
  for (int f = 0; f < kHandFingers; ++f) tips_H_[f] = pose.joints[f][3];
  rig_ = std::make_unique<SpringHandRig>(world, space, config.params, config.left, tracked());
}

TrackedHand SpringHand::tracked() const {
  TrackedHand t;
  t.p_W = handles_[0].p_WH;
  t.q_W = handles_[0].q_WH;
  t.angles = angles_;
  t.has_velocity = true;
  t.v_W = handles_[0].v_WH;
  t.w_W = handles_[0].w_WH;
  return t;
}

HandleInfo SpringHand::handle_info(int, int) const {
  HandleInfo info;
  info.mass_kg = config_.handle_mass_kg;
  // A ball of that mass and 1 cm radius.
  info.inertia_B = Eigen::Matrix3d::Identity() * 0.4 * config_.handle_mass_kg * 1e-4;
  return info;
}

bool SpringHand::set_target(int j, const HandleTarget& target) {
  if (j != 0 || !target.p_W.allFinite() || !target.q_W.coeffs().allFinite() || !target.v_W.allFinite() ||
      !target.w_W.allFinite() || !(target.q_W.norm() > 0))
    return false;
  HandleState& h = handles_[0];
  h.p_WH = target.p_W;
  h.q_WH = target.q_W.normalized();
  h.v_WH = target.v_W;
  h.w_WH = target.w_W;
  return true;
}

void SpringHand::place(const Eigen::Vector3d& p_W, const Eigen::Quaterniond& q_W) {
  HandleState& h = handles_[0];
  h = HandleState{};
  h.p_WH = p_W;
  h.q_WH = q_W.normalized();
  rig_->place(tracked());
}

void SpringHand::step(HandleLinearization*) { rig_->set_tracked(tracked()); }

void SpringHand::after_ode_steps() {
  if (rig_->sane(config_.max_speed_m_s, config_.max_distance_m)) return;
  ++resets_;
  rig_->place(tracked());
}

void SpringHand::recover(const Eigen::Vector3d& fallback_p_W, const Eigen::Quaterniond& fallback_q_W) {
  ++resets_;
  const HandleState& h = handles_[0];
  if (h.p_WH.allFinite() && h.q_WH.coeffs().allFinite()) {
    rig_->place(tracked());
  } else if (fallback_p_W.allFinite() && fallback_q_W.coeffs().allFinite()) {
    place(fallback_p_W, fallback_q_W);
  } else {
    place(Eigen::Vector3d::Zero(), Eigen::Quaterniond::Identity());
  }
}

Vector6d SpringHand::reaction(const HandleState& h) const {
  const SpringHandParams& p = config_.params;
  const dBodyID palm = rig_->palm_body();
  const Eigen::Vector3d p_s = rig_->palm_position();
  const dReal* v = dBodyGetLinearVel(palm);
  const dReal* w = dBodyGetAngularVel(palm);
  const Eigen::Vector3d v_s(v[0], v[1], v[2]), w_s(w[0], w[1], w[2]);
  Vector6d out;
  out.head<3>() = -p.palm_linear.k * (h.p_WH - p_s) - p.palm_linear.b * (h.v_WH - v_s);
  out.tail<3>() = -palm_restoring_torque(p.palm_torsional.k, rig_->palm_orientation(), h.q_WH) -
                  p.palm_torsional.b * (h.w_WH - w_s);
  for (int f = 0; f < kHandFingers; ++f) {
    const Eigen::Vector3d r = h.q_WH * tips_H_[f];
    const Eigen::Vector3d f_tip =
        linear_spring_force(p.tip, h.p_WH + r, rig_->tip_W(f), rig_->tip_velocity_W(f), h.v_WH + h.w_WH.cross(r));
    out.head<3>() -= f_tip;
    out.tail<3>() -= r.cross(f_tip);
  }
  return out;
}

bool SpringHand::linearize_next_step(HandleLinearization& out, ContactLinearization) {
  out = HandleLinearization{};
  out.x0 = handles_;
  const HandleState& x0 = handles_[0];
  out.F0 = reaction(x0);
  out.K = Matrix6d::Zero();
  out.D = Matrix6d::Zero();
  // Central differences: the reaction is linear in the velocities and in the position, and smooth
  // in the rotation (the model's rotation coordinate: a world rotation vector applied to q0).
  constexpr double e = 1e-6;
  for (int i = 0; i < 3; ++i) {
    HandleState a = x0, b = x0;
    a.p_WH[i] += e, b.p_WH[i] -= e;
    out.K.col(i) = (reaction(a) - reaction(b)) / (2 * e);
    a = x0, b = x0;
    a.q_WH = Eigen::Quaterniond(Eigen::AngleAxisd(e, Eigen::Vector3d::Unit(i))) * x0.q_WH;
    b.q_WH = Eigen::Quaterniond(Eigen::AngleAxisd(-e, Eigen::Vector3d::Unit(i))) * x0.q_WH;
    out.K.col(3 + i) = (reaction(a) - reaction(b)) / (2 * e);
    a = x0, b = x0;
    a.v_WH[i] += e, b.v_WH[i] -= e;
    out.D.col(i) = (reaction(a) - reaction(b)) / (2 * e);
    a = x0, b = x0;
    a.w_WH[i] += e, b.w_WH[i] -= e;
    out.D.col(3 + i) = (reaction(a) - reaction(b)) / (2 * e);
  }
  return out.F0.allFinite() && out.K.allFinite() && out.D.allFinite();
}

Eigen::VectorXd SpringHand::coupling_wrench() const { return reaction(handles_[0]); }

Eigen::Vector3d SpringHand::skin_point(int i) const {
  if (i <= 0) return rig_->palm_position();
  if (i <= kHandPhalanges) return rig_->phalanx_pose(i - 1).translation();
  return rig_->tip_W(i - 1 - kHandPhalanges);
}

}  // namespace hapticd::hand::spring
