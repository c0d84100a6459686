#pragma once
// A scene device bound to its world hand: what the haptic loop needs of it.
#include <array>
#include <cstdint>
#include <span>
#include <string>

#include "protocol/messages.hpp"
#include "server/haptic/virtual_coupling.hpp"
#include "server/world/world.hpp"

namespace hapticd::haptic {

// How a device's frames get their forces: each its own coupling wrench, or one
// force per finger along its actuator's line of action.
enum class ForceOutput { frames, finger_lines };

// A scene device bound to a world hand: everything the haptic loop needs of it.
struct DeviceLink {
  std::string name;
  protocol::DeviceKind kind = protocol::DeviceKind::kStylus;
  int hand = 0;
  bool left = false;  // the hand's side: a Hello naming a hand binds only to a link on a hand of that side
  int handles = 1;
  double mass_kg[kMaxHapticHandles]{};
  Eigen::Matrix3d inertia_B[kMaxHapticHandles];
  DeviceMap map;
  CouplingGains gains;
  DeviceLimits limits;
  // Gloves: a frame whose part of the hand touches nothing gets no force (seed
  // 002 section 4.5 practice): free-space coupling lag is not rendered.
  bool contact_gated = false;
  ForceOutput output = ForceOutput::frames;
  Eigen::Vector3d actuator_line_F = Eigen::Vector3d::UnitZ();  // finger_lines: unit, in the distal frame
  std::array<double, 4> feedback_a{0.0, 0.0, 0.0, 1.0};        // finger_lines: seed 002 section 4.5's a1..a4
};

// The finger (0 thumb .. 4 little) tracked frame j of a glove with `frames`
// frames belongs to, -1 for the palm; and the distal frame of finger f.
int finger_of_frame(int frames, int j);
int distal_frame(int frames, int f);

// Actuator-line output (a CyberGrasp-like glove, one cable per finger; seed 002
// section 4.5): f = -(a1 f_tau1 + a2 f_tau2 + a3 f_tau3 + a4 f_ls) . n, n the
// finger's actuator line of action (the distal frame's actuator_line_F), kept
// only if it pulls along it (a cable cannot push), clamped to the force limit,
// and rendered on the distal frame along n; the other frames get nothing.
// Taken from the wrenches the hand's frames get (the hand's on them, f_D and
// tau_D, opposite to the paper's forces on the simulated hand): f_ls, the
// finger's frame forces summed; f_tau k, flexion joint k's torque (its child
// segment's), the moment of everything beyond the joint about its axis (the
// segment frame's x) less the finger's force taken at the fingertip, as a force
// at the fingertip (flexion_torque_force). The joints and the fingertip stand
// on the standard skeleton (the frames are its segments' centres), so a1..a3
// need a 16-frame glove. `device_W` are the frames' handle poses in world
// (ProxyHand::device). In place on `w`.
void project_onto_finger_lines(const DeviceLink& link, const HapticPose* device_W, ReplyWrench* w);

// The link of scene device `d` in `world` at the given haptic rate: its hand's
// handle masses, the workspace map with each tracked frame's handle offset (a
// glove's frames are the palm and phalanx frames of the standard skeleton,
// hand_skeleton.hpp, and carry the handles built on them; a stylus's pose is
// its handle's), the coupling gains and the output limits. Throws
// std::runtime_error naming the device when its hand cannot be served.
DeviceLink make_device_link(const world::World& world, const world::DeviceDesc& d, double haptic_rate_hz);

// The Welcome that grants a session on `link`: its limits, the rate, and frame_ids[j] mapped to handle
// j. Written in place, allocating nothing (the haptic thread's handshake calls it).
void fill_welcome(const DeviceLink& link, std::uint64_t session_id, std::uint32_t rate_hz,
                  std::span<const std::uint16_t> frame_ids, protocol::Welcome& out);

}  // namespace hapticd::haptic
