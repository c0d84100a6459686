// seed 004 section 3 (after GO09): with the visual loop at 30 Hz, the haptic
// loop renders the hand through the handle-space linearized model at 1 kHz.
// Measured here against a world stepped at every haptic tick, open loop (every
// run replays the reference's device poses: server/offline/multirate.hpp), and
// closed loop (the simulated stylus feels what is rendered).
#include <gtest/gtest.h>

#include <cstdio>

#include "server/offline/multirate.hpp"
#include "server/world/scene_loader.hpp"

namespace hapticd {
namespace {

SceneDesc stylus_scene() { return load_scene(std::string(HAPTICD_SCENES_DIR) + "/stylus_bunny.json"); }

// The press at 30 Hz, open loop, with the linearized model and the zero-order hold: the ratio of
// their RMS force errors against the every-tick world, after the checks that the runs mean
// something (the press loads the device; neither the reference nor the linearized run reset).
double zoh_over_linearized_at_30_hz(const Interaction& press) {
  const MultirateRuns runs = run_multirate(press, {33}, {HandleModelKind::linearized, HandleModelKind::zoh});
  if (runs.rows.size() != 2u) {
    ADD_FAILURE() << runs.rows.size() << " rows";
    return 0;
  }
  const MultirateRow &lin = runs.rows[0], &zoh = runs.rows[1];
  EXPECT_EQ(lin.model, HandleModelKind::linearized);
  EXPECT_EQ(zoh.model, HandleModelKind::zoh);
  const double ratio = zoh.error.rms_n / lin.error.rms_n;
  std::printf(
      "30 Hz %s: reference RMS force %.3f N; RMS error linearized %.4f N (max %.4f), zoh %.4f N (max %.4f, %ld "
      "resets): %.2fx\n",
      press.name.c_str(), rms_force(runs.reference), lin.error.rms_n, lin.error.max_n, zoh.error.rms_n, zoh.error.max_n,
      zoh.resets, ratio);
  EXPECT_GT(rms_force(runs.reference), 0.5) << "the press loads the device";
  EXPECT_EQ(runs.reference.resets, 0);
  EXPECT_EQ(lin.resets, 0);
  return ratio;
}

TEST(Multirate, LinearizedModelBeatsAZeroOrderHoldInRmsForceErrorAt30HzOnTheStylusPress) {
  // The bench's default stylus press: settle 0.5 s, 2 cm (device) down over 1 s onto the bunny, 1 s held.
  // On the movable bunny the ratio is below seed 004's 5x (the next test asserts
  // it on a fixed object): measured 3.4x at this revision. The zero-order hold's error is that of an
  // unstable loop (the proxy under a force held for 33 ms resets ~1500 times in
  // 2.5 s); the linearized model's (0.67 N RMS of 0.97 N) comes from the world
  // at 30 Hz, not from the haptic loop: (1) the first step that touches the rigid
  // bunny is linearized without the bunny's supports (its held contacts are the
  // previous step's, which had none), so for one visual step the model lets the
  // bunny fall and pulls the hand after it (-1.5 N on the device where the
  // reference pushes +0.4 N); (2) under the held hand the 30 Hz world lets the
  // bunny slide ~4 mm, the 1 kHz world does not. With the bunny static the same
  // press gives 16.7x. A regression below 3x fails here; the zero-order hold's
  // error, an unstable loop's, moves by ~10 % with any change to the rounding.
  EXPECT_GE(zoh_over_linearized_at_30_hz(stylus_press(stylus_scene(), 2.5)), 3.0);
}

// The claim itself, where only the rendering differs: the same press on the bunny made static
// (stylus_press_fixed). Seed 004's linearized model against the zero-order hold at 30 Hz.
TEST(Multirate, LinearizedModelBeatsAZeroOrderHoldFiveTimesAt30HzOnTheStylusPressOnAFixedObject) {
  EXPECT_GE(zoh_over_linearized_at_30_hz(stylus_press_fixed(stylus_scene(), 2.5)), 5.0);  // measured 16.7x
}

TEST(Multirate, At30HzOnlyTheLinearizedModelRendersTheStylusPressStablyInClosedLoop) {
  // The press with the simulated stylus feeling each run's forces (closed loop):
  // the linearized model renders it as the 1 kHz world does; holding the last
  // visual force, on the proxy or out of a virtual coupling simulated at 30 Hz,
  // puts energy into the device until the force limit (8 N) or a reset stops it.
  const Interaction press = stylus_press(stylus_scene(), 2.5);
  struct Result {
    double rms_force_n = 0, max_force_n = 0, energy_j = 0;
    long resets = 0;
  };
  auto run = [&](HandleModelKind model, int visual_every_ticks) {
    OfflineOptions options;
    options.visual_every_ticks = visual_every_ticks;
    options.model = model;
    options.settle_s = press.settle_s;
    OfflineLoops loops(press.scene, options);
    const std::unique_ptr<OfflineDevice> device = press.device(loops);
    const OfflineTrace trace = run_offline(loops, *device, 2500);
    Result r{rms_force(trace), 0, dynamic_cast<const SimulatedStylus&>(*device).energy_j(), trace.resets};
    for (const DeviceReply& reply : trace.replies) r.max_force_n = std::max(r.max_force_n, reply.wrench[0].f_D.norm());
    std::printf(
        "closed loop, every %d ticks, %-12s: RMS force %.3f N, max %.3f N, energy into the device %+.4f J, "
        "%ld resets\n",
        visual_every_ticks, to_string(model), r.rms_force_n, r.max_force_n, r.energy_j, r.resets);
    return r;
  };
  // The world stepped at every tick, measured: RMS force 0.973 N, max 1.375 N, -0.004 J, no reset.
  const Result lin = run(HandleModelKind::linearized, 33), zoh = run(HandleModelKind::zoh, 33),
               coupled = run(HandleModelKind::zoh_coupling, 33);
  EXPECT_EQ(lin.resets, 0);
  EXPECT_NEAR(lin.rms_force_n, 0.973, 0.1);  // measured 1.004 N
  EXPECT_LT(lin.max_force_n, 2.0);           // measured 1.606 N
  EXPECT_LT(lin.energy_j, 0.01);             // measured +0.003 J
  EXPECT_GT(zoh.resets, 100);
  EXPECT_GT(coupled.energy_j, 1.0);
  EXPECT_GT(coupled.max_force_n, 0.99 * 8.0);
}

}  // namespace
}  // namespace hapticd
