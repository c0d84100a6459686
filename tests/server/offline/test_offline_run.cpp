// The offline mode is deterministic: the same scripted interaction gives the
// same force stream bit for bit, and replaying a run's recorded device poses
// (the open-loop input of haptic-bench multirate) reproduces its replies exactly.
#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <cstring>
#include <numbers>
#include <optional>

#include "server/offline/multirate.hpp"
#include "server/world/scene_loader.hpp"

namespace hapticd::offline {
namespace {

world::SceneDesc stylus_scene() { return world::load_scene(std::string(HAPTICD_SCENES_DIR) + "/stylus_bunny.json"); }
world::SceneDesc glove_scene() { return world::load_scene(std::string(HAPTICD_SCENES_DIR) + "/glove_grasp.json"); }

OfflineTrace run_closed_loop(const Interaction& in, int visual_every_ticks) {
  OfflineOptions options;
  options.visual_every_ticks = visual_every_ticks;
  OfflineLoops loops(in.scene, options);
  const std::unique_ptr<OfflineDevice> device = in.device(loops);
  return run_offline(loops, *device, std::lround(in.seconds / options.haptic_period_s));
}

// Every sample of every frame's wrench, bitwise (memcmp: -0.0 vs 0.0 or a NaN would count).
long differing_samples(const OfflineTrace& a, const OfflineTrace& b) {
  long differ = 0;
  EXPECT_EQ(a.replies.size(), b.replies.size());
  for (std::size_t k = 0; k < std::min(a.replies.size(), b.replies.size()); ++k) {
    const DeviceReply &x = a.replies[k], &y = b.replies[k];
    EXPECT_EQ(x.frames, y.frames);
    for (int j = 0; j < x.frames; ++j)
      if (std::memcmp(x.wrench[j].f_D.data(), y.wrench[j].f_D.data(), 3 * sizeof(double)) != 0 ||
          std::memcmp(x.wrench[j].tau_D.data(), y.wrench[j].tau_D.data(), 3 * sizeof(double)) != 0)
        ++differ;
  }
  return differ;
}

double max_force(const OfflineTrace& t) {
  double m = 0;
  for (const DeviceReply& r : t.replies)
    for (int j = 0; j < r.frames; ++j) m = std::max(m, r.wrench[j].f_D.norm());
  return m;
}

TEST(OfflineRun, TwoRunsOfTheStylusPressGiveBitIdenticalForceStreams) {
  // Settle, then down into the bunny (contact from ~1.1 s), 60 Hz visual loop.
  const Interaction press = stylus_press(stylus_scene(), 2.0);
  const OfflineTrace a = run_closed_loop(press, 17), b = run_closed_loop(press, 17);
  ASSERT_EQ(a.replies.size(), 2000u);
  std::printf("stylus press: max force %.3f N, resets %ld\n", max_force(a), a.resets);
  EXPECT_GT(max_force(a), 0.2) << "the press reaches the bunny";
  EXPECT_EQ(differing_samples(a, b), 0);
  for (std::size_t k = 0; k < a.poses.size(); ++k)
    ASSERT_EQ(std::memcmp(a.poses[k].p_D[0].data(), b.poses[k].p_D[0].data(), 3 * sizeof(double)), 0) << "tick " << k;
}

TEST(OfflineRun, ReplayingTheRecordedPosesReproducesTheClosedLoopRunExactly) {
  // The open loop of the multirate experiment: a run fed the poses a closed-loop
  // run recorded renders the same forces at the same ticks (same input, same pipeline).
  const Interaction press = stylus_press(stylus_scene(), 2.0);
  const OfflineTrace closed = run_closed_loop(press, 17);
  OfflineOptions options;
  options.visual_every_ticks = 17;
  OfflineLoops loops(press.scene, options);
  RecordedDevice replay(closed.poses);
  const OfflineTrace open = run_offline(loops, replay, static_cast<long>(closed.poses.size()));
  EXPECT_EQ(differing_samples(open, closed), 0);
  EXPECT_EQ(force_error(open, closed).max_n, 0.0);
}

TEST(OfflineRun, TwoRunsOfTheGloveGraspGiveBitIdenticalForceStreams) {
  // The fingertips glove (6 frames) closing into the power grasp over the box, 30 Hz visual loop.
  const Interaction grasp = glove_grasp(glove_scene(), 1.2, 6);
  const OfflineTrace a = run_closed_loop(grasp, 33), b = run_closed_loop(grasp, 33);
  std::printf("glove grasp: max frame force %.3f N, resets %ld\n", max_force(a), a.resets);
  EXPECT_GT(max_force(a), 0.05) << "the grasp touches the box";
  EXPECT_EQ(differing_samples(a, b), 0);
}

TEST(OfflineRun, TheVisualLoopStepsEveryKTicksByKPeriods) {
  const Interaction press = stylus_press(stylus_scene(), 0.1);
  for (int k : {1, 7, 33}) {
    OfflineOptions options;
    options.visual_every_ticks = k;
    OfflineLoops loops(press.scene, options);
    const std::unique_ptr<OfflineDevice> device = press.device(loops);
    const OfflineTrace t = run_offline(loops, *device, 100);
    // Steps at ticks 0, k, 2k, ... < 100, each of k ms of simulated time.
    const long steps = (100 + k - 1) / k;
    EXPECT_EQ(t.timings.visual_steps, steps) << "k = " << k;
    EXPECT_EQ(loops.world().snapshot().step, steps) << "k = " << k;
    EXPECT_NEAR(loops.world().snapshot().t_s, steps * k * 1e-3, 1e-12) << "k = " << k;
  }
}

TEST(OfflineRun, ProxiesTimedAtTheEndOfTheirTickKeepAFreeSpaceSweepPassiveAtEveryVisualRate) {
  // A 2 cm, 1 Hz sweep along y (device space) for 3 s in free space. The world
  // stepped at every tick takes energy out of the device (measured -0.115 J);
  // so must the loops at 60 and 240 Hz. With the proxies taken one period stale (the visual step
  // timed from the tick's start, as hapticd's visual loop can read them) the
  // model's step is misplaced by a tick and the loops give energy out: shown with the hand at its
  // material's full mass, whose momentum the misplaced step pumps (the served light hand has too little
  // to gain more than the coupling takes out: -0.004 J stale), and both hands are passive on time.
  auto sweep = [](int visual_every_ticks, bool stale, std::optional<double> mass_scale = std::nullopt) {
    OfflineOptions options;
    options.visual_every_ticks = visual_every_ticks;
    options.targets_one_tick_stale = stale;
    options.palm_hand_mass_scale = mass_scale;
    OfflineLoops loops(stylus_scene(), options);
    Eigen::Vector3d start_D;
    Eigen::Quaterniond q_D;
    loops.frame_pose_at_handle(0, start_D, q_D);
    SimulatedStylus device(
        start_D, [](double t) { return Eigen::Vector3d(0, 0.02 * std::sin(2 * std::numbers::pi * t), 0); }, 1e-3);
    run_offline(loops, device, 3000);
    std::printf("sweep, every %d ticks%s%s: energy into the device %+.4f J, resets %ld\n", visual_every_ticks,
                stale ? ", stale proxies" : "", mass_scale ? ", full-mass hand" : "", device.energy_j(),
                loops.resets());
    return device.energy_j();
  };
  EXPECT_LT(sweep(17, false), 0.0);
  EXPECT_LT(sweep(4, false), 0.0);
  EXPECT_LT(sweep(17, false, 1.0), 0.0);
  EXPECT_LT(sweep(4, false, 1.0), 0.0);
  EXPECT_GT(sweep(4, true, 1.0), 0.0);
}

}  // namespace
}  // namespace hapticd::offline
