#include "server/haptic/virtual_coupling.hpp"

#include <algorithm>
#include <cmath>

#include "hand_models/rigid_handle.hpp"

namespace hapticd {
namespace {

// A proxy faster than this has diverged (no hand moves a handle at 20 m/s).
constexpr double kMaxProxySpeed_m_s = 20.0;
// Device velocity: first-order low-pass of the pose differences (about 150 Hz at 1 kHz).
constexpr double kVelocityFilter = 0.6;

// Limits |v| to `limit`; true if it had to.
bool clamp_norm(Eigen::Vector3d& v, double limit) {
  const double n = v.norm();
  if (n <= limit) return false;
  v *= limit / n;
  return true;
}

}  // namespace

DeviceMap::DeviceMap() {
  for (int j = 0; j < kMaxHapticHandles; ++j) handle_p_F[j].setZero(), handle_q_F[j].setIdentity();
}

DeviceMap::DeviceMap(double s, const Eigen::Vector3d& offset, const Eigen::Quaterniond& R) : DeviceMap() {
  scale = s;
  offset_W = offset;
  R_WD = R;
}

HapticPose DeviceMap::to_world(int j, const Eigen::Vector3d& p_D, const Eigen::Quaterniond& q_D) const {
  const HapticPose frame = to_world(p_D, q_D);
  return {frame.p_W + frame.q_W * handle_p_F[j], (frame.q_W * handle_q_F[j]).normalized()};
}

HapticPose DeviceMap::to_world(const Eigen::Vector3d& p_D, const Eigen::Quaterniond& q_D) const {
  return {offset_W + scale * (R_WD * p_D), (R_WD * q_D).normalized()};
}

CouplingGains coupling_gains_for(double device_stiffness_n_m, double scale, double period_s) {
  CouplingGains g;
  const double s2 = scale * scale;
  g.k_n_m = device_stiffness_n_m / s2;
  g.b_ns_m = std::max(1.5 * 0.5 * device_stiffness_n_m * period_s, 0.5) / s2;
  return g;
}

void ProxyHand::configure(int handles, const double* mass_kg, const Eigen::Matrix3d* inertia_B,
                          const CouplingGains& gains, const DeviceLimits& limits, const DeviceMap& map) {
  handles_ = std::clamp(handles, 0, kMaxHapticHandles);
  gains_ = gains;
  safe_k_n_m_ = kSafeStiffness * gains_.k_n_m;
  safe_k_nm_rad_ = kSafeStiffness * gains_.k_nm_rad;
  limits_ = limits;
  map_ = map;
  for (int j = 0; j < handles_; ++j) {
    mass_[j] = mass_kg[j];
    inertia_B_[j] = inertia_B[j];
    // Critical damping of the proxy on coupling and safe spring together (2 sqrt(k m), the
    // rotation with the inertia's trace), and at least b_c k_safe / k_c (the device's port passive).
    const auto damping = [](double k_c, double b_c, double k_s, double inertia) {
      return std::max(2.0 * std::sqrt((k_c + k_s) * inertia) - b_c, k_c > 0 ? b_c * k_s / k_c : 0.0);
    };
    safe_b_ns_m_[j] = damping(gains_.k_n_m, gains_.b_ns_m, safe_k_n_m_, mass_[j]);
    safe_b_nms_rad_[j] = damping(gains_.k_nm_rad, gains_.b_nms_rad, safe_k_nm_rad_, inertia_B_[j].trace());
  }
  const int n = 6 * handles_;
  A_.resize(n, n);
  b_.resize(n);
  x_rel_.resize(n);
  v_next_.resize(n);
  lu_ = Eigen::PartialPivLU<HapticMatrix>(n);
  have_device_ = false;
  for (int j = 0; j < kMaxHapticHandles; ++j) {
    v_[j].setZero(), w_[j].setZero(), v_dev_[j].setZero(), w_dev_[j].setZero();
    last_f_D_[j].setZero(), last_tau_D_[j].setZero();
    energy_in_[j] = 0;
  }
}

void ProxyHand::reset() {
  ++resets_;
  resync();
  for (int j = 0; j < handles_; ++j) last_f_D_[j].setZero(), last_tau_D_[j].setZero(), energy_in_[j] = 0;
}

void ProxyHand::resync() {
  for (int j = 0; j < handles_; ++j) {
    proxy_[j] = device_[j];
    v_[j].setZero(), w_[j].setZero(), v_dev_[j].setZero(), w_dev_[j].setZero();
  }
}

void ProxyHand::set_device_pose(int j, const Eigen::Vector3d& p_D, const Eigen::Quaterniond& q_D) {
  if (j >= 0 && j < handles_) pending_[j] = map_.to_world(j, p_D, q_D);
}

bool ProxyHand::commit_sample(double t_s, double resync_gap_s) {
  const double dt = t_s - t_dev_;
  const bool resync_now = !have_device_ || !(dt <= resync_gap_s) || dt < 0;
  for (int j = 0; j < handles_; ++j) {
    if (!resync_now && dt > 0) {
      const Eigen::Vector3d v = (pending_[j].p_W - device_[j].p_W) / dt;
      const Eigen::Vector3d w = rotation_difference(pending_[j].q_W, device_[j].q_W) / dt;
      v_dev_[j] += kVelocityFilter * (v - v_dev_[j]);
      w_dev_[j] += kVelocityFilter * (w - w_dev_[j]);
    }
    device_[j] = pending_[j];
  }
  t_dev_ = t_s;
  have_device_ = true;
  if (resync_now) resync();
  return resync_now;
}

void ProxyHand::integrate(const HapticModel& model, double dt, double lookahead_s, double model_weight) {
  if (handles_ == 0 || !have_device_) return;
  const double weight = std::clamp(model_weight, 0.0, 1.0);
  const bool use_model = model.handles == handles_ && weight > 0;
  const double safe = 1.0 - weight;  // the safe model's share
  // seed 004 section 3: implicit Euler of the proxies under F* and the coupling, F*
  // taken at the pose extrapolated to the model's step end, x + tau v' (tau >= h):
  //   [M - h D - h tau K + h B_c + h^2 K_c] v' = M v + h [F0 + K (x - x0) - D v0 + K_c (x_dev - x) + B_c v_dev].
  const double tau = std::max(lookahead_s, dt);
  // A model that arrives after its step's end (the visual step took longer than
  // the step it simulated) has its anchor carried along by the handle's
  // velocity for the time since: the flesh kept moving meanwhile.
  const double late = std::max(0.0, -lookahead_s);
  A_.setZero();
  b_.setZero();
  for (int j = 0; j < handles_; ++j) {
    const Eigen::Matrix3d R = proxy_[j].q_W.toRotationMatrix();
    const Eigen::Matrix3d I_W = R * inertia_B_[j] * R.transpose();
    A_.block<3, 3>(6 * j, 6 * j).diagonal().array() += mass_[j] + dt * gains_.b_ns_m + dt * dt * gains_.k_n_m;
    A_.block<3, 3>(6 * j + 3, 6 * j + 3) += I_W;
    A_.block<3, 3>(6 * j + 3, 6 * j + 3).diagonal().array() += dt * gains_.b_nms_rad + dt * dt * gains_.k_nm_rad;
    b_.segment<3>(6 * j) = mass_[j] * v_[j] + dt * (gains_.k_n_m * (device_[j].p_W - proxy_[j].p_W) +
                                                     gains_.b_ns_m * v_dev_[j]);
    b_.segment<3>(6 * j + 3) =
        I_W * w_[j] + dt * (gains_.k_nm_rad * rotation_difference(device_[j].q_W, proxy_[j].q_W) +
                            gains_.b_nms_rad * w_dev_[j]);
    if (safe > 0) {
      // The safe model, implicit like the coupling: spring and damper toward the device.
      const double k = safe * safe_k_n_m_, b = safe * safe_b_ns_m_[j];
      const double k_rot = safe * safe_k_nm_rad_, b_rot = safe * safe_b_nms_rad_[j];
      A_.block<3, 3>(6 * j, 6 * j).diagonal().array() += dt * b + dt * dt * k;
      A_.block<3, 3>(6 * j + 3, 6 * j + 3).diagonal().array() += dt * b_rot + dt * dt * k_rot;
      b_.segment<3>(6 * j) += dt * (k * (device_[j].p_W - proxy_[j].p_W) + b * v_dev_[j]);
      b_.segment<3>(6 * j + 3) += dt * (k_rot * rotation_difference(device_[j].q_W, proxy_[j].q_W) + b_rot * w_dev_[j]);
    }
    if (use_model) {
      x_rel_.segment<3>(6 * j) = proxy_[j].p_W - model.x0[j].p_W - late * model.v0[j];
      x_rel_.segment<3>(6 * j + 3) = rotation_difference(proxy_[j].q_W, model.x0[j].q_W) - late * model.w0[j];
    }
  }
  if (use_model) {
    const double h = weight * dt;
    A_.noalias() -= h * model.D;
    A_.noalias() -= (h * tau) * model.K;
    b_.noalias() += h * model.F0;
    b_.noalias() += h * (model.K * x_rel_);
    // - h D v0: D couples the handles, so handle j's anchor velocity acts through its columns of D on
    // all 6m rows, not only on handle j's.
    for (int j = 0; j < handles_; ++j) {
      b_.noalias() -= h * model.D.middleCols<3>(6 * j) * model.v0[j];
      b_.noalias() -= h * model.D.middleCols<3>(6 * j + 3) * model.w0[j];
    }
  }
  bool ok = A_.allFinite() && b_.allFinite();
  if (ok) {
    lu_.compute(A_);
    v_next_.noalias() = lu_.solve(b_);
    ok = v_next_.allFinite();
    for (int j = 0; ok && j < handles_; ++j) ok = v_next_.segment<3>(6 * j).norm() < kMaxProxySpeed_m_s;
  }
  if (!ok) {
    // Safety (DESIGN.md section 5): a non-finite or absurd state never propagates;
    // the proxies restart on the device and the force drops to zero at once.
    reset();
    return;
  }
  for (int j = 0; j < handles_; ++j) {
    v_[j] = v_next_.segment<3>(6 * j);
    w_[j] = v_next_.segment<3>(6 * j + 3);
    proxy_[j].p_W += dt * v_[j];
    proxy_[j].q_W = rotate_by(proxy_[j].q_W, dt * w_[j]);
  }
}

ReplyWrench ProxyHand::reply(int j, double output_scale, double dt_since_last_s) {
  ReplyWrench r;
  if (j < 0 || j >= handles_ || !have_device_) return r;
  // The coupling wrench on the proxy; the device feels it reversed (f_D = s R^T f_W keeps power equal).
  const Eigen::Vector3d f_W = gains_.k_n_m * (device_[j].p_W - proxy_[j].p_W) + gains_.b_ns_m * (v_dev_[j] - v_[j]);
  const Eigen::Vector3d tau_W = gains_.k_nm_rad * rotation_difference(device_[j].q_W, proxy_[j].q_W) +
                                gains_.b_nms_rad * (w_dev_[j] - w_[j]);
  const Eigen::Matrix3d R_DW = map_.R_WD.toRotationMatrix().transpose();
  // About the frame's origin: the handle sits at r = q_frame handle_p_F from it.
  const Eigen::Vector3d r_W = device_[j].q_W * (map_.handle_q_F[j].conjugate() * map_.handle_p_F[j]);
  Eigen::Vector3d f = -output_scale * map_.scale * (R_DW * f_W);
  Eigen::Vector3d tau = -output_scale * (R_DW * (tau_W + r_W.cross(f_W)));
  if (!f.allFinite() || !tau.allFinite()) {
    reset();
    return r;
  }
  const double dt = std::clamp(dt_since_last_s, 1e-4, 0.1);
  // The port's power is f . v + tau . w with both about the handle; tau about
  // the frame's origin adds r x f, and v there lacks w x r: the same power.
  const Eigen::Vector3d v_D = R_DW * v_dev_[j] / map_.scale, w_D = R_DW * w_dev_[j];
  const Eigen::Vector3d r_D = R_DW * r_W / map_.scale;
  // Passivity controller: the damping that brings the observer's deficit back to zero this tick,
  // shared by the two channels in proportion to what each can take.
  const double v2 = v_D.squaredNorm() + kPassivityRotationWeight_m2 * w_D.squaredNorm();
  if (passivity_control_ && energy_in_[j] < 0 && v2 > 1e-10) {
    const double b = std::min(-energy_in_[j] / (dt * v2), kMaxPassivityDamping_ns_m);
    f -= b * v_D;  // at the handle, so about the frame's origin with its moment
    tau -= b * kPassivityRotationWeight_m2 * w_D + r_D.cross(b * v_D);
    ++passivity_actions_;
  }
  r.clamped = clamp_norm(f, limits_.max_force_n);
  r.clamped = clamp_norm(tau, limits_.max_torque_nm) || r.clamped;
  // Slew limit against the last reply: a jump of the target force becomes a ramp.
  Eigen::Vector3d df = f - last_f_D_[j], dtau = tau - last_tau_D_[j];
  const double torque_rate = limits_.max_force_rate_n_s * limits_.max_torque_nm / limits_.max_force_n;
  r.clamped = clamp_norm(df, limits_.max_force_rate_n_s * dt) || r.clamped;
  r.clamped = clamp_norm(dtau, torque_rate * dt) || r.clamped;
  r.f_D = last_f_D_[j] + df;
  r.tau_D = last_tau_D_[j] + dtau;
  last_f_D_[j] = r.f_D;
  last_tau_D_[j] = r.tau_D;
  // The device moving against the wrench it feels does work on the rendering.
  energy_in_[j] -= (r.f_D.dot(v_D) + (r.tau_D - r_D.cross(r.f_D)).dot(w_D)) * dt;
  if (r.clamped) ++clamps_;
  return r;
}

}  // namespace hapticd
