// No sinking (issue 17, item 3): the simulated stylus pressed into the bunny with five times its
// 8 N force limit for 3 s, then released, closed loop through the lockstep runner with the scene's
// constraint contact and the passivity controller on, at visual rates of 60 and 15 Hz, on the
// movable, the fixed and the deformable bunny (the "rigid or deformable"). While a hand met a
// deformable object only within 2 mm of it (6847105), the skin went 19.3 mm into the deformable bunny
// at 15 Hz; since it meets it ahead of a step as it meets rigid objects (cbd33e2), 0.00 mm.
//
// HardPress: the skin goes at most 2 mm into the bunny while held (the bound) and never
// reaches the table under it; the device is pushed back out (up), never pulled in; nothing resets; no
// energy goes into the device; a second after the release nothing is flagged and less than 0.3 N
// (the pull the issue allows after a lift) is felt. When it was written as one strict test, the
// hand went 196 mm (60 Hz) and 677 mm (15 Hz) deep through the fixed bunny and the table and was
// held under it at -8 N, and at 15 Hz the movable bunny was thrown and the proxy reset 458 times:
// the coupling pulled the proxy, and through it the hand, with ~100 N (world) while the device
// rendered at most 8 N; the haptic model lost the bunny's supports (a 2.4 mm bounce off the table
// at a 67 ms step, then more hand contacts than its rows); and a proxy that slid off the bunny fell
// through the table within one visual step. Fixed by the coupling's saturation, the supports' reach
// and share of the rows, and the tick's clearance planes (ProxyHand::limit_to_clearance). The depth
// on the movable bunny at 15 Hz was 12.6 mm while its supports were ODE's contacts, under one foot
// at a time (it rocked 10-15 degrees a step), 3.0 mm with its vertices as supports while ODE still
// stepped it (1-2 degrees a step), and 0.02 mm since it ends each step where the hand's solve took it.
//
// A second after the release nothing is felt (the 0.05 N): with the served hand at its
// material's full mass the user's arm still rang with it, 0.15 N at 60 Hz; the served stylus hand is
// light now (haptic::kServedPalmHandMassScale).
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <string>

#include "server/offline/offline_run.hpp"
#include "server/offline/touch.hpp"

namespace hapticd::offline {
namespace {

constexpr double kPeriod = 1e-3;

struct HardPressCase {
  const char* object;  // press_scene's: movable_bunny, fixed_bunny, deformable_bunny
  int visual_every_ticks;
};

std::string hard_press_name(const ::testing::TestParamInfo<HardPressCase>& info) {
  return std::string(info.param.object) + "_" +
         std::to_string(static_cast<int>(std::lround(1.0 / (info.param.visual_every_ticks * kPeriod)))) + "Hz";
}

// The measurements of one hard press.
struct HardPressRun {
  double deepest_m = 0;          // the deepest skin point of the world's contacts while held
  double lowest_skin_z_m = 1e9;  // the lowest skin point of the hand, ever
  double table_top_z_m = 0;
  double pulled_in_n = 0;  // the largest force into the object (down) while held
  double pushed_out_n = 0;  // the least force out of it (up) over the hold's last second
  double after_n = 0;      // the largest force a second after the release
  bool flagged = false;    // InContact a second after the release
  long resets = 0;
  double energy_j = 0;
};

HardPressRun run_hard_press(const HardPressCase& c) {
  const world::SceneDesc scene = press_scene(c.object);
  HardPressRun out;
  for (const world::ObjectDesc& o : scene.objects)
    if (o.name == "table") out.table_top_z_m = o.pose.p_W.z() + 0.5 * o.shape.size.z();
  OfflineOptions options;
  options.visual_every_ticks = c.visual_every_ticks;
  options.settle_s = 0.5;
  options.contact.reset();  // the scene's: constraint contact
  OfflineLoops loops(scene, options);
  Eigen::Vector3d start;
  Eigen::Quaterniond q;
  loops.frame_pose_at_handle(0, start, q);
  // The arm (sim::DeviceParams: 200 N/m) pushes 40 N once the command is 20 cm under the tip; the
  // palm meets the bunny ~1 cm down. Ramped in 1 s, held 3 s, released in 1 s to 2 cm above the start.
  const double limit_n = scene.devices[0].max_force_n,
               deep = 0.01 + 5 * limit_n / sim::DeviceParams{}.arm_stiffness_n_per_m;
  const auto command = [deep](double t) {
    if (t < 0.3) return 0.0;
    if (t < 1.3) return -deep * (t - 0.3);
    if (t < 4.3) return -deep;
    return std::min(0.02, -deep + (deep + 0.02) * (t - 4.3));
  };
  SimulatedStylus stylus(
      start, [&command](double t) { return Eigen::Vector3d(0, 0, command(t)); }, kPeriod);
  const long ticks = std::lround(6.5 / kPeriod);
  const long hold_start = std::lround(1.3 / kPeriod), hold_end = std::lround(4.3 / kPeriod);
  long seen_step = -1;
  const OfflineTrace trace = run_offline(loops, stylus, ticks, [&](long tick) {
    const world::World& world = loops.world();
    if (tick >= hold_start && tick < hold_end)
      out.deepest_m = std::max(out.deepest_m, world.snapshot().max_penetration_m);
    if (world.snapshot().step == seen_step) return;  // the skin moves only with the world's steps
    seen_step = world.snapshot().step;
    for (int i = 0; i < world.hand(0).num_skin_points(); ++i)
      out.lowest_skin_z_m = std::min(out.lowest_skin_z_m, world.hand(0).skin_point(i).z());
  });
  EXPECT_EQ(static_cast<long>(trace.replies.size()), ticks);
  if (static_cast<long>(trace.replies.size()) != ticks) return out;
  out.pushed_out_n = INFINITY;
  for (long k = hold_start; k < hold_end; ++k) {
    out.pulled_in_n = std::max(out.pulled_in_n, -trace.replies[k].wrench[0].f_D.z());
    if (k >= hold_end - 1000) out.pushed_out_n = std::min(out.pushed_out_n, trace.replies[k].wrench[0].f_D.z());
  }
  for (long k = std::lround(6.3 / kPeriod); k < ticks; ++k) {
    out.after_n = std::max(out.after_n, trace.replies[k].wrench[0].f_D.norm());
    out.flagged = out.flagged || trace.replies[k].in_contact[0];
  }
  out.resets = trace.resets;
  out.energy_j = stylus.energy_j();
  std::printf(
      "%s at %d ticks: deepest skin point %.2f mm while held, lowest skin point %.1f mm above the table top, "
      "largest pull in %.2f N, least push out over the hold's last second %.2f N, a second after the release "
      "%.3f N%s, resets %ld, energy %+.4f J\n",
      c.object, c.visual_every_ticks, 1e3 * out.deepest_m, 1e3 * (out.lowest_skin_z_m - out.table_top_z_m),
      out.pulled_in_n, out.pushed_out_n, out.after_n, out.flagged ? " InContact" : "", out.resets, out.energy_j);
  return out;
}

const auto kHardPressCases = ::testing::Values(
    HardPressCase{"movable_bunny", 17}, HardPressCase{"movable_bunny", 67}, HardPressCase{"fixed_bunny", 17},
    HardPressCase{"fixed_bunny", 67}, HardPressCase{"deformable_bunny", 17}, HardPressCase{"deformable_bunny", 67});

class HardPress : public ::testing::TestWithParam<HardPressCase> {};

TEST_P(HardPress, FiveTimesTheForceLimitNeverReachesTheTableAndPushesTheDeviceOut) {
  const HardPressRun r = run_hard_press(GetParam());
  ASSERT_GT(r.table_top_z_m, 0.5) << "the scene has its table";
  // A precondition: the bunny held the device out at its force limit (8 N; the press asks for 40).
  EXPECT_GT(r.pushed_out_n, 0.9 * 8.0) << "the press did not bear on the bunny";
  EXPECT_GE(r.lowest_skin_z_m, r.table_top_z_m - 2e-3) << "the hand went into or through the table";
  EXPECT_LE(r.deepest_m, 2e-3) << "the skin went into the bunny";
  EXPECT_LE(r.pulled_in_n, 0.0) << "the device was pulled into the object";
  EXPECT_LE(r.after_n, 0.05);
  EXPECT_FALSE(r.flagged);
  EXPECT_EQ(r.resets, 0);
  EXPECT_LE(r.energy_j, 0.0);
}

INSTANTIATE_TEST_SUITE_P(Touch, HardPress, kHardPressCases, hard_press_name);

}  // namespace
}  // namespace hapticd::offline
