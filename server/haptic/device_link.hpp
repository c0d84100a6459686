#pragma once
// A scene device bound to its world hand: what the haptic loop needs of it.
#include <string>

#include "protocol/messages.hpp"
#include "server/haptic/virtual_coupling.hpp"
#include "server/world/world.hpp"

namespace hapticd {

// A scene device bound to a world hand: everything the haptic loop needs of it.
struct DeviceLink {
  std::string name;
  protocol::DeviceKind kind = protocol::DeviceKind::kStylus;
  int hand = 0;
  int handles = 1;
  double mass_kg[kMaxHapticHandles]{};
  Eigen::Matrix3d inertia_B[kMaxHapticHandles];
  DeviceMap map;
  CouplingGains gains;
  DeviceLimits limits;
};

// The link of scene device `d` in `world` at the given haptic rate: its hand's
// handle masses, the workspace map with each tracked frame's handle offset (a
// glove's frames are the palm and phalanx frames of the standard skeleton,
// hand_skeleton.hpp, and carry the handles built on them; a stylus's pose is
// its handle's), the coupling gains and the output limits. Throws
// std::runtime_error naming the device when its hand cannot be served.
DeviceLink make_device_link(const World& world, const DeviceDesc& d, double haptic_rate_hz);

}  // namespace hapticd
