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
// PressHoldLift asserts the energy, the flag one second after the lift and that nothing resets: it
// holds on every case. Measured before rigid meshes' vertices were found in the hand's flesh, ODE
// stepped in substeps and deformable objects looked ahead by their step: at 15 Hz the movable bunny
// held the stylus 3.3 N toward it 2 s after the lift (InContact), the deformable bunny took +0.46 J
// and the device's 8 N force limit, and the deep press on the movable bunny +0.021 J.
//
// Issue17KnownFault/PressHoldLift asserts the issue's force bounds too (no pull above 0.3 N after the
// lift, under 0.01 N a second later), beside the same motion in free space (40 cm above everything):
// a known fault of issue 17, run by tests/CMakeLists.txt as one ctest expected to fail. Measured:
// lifting the served hand at 5 cm/s (device) costs 0.26-0.55 N of its own inertia and damping in
// free space, 1.1-1.6 N at 15 cm/s, and a second later it still carries 0.006-0.16 N; on the objects
// the pull is the free-space one within 0.25 N, except the deep press on the deformable bunny at
// 15 Hz (2.29 N against 1.11 N).
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <string>

#include "server/offline/offline_run.hpp"
#include "server/world/scene_loader.hpp"

namespace hapticd::offline {
namespace {

constexpr double kPeriod = 1e-3;
constexpr double kMaxPullN = 0.3;   // the largest force toward the object allowed after the lift
constexpr double kQuietN = 0.01;    // "no force" one second after the lift

world::SceneDesc scene_file(const std::string& name) {
  return world::load_scene(std::string(HAPTICD_SCENES_DIR) + "/" + name + ".json");
}

// The stylus hand (and its device's workspace) moved to hover at `p` (world).
void move_hand(world::SceneDesc& s, const Eigen::Vector3d& p) {
  const Eigen::Vector3d shift = p - s.hands[0].pose.p_W;
  s.hands[0].pose.p_W = p;
  s.devices[0].workspace.offset_W += shift;
}

world::SceneDesc object_scene(const std::string& object) {
  if (object == "movable_bunny") return scene_file("stylus_bunny");
  if (object == "fixed_bunny") {
    world::SceneDesc s = scene_file("stylus_bunny");
    for (world::ObjectDesc& o : s.objects)
      if (o.name == "bunny") o.kind = world::BodyKind::static_body;
    return s;
  }
  if (object == "deformable_bunny") {
    world::SceneDesc s = scene_file("deformable_bunny");
    move_hand(s, Eigen::Vector3d(0.08, 0.1, 0.9));  // over the bunny, as in stylus_bunny
    return s;
  }
  if (object == "free_space") {
    world::SceneDesc s = scene_file("stylus_bunny");
    move_hand(s, Eigen::Vector3d(0.08, 0.1, 1.3));
    return s;
  }
  // The table's +x edge (the top at z = 0.75 ends at x = 0.5): half the palm over it.
  world::SceneDesc s = scene_file("stylus_bunny");
  move_hand(s, Eigen::Vector3d(0.5, 0.0, 0.8));
  return s;
}

struct Press {
  double depth_m;      // device units, below the start
  double down_m_s;     // device speed down
  double up_m_s;       // and up
};

struct Case {
  std::string object;
  int visual_every_ticks;
  Press press;
};

std::string case_name(const ::testing::TestParamInfo<Case>& info) {
  const Case& c = info.param;
  return c.object + "_" + std::to_string(static_cast<int>(std::lround(1.0 / (c.visual_every_ticks * kPeriod)))) +
         "Hz_" + std::to_string(static_cast<int>(std::lround(c.press.depth_m * 1000))) + "mm";
}

// The commanded tip height (device units, relative to the start) of the press-hold-lift.
struct Schedule {
  explicit Schedule(const Press& p) : press(p) {
    down_start = 0.3;
    down_end = down_start + p.depth_m / p.down_m_s;
    up_start = down_end + 0.5;
    up_end = up_start + (p.depth_m + kClearance) / p.up_m_s;
    end = up_end + 1.2;
  }
  double z(double t) const {
    if (t < down_start) return 0;
    if (t < down_end) return -press.down_m_s * (t - down_start);
    if (t < up_start) return -press.depth_m;
    if (t < up_end) return -press.depth_m + press.up_m_s * (t - up_start);
    return kClearance;
  }
  static constexpr double kClearance = 0.01;  // the lift ends 1 cm above the start
  Press press;
  double down_start, down_end, up_start, up_end, end;
};

struct PressRun {
  OfflineTrace trace;
  double energy_j = 0;
};

// The press-hold-lift of `c` on `object` (free_space: the same motion, 40 cm above everything).
PressRun press_hold_lift(const Case& c, const std::string& object, const Schedule& schedule) {
  OfflineOptions options;
  options.visual_every_ticks = c.visual_every_ticks;
  options.settle_s = 0.5;
  options.passivity_control = false;  // the model's own passivity
  options.contact.reset();            // the scene's: constraint contact
  OfflineLoops loops(object_scene(object), options);
  Eigen::Vector3d start_D;
  Eigen::Quaterniond q_D;
  loops.frame_pose_at_handle(0, start_D, q_D);
  SimulatedStylus stylus(
      start_D, [&schedule](double t) { return Eigen::Vector3d(0, 0, schedule.z(t)); }, kPeriod);
  PressRun r;
  r.trace = run_offline(loops, stylus, std::lround(schedule.end / kPeriod));
  r.energy_j = stylus.energy_j();
  return r;
}

// What a run ended with after the lift.
struct AfterLift {
  long touch = -1;       // the first tick flagged InContact
  double largest = 0;    // the largest force of the run, N
  double after = 0;      // the largest force one second after the lift, N
  bool flagged = false;  // InContact then
};

AfterLift after_lift(const OfflineTrace& trace, const Schedule& schedule) {
  AfterLift a;
  const long ticks = static_cast<long>(trace.replies.size());
  for (long k = 0; k < ticks; ++k) {
    a.largest = std::max(a.largest, trace.replies[k].wrench[0].f_D.norm());
    if (a.touch < 0 && trace.replies[k].in_contact[0]) a.touch = k;
  }
  for (long k = std::lround((schedule.up_end + 1.0) / kPeriod); k < ticks; ++k) {
    a.after = std::max(a.after, trace.replies[k].wrench[0].f_D.norm());
    a.flagged = a.flagged || trace.replies[k].in_contact[0];
  }
  return a;
}

class PressHoldLift : public ::testing::TestWithParam<Case> {};

TEST_P(PressHoldLift, TakesEnergyOutOfTheDeviceAndLetsGo) {
  const Case& c = GetParam();
  const Schedule schedule(c.press);
  const PressRun run = press_hold_lift(c, c.object, schedule);
  ASSERT_EQ(static_cast<long>(run.trace.replies.size()), std::lround(schedule.end / kPeriod));
  const AfterLift a = after_lift(run.trace, schedule);
  ASSERT_GE(a.touch, 0) << "the press never touched";
  std::printf("%s at %d ticks: touch at %.1f mm, largest %.2f N, energy %+.5f J, 1 s after the lift %.4f N%s\n",
              c.object.c_str(), c.visual_every_ticks, 1e3 * schedule.z(a.touch * kPeriod), a.largest, run.energy_j,
              a.after, a.flagged ? ", InContact" : "");
  EXPECT_EQ(run.trace.resets, 0);
  EXPECT_LE(run.energy_j, 0.0) << "the rendering put energy into the device";
  EXPECT_FALSE(a.flagged) << "InContact one second after the lift";
}

class PressHoldLiftForces : public ::testing::TestWithParam<Case> {};

TEST_P(PressHoldLiftForces, PullNothingAfterTheLiftAndFallQuiet) {
  const Case& c = GetParam();
  const Schedule schedule(c.press);
  const long ticks = std::lround(schedule.end / kPeriod);
  const PressRun run = press_hold_lift(c, c.object, schedule);
  // The same motion in free space: what the hand's own inertia and damping make the device feel.
  const PressRun free = press_hold_lift(c, "free_space", schedule);
  const OfflineTrace& trace = run.trace;
  ASSERT_EQ(static_cast<long>(trace.replies.size()), ticks);
  const AfterLift a = after_lift(trace, schedule), free_a = after_lift(free.trace, schedule);
  ASSERT_GE(a.touch, 0) << "the press never touched";
  const double touch_z = schedule.z(a.touch * kPeriod);
  // Once the commanded tip is above the touch height for a haptic and a visual period, the force
  // toward the object, and the free-space run's at the same ticks.
  const double grace = kPeriod + c.visual_every_ticks * kPeriod;
  double pull = 0, free_pull = 0;
  long above = -1;
  for (long k = std::lround(schedule.up_start / kPeriod); k < ticks; ++k) {
    const double t = k * kPeriod;
    if (above < 0 && schedule.z(t) > touch_z) above = k;
    if (above < 0 || t < above * kPeriod + grace) continue;
    pull = std::max(pull, -trace.replies[k].wrench[0].f_D.z());
    free_pull = std::max(free_pull, -free.trace.replies[k].wrench[0].f_D.z());
  }
  std::printf("%s at %d ticks: touch at %.1f mm, energy %+.5f J (free %+.5f J), pull after lift %.3f N (free space "
              "%.3f N), 1 s later %.4f N (free space %.4f N)\n",
              c.object.c_str(), c.visual_every_ticks, 1e3 * touch_z, run.energy_j, free.energy_j, pull, free_pull,
              a.after, free_a.after);
  EXPECT_LE(pull, kMaxPullN) << "pulled toward the object after the lift";
  EXPECT_LE(a.after, kQuietN);
}

std::vector<Case> cases() {
  std::vector<Case> out;
  const Press gentle{0.02, 0.02, 0.05}, deep_fast{0.035, 0.06, 0.15};
  for (const char* object : {"movable_bunny", "fixed_bunny", "deformable_bunny", "table_edge"})
    for (int every : {67, 33, 17})  // 15, 30, 60 Hz
      for (const Press& p : {gentle, deep_fast}) out.push_back({object, every, p});
  return out;
}

INSTANTIATE_TEST_SUITE_P(Touch, PressHoldLift, ::testing::ValuesIn(cases()), case_name);
INSTANTIATE_TEST_SUITE_P(Issue17KnownFault, PressHoldLiftForces, ::testing::ValuesIn(cases()), case_name);

}  // namespace
}  // namespace hapticd::offline
