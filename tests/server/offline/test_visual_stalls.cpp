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
#include <utility>

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
// for longer than the re-sync gap (50 ms): the haptic thread and, 30 ms longer, the visual thread
// (OfflineOptions::haptic_stalls_s, visual_stalls_s; the haptic thread runs first, at real-time
// priority). The device holds its last reply and fades it out after 20 ms without one, over 50 ms
// (its watchdog, as haptic-device's), pressing on meanwhile. The samples that waited are no gap in
// the device's samples (their time stamps are its pace): the haptic loop integrates the proxies
// through the stop along them (HapticCore::catch_up), and the stretch the device built while its
// reply faded, in the share it did not feel, is unfelt (ProxyHand::reply's `unfelt_share`). Before,
// in turn:
// - re-synced there, the hand was placed inside the bunny and held the lifted stylus 4.2-4.7 N toward
//   it, InContact (through hapticd stopped 100-200 ms, 3 of 4 runs at 12f7753); then placed no
//   farther than its contacts and clearance planes let it (VisualStep::place_resynced), the re-sync
//   still dropped the force the proxies held, the stylus sank, and the hand pushed it back out:
//   +1.7e-2 to +2.0e-2 J for the three stops while pressing and holding;
// - caught up but felt in full, the proxies on the surface pushed the sunk stylus out as much:
//   +1.4e-2 to +1.7e-2 J, the force at the device's 8 N limit.
// Now -1.6e-3 to -5.6e-3 J, pulls up to 0.18 N (-1.7e-3 to -4.5e-3 J while only the faded share of
// the stretch grown through the stop was unfelt).
const PressSchedule kStopSchedule(Press{0.02, 0.05, 0.08});
constexpr double kVisualAfter_s = 0.03;

struct Stopped {
  TouchRun run;
  AfterLift after;
};

// What stops: the server (its threads descheduled), the device's samples (its link lost them), or
// the machine (both: the server stops with the device's last sample before the gap waiting in its
// socket, read late just before the first after it).
enum class Stop { server, device, machine };

Stopped stop(const Stall& s, Stop what) {
  OfflineOptions options = movable_bunny_press_options();
  if (what == Stop::server) {
    options.haptic_stalls_s = {{s.from_s, s.from_s + s.length_s}};
    options.visual_stalls_s = {{s.from_s, s.from_s + s.length_s + kVisualAfter_s}};
  } else if (what == Stop::device) {
    options.withheld_samples_s = {{s.from_s, s.from_s + s.length_s}};
  } else {
    options.stop_machine(s.from_s, s.from_s + s.length_s);
  }
  Stopped out{run_press_hold_lift(press_scene("movable_bunny"), kStopSchedule, options), {}};
  out.after = after_lift(out.run.trace, kStopSchedule, options);
  std::printf("%s %4.0f ms %-24s: energy %+.2e J, pull %.3f N, largest %.2f N, a second after %.3f N%s, resets %ld\n",
              what == Stop::server   ? "server stopped"
              : what == Stop::device ? "device gap    "
                                     : "machine stop  ",
              1e3 * s.length_s, s.when, out.run.energy_j, out.after.pull, out.after.largest, out.after.after,
              out.after.flagged ? " flagged" : "", out.run.trace.resets);
  return out;
}

void expect_not_glued(const Stopped& r, const Stall& s) {
  EXPECT_EQ(r.run.trace.resets, 0) << s.when;
  EXPECT_GE(r.after.touch, 0) << s.when;
  EXPECT_LE(r.after.pull, kMaxPullN) << s.when;
  EXPECT_LE(r.after.after, kMaxPullN) << s.when;
  EXPECT_FALSE(r.after.flagged) << s.when;
}

const double kStopDown = kStopSchedule.down_end - kStopSchedule.down_start;
const Stall kPressing{"pressing into the bunny", kStopSchedule.down_start + 0.8 * kStopDown, 0.1};
const Stall kHolding[] = {
    {"holding", kStopSchedule.down_end + 0.1, 0.1},
    {"holding, 300 ms", kStopSchedule.down_end + 0.1, 0.3},
};
const Stall kLifting{"lifting", kStopSchedule.up_start + 0.15, 0.1};

TEST(ServerStalls, AStylusThroughAStoppedServerIsNeitherGluedToTheBunnyNorGivenEnergy) {
  for (const Stall& s : {kPressing, kHolding[0], kHolding[1], kLifting}) {
    const Stopped r = stop(s, Stop::server);
    expect_not_glued(r, s);
    EXPECT_LE(r.run.energy_j, 0.0) << s.when;
  }
}

// A gap as long in the device's own samples (its link lost them: they resume with the gap in their
// time stamps) is bridged (ProxyHand::commit_sample): the device's motion across it is a clutch,
// released as it backs out. Re-synced onto the sunk device instead, the proxies were inside the bunny
// and the hand pushed them and the stylus back out: +1.8e-2 J pressing, +1.6e-2 J holding 100 ms,
// +1.1e-2 J holding 300 ms (a known fault of issue 17 until bridged), and +3.8e-4 and +2.8e-3 J for
// the gaps that began just above the bunny and ended in it.
const Stall kApproaching[] = {
    {"approaching the bunny", kStopSchedule.down_start + 0.3 * kStopDown, 0.1},
    {"just above the bunny", kStopSchedule.down_start + 0.4 * kStopDown, 0.1},
};

TEST(ServerStalls, AStylusThroughAGapInItsDevicesSamplesIsNeitherGluedToTheBunnyNorGivenEnergy) {
  for (const Stall& s : {kApproaching[0], kApproaching[1], kPressing, kHolding[0], kHolding[1], kLifting}) {
    const Stopped r = stop(s, Stop::device);
    expect_not_glued(r, s);
    EXPECT_LE(r.run.energy_j, 0.0) << s.when;
  }
}

// The whole machine stopped (a virtual machine paused, a busy host): the device's samples stop, and
// so does the server, with the device's last sample before the gap waiting in its socket. Read late,
// just before the first sample after the gap, it hid the gap from the read times: the device, its
// reply faded out meanwhile, had sunk into the bunny, and the force it had felt before came back in
// full there and pushed it out: +2.2e-3 J just above the bunny, +1.75e-2 J pressing, +1.55e-2 and
// +1.39e-2 J holding 100 and 300 ms, the force at the device's 8 N limit, and lifting a 2.8 N pull
// (at b2c1d3d). A gap is now one in the device's time stamps (HapticCore::on_pose). Stopped 30 ms,
// below the re-sync gap, while lifting: a 0.92 N pull toward the bunny while only the faded share
// of the stretch the device built through the stop was unfelt; now all of it is (the device held
// the reply from before the stop, then less: it felt none of that growth; ProxyHand::reply).
const Stall kShortStop{"lifting, 30 ms", kStopSchedule.up_start + 0.15, 0.03};

TEST(ServerStalls, AStylusThroughAStoppedMachineIsNeitherGluedToTheBunnyNorGivenEnergy) {
  for (const Stall& s : {kApproaching[0], kApproaching[1], kPressing, kHolding[0], kHolding[1], kLifting, kShortStop}) {
    const Stopped r = stop(s, Stop::machine);
    expect_not_glued(r, s);
    EXPECT_LE(r.run.energy_j, 0.0) << s.when;
  }
}

}  // namespace
}  // namespace hapticd::offline
