#include "server/haptic/device_link.hpp"

#include <stdexcept>

#include "hand_models/press_scenario.hpp"

namespace hapticd {

DeviceLink make_device_link(const World& world, const DeviceDesc& d, double haptic_rate_hz) {
  DeviceLink link;
  link.name = d.name;
  link.kind = d.kind == DeviceKind::glove ? protocol::DeviceKind::kGlove : protocol::DeviceKind::kStylus;
  link.hand = world.find_hand(d.hand);
  if (link.hand < 0) throw std::runtime_error("devices." + d.name + ": no hand named " + d.hand);
  const WorldHand& hand = world.hand(link.hand);
  const HandModel& model = *hand.model;
  link.handles = model.num_handles();
  if (link.handles > kMaxHapticHandles)
    throw std::runtime_error("devices." + d.name + ": " + std::to_string(link.handles) + " handles, at most " +
                             std::to_string(kMaxHapticHandles));
  for (int j = 0; j < link.handles; ++j) {
    link.mass_kg[j] = model.handles()[j].mass_kg;
    link.inertia_B[j] = model.handles()[j].inertia_B;
  }
  link.map = DeviceMap(d.workspace.scale, d.workspace.offset_W, d.workspace.R_WD);
  if (d.kind == DeviceKind::glove) {
    const std::vector<HandFrame> frames = procedural_handle_frames(hand.shape, link.handles);
    for (int j = 0; j < link.handles; ++j) {
      const FrameToHandle o = frame_to_handle(frames[j].p, frames[j].R, model.handles()[j]);
      link.map.handle_p_F[j] = o.p_F;
      link.map.handle_q_F[j] = o.q_F;
    }
  }
  link.gains = coupling_gains_for(d.stiffness_n_m, d.workspace.scale, 1.0 / haptic_rate_hz);
  link.limits = {d.max_force_n, d.max_torque_nm, d.max_force_rate_n_s};
  return link;
}

}  // namespace hapticd
