// A visual loop that stops for 300 ms (issue 17: on a loaded CI machine the descheduled visual thread
// left the stylus lifting away from the bunny pulled 0.43 N toward it; press_hold_lift_busy.sh). The
// lockstep runner stops the visual step (OfflineOptions::visual_stalls_s) at moments of a
// press-hold-lift on the shipped scene's movable bunny at 59 Hz, the passivity controller off: the
// haptic loop serves the model it has, late from its step's end, then fades it (HapticCore's
// watchdog: overdue by 0.1 s, faded over 0.1 s, the surfaces felt 0.5 s longer). Each run must take
// energy out of the device, reset nothing, and pull the lifting stylus toward the bunny no harder
// than press_hold_lift_busy.sh allows (0.3 N) once it is back above the height where it first touched.
//
// Measured before this test's fixes (the reference run, without a stall: -2.4e-3 J, 0.11 N):
// - stalled while lifting: pulls of 0.67 N, leaving the bunny 0.26 N: a late model's K (x - x0)
//   stretched as the proxy travelled on for the 100 ms before the fade (hapticd with a 300 ms stall
//   injected into its visual thread in the lift: 0.37-0.57 N). ProxyHand::integrate now takes K at
//   the proxy's pose of the model's first late tick.
// - stalled while pressing or holding: +9.2e-3 and +9.5e-3 J put into the device. The fade took the
//   bunny out of what the device felt at once; the device sank into it unfelt and was pushed back out
//   when models came again. With the passivity controller on, the energy was taken back by damping
//   that then dragged the lift: a 1.0 N pull. The device now feels the model's surfaces for
//   ServerOptions::model_contacts_hold_s past the fade.
// - the same stalls with one visual step 165 ms into them (how a starved visual thread ran on a busy
//   machine): +1e-3 to +5e-3 J into the device, the step after a stall replaying the proxies' 165 ms
//   of motion in one visual period. That step now spans the time lost, up to the longest step
//   (detail::StepClock in hapticd, as this runner does).
#include <gtest/gtest.h>

#include <cstdio>
#include <iterator>
#include <utility>
#include <vector>

#include "server/offline/touch.hpp"

namespace hapticd::offline {
namespace {

constexpr double kMaxPullN = 0.3;  // press_hold_lift_busy.sh's bound

// A stall of length_s from from_s; with `step_at_s` > 0, the visual thread gets through one step that
// far into it (a starved thread's crumb of CPU).
struct Stall {
  const char* when;
  double from_s, length_s, step_at_s = 0;
};

TEST(VisualStalls, AStylusPressingOrLiftingThroughAStalledVisualLoopIsNeitherPushedOutNorPulledBack) {
  const PressSchedule schedule(Press{0.02, 0.05, 0.08});
  const double down = schedule.down_end - schedule.down_start;
  const Stall stalls[] = {
      {"pressing into the bunny", schedule.down_start + 0.6 * down, 0.3},
      {"holding", schedule.down_end + 0.1, 0.3},
      {"leaving the bunny", schedule.up_start + 0.05, 0.3},
      {"lifting", schedule.up_start + 0.15, 0.3},
      // Past the surfaces' hold (ServerOptions::model_contacts_hold_s): the device stops feeling
      // the bunny 0.6 s into the stall, while the lift has begun.
      {"holding, 1 s", schedule.down_end + 0.1, 1.0},
      {"holding, one step in", schedule.down_end + 0.1, 0.3, 0.165},
      {"lifting, one step in", schedule.up_start + 0.1, 0.3, 0.165},
  };
  OfflineOptions options = movable_bunny_press_options();
  const world::SceneDesc scene = press_scene("movable_bunny");
  const TouchRun reference = run_press_hold_lift(scene, schedule, options);
  const AfterLift r = after_lift(reference.trace, schedule, options);
  std::printf("no stall%28s: energy %+.2e J, pull %.3f N, largest %.2f N\n", "", reference.energy_j, r.pull, r.largest);
  for (const Stall& s : stalls) {
    options.visual_stalls_s = {{s.from_s, s.from_s + s.length_s}};
    if (s.step_at_s > 0)
      options.visual_stalls_s = {{s.from_s, s.from_s + s.step_at_s},
                                 {s.from_s + s.step_at_s + 0.002, s.from_s + s.length_s}};
    const TouchRun run = run_press_hold_lift(scene, schedule, options);
    const AfterLift a = after_lift(run.trace, schedule, options);
    std::printf(
        "stalled %4.0f ms %-20s: energy %+.2e J, pull %.3f N, largest %.2f N, a second after %.3f N%s, "
        "resets %ld\n",
        1e3 * s.length_s, s.when, run.energy_j, a.pull, a.largest, a.after, a.flagged ? " flagged" : "",
        run.trace.resets);
    EXPECT_LE(run.energy_j, 0.0) << s.when;
    EXPECT_EQ(run.trace.resets, 0) << s.when;
    EXPECT_GE(a.touch, 0) << s.when;
    EXPECT_LE(a.pull, kMaxPullN) << s.when;
    EXPECT_LE(a.after, kMaxPullN) << s.when;
    EXPECT_FALSE(a.flagged) << s.when;
  }
}

}  // namespace
}  // namespace hapticd::offline

namespace hapticd::offline {
namespace {

// The whole server stopped (a descheduled process; SERVER_PAUSE in tests/e2e/press_hold_lift_busy.sh)
// for longer than the re-sync gap (50 ms), the device holding its last reply: the haptic thread and,
// 30 ms longer, the visual thread (OfflineOptions::haptic_stalls_s, visual_stalls_s; the haptic
// thread runs first, at real-time priority). The first sample read after it re-syncs the proxies onto
// the device, whose force drops: the stylus sinks into the bunny, and the visual step places the hand
// at the proxies. Found through hapticd stopped 100-200 ms while the stylus pressed the movable bunny
// (3 of 4 runs at 12f7753): the hand was placed inside the bunny and held the lifted stylus 4.2-4.7 N
// toward it, InContact, for the rest of the run. Here, before the hand was placed no farther than its
// contacts and clearance planes let it (VisualStep::place_resynced): stopped while pressing into the
// bunny, a 5.14 N pull in the lift, the force at the device's 8 N limit, +0.25 J.
const PressSchedule kStopSchedule(Press{0.02, 0.05, 0.08});
constexpr double kVisualAfter_s = 0.03;

struct Stopped {
  TouchRun run;
  AfterLift after;
};

Stopped stop_server(const Stall& s) {
  OfflineOptions options = movable_bunny_press_options();
  options.haptic_stalls_s = {{s.from_s, s.from_s + s.length_s}};
  options.visual_stalls_s = {{s.from_s, s.from_s + s.length_s + kVisualAfter_s}};
  Stopped out{run_press_hold_lift(press_scene("movable_bunny"), kStopSchedule, options), {}};
  out.after = after_lift(out.run.trace, kStopSchedule, options);
  std::printf(
      "stopped %4.0f ms %-24s: energy %+.2e J, pull %.3f N, largest %.2f N, a second after %.3f N%s, resets %ld\n",
      1e3 * s.length_s, s.when, out.run.energy_j, out.after.pull, out.after.largest, out.after.after,
      out.after.flagged ? " flagged" : "", out.run.trace.resets);
  return out;
}

const double kStopDown = kStopSchedule.down_end - kStopSchedule.down_start;
const Stall kPressingStops[] = {
    {"pressing into the bunny", kStopSchedule.down_start + 0.8 * kStopDown, 0.1},
    {"holding", kStopSchedule.down_end + 0.1, 0.1},
    {"holding, 300 ms", kStopSchedule.down_end + 0.1, 0.3},
};

TEST(ServerStalls, AStylusPressingThroughAStoppedServerIsNotGluedToTheBunny) {
  std::vector<Stall> stops(std::begin(kPressingStops), std::end(kPressingStops));
  stops.push_back({"lifting", kStopSchedule.up_start + 0.15, 0.1});
  for (const Stall& s : stops) {
    const Stopped r = stop_server(s);
    EXPECT_EQ(r.run.trace.resets, 0) << s.when;
    EXPECT_GE(r.after.touch, 0) << s.when;
    EXPECT_LE(r.after.pull, kMaxPullN) << s.when;
    EXPECT_LE(r.after.after, kMaxPullN) << s.when;
    EXPECT_FALSE(r.after.flagged) << s.when;
  }
}

// A known fault of issue 17 (tests/CMakeLists.txt runs it as one ctest expected to fail): the same
// stops while pressing put +6.6e-3 to +8.7e-3 J into the stylus. The re-sync drops the force the
// proxies held, the stylus sinks into the bunny, and the hand's surfaces push it back out (through
// hapticd, 1.5:0.1 and 2.5:0.2: +5e-3 and +9e-3 J without the passivity controller; with it, the
// damping that takes the energy back drags the lift 1.1-1.7 N). A sample that waited through a
// stopped server is no gap in the device's samples, and should not drop the force it held.
TEST(Issue17KnownFault, AStylusPressingThroughAStoppedServerGetsNoEnergy) {
  for (const Stall& s : kPressingStops) EXPECT_LE(stop_server(s).run.energy_j, 0.0) << s.when;
}

}  // namespace
}  // namespace hapticd::offline
