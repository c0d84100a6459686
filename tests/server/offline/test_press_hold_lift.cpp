// Touch that lets go (issue 17): the simulated stylus presses into an object, holds, and lifts away,
// closed loop through the lockstep runner (hapticd's own haptic tick and visual step), on a movable
// rigid bunny, the same bunny fixed, a deformable bunny and a table edge, at two depths and speeds
// and at visual rates of 15, 30 and 60 Hz. What a user's hand must never feel:
//   - energy put into the device over the run (the work of the rendered forces on the tip; the run
//     ends with the tip in free space, so nothing is held elastically);
//   - any force, or the InContact flag, one second after the lift;
//   - a pull toward the object once the commanded tip is back above the height where it first
//     touched, after one haptic period plus one visual period.
// The passivity controller is off: these are the model's own.
//
// PressHoldLift asserts the energy, the flag one second after the lift and that nothing resets. Measured
// before rigid meshes' vertices were found in the hand's flesh, ODE stepped in substeps and deformable
// objects looked ahead by their step: at 15 Hz the movable bunny held the stylus 3.3 N toward it 2 s
// after the lift (InContact), the deformable bunny took +0.46 J and the device's 8 N force limit, and
// the deep press on the movable bunny +0.021 J.
//
// PressHoldLiftForces asserts the force bounds: no pull above 0.3 N after the lift, under
// 0.01 N a second later. With the served hand at its material's full mass (~0.4 kg, 1.6 kg on the
// stylus at scale 2) the lift cost its inertia: 0.24-0.55 N at 5 cm/s (device), 1.1-1.6 N at 15 cm/s,
// in free space as much, still ringing at 0.006-0.16 N a second later. The served stylus hand is light
// now (haptic::kServedPalmHandMassScale); the same motion in free space is printed beside each run.
//
// The gentle press on the movable bunny at 60 Hz put +0.0004 J into the device once the served hand was
// light (-0.0006 J with the controller on): with 8 supports on the table the bunny rocked under the
// pressed hand, 0.5-0.9 mm into the table at up to 0.55 rad/s in a cycle of four visual steps, which the
// full-mass hand had filtered (-0.0047 J). With 16 (RigidWorld::supports_of): -0.0012 J.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <string>

#include "server/offline/touch.hpp"

namespace hapticd::offline {
namespace {

constexpr double kPeriod = 1e-3;
constexpr double kMaxPullN = 0.3;  // the largest force toward the object allowed after the lift
constexpr double kQuietN = 0.01;   // "no force" one second after the lift

struct Case {
  std::string object;
  int visual_every_ticks;
  Press press;
};

OfflineOptions options_of(const Case& c) {
  OfflineOptions options;
  options.visual_every_ticks = c.visual_every_ticks;
  options.settle_s = 0.5;
  options.passivity_control = false;  // the model's own passivity
  return options;
}

std::string case_name(const ::testing::TestParamInfo<Case>& info) {
  const Case& c = info.param;
  return c.object + "_" + std::to_string(static_cast<int>(std::lround(1.0 / (c.visual_every_ticks * kPeriod)))) +
         "Hz_" + std::to_string(static_cast<int>(std::lround(c.press.depth_m * 1000))) + "mm";
}

// The press-hold-lift of `c` on `object` (free_space: the same motion, 40 cm above everything).
TouchRun press_hold_lift(const Case& c, const std::string& object, const PressSchedule& schedule) {
  return run_press_hold_lift(press_scene(object), schedule, options_of(c));
}

class PressHoldLift : public ::testing::TestWithParam<Case> {};

// The free space of the same hand model as `object` ("spring_fixed_bunny": "spring_free_space").
std::string free_space_of(const std::string& object) {
  for (const char* model : {"spring_", "contact_point_"})
    if (object.rfind(model, 0) == 0) return std::string(model) + "free_space";
  return "free_space";
}

TEST_P(PressHoldLift, TakesEnergyOutOfTheDeviceAndLetsGo) {
  const Case& c = GetParam();
  const PressSchedule schedule(c.press);
  const TouchRun run = press_hold_lift(c, c.object, schedule);
  ASSERT_EQ(static_cast<long>(run.trace.replies.size()), std::lround(schedule.end / kPeriod));
  const AfterLift a = after_lift(run.trace, schedule, options_of(c));
  ASSERT_GE(a.touch, 0) << "the press never touched";
  std::printf("%s at %d ticks: touch at %.1f mm, largest %.2f N, energy %+.5f J, 1 s after the lift %.4f N%s\n",
              c.object.c_str(), c.visual_every_ticks, 1e3 * schedule.z(a.touch * kPeriod), a.largest, run.energy_j,
              a.after, a.flagged ? ", InContact" : "");
  EXPECT_EQ(run.trace.resets, 0);
  EXPECT_LE(run.energy_j, 0.0) << "the rendering put energy into the device";
  EXPECT_FALSE(a.flagged) << "InContact one second after the lift";
}

// What the device feels once the commanded tip is back above the touch height (a haptic and a visual
// period later): the largest force toward the object, and the same motion's in free space at the same
// ticks (the served hand's own inertia and damping, which no contact model can take away).
struct LiftPulls {
  AfterLift run, free;
  double free_pull = 0;
};

LiftPulls lift_pulls(const Case& c) {
  const PressSchedule schedule(c.press);
  const long ticks = std::lround(schedule.end / kPeriod);
  const TouchRun run = press_hold_lift(c, c.object, schedule);
  const TouchRun free = press_hold_lift(c, free_space_of(c.object), schedule);
  LiftPulls out;
  EXPECT_EQ(static_cast<long>(run.trace.replies.size()), ticks);
  EXPECT_EQ(static_cast<long>(free.trace.replies.size()), ticks);
  if (static_cast<long>(run.trace.replies.size()) != ticks || static_cast<long>(free.trace.replies.size()) != ticks)
    return out;
  out.run = after_lift(run.trace, schedule, options_of(c));
  out.free = after_lift(free.trace, schedule, options_of(c));
  EXPECT_GE(out.run.touch, 0) << "the press never touched";
  if (out.run.touch < 0) return out;
  const double touch_z = schedule.z(out.run.touch * kPeriod);
  const double grace = kPeriod + c.visual_every_ticks * kPeriod;
  long above = -1;
  for (long k = std::lround(schedule.up_start / kPeriod); k < ticks; ++k) {
    const double t = k * kPeriod;
    if (above < 0 && schedule.z(t) > touch_z) above = k;
    if (above < 0 || t < above * kPeriod + grace) continue;
    out.free_pull = std::max(out.free_pull, -free.trace.replies[k].wrench[0].f_D.z());
  }
  std::printf(
      "%s at %d ticks: touch at %.1f mm, energy %+.5f J, pull after lift %.3f N (free space %.3f N), 1 s later "
      "%.4f N (free space %.4f N)\n",
      c.object.c_str(), c.visual_every_ticks, 1e3 * touch_z, run.energy_j, out.run.pull, out.free_pull, out.run.after,
      out.free.after);
  return out;
}

// The bounds as written, the hand's inertia included.
class PressHoldLiftForces : public ::testing::TestWithParam<Case> {};

TEST_P(PressHoldLiftForces, PullNothingAfterTheLiftAndFallQuiet) {
  const LiftPulls p = lift_pulls(GetParam());
  EXPECT_LE(p.run.pull, kMaxPullN) << "pulled toward the object after the lift";
  EXPECT_LE(p.run.after, kQuietN);
}

const Press kGentle{0.02, 0.02, 0.05}, kDeepFast{0.035, 0.06, 0.15};

// At 7 Hz too: 150 ms, the longest step the visual loop takes on a loaded machine (kMaxStep_s).
std::vector<Case> cases() {
  std::vector<Case> out;
  for (const char* object : {"movable_bunny", "fixed_bunny", "deformable_bunny", "table_edge"})
    for (int every : {150, 67, 33, 17})  // 7, 15, 30, 60 Hz
      for (const Press& p : {kGentle, kDeepFast}) out.push_back({object, every, p});
  return out;
}

// Slower still, the deep press at 10 and 5 Hz (200 ms steps, beyond kMaxStep_s). Before a hand's
// points met a deformable object farther than 2 mm from it (speculative rows and clearance planes, as
// against rigid objects: World::collide_with_deformables), the deformable bunny put +7.9e-4 J into the
// stylus at 10 Hz, and at 5 Hz the hand first touched it 30 mm down instead of 18, pulled 4.1 N toward
// it after the lift and was still InContact a second later.
std::vector<Case> slow_cases() {
  std::vector<Case> out;
  for (const char* object : {"movable_bunny", "fixed_bunny", "deformable_bunny", "table_edge"})
    for (int every : {200, 100}) out.push_back({object, every, kDeepFast});
  return out;
}

// Seed 002's spring hand (issue 18) on the rigid objects: the same bounds. When added they failed in 25
// of 36 cases (run as a known fault): the device carried the served spring hand's 0.65 kg through its
// 2000 N/m palm spring, with the hand held where each step left it. At 30 and 60 Hz the lift pulled
// 2.5-4.6 N and a second later the device still rang at 0.36-1.85 N, as much as the same motion in
// free space; at 15 Hz that drag (2.8 N) kept the stylus from reaching the bunny. The stylus's model
// is now the springs pressing a massless copy of the hand against the objects (SpringHand's
// linearize_through_springs): measured, energy -0.0002 to -0.009 J, pulls 0.05-0.16 N (the free
// space's), nothing a second later.
std::vector<Case> spring_cases() {
  std::vector<Case> out;
  for (const char* object : {"spring_movable_bunny", "spring_fixed_bunny", "spring_table_edge"})
    for (int every : {67, 33, 17})
      for (const Press& p : {kGentle, kDeepFast}) out.push_back({object, every, p});
  return out;
}

// Seed 001's contact-point hand (issue 18) on the rigid objects: the same bounds. Its model is its
// own force law (penalty rows the tick solves), and the served hand has no mass. When added, the force
// bounds failed in 5 of 18 cases (the lift pulled 0.32-1.5 N on the bunny) while the world's own
// contacts carried at most 0.15 N: the rows were taken at the poses the world was stepped to, 2-4 cm
// behind a lifting stylus at the model's step end; samples the world had let go (their hand points
// past the threshold outside) kept their tangent planes; and sliding samples had the static cone.
// Measured after the fixes (ContactPointHand::linearize_next_step): pulls 0.05-0.27 N.
std::vector<Case> contact_point_cases() {
  std::vector<Case> out;
  for (const char* object : {"contact_point_movable_bunny", "contact_point_fixed_bunny", "contact_point_table_edge"})
    for (int every : {67, 33, 17})
      for (const Press& p : {kGentle, kDeepFast}) out.push_back({object, every, p});
  return out;
}

INSTANTIATE_TEST_SUITE_P(Touch, PressHoldLift, ::testing::ValuesIn(cases()), case_name);
INSTANTIATE_TEST_SUITE_P(Touch, PressHoldLiftForces, ::testing::ValuesIn(cases()), case_name);
INSTANTIATE_TEST_SUITE_P(SlowTouch, PressHoldLift, ::testing::ValuesIn(slow_cases()), case_name);
INSTANTIATE_TEST_SUITE_P(SlowTouch, PressHoldLiftForces, ::testing::ValuesIn(slow_cases()), case_name);
INSTANTIATE_TEST_SUITE_P(SpringTouch, PressHoldLift, ::testing::ValuesIn(spring_cases()), case_name);
INSTANTIATE_TEST_SUITE_P(SpringTouch, PressHoldLiftForces, ::testing::ValuesIn(spring_cases()), case_name);
INSTANTIATE_TEST_SUITE_P(ContactPointTouch, PressHoldLift, ::testing::ValuesIn(contact_point_cases()), case_name);
INSTANTIATE_TEST_SUITE_P(ContactPointTouch, PressHoldLiftForces, ::testing::ValuesIn(contact_point_cases()), case_name);

// The tick's contact sweeps at most (OfflineOptions::tick_contact_sweeps, hapticd's
// --tick-contact-sweeps, haptic-bench touch --tick-sweeps) reach every session's tick: at one, each
// contact solve of a press on the movable bunny runs one sweep (8 by default, nearly all of them 8).
TEST(TickContactSweeps, TheOptionReachesTheTicksOfThePress) {
  OfflineOptions options = movable_bunny_press_options();
  options.tick_contact_sweeps = 1;
  const TouchRun run =
      run_press_hold_lift(press_scene("movable_bunny"), PressSchedule(Press{0.02, 0.02, 0.05}), options);
  EXPECT_GT(run.trace.contact_solves.solves, 100);
  EXPECT_EQ(run.trace.contact_solves.sweeps, run.trace.contact_solves.solves);
}

}  // namespace
}  // namespace hapticd::offline
