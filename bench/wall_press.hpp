#pragma once
// The scripted interaction of `haptic-bench contact` and `haptic-bench haptic_rate`: the
// simulated stylus presses the stylus scene's hand into a static box (a wall) placed a few
// millimetres under the hand's lowest flesh, then lifts it off (offline mode, deterministic).
#include <Eigen/Core>
#include <string>

#include "server/offline/offline_run.hpp"

namespace hapticd::bench {

// Half-cosine ramps (continuous commanded velocity), device space, straight down (-z):
// settle, down by depth over ramp, hold, back up over ramp, rest.
struct PressProfile {
  double settle_s = 0.5, ramp_s = 1.0, hold_s = 1.0, rest_s = 0.5;
  double depth_m = 0.02;
  double total_s() const { return settle_s + 2 * ramp_s + hold_s + rest_s; }
  // The pressed part of the press (down and held): where penetration is sampled for its RMS.
  double pressed_from_s() const { return settle_s; }
  double pressed_to_s() const { return settle_s + ramp_s + hold_s; }
  // The commanded tip's displacement from its start at t, m (device space).
  Eigen::Vector3d offset(double t_s) const;
};
// The project's press (clients/sim/trajectory.hpp: 0.5 s, 2 cm down over 1 s, 1 s held, up over 1 s,
// 0.5 s), and a short one for smoke runs (0.05 s, 2 cm down over 0.5 s, 0.1 s held, up, 0.05 s: at
// most twice the default press's speed; at seven times (2 cm over 0.15 s) 30 Hz constraint contact
// penetrates deeper than penalty, measured 5.8 mm against 3.1 mm: a 30 Hz step then carries the skin
// past the 2 mm speculative margin). It presses as deep as the default: 1 cm went 3 mm past the box's
// top, which the light served hand barely reached (0.04 N RMS).
PressProfile default_press();
PressProfile tiny_press();

// The scene at `path` with its objects replaced by one static box whose top lies `gap_m`
// (world) under the lowest node of the first hand at its pose; hands at `hand_tets` (0: the
// scene's). The box is 30 x 30 cm, 4 cm thick, centred under the hand.
world::SceneDesc wall_scene(const std::string& path, int hand_tets, double gap_m);

struct PressRun {
  offline::OfflineTrace trace;
  // Deepest skin point inside the wall (World snapshot max_penetration_m, clamped at 0) after
  // each visual step: the largest over the run, and the RMS over the steps that end while
  // the press is down or held (PressProfile::pressed_*), m.
  double penetration_max_m = 0, penetration_rms_m = 0;
};
// As run_offline, sampling the world's penetration after every visual step.
PressRun run_press(offline::OfflineLoops& loops, offline::OfflineDevice& device, long ticks, const PressProfile& press);

// The simulated stylus at the hand's handle following the press.
offline::SimulatedStylus press_stylus(const offline::OfflineLoops& loops, const PressProfile& press,
                                      const sim::DeviceParams& params);

}  // namespace hapticd::bench
