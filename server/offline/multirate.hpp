#pragma once
// The multi-rate experiment (seed 004 section 3): how far the force a device
// receives drifts from the force of a world stepped at every haptic tick when
// the visual loop runs slower, with the handle-space linearized model or with a
// zero-order hold of the last visual force between visual steps
// (HandleModelKind).
//
// Open loop: the reference run is closed (its simulated device feels the
// reference forces); every other run replays the device poses the reference
// recorded, tick by tick, whatever it renders. Both runs then see the same
// device input at every tick, and the error at a tick is the model's alone:
// the force the haptic loop renders against the reference's force for the same
// input. (Driving each run by the same device command instead would let the
// device's motion diverge with the rendered force, and the error would mix the
// model's with the device's response to it.)
#include <functional>
#include <limits>
#include <memory>
#include <string>
#include <vector>

#include "server/offline/offline_run.hpp"

namespace hapticd::offline {

// A scripted interaction: a scene and the simulated device that drives it.
struct Interaction {
  std::string name;
  world::SceneDesc scene;
  double seconds = 1.0;
  // Every run's rigid bodies first settle this long at the haptic period
  // (OfflineOptions::settle_s), so all runs start from the same world.
  double settle_s = 1.0;
  // The device of the reference run (closed loop), built for its loops (it may start at their handles).
  std::function<std::unique_ptr<OfflineDevice>(const OfflineLoops&)> device;
};

// The simulated stylus along sim::Trajectory::press (settle, 2 cm down over
// 1 s, hold; device space), starting where the scene's handle is.
Interaction stylus_press(world::SceneDesc scene, double seconds);
// `scene` with its rigid bodies made static, at rest where they stand.
world::SceneDesc with_rigid_bodies_fixed(world::SceneDesc scene);
// The same press with the scene's rigid bodies made static ("stylus_press_fixed"): nothing but the
// hand moves, so the world at the visual rate differs from the every-tick world only in the hand
// and its contacts, and the error is the rendering's own. On the movable bunny the 30 Hz world
// also lets the bunny slide under the held stylus and starts the contact a step late.
Interaction stylus_press_fixed(world::SceneDesc scene, double seconds);
// The simulated glove along sim::GloveTrajectory::grasp (rest, close into the
// power grasp over 1 s, hold), its palm starting on the palm handle; `frames`
// 16 (phalanges handles) or 6 (fingertips), the scene's first hand set to match.
Interaction glove_grasp(world::SceneDesc scene, double seconds, int frames);

struct ForceError {
  // Per tick, e = sqrt(sum over frames |f_D - f_D,ref|^2) (the force each frame
  // receives, device space); its RMS and largest value over the ticks, N.
  double rms_n = 0, max_n = 0;
  // With a visual step every `visual_ticks` >= 4 ticks (P): e's RMS over the replies within P/8 of the
  // visual steps (tick k with k mod P within P/8 of 0) and over those within P/8 of mid-period (NaN
  // for smaller P). Each step builds its model for the state the world reaches at the next step, and
  // its replies fit the every-tick world best near the steps: what they miss there is mostly the
  // world stepped at the visual rate against the world stepped every tick (a different trajectory);
  // what they miss more at mid-period is the linearization's (stylus_press_fixed at 15 Hz: 0.017 N
  // near the steps, 0.071 N at mid-period).
  double rms_near_steps_n = std::numeric_limits<double>::quiet_NaN();
  double rms_mid_period_n = std::numeric_limits<double>::quiet_NaN();
};
ForceError force_error(const OfflineTrace& run, const OfflineTrace& reference, int visual_ticks = 1);
// RMS over ticks of sqrt(sum over frames |f_D|^2): the scale of the errors, N.
double rms_force(const OfflineTrace& trace);

struct MultirateRow {
  std::string interaction;
  int visual_ticks = 1;  // the world steps every this many haptic ticks
  double visual_hz = 0;  // 1 / (visual_ticks T)
  haptic::HandleModelKind model = haptic::HandleModelKind::linearized;
  ForceError error;
  OfflineTimings timings;
  long resets = 0;
};

struct MultirateRuns {
  OfflineTrace reference;  // visual step every tick, linearized, closed loop
  std::vector<MultirateRow> rows;
};

// The reference run, then for each visual period (in ticks) and model an open-loop
// replay of the reference's device poses. A visual period of 1 with the linearized
// model is the reference itself (its row has no error by definition).
MultirateRuns run_multirate(const Interaction& interaction, const std::vector<int>& visual_ticks,
                            const std::vector<haptic::HandleModelKind>& models, double haptic_period_s = 1e-3);

}  // namespace hapticd::offline
