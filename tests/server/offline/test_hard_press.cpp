// No sinking (issue 17, item 3): the simulated stylus pressed into the bunny with five times its
// 8 N force limit for 3 s, then released, closed loop through the lockstep runner with the scene's
// constraint contact and the passivity controller on, at visual rates of 60 and 15 Hz, on the
// movable and on the fixed bunny. While held, the hand's skin stays within 2 mm of the surface and
// the device is pushed back out (up), not pulled in; a second after the release nothing is felt or
// flagged; nothing resets; no energy goes into the device.
//
// A known fault of issue 17, run by tests/CMakeLists.txt as one ctest expected to fail. Measured
// when it was written: movable bunny at 60 Hz, 0.37 mm while held but 0.24 N a second after the
// release; at 15 Hz 40 mm, 458 resets, +1.02 J, and -8 N with InContact after the release; fixed
// bunny 196 mm (60 Hz) and 677 mm (15 Hz) deep: the hand went through the bunny and the table and was
// held under it at -8 N. The coupling spring pulls the proxy, and through it the hand, with ~100 N
// (world) while the device renders at most 8 N.
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

struct HardPressCase {
  bool movable;
  int visual_every_ticks;
};

std::string hard_press_name(const ::testing::TestParamInfo<HardPressCase>& info) {
  return std::string(info.param.movable ? "movable" : "fixed") + "_bunny_" +
         std::to_string(static_cast<int>(std::lround(1.0 / (info.param.visual_every_ticks * kPeriod)))) + "Hz";
}

class HardPress : public ::testing::TestWithParam<HardPressCase> {};

TEST_P(HardPress, FiveTimesTheForceLimitLeavesTheSkinOnTheSurfaceAndTheDevicePushedOut) {
  const HardPressCase& c = GetParam();
  world::SceneDesc scene = world::load_scene(std::string(HAPTICD_SCENES_DIR) + "/stylus_bunny.json");
  if (!c.movable)
    for (world::ObjectDesc& o : scene.objects)
      if (o.name == "bunny") o.kind = world::BodyKind::static_body;
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
  const double limit_n = scene.devices[0].max_force_n, deep = 0.01 + 5 * limit_n / sim::DeviceParams{}.arm_stiffness_n_per_m;
  const auto command = [deep](double t) {
    if (t < 0.3) return 0.0;
    if (t < 1.3) return -deep * (t - 0.3);
    if (t < 4.3) return -deep;
    return std::min(0.02, -deep + (deep + 0.02) * (t - 4.3));
  };
  SimulatedStylus stylus(start, [&command](double t) { return Eigen::Vector3d(0, 0, command(t)); }, kPeriod);
  const long ticks = std::lround(6.5 / kPeriod);
  const long hold_start = std::lround(1.3 / kPeriod), hold_end = std::lround(4.3 / kPeriod);
  double deepest = 0, pulled_in = 0, after = 0;
  // The deepest skin point of the world's contacts while held (WorldSnapshot::max_penetration_m).
  const OfflineTrace trace = run_offline(loops, stylus, ticks, [&](long tick) {
    if (tick >= hold_start && tick < hold_end) deepest = std::max(deepest, loops.world().snapshot().max_penetration_m);
  });
  ASSERT_EQ(static_cast<long>(trace.replies.size()), ticks);
  bool flagged = false;
  for (long k = hold_start; k < hold_end; ++k) pulled_in = std::max(pulled_in, -trace.replies[k].wrench[0].f_D.z());
  for (long k = std::lround(6.3 / kPeriod); k < ticks; ++k) {
    after = std::max(after, trace.replies[k].wrench[0].f_D.norm());
    flagged = flagged || trace.replies[k].in_contact[0];
  }
  std::printf("%s at %d ticks: deepest skin point %.2f mm while held, largest pull in %.2f N, a second after the "
              "release %.3f N%s, resets %ld, energy %+.4f J\n",
              c.movable ? "movable bunny" : "fixed bunny", c.visual_every_ticks, 1e3 * deepest, pulled_in, after,
              flagged ? " InContact" : "", trace.resets, stylus.energy_j());
  EXPECT_LE(deepest, 2e-3);
  EXPECT_LE(pulled_in, 0.0) << "the device was pulled into the object";
  EXPECT_LE(after, 0.05);
  EXPECT_FALSE(flagged);
  EXPECT_EQ(trace.resets, 0);
  EXPECT_LE(stylus.energy_j(), 0.0);
}

INSTANTIATE_TEST_SUITE_P(Issue17KnownFault, HardPress,
                         ::testing::Values(HardPressCase{true, 17}, HardPressCase{true, 67}, HardPressCase{false, 17},
                                           HardPressCase{false, 67}),
                         hard_press_name);

}  // namespace
}  // namespace hapticd::offline
