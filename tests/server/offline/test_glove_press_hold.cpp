// A glove pressing into a fixed object and held still (issue 17, "Passive by construction, under
// load"): the simulated 16-frame glove closes into the power grasp over the 5 cm box of
// glove_grasp.json made static, closed loop through the lockstep runner (hapticd's own haptic tick
// and visual step). The grasp's posture lies up to 1.5 cm inside the box, so the index, middle,
// ring and little fingers press into it and stay there; from 1.5 s the glove's command holds still.
//
// Asserted, at visual rates 60, 30 and 15 Hz, the passivity controller on (as in hapticd) and off
// (the controller guards the port, it must not hide a wrong model):
//   - no reset of a proxy or of the world;
//   - the energy bound: the rendering puts no energy into the glove over the run
//     (GloveSimulation::passivity_energy_j, the work of the rendered forces on its palm and joints);
//   - the glove holds still: over the last 0.5 s every frame's force stays within 0.05 N of its
//     mean. A glove ringing in a limit cycle while its command holds still is how the rendering
//     gives it energy, whether or not the run's total has turned positive yet.
// Measured at 5ab32e3, before the three causes below were fixed, total energy and the largest swing:
//   controller on:  60 Hz -0.062 J 0.52 N, 30 Hz -0.076 J 0.51 N, 15 Hz +0.78 J 4.2 N;
//   controller off: 60 Hz +0.53 J 4.8 N,   30 Hz +0.011 J 1.0 N,  15 Hz +3.6 J 4.0 N.
// Through the real server the same press gained -0.001 to +0.27 J over 4 s (-0.048 to +0.043 J with
// the fixes, README). The three causes, each
// traced to a frame (controller off), and their fixes:
//   - Contact gating worked as a relay. A finger frame whose part touches nothing is gated to zero
//     force, but its proxy still feels the coupling to its device. The ring finger's middle
//     phalanx, resting on the box's edge, alternated between touching and not from one visual step
//     to the next: felt, its device was pushed 5 mm out at ~2.5 N; gated, it sank back in at no
//     cost; felt again, it was pushed out from deeper (period two steps, ~12 mJ a cycle). Fixed: a
//     gated frame's stretch stays unfelt after its gate opens, released only as the device backs
//     out of it (ProxyHand::reply).
//   - A prepared glove tick solved its contact rows on an operator formed at half the step's
//     lookahead (TickContacts::W_proxy) while the rows' velocities and the proxies' response took
//     the live lookahead, from the whole step down to h: the rows overshot early in each step. A
//     fingertip proxy (3.8 g) arriving at its rows at -0.94 m/s as a model switched (the rows
//     seeing its velocity as 3 cm of penetration) left them at +1.29 m/s, flew 7 mm out and came
//     back by the step's end (30 Hz). Fixed: such a model is served at its operator's lookahead
//     through its step (ProxyHand::integrate).
//   - The rotational coupling's damper, 0.01 N m s/rad, on the glove's distal joint (5e-6 kg m^2,
//     0.0022 N m s/rad, sim::GloveParams): B T / I = 2, and Colgate and Schenkel's b > K T / 2 + |B|
//     failed. Every pressed fingertip rang at 500 Hz (+-1.2 mrad a tick), +0.012 J/s each. Fixed:
//     a glove's is 1.5 K T / 2 (glove_rotational_damping).
// Each fix alone left four to six of the cases failing (measured: the rotational damping alone,
// 60 Hz on -0.11 J 0.61 N, 30 Hz on +0.58 J; with the gate too, 30 Hz on +0.43 J 2.3 N).
#include <gtest/gtest.h>

#include <Eigen/Core>
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <memory>
#include <string>

#include "server/offline/multirate.hpp"
#include "server/offline/offline_run.hpp"
#include "server/world/scene_loader.hpp"

namespace hapticd::offline {
namespace {

constexpr double kPeriod = 1e-3;
constexpr double kHoldFrom_s = 2.0, kEnd_s = 4.0;
constexpr double kStillFor_s = 0.5;
constexpr double kStillSwing_N = 0.05;

struct PressCase {
  int visual_hz;
  bool passivity_control;
};

std::string case_name(const ::testing::TestParamInfo<PressCase>& info) {
  return std::to_string(info.param.visual_hz) + "Hz" + (info.param.passivity_control ? "" : "_no_controller");
}

class GlovePressHold : public ::testing::TestWithParam<PressCase> {};

TEST_P(GlovePressHold, AStillHoldPutsNoEnergyIntoTheGloveAndHoldsStill) {
  const PressCase& c = GetParam();
  const Interaction press =
      glove_grasp(with_rigid_bodies_fixed(world::load_scene(std::string(HAPTICD_SCENES_DIR) + "/glove_grasp.json")),
                  kEnd_s, sim::kGloveFramesAll);
  OfflineOptions options;
  options.haptic_period_s = kPeriod;
  options.visual_every_ticks = static_cast<int>(std::lround(1.0 / (c.visual_hz * kPeriod)));
  options.passivity_control = c.passivity_control;
  OfflineLoops loops(press.scene, options);
  const std::unique_ptr<OfflineDevice> device = press.device(loops);
  const auto& glove = dynamic_cast<const SimulatedGlove&>(*device);
  const long hold_tick = std::lround(kHoldFrom_s / kPeriod), end_tick = std::lround(kEnd_s / kPeriod);
  double at_hold = 0;
  const OfflineTrace trace = run_offline(loops, *device, end_tick, [&](long tick) {
    if (tick + 1 == hold_tick) at_hold = glove.simulation().passivity_energy_j();
  });
  const double energy = glove.simulation().passivity_energy_j();
  // How far each frame's force strays from its mean over the last kStillFor_s: a glove ringing
  // in a limit cycle is what takes energy from the rendering while its command holds still.
  const long still_from = end_tick - std::lround(kStillFor_s / kPeriod);
  double swing = 0;
  for (int j = 0; j < trace.replies.back().frames; ++j) {
    Eigen::Vector3d mean = Eigen::Vector3d::Zero();
    for (long k = still_from; k < end_tick; ++k) mean += trace.replies[k].wrench[j].f_D;
    mean /= static_cast<double>(end_tick - still_from);
    for (long k = still_from; k < end_tick; ++k)
      swing = std::max(swing, (trace.replies[k].wrench[j].f_D - mean).norm());
  }
  std::printf(
      "glove press on the fixed box at %d Hz, controller %s: energy %+.4f J (%+.4f J at %.1f s, %+.4f J over "
      "the still hold), largest swing of a frame's force over the last %.1f s %.4f N, resets %ld\n",
      c.visual_hz, c.passivity_control ? "on" : "off", energy, at_hold, kHoldFrom_s, energy - at_hold, kStillFor_s,
      swing, trace.resets);
  EXPECT_EQ(trace.resets, 0);
  EXPECT_LE(energy, 0.0) << "the rendering put energy into the glove";
  EXPECT_LT(swing, kStillSwing_N) << "the glove does not hold still";
}

INSTANTIATE_TEST_SUITE_P(Touch, GlovePressHold,
                         ::testing::Values(PressCase{60, true}, PressCase{30, true}, PressCase{15, true},
                                           PressCase{60, false}, PressCase{30, false}, PressCase{15, false}),
                         case_name);

}  // namespace
}  // namespace hapticd::offline
