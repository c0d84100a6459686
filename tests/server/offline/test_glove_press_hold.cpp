// A glove pressing into a fixed object and held still (issue 17, "Passive by construction, under
// load"): the simulated 16-frame glove closes into the power grasp over the 5 cm box of
// glove_grasp.json made static, closed loop through the lockstep runner (hapticd's own haptic tick
// and visual step). The grasp's posture lies up to 1.5 cm inside the box, so the index, middle,
// ring and little fingers press into it and stay there; from 1.5 s the glove's command holds still.
// A still hold is where a passive rendering can only take energy out: whatever the rendering puts
// into the glove from 2 s (settled) to the end of the run (4 s) is energy it made.
//
// Asserted, at visual rates 60, 30 and 15 Hz, the passivity controller on (as in hapticd) and off
// (the controller guards the port, it must not hide a wrong model):
//   - no reset of a proxy or of the world;
//   - the glove gains at most 1 mJ over the still hold (GloveSimulation::passivity_energy_j, the
//     work of the rendered forces on its palm and joints; 1 mJ is what the 300 N/m coupling holds
//     at 2.6 mm).
// A known fault (tests/CMakeLists.txt): measured at 87b8eea, the gain over the hold is +0.05 J
// (60 Hz), +0.04 J (30 Hz) and +0.30 J (15 Hz) with the controller, +0.60, +0.12 and +2.2 J
// without it; through the real server the same press gains -0.001 to +0.27 J over 4 s
// (tests/e2e/glove_loopback.sh on tests/e2e/fem_static_box.json, README). What was found, without
// the controller (temporary switches in the haptic tick; gain over the hold at 60 / 30 / 15 Hz):
//   - Contact gating works as a relay. A finger frame whose part touches nothing is gated to zero
//     force, but its proxy still feels the coupling to its device. The ring finger's middle
//     phalanx, resting on the box's edge, alternated between touching and not from one visual step
//     to the next: felt, its device was pushed 5 mm out at ~2.5 N; gated, it sank back in at no
//     cost; felt again, it was pushed out from deeper (period two steps, ~12 mJ a cycle). Not
//     gated at all: +0.13, +0.32, +2.2 J (a steady gain of ~0.01 J/s at each fingertip, and at
//     15 Hz every frame at the 5 N limit); gated but held 0.1-0.3 s after the last contact:
//     +0.05 to +1.4 J.
//   - The lookahead (F* at x + tau v', tau the time left to the model's step end) kicks a light
//     proxy at every model switch: a fingertip proxy (3.8 g, K_yy -103 N/m) arriving at its rows at
//     -0.94 m/s leaves them at +1.29 m/s when tau jumps from 1 to 33 ms, flies 7 mm out and comes
//     back by the step's end (30 Hz, ungated, 50 N limit). The tick's contact solve, unconverged
//     by its 1e-10 test at almost every tick of a glove or a stylus in contact (hapticd's
//     contact_unconverged), is not the cause: 1000 sweeps give the same impulses. Without the
//     lookahead: +0.36, +0.07, +0.92 J gated, +0.13, +0.13, +0.78 J ungated; with a constant tau of
//     8 ms: +0.45, +0.02, +0.75 J gated, +0.10, +0.13, +0.05 J ungated.
//   - The zero-order hold resets the proxies 300 times a run; the bilateral model gains +0.07 to
//     +0.83 J.
#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <string>

#include "server/offline/multirate.hpp"
#include "server/offline/offline_run.hpp"
#include "server/world/scene_loader.hpp"

namespace hapticd::offline {
namespace {

constexpr double kPeriod = 1e-3;
constexpr double kHoldFrom_s = 2.0, kEnd_s = 4.0;
constexpr double kHoldGainBound_J = 1e-3;

struct PressCase {
  int visual_hz;
  bool passivity_control;
};

std::string case_name(const ::testing::TestParamInfo<PressCase>& info) {
  return std::to_string(info.param.visual_hz) + "Hz" + (info.param.passivity_control ? "" : "_no_controller");
}

class GlovePressHold : public ::testing::TestWithParam<PressCase> {};

TEST_P(GlovePressHold, AStillHoldPutsNoEnergyIntoTheGlove) {
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
  const long hold_tick = std::lround(kHoldFrom_s / kPeriod);
  double at_hold = 0;
  const OfflineTrace trace = run_offline(loops, *device, std::lround(kEnd_s / kPeriod), [&](long tick) {
    if (tick + 1 == hold_tick) at_hold = glove.simulation().passivity_energy_j();
  });
  const double gain = glove.simulation().passivity_energy_j() - at_hold;
  std::printf(
      "glove press on the fixed box at %d Hz, controller %s: energy %+.4f J at %.1f s, %+.4f J over the "
      "still hold, resets %ld\n",
      c.visual_hz, c.passivity_control ? "on" : "off", at_hold, kHoldFrom_s, gain, trace.resets);
  EXPECT_EQ(trace.resets, 0);
  EXPECT_LE(gain, kHoldGainBound_J) << "the rendering put energy into the glove while it held still";
}

INSTANTIATE_TEST_SUITE_P(Issue17KnownFault, GlovePressHold,
                         ::testing::Values(PressCase{60, true}, PressCase{30, true}, PressCase{15, true},
                                           PressCase{60, false}, PressCase{30, false}, PressCase{15, false}),
                         case_name);

}  // namespace
}  // namespace hapticd::offline
