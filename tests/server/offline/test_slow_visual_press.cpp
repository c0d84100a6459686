// The press of the loopback stylus test (tests/e2e/stylus_loopback.sh: haptic-device's press-stroke
// trajectory from the device's origin, on stylus_static_bunny.json) through the lockstep runner, with
// the visual loop at the rates a loaded machine drops it to (issue 17: "the visual loop's slowdown under
// load must never make the rendering active"), 60 Hz down to 6.7 Hz, the passivity controller off (the
// model's own passivity). Asserted at every tick over one whole press cycle (4 s) and the start of the
// stroke: the rendering has never given the stylus more energy than it took from it (the work of the
// rendered forces on the tip <= 0, to 1e-9 J), and the press reached the bunny.
//
// Found by that e2e test with four CPU-bound competitors (the visual loop at 8.9 Hz): +3.5e-4 J. Here,
// at 15 Hz: +6.6e-4 J at the lift, +4.3e-4 J at the end. A hand's points looked a fixed 2 mm ahead for
// speculative contacts while the stylus (workspace scale 2) moved the hand 4 mm a step: the step that
// reached the bunny found no contact, the hand ended it 0.5 mm deeper than the final pressed pose, and
// pushing it back out drove the stylus up through the hold. A hand's point that closes its gap within
// the step is now a row too (World's collide).
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <string>
#include <vector>

#include "clients/sim/trajectory.hpp"
#include "server/offline/offline_run.hpp"
#include "server/offline/touch.hpp"
#include "server/world/scene_loader.hpp"

namespace hapticd::offline {
namespace {

constexpr double kPeriod = 1e-3;

struct PressRun {
  double end_j = 0, most_j = -1e9, most_at_s = 0, largest_n = 0;
  long resets = 0;
};

PressRun slow_visual_press(const OfflineOptions& options) {
  OfflineLoops loops(world::load_scene(std::string(HAPTICD_E2E_DIR) + "/stylus_static_bunny.json"), options);
  const sim::Trajectory press = sim::Trajectory::press_stroke();
  SimulatedStylus stylus(
      Eigen::Vector3d::Zero(),
      [&press](double t) {
        const sim::Vec3d p = press.position(t);
        return Eigen::Vector3d(p.x, p.y, p.z);
      },
      kPeriod);
  PressRun r;
  const OfflineTrace trace = run_offline(loops, stylus, 4500, [&](long tick) {
    if (stylus.energy_j() > r.most_j) r.most_j = stylus.energy_j(), r.most_at_s = tick * kPeriod;
  });
  for (const DeviceReply& reply : trace.replies) r.largest_n = std::max(r.largest_n, reply.wrench[0].f_D.norm());
  r.end_j = stylus.energy_j();
  r.resets = trace.resets;
  std::printf(
      "%.1f Hz, models %d + up to %d ticks late: energy %+.3e J at the end, at most %+.3e J (at %.3f s); largest "
      "force %.2f N, resets %ld\n",
      1.0 / (options.visual_every_ticks * kPeriod), options.model_delay_ticks, options.late_model_max_ticks, r.end_j,
      r.most_j, r.most_at_s, r.largest_n, r.resets);
  return r;
}

void expect_passive(const PressRun& r) {
  EXPECT_LE(r.most_j, 1e-9) << "the rendering gave the stylus more energy than it took";
  EXPECT_GT(r.largest_n, 1.0) << "the press did not reach the bunny";
  EXPECT_EQ(r.resets, 0);
}

class SlowVisualPress : public ::testing::TestWithParam<int> {};

TEST_P(SlowVisualPress, NeverGivesTheStylusMoreEnergyThanItTook) {
  OfflineOptions options;
  options.haptic_period_s = kPeriod;
  options.visual_every_ticks = GetParam();
  options.passivity_control = false;
  expect_passive(slow_visual_press(options));
}

// 60, 30, 20, 15, 12, 10, 8 and 6.7 Hz.
INSTANTIATE_TEST_SUITE_P(Touch, SlowVisualPress, ::testing::Values(17, 33, 50, 67, 83, 100, 125, 150),
                         [](const ::testing::TestParamInfo<int>& param_info) {
                           return std::to_string(param_info.param) + "ticks";
                         });

// The same press with the models late, as a loaded machine makes them (the world simulated up to the
// planned publication, the model reaching the haptic loop up to tens of ticks after it): four settings,
// each with four seeds of the lateness, the controller off. While a late model's anchor was carried
// on at the handle's velocity (as if the world had gone on moving the hand), at most +1.5e-4 J (9 Hz,
// models 20 + up to 90 ticks late), +3.9e-4 J (8 Hz, 40 + up to 84), +2.0e-4 J (10 Hz, 30 + up to 69)
// and +5.9e-5 J (15 Hz, 20 + up to 46) with the default seed and the controller on (619fac6, then a
// known fault); in a sweep of seven settings and four seeds (a temporary test), 14 of 28 runs active,
// up to +8.7e-4 J. hapticd with four CPU-bound competitors at a
// higher priority (its visual loop at 7.4-9.2 Hz, the simulated device at real-time priority missing no
// tick): +0.7 to +3.1 mJ, the server's own observer agreeing, the capped damping taking back 0.04-0.14
// mJ. The anchor now stays where the world left the hand: 0 of 32 such runs active; the loaded hapticd
// (tests/e2e/stylus_loopback.sh with 4 competitors), 7 runs: -4.9e-4 to +1.7e-4 J (3 above zero, two
// past the controller's 0.1 mJ budget).
struct LateCase {
  int every, delay, late;
  std::uint64_t seed;
};

class LateModels : public ::testing::TestWithParam<LateCase> {};

TEST_P(LateModels, NeverGiveTheStylusMoreEnergyThanItTook) {
  const LateCase c = GetParam();
  OfflineOptions options;
  options.haptic_period_s = kPeriod;
  options.visual_every_ticks = c.every;
  options.model_delay_ticks = c.delay;
  options.late_model_max_ticks = c.late;
  options.late_model_seed = c.seed;
  options.passivity_control = false;
  expect_passive(slow_visual_press(options));
}

std::vector<LateCase> late_cases() {
  std::vector<LateCase> out;
  for (const LateCase& c : {LateCase{111, 20, 91, 0}, LateCase{125, 40, 85, 0}, LateCase{100, 30, 70, 0},
                            LateCase{67, 20, 47, 0}})
    for (const std::uint64_t seed : {12345ull, 1ull, 2ull, 3ull}) out.push_back({c.every, c.delay, c.late, seed});
  return out;
}

INSTANTIATE_TEST_SUITE_P(Touch, LateModels, ::testing::ValuesIn(late_cases()),
                         [](const ::testing::TestParamInfo<LateCase>& param_info) {
                           const LateCase& c = param_info.param;
                           return std::to_string(c.every) + "ticks_" + std::to_string(c.delay) + "plus" +
                                  std::to_string(c.late) + "late_seed" + std::to_string(c.seed);
                         });

// The press-hold-lift (touch.hpp) with the models late (9 Hz, 20 + up to 90 ticks late, the
// default seed), controller off: the energy, pull and release bounds of Touch/PressHoldLift. The FEM
// hand on the movable and the fixed bunny and the table's edge, both presses: measured energy -1.0e-3
// to -7.1e-3 J, pulls 0.07-0.20 N, nothing a second later. On the deformable bunny: +4.1e-4 J (20 mm)
// and +3.5e-4 J (35 mm) while the hand met it only within 2 mm; -8.1e-4 and -6.0e-3 J, pulls 0.07
// and 0.20 N once it met it as it meets rigid objects (speculative rows, clearance planes).
struct LatePress {
  const char* object;
  Press press;
};

std::string late_press_name(const ::testing::TestParamInfo<LatePress>& info) {
  return std::string(info.param.object) + "_" + std::to_string(std::lround(info.param.press.depth_m * 1000)) + "mm";
}

class LateModelsPressHoldLift : public ::testing::TestWithParam<LatePress> {};

TEST_P(LateModelsPressHoldLift, TakesEnergyOutPullsNothingAndLetsGo) {
  const LatePress c = GetParam();
  OfflineOptions options;
  options.haptic_period_s = kPeriod;
  options.visual_every_ticks = 111;
  options.model_delay_ticks = 20;
  options.late_model_max_ticks = 91;
  options.passivity_control = false;
  options.settle_s = 0.5;
  const PressSchedule schedule(c.press);
  const TouchRun run = run_press_hold_lift(press_scene(c.object), schedule, options);
  const AfterLift a = after_lift(run.trace, schedule, options);
  std::printf("%s, %.0f mm: energy %+.3e J, pull after the lift %.3f N, a second later %.4f N, resets %ld\n", c.object,
              1e3 * c.press.depth_m, run.energy_j, a.pull, a.after, run.trace.resets);
  EXPECT_GE(a.touch, 0) << "the press never touched";
  EXPECT_LE(run.energy_j, 0.0) << "the rendering put energy into the stylus";
  EXPECT_LE(a.pull, 0.3) << "pulled toward the object after the lift";
  EXPECT_LE(a.after, 0.01);
  EXPECT_EQ(run.trace.resets, 0);
}

const Press kGentlePress{0.02, 0.02, 0.05}, kDeepFastPress{0.035, 0.06, 0.15};

INSTANTIATE_TEST_SUITE_P(
    Touch, LateModelsPressHoldLift,
    ::testing::Values(LatePress{"movable_bunny", kGentlePress}, LatePress{"movable_bunny", kDeepFastPress},
                      LatePress{"fixed_bunny", kGentlePress}, LatePress{"fixed_bunny", kDeepFastPress},
                      LatePress{"table_edge", kGentlePress}, LatePress{"table_edge", kDeepFastPress},
                      LatePress{"deformable_bunny", kGentlePress}, LatePress{"deformable_bunny", kDeepFastPress},
                      // The contact-point hand's deep press pulled the stylus 1.09 N toward the bunny after
                      // the lift while its model kept the samples' contact points where the world had left
                      // them, a step behind the model's anchor (ContactPointHand::linearize_next_step);
                      // measured since they slide there as the world's next step slides them: 0.16 N.
                      LatePress{"contact_point_movable_bunny", kGentlePress},
                      LatePress{"contact_point_movable_bunny", kDeepFastPress},
                      // The spring hand's gentle press on the movable bunny put +8.5e-4 J into the stylus
                      // while its model's speculative rows over the bunny's top peak took the distance
                      // field's normals, up to 56 degrees from ODE's (SpringHand::probe_rows; the model
                      // against the world: WorldSpringHand.AStylussModelHoldsAFlatPalmOnAPeakAlongThePalmsNormal).
                      LatePress{"spring_movable_bunny", kGentlePress},
                      LatePress{"spring_movable_bunny", kDeepFastPress}, LatePress{"spring_fixed_bunny", kGentlePress},
                      LatePress{"spring_fixed_bunny", kDeepFastPress}, LatePress{"spring_table_edge", kGentlePress},
                      LatePress{"spring_table_edge", kDeepFastPress}),
    late_press_name);

}  // namespace
}  // namespace hapticd::offline
