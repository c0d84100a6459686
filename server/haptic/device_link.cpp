#include "server/haptic/device_link.hpp"

#include <algorithm>
#include <cmath>
#include <stdexcept>

#include "hand_models/spring/spring_law.hpp"

namespace hapticd::haptic {

DeviceLink make_device_link(const world::World& world, const world::DeviceDesc& d, double haptic_rate_hz) {
  DeviceLink link;
  link.name = d.name;
  link.kind = d.kind == world::DeviceKind::glove ? protocol::DeviceKind::kGlove : protocol::DeviceKind::kStylus;
  link.hand = world.find_hand(d.hand);
  if (link.hand < 0) throw std::runtime_error("devices." + d.name + ": no hand named " + d.hand);
  const hand::Hand& hand = world.hand(link.hand);
  link.left = hand.left();
  link.handles = hand.num_handles();
  if (link.handles > kMaxHapticHandles)
    throw std::runtime_error("devices." + d.name + ": " + std::to_string(link.handles) + " handles, at most " +
                             std::to_string(kMaxHapticHandles));
  link.map = DeviceMap(d.workspace.scale, d.workspace.offset_W, d.workspace.R_WD);
  // A glove tracks a frame per handle; a stylus, the palm's.
  const int tracked = d.kind == world::DeviceKind::glove ? link.handles : 1;
  for (int j = 0; j < link.handles; ++j) {
    const hand::HandleInfo info = hand.handle_info(j, tracked);
    link.mass_kg[j] = info.mass_kg;
    link.inertia_B[j] = info.inertia_B;
    link.map.handle_p_F[j] = info.in_frame.p_F;
    link.map.handle_q_F[j] = info.in_frame.q_F;
  }
  if (d.kind == world::DeviceKind::glove) {
    link.contact_gated = true;
    link.output =
        d.force_output == world::GloveForceOutput::finger_lines ? ForceOutput::finger_lines : ForceOutput::frames;
    link.actuator_line_F = d.actuator_line_F;
    link.feedback_a = d.feedback_a;
    if (link.output == ForceOutput::finger_lines && link.handles != 6 && link.handles != 16)
      throw std::runtime_error("devices." + d.name + ": finger_lines output needs a hand with fingertip or phalanx "
                               "handles");
  }
  link.gains = coupling_gains_for(d.stiffness_n_m, d.workspace.scale, 1.0 / haptic_rate_hz);
  if (d.kind == world::DeviceKind::glove) link.gains.b_nms_rad = glove_rotational_damping(link.gains, haptic_rate_hz);
  link.limits = {d.max_force_n, d.max_torque_nm, d.max_force_rate_n_s};
  return link;
}

void fill_welcome(const DeviceLink& link, std::uint64_t session_id, std::uint32_t rate_hz,
                  std::span<const std::uint16_t> frame_ids, protocol::Welcome& out) {
  out = protocol::Welcome{};
  out.session_id = session_id;
  out.rate_hz = rate_hz;
  out.force_limit_n = static_cast<float>(link.limits.max_force_n);
  out.torque_limit_nm = static_cast<float>(link.limits.max_torque_nm);
  out.max_force_rate_n_per_s = static_cast<float>(link.limits.max_force_rate_n_s);
  for (std::size_t j = 0; j < frame_ids.size(); ++j)
    out.frame_map.push_back({frame_ids[j], static_cast<std::uint16_t>(j)});
}

int finger_of_frame(int frames, int j) {
  if (j <= 0 || j >= frames) return -1;
  return frames == 6 ? j - 1 : (j - 1) / 3;
}

int distal_frame(int frames, int f) { return frames == 6 ? 1 + f : 3 + 3 * f; }

void project_onto_finger_lines(const DeviceLink& link, const HapticPose* device_W, ReplyWrench* w) {
  const Eigen::Matrix3d R_WD = link.map.R_WD.toRotationMatrix(), R_DW = R_WD.transpose();
  const std::array<double, 4>& a = link.feedback_a;
  const bool torques = link.handles == 1 + hand::kHandPhalanges && (a[0] > 0 || a[1] > 0 || a[2] > 0);
  double along[5] = {0, 0, 0, 0, 0};
  Eigen::Vector3d line_D[5];
  for (int f = 0; f < 5; ++f) {
    const int d = distal_frame(link.handles, f);
    const Eigen::Quaterniond q_frame_W = device_W[d].q_W * link.map.handle_q_F[d].conjugate();
    line_D[f] = R_DW * (q_frame_W * link.actuator_line_F);
  }
  for (int j = 0; j < link.handles; ++j) {
    const int f = finger_of_frame(link.handles, j);
    if (f >= 0) along[f] += a[3] * w[j].f_D.dot(line_D[f]);
  }
  if (torques) {
    // World frame: the hand's wrenches on the frames (f_D = s R_DW f_W keeps the port's power), the
    // segment frames (handle poses less their offsets) and, on the skeleton, the flexion joints'
    // axes and centres and the fingertip.
    for (int f = 0; f < 5; ++f) {
      const hand::FingerGeometry& g = hand::finger_geometry()[f];
      Eigen::Vector3d o[3], x[3], joint[3], force[3], torque[3];
      for (int k = 0; k < 3; ++k) {
        const int j = 1 + 3 * f + k;
        const Eigen::Quaterniond q_frame = device_W[j].q_W * link.map.handle_q_F[j].conjugate();
        o[k] = device_W[j].p_W;  // the handle's origin: its wrench's torque is about it
        const Eigen::Vector3d frame_origin = o[k] - q_frame * link.map.handle_p_F[j];
        // The flexion axis: the segment's side axis before the finger's roll about its bone (the
        // thumb's pronation; hand_skeleton.cpp), mirrored for a left hand.
        x[k] = q_frame * Eigen::Vector3d((link.left ? -1.0 : 1.0) * std::cos(g.roll), 0.0, -std::sin(g.roll));
        joint[k] = frame_origin - 0.5 * g.length[k] * (q_frame * Eigen::Vector3d::UnitY());
        force[k] = R_WD * w[j].f_D / link.map.scale;
        torque[k] = R_WD * w[j].tau_D;
      }
      const int d = 3 + 3 * f;  // the distal frame
      const Eigen::Vector3d tip =
          joint[2] + g.length[2] * ((device_W[d].q_W * link.map.handle_q_F[d].conjugate()) * Eigen::Vector3d::UnitY());
      std::array<Eigen::Vector3d, 3> f_tau;
      for (int k = 0; k < 3; ++k) {
        Eigen::Vector3d beyond = Eigen::Vector3d::Zero();
        double moment = 0;
        for (int m = k; m < 3; ++m) {
          moment += (torque[m] + (o[m] - joint[k]).cross(force[m])).dot(x[k]);
          beyond += force[m];
        }
        const double tau = -moment + (tip - joint[k]).cross(beyond).dot(x[k]);  // on the hand, as the paper's
        f_tau[k] = hand::spring::flexion_torque_force(x[k], joint[k], tip, tau);
      }
      const std::array<double, 4> a_torques{a[0], a[1], a[2], 0.0};
      const Eigen::Vector3d line_W = R_WD * line_D[f];
      along[f] += link.map.scale * hand::spring::glove_feedback(a_torques, f_tau, Eigen::Vector3d::Zero(), line_W);
    }
  }
  for (int j = 0; j < link.handles; ++j) {
    const bool clamped = w[j].clamped;
    w[j] = ReplyWrench{};
    w[j].clamped = clamped;
  }
  for (int f = 0; f < 5; ++f) {
    const double pull = std::min(std::max(along[f], 0.0), link.limits.max_force_n);
    ReplyWrench& out = w[distal_frame(link.handles, f)];
    out.f_D = pull * line_D[f];
    out.clamped = out.clamped || along[f] > link.limits.max_force_n;
  }
}

}  // namespace hapticd::haptic
