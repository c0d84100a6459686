// The two loops run in step, deterministically, in one thread (server/offline:
// the offline mode): the shipped stylus scene's world stepped every 17 ms
// (~60 Hz) with the proxy as the handle's target, the proxy integrated every
// 1 ms under the last published model, and the simulated stylus of clients/sim
// (0.1 kg tip held by the user's arm, 200 N/m, 5 N s/m) feeling the replies.
// Free space must feel free and put no net energy in.
#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <numbers>
#include <optional>
#include <vector>

#include "box_scene.hpp"
#include "hand_models/fem_hand.hpp"
#include "server/offline/offline_run.hpp"
#include "server/world/scene_loader.hpp"

namespace hapticd::haptic {
namespace {

// A settled moment of a run: the device's force and position (device space), the
// proxy's height below its start and the world's coupling force on the handle (world).
struct Settled {
  double f_D = 0, p_D = 0, proxy_dz = 0, hand_force = 0;
};

struct LoopRun {
  double max_force_n = 0, max_force_late_n = 0;
  std::vector<Settled> settled;  // at the times asked for
  double energy_j = 0;           // net work of the rendered force on the device
  double gross_energy_j = 0;     // the work exchanged either way, sum |f . v| dt
  long resets = 0;
};

// `command(t)`: where the user's arm pulls the device tip (device space), from where it starts (on the handle).
// `delay_ticks`: how long after its step a model reaches the haptic loop (the visual step's compute time).
// `settle_at`: times (s) at which to record a Settled (z components).
LoopRun run_loops(double seconds, const offline::SimulatedStylus::Command& command, int delay_ticks = 0,
                  world::SceneDesc scene = world::load_scene(std::string(HAPTICD_SCENES_DIR) + "/stylus_bunny.json"),
                  const std::vector<double>& settle_at = {},
                  std::optional<double> palm_hand_mass_scale = std::nullopt) {
  offline::OfflineOptions options;
  options.palm_hand_mass_scale = palm_hand_mass_scale;
  options.visual_every_ticks = 17;  // 17 ticks of 1 ms: world time keeps pace with the proxies
  options.model_delay_ticks = delay_ticks;
  options.passivity_control = false;  // the loops' own passivity
  offline::OfflineLoops loops(scene, options);
  const double period = options.haptic_period_s;
  // The device starts where the handle is (no jump to excite the flesh); `command` is an offset from there.
  const hand::HandleState h0 = loops.world().snapshot().handles[0][0];
  Eigen::Vector3d start_D;
  Eigen::Quaterniond q_D;
  loops.frame_pose_at_handle(0, start_D, q_D);
  offline::SimulatedStylus device(start_D, command, period);
  offline::DeviceFrames sample;
  offline::DeviceReply reply;
  Eigen::Vector3d f = Eigen::Vector3d::Zero();  // the force the device holds
  LoopRun out;
  for (int k = 0; k < static_cast<int>(seconds / period); ++k) {
    const double t = k * period;
    device.advance(k, t, sample);
    const sim::Vec3d v = device.state().v_DT_m_s;
    out.gross_energy_j += std::abs(f.dot(Eigen::Vector3d(v.x, v.y, v.z))) * period;
    loops.tick(sample, reply);
    device.receive(reply);
    f = reply.wrench[0].f_D;
    out.max_force_n = std::max(out.max_force_n, f.norm());
    if (t > 0.5 * seconds) out.max_force_late_n = std::max(out.max_force_late_n, f.norm());
    for (double at : settle_at)
      if (k == static_cast<int>(std::lround(at / period))) {
        const hand::FemHand& hand = hand::as_fem(loops.world().hand(0));
        out.settled.push_back({f.z(), sample.p_D[0].z(), loops.proxy().proxy(0).p_W.z() - h0.p_WH.z(),
                               coupling_wrench(*hand.model, hand.state.x, hand.state.v, hand.state.handles)[2]});
      }
  }
  out.energy_j = device.energy_j();
  out.resets = loops.resets();
  return out;
}

TEST(LoopsOffline, DeviceHeldStillInFreeSpaceFeelsNothing) {
  const LoopRun r = run_loops(2.0, [](double) { return Eigen::Vector3d(Eigen::Vector3d::Zero()); });
  std::printf("held: max force %.4f N (late %.4f N), energy %.2e J\n", r.max_force_n, r.max_force_late_n, r.energy_j);
  EXPECT_LT(r.max_force_late_n, 0.05);
  EXPECT_EQ(r.resets, 0);
}

TEST(LoopsOffline, DeviceSweptThroughFreeSpaceFeelsOnlyTheServedHandsLightInertiaAndIsPassive) {
  // A 2 cm, 1 Hz sweep along y for 6 s (4 cm in the world: the hand at 1.6 m/s^2), with the hand at its
  // material's full mass (~0.4 kg) and as hapticd serves it (haptic::kServedPalmHandMassScale of that).
  const auto sweep = [](std::optional<double> mass_scale) {
    return run_loops(
        6.0, [](double t) { return Eigen::Vector3d(0, 0.02 * std::sin(2 * std::numbers::pi * t), 0); }, 0,
        world::load_scene(std::string(HAPTICD_SCENES_DIR) + "/stylus_bunny.json"), {}, mass_scale);
  };
  const LoopRun full = sweep(1.0), served = sweep(std::nullopt);
  for (const LoopRun* r : {&full, &served}) {
    std::printf("swept, %s hand: max force %.3f N, net energy %.3e J of %.3e J exchanged\n",
                r == &full ? "full-mass" : "served", r->max_force_n, r->energy_j, r->gross_energy_j);
    // Free space is passive: no net energy into the device over the sweep. (With the proxies taken one
    // period stale, OfflineOptions::targets_one_tick_stale, the loops put energy in: the fault this test
    // was written against, which it let through up to 10 % of the work exchanged.)
    ASSERT_GT(r->gross_energy_j, 0.0) << "no work exchanged: the sweep did not run";
    EXPECT_LE(r->energy_j, 0.0);
    EXPECT_EQ(r->resets, 0);
  }
  EXPECT_GT(full.max_force_n, 0.5);  // the full hand's inertia is felt (2 x 0.4 kg x 1.6 m/s^2 on the device)...
  EXPECT_LT(full.max_force_n, 3.0);  // ...and nothing more
  // The served hand has kServedPalmHandMassScale of that inertia: what is left is mostly the coupling's
  // damping, well under a tenth of the full hand's.
  EXPECT_LT(served.max_force_n, 0.1 * full.max_force_n);
}

TEST(LoopsOffline, StylusPressedOnAStaticBoxFeelsTheSeriesStiffnessOfCouplingAndHand) {
  // Pressed 1.2 cm (device space) and settled, then 1 mm deeper and settled: the
  // rendered stiffness is the device-side coupling in series with the hand on the
  // box, whose stiffness the world shows between the same two settled states
  // (contact makes the hand path dependent, so both come from one run).
  const double scale = 2.0, k_dev = 1000.0;
  const LoopRun r =
      run_loops(6.0,
                [](double t) {
                  return Eigen::Vector3d(0, 0, -0.012 * std::min(1.0, t) - 0.001 * std::clamp(2 * (t - 3), 0.0, 1.0));
                },
                0, test::static_box_scene(), {3.0, 5.99});
  ASSERT_EQ(r.settled.size(), 2u);
  const Settled &a = r.settled[0], &b = r.settled[1];
  ASSERT_GT(a.f_D, 0.2) << "the stylus presses on the box";
  const double k_rendered = (b.f_D - a.f_D) / (a.p_D - b.p_D);
  const double k_hand = (b.hand_force - a.hand_force) / (a.proxy_dz - b.proxy_dz);
  const double k_series = 1.0 / (1.0 / k_dev + 1.0 / (scale * scale * k_hand));
  std::printf("rendered %.1f N/m; coupling %.0f N/m in series with the hand %.1f N/m (x s^2 = %.1f): %.1f N/m\n",
              k_rendered, k_dev, k_hand, scale * scale * k_hand, k_series);
  EXPECT_NEAR(k_rendered, k_series, 0.05 * k_series);
  // And the force is the hand's, through the map: f_D = s F.
  EXPECT_NEAR(b.f_D, scale * b.hand_force, 0.05 * scale * b.hand_force);
}

TEST(LoopsOffline, PressAndStrokeOnTheBunnyWithModelsArrivingHalfAStepLateIsPassive) {
  // Down 2 cm (4 cm in the world: the palm onto the bunny) in 1 s, then a 2 cm
  // stroke along x; each model reaches the haptic loop 8 ms after its step (the
  // visual step's own latency), as in the server.
  const LoopRun r = run_loops(
      5.0,
      [](double t) {
        return Eigen::Vector3d(t > 2 ? 0.02 * std::sin(std::numbers::pi * (t - 2)) : 0, 0, -0.02 * std::min(1.0, t));
      },
      8);
  std::printf("press-stroke: max force %.3f N, net energy %.2e J of %.2e J exchanged\n", r.max_force_n, r.energy_j,
              r.gross_energy_j);
  EXPECT_GT(r.max_force_n, 0.2);  // it touches
  EXPECT_LE(r.energy_j, 0.0);
  EXPECT_EQ(r.resets, 0);
}

}  // namespace
}  // namespace hapticd::haptic
