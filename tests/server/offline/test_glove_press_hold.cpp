// A glove pressing into a fixed object and held still (issue 17, "Passive by construction, under
// load"): the simulated 16-frame glove closes into the power grasp over the 5 cm box of
// glove_grasp.json made static, closed loop through the lockstep runner (hapticd's own haptic tick
// and visual step). The grasp's posture lies up to 1.5 cm inside the box, so the index, middle,
// ring and little fingers press into it and stay there; from 1.5 s the glove's command holds still.
//
// Asserted, at visual rates 60, 30 and 15 Hz, the passivity controller on (as in hapticd) and off
// (the controller guards the port, it must not hide a wrong model):
//   - no reset of a proxy or of the world;
//   - the issue's energy bound: the rendering puts no energy into the glove over the run
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
#include <cstdint>
#include <cstdio>
#include <memory>
#include <string>

#include "server/offline/multirate.hpp"
#include "server/offline/offline_run.hpp"
#include "server/world/scene_loader.hpp"
#include "stiffness_scale.hpp"

namespace hapticd::offline {
namespace {

constexpr double kPeriod = 1e-3;
constexpr double kHoldFrom_s = 2.0, kEnd_s = 4.0;
constexpr double kStillFor_s = 0.5;
constexpr double kStillSwing_N = 0.05;

struct PressCase {
  int visual_hz;
  bool passivity_control;
  // A busy machine's models (OfflineOptions::model_delay_ticks, late_model_max_ticks): each reaches
  // the haptic loop `delay` ticks after its step plus 0 .. late - 1 more, drawn from `seed`.
  int delay = 0, late = 0;
  std::uint64_t seed = 12345;
  double end_s = kEnd_s;  // the run's length: the hold lasts from kHoldFrom_s to here
};

std::string case_name(const ::testing::TestParamInfo<PressCase>& info) {
  const PressCase& c = info.param;
  return std::to_string(c.visual_hz) + "Hz" +
         (c.late > 0 ? "_late" + std::to_string(c.delay) + "to" + std::to_string(c.delay + c.late - 1) + "_seed" +
                           std::to_string(c.seed)
                     : "") +
         (c.passivity_control ? "" : "_no_controller");
}

class GlovePressHold : public ::testing::TestWithParam<PressCase> {};

TEST_P(GlovePressHold, AStillHoldPutsNoEnergyIntoTheGloveAndHoldsStill) {
  const PressCase& c = GetParam();
  const Interaction press =
      glove_grasp(with_rigid_bodies_fixed(world::load_scene(std::string(HAPTICD_SCENES_DIR) + "/glove_grasp.json")),
                  c.end_s, sim::kGloveFramesAll);
  OfflineOptions options;
  options.haptic_period_s = kPeriod;
  options.visual_every_ticks = static_cast<int>(std::lround(1.0 / (c.visual_hz * kPeriod)));
  options.passivity_control = c.passivity_control;
  options.model_delay_ticks = c.delay;
  options.late_model_max_ticks = c.late;
  options.late_model_seed = c.seed;
  // A perturbed run (OfflineOptions::model_stiffness_scale), as the comments' six runs a case were measured.
  apply_stiffness_scale_from_env(options);
  OfflineLoops loops(press.scene, options);
  const std::unique_ptr<OfflineDevice> device = press.device(loops);
  const auto& glove = dynamic_cast<const SimulatedGlove&>(*device);
  const long hold_tick = std::lround(kHoldFrom_s / kPeriod), end_tick = std::lround(c.end_s / kPeriod);
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
      "glove press on the fixed box at %d Hz, models %d + 0..%d ticks late, controller %s: energy %+.4f J (%+.4f J "
      "at %.1f s, %+.4f J over the still hold), largest swing of a frame's force over the last %.1f s %.4f N, "
      "resets %ld; %ld models' stiffness made passive (largest eigenvalue removed %.3g of the coupling's)\n",
      c.visual_hz, c.delay, std::max(c.late - 1, 0), c.passivity_control ? "on" : "off", energy, at_hold, kHoldFrom_s,
      energy - at_hold, kStillFor_s, swing, trace.resets, loops.preparer().stiffness_made_passive(),
      loops.preparer().stiffness_removed_max());
  EXPECT_EQ(trace.resets, 0);
  EXPECT_LE(energy, 0.0) << "the rendering put energy into the glove";
  EXPECT_LT(swing, kStillSwing_N) << "the glove does not hold still";
}

INSTANTIATE_TEST_SUITE_P(Touch, GlovePressHold,
                         ::testing::Values(PressCase{60, true}, PressCase{30, true}, PressCase{15, true},
                                           PressCase{60, false}, PressCase{30, false}, PressCase{15, false}),
                         case_name);

// The same through a busy machine's visual loop (GloveLateModels/GlovePressHold): the scene's 1.7k-tet hand
// steps in ~50 ms on a loaded 2-core machine, so hapticd runs its visual loop at ~16 Hz and each
// model reaches the haptic loop 45-59 ms after its step began (through the real server, this press
// gave -0.085 to +0.023 J in four quiet runs, tests/e2e/glove_loopback.sh); at 30 Hz, 10-24 ms.
// Measured before a prepared model was served at its operator's lookahead past its step's end too
// (ProxyHand::integrate), the first four cases in order: +0.028, +0.079, +0.0036 and +0.24 J, the
// frames' forces swinging 0.7-1.4 N over the last 0.5 s (a pressed phalanx's force ramped ~0.3 N
// through each step and dropped at the next model, its finger pushed out along it ~2 mm a step).
// After, seeds 1-9 at 16 Hz: -0.039 to -0.054 J at 4 s. Seed 1's hold settles slowly (its frames'
// forces wander by up to 0.3 N until ~5 s, the glove taking back 3 mJ of its -0.043 J), so these
// runs last 5.5 s: the glove must be still from 5.0 s.
// Whether a late-model hold is still by then is chaotic: with K scaled by 1, 1 +- 1e-6, 1 +- 1e-5 and
// 1 + 1e-4 (six runs a case: HAPTICD_STIFFNESS_SCALE=1.000001 offline_tests --gtest_filter=...), at
// faa7000 (before passive_stiffness) 16 Hz seed 1 swung above 0.05 N in 4 runs, 16 Hz seed 2 in 3,
// 30 Hz seed 2 in 2 (up to 1.19 N), though each passes as it stands; with
// passive_stiffness, 16 Hz seed 2 in 1, 16 Hz seed 2 without the controller in 3, 30 Hz seed 2 in 2,
// 14 Hz in 1. Every one of these runs, either way, ended passive (-0.030 J or less).
constexpr double kLateEnd_s = 5.5;
INSTANTIATE_TEST_SUITE_P(GloveLateModels, GlovePressHold,
                         ::testing::Values(PressCase{16, true, 45, 15, 1, kLateEnd_s},
                                           PressCase{30, true, 10, 15, 2, kLateEnd_s},
                                           PressCase{13, true, 0, 0, 12345, kLateEnd_s},
                                           PressCase{14, true, 53, 17, 2, kLateEnd_s}),
                         case_name);

// A slow visual loop (12, 10 and 8 Hz, models on time; 13 Hz with models 57-75 ticks late). Measured at
// faa7000, before the tick's stiffness lost its positive eigenvalues (passive_stiffness): at 12 Hz
// the held press gained +0.024 J with the controller and +0.145 J without it (10 Hz -0.039 and +0.11 J,
// 8 Hz +0.012 and +0.14 J; 13 Hz late, with the controller, its frames swung 0.11 N at 5.5 s). Without
// the controller at 12 Hz: the ring finger's middle phalanx (frame 11) touches nothing, so it is gated
// (unfelt), while its pressing neighbours' flesh holds its proxy 17 mm from its device with the
// coupling saturated at the device's 5 N and 0.2 N m. The model's stiffness on that phalanx's rotation
// had an eigenvalue of up to +7.3 N m/rad (its coupling's is 1 N m/rad): turned, the flesh turned it
// further. From 3.16 s the proxy turned against its device at up to 23 rad/s, half a turn by 3.44 s,
// and at 3.57 s spun at up to 2000 rad/s and was thrown 20 mm into the box, its force at the 5 N
// limit. With the stiffness made passive, the most energy over six runs of K scaled as above: -0.016 J
// at 12 Hz either way, -0.022 J at 10 Hz, -0.011 J at 8 Hz, -0.007 J at 13 Hz late; the 13 Hz late holds,
// still as they stand, swung above 0.05 N in 2 (controller on, up to 1.09 N) and 1 (off) of those six.
INSTANTIATE_TEST_SUITE_P(SlowVisualLoop, GlovePressHold,
                         ::testing::Values(PressCase{12, false}, PressCase{10, true}, PressCase{10, false},
                                           PressCase{8, true}, PressCase{13, true, 57, 19, 2, kLateEnd_s},
                                           PressCase{13, false, 57, 19, 2, kLateEnd_s}),
                         case_name);

// A known fault of issue 17 (tests/CMakeLists.txt runs it as one ctest expected to fail): holds that end
// passive but whose frames still swing over the last 0.5 s (bound 0.05 N). With OpenBLAS's AVX2 kernels,
// which the tests pin (tests/CMakeLists.txt): at 12 Hz with the controller 0.342 N (-0.0171 J); at 8 Hz
// without it 0.197 N (-0.0119 J); at 16 Hz with models late (seed 2) 0.605 N without it (-0.0399 J) and
// 0.514 N with it (-0.0384 J). Measured on an Intel Xeon before the pin (the perturbed runs above):
// 0.34 N (0.015 N in four of the six runs of K scaled), 0.063 N (0.20 N in three of six), 0.53 N (passed
// as it stood at faa7000, and in three of six runs), and the last held still. On one AMD EPYC, the same
// build: with the AVX-512 kernels (OPENBLAS_CORETYPE=SkylakeX) that last hold swung 0.0001 N (-0.0305 J),
// with the AVX ones (Sandybridge) 0.0018 N (-0.0400 J): the factorizations' last bits decide it.
INSTANTIATE_TEST_SUITE_P(Issue17KnownFault, GlovePressHold,
                         ::testing::Values(PressCase{12, true}, PressCase{8, false},
                                           PressCase{16, false, 45, 15, 2, kLateEnd_s},
                                           PressCase{16, true, 45, 15, 2, kLateEnd_s}),
                         case_name);

}  // namespace
}  // namespace hapticd::offline
