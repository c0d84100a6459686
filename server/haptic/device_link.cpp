#include "server/haptic/device_link.hpp"

#include <algorithm>
#include <stdexcept>


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
    if (link.output == ForceOutput::finger_lines && link.handles != 6 && link.handles != 16)
      throw std::runtime_error("devices." + d.name + ": finger_lines output needs a hand with fingertip or phalanx "
                               "handles");
  }
  link.gains = coupling_gains_for(d.stiffness_n_m, d.workspace.scale, 1.0 / haptic_rate_hz);
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
  const Eigen::Matrix3d R_DW = link.map.R_WD.toRotationMatrix().transpose();
  double along[5] = {0, 0, 0, 0, 0};
  Eigen::Vector3d line_D[5];
  for (int f = 0; f < 5; ++f) {
    const int d = distal_frame(link.handles, f);
    const Eigen::Quaterniond q_frame_W = device_W[d].q_W * link.map.handle_q_F[d].conjugate();
    line_D[f] = R_DW * (q_frame_W * link.actuator_line_F);
  }
  for (int j = 0; j < link.handles; ++j) {
    const int f = finger_of_frame(link.handles, j);
    if (f >= 0) along[f] += w[j].f_D.dot(line_D[f]);
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
