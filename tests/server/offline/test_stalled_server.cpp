// A stalled server (issue 17: safety on a busy machine). The process is descheduled for tens of
// milliseconds while the user keeps moving: the tick that resumes sees the device centimetres on,
// the proxy rushes after it, the world's step is stretched toward kMaxStep_s (150 ms) by the lag, and
// its model arrives late. The lockstep runner plays this on the stylus bunny, movable and fixed, at a
// 10 Hz visual step (and at 150 and 200 ms, LongerSteps; the deformable bunny at all three): the device presses 2.5 cm
// down, strokes along the bunny, and every 250 ms jumps within one tick, alternately down, up, +x and -x.
//
// ThreeCentimetreJumps (a 40 ms stall at 0.75 m/s; models 30 ms late) and FiveCentimetreJumps
// (models 90 ms late): nothing resets and the hand stays out of the bunny (at most kClearanceFloor_m,
// 5 mm, which a handle may close toward a surface in one visual step). Measured when written:
//   - at 3 cm the world's target extrapolated the proxy, rushing at 4 m/s after the device, over the
//     late step: the hand went 33 mm into the movable bunny and 1.2 m through the fixed one (a torn
//     hand the world then reset); fixed by stopping the extrapolation at the handle's clearance
//     planes (proxy_target): 2.7 and 2.1 mm;
//   - at 5 cm (10 cm in the world) the handle was more than the 5 cm the world then looked ahead for
//     clearance planes from every surface, so nothing bounded it: 114 and 164 mm; with the world
//     looking 10 cm ahead (kClearanceLook_m), 0.4 and 1.7 mm.
//
// EightCentimetreJumps (models 90 ms late): no proxy reset, the force within the device's limit and
// rate limit. CI's make test failed on proxy resets through hapticd (haptic-bench soak: 2 in a window
// of 28 overruns); here the tick's contact solve threw the proxy past kMaxProxySpeed_m_s and reset it
// 259 times on the fixed bunny (none on the movable one), the force dropping at 8000 N/s. Fixed by
// solving again without the lookahead, then holding the proxy still (ProxyHand::integrate): 79 and
// 134 such solves, 134 holds. Since the skin's travel within one model is bounded too (below), the
// proxy no longer gets far enough from its anchor for either here: the precondition is that bound.
// 16 cm in the world is beyond the 10 cm the clearance planes look ahead: the hand went 19.5 mm
// into the movable bunny and 2.9 m through the fixed one (2 world resets); with the proxy and the
// step's target carrying no skin point farther than that from where the planes were measured
// (hand::free_travel_share), 11.8 and 12.6 mm, nothing reset.
//
// LongerSteps: 150 and 200 ms steps (kMaxStep_s was 100 ms, and is 150 ms since they pass). Measured before the fix
// below, the deepest contact at 150 / 200 ms: 3 cm jumps 11.4 / 18.0 mm on the movable bunny,
// 1660 / 204 mm on the fixed one (a world reset at 150 ms); 8 cm jumps 11.5 / 3.5 mm and
// 17.6 / 12.5 mm. And at 100 ms, 2 cm jumps with models 90 ms late: 18.0 mm on the movable bunny.
// Traced (temporary prints): at 150 ms, 3 cm, on the fixed bunny, a step carried the hand 4.6 cm
// down with no contact row, closing a clearance plane's 44.5 mm gap whole, and the bunny's vertices
// were 11 mm inside the palm at its end; at 100 ms, 2 cm, on the movable one, a step carried it
// 84 mm down with no plane at all. Two gaps in the planes, both closed:
//   - the bunny's distance grid answers to 1.65 cm only, so a skin point farther off had no
//     clearance plane from it (the 10 cm look held for boxes, not meshes). Now a coarser grid
//     answers to 10 cm (RigidWorld::far_clearance);
//   - a skin point within the step's reach is a speculative row, not a plane, so when the hand had
//     been fast (reach up to 5 cm) nothing but those rows, tangent to the bunny where they were
//     found, bounded the next step's target. Now a row farther than kClearanceFloor_m is a plane too.
// Every run here now ends at most 2.2 mm deep, none resets. Each fix is needed (a temporary switch):
// without the coarse grid 10 of the 24 runs went past 5 mm (up to 1.78 m), without the rows' planes
// one did (10.9 mm: the fixed bunny, 150 ms steps, 2 cm jumps). A step may still close a far gap whole.
// A step that closed at most half of a gap beyond the floor kept 2-10 cm jumps at 100-200 ms steps
// within 0.5 mm (against 2.3 mm without it), but made the glove's grasp sensitive to a missed sample
// (SampleGaps: up to 0.97 N against 0.05 N), and was not kept.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <numbers>
#include <string>
#include <utility>

#include "server/offline/offline_run.hpp"
#include "server/offline/touch.hpp"
#include "server/world/scene_loader.hpp"

namespace hapticd::offline {
namespace {

constexpr double kPeriod = 1e-3;

struct StallRun {
  long proxy_resets = 0, world_resets = 0, fallbacks = 0, holds = 0, contact_ticks = 0, bounded = 0;
  double max_force_n = 0, max_rate_n_s = 0;
  double deepest_m = 0;  // the deepest of the world's contacts (WorldSnapshot::max_penetration_m)
};

StallRun run_stalls(const world::SceneDesc& scene, double jump_m, int model_delay_ticks, int step_ticks = 100) {
  OfflineOptions options;
  options.visual_every_ticks = step_ticks;
  options.model_delay_ticks = model_delay_ticks;
  options.settle_s = 0.5;
  options.contact.reset();  // the scene's constraint contact
  OfflineLoops loops(scene, options);
  StallRun out;
  Eigen::Vector3d start;
  DeviceFrames sample;
  sample.frames = 1;
  loops.frame_pose_at_handle(0, start, sample.q_D[0]);
  // Down 2.5 cm in 1 s (the palm meets the bunny ~1 cm down), then stroked +-2 cm along x at 0.5 Hz.
  const auto path = [](double t) {
    return Eigen::Vector3d(t > 1.0 ? 0.02 * std::sin(std::numbers::pi * (t - 1.0)) : 0.0, 0, -0.025 * std::min(t, 1.0));
  };
  const Eigen::Vector3d jumps[4] = {{0, 0, -1}, {0, 0, 1}, {1, 0, 0}, {-1, 0, 0}};
  Eigen::Vector3d jumped = Eigen::Vector3d::Zero(), last_f = Eigen::Vector3d::Zero();
  DeviceReply reply;
  const long ticks = std::lround(5.0 / kPeriod);
  for (long k = 0; k < ticks; ++k) {
    if (k > 1000 && k % 250 == 0) jumped += jump_m * jumps[(k / 250) % 4];
    sample.p_D[0] = start + path(k * kPeriod) + jumped;
    loops.tick(sample, reply);
    const Eigen::Vector3d f = reply.wrench[0].f_D;
    out.max_force_n = std::max(out.max_force_n, f.norm());
    if (k > 0) out.max_rate_n_s = std::max(out.max_rate_n_s, (f - last_f).norm() / kPeriod);
    last_f = f;
    out.contact_ticks += reply.in_contact[0];
    out.deepest_m = std::max(out.deepest_m, loops.world().snapshot().max_penetration_m);
  }
  const haptic::ProxyHand& proxy = loops.proxy();
  out.proxy_resets = proxy.resets();
  out.world_resets = loops.resets() - proxy.resets();
  out.fallbacks = proxy.lookahead_fallbacks();
  out.holds = proxy.contact_holds();
  out.bounded = proxy.travel_limits();
  std::printf(
      "%s, %d ms steps, %.0f cm jumps, models %d ms late: proxy resets %ld, world resets %ld, contact solves "
      "without the lookahead %ld, holds %ld, ticks held by the travel bound %ld, contact ticks %ld, largest force "
      "%.2f N, fastest change %.0f N/s, deepest contact %.1f mm\n",
      scene.name.c_str(), step_ticks, 100 * jump_m, model_delay_ticks, out.proxy_resets, out.world_resets,
      out.fallbacks, out.holds, out.bounded, out.contact_ticks, out.max_force_n, out.max_rate_n_s, 1e3 * out.deepest_m);
  return out;
}

world::SceneDesc bunny_scene(bool movable) {
  world::SceneDesc scene = world::load_scene(std::string(HAPTICD_SCENES_DIR) + "/stylus_bunny.json");
  scene.name = movable ? "movable bunny" : "fixed bunny";
  for (world::ObjectDesc& o : scene.objects)
    if (!movable && o.name == "bunny") o.kind = world::BodyKind::static_body;
  return scene;
}

// Whether the force stayed within the device's limits and nothing reset on the haptic side.
void expect_safe_force(const world::SceneDesc& scene, const StallRun& r) {
  EXPECT_EQ(r.proxy_resets, 0) << scene.name;
  EXPECT_LE(r.max_force_n, scene.devices[0].max_force_n + 1e-6) << scene.name;
  EXPECT_LE(r.max_rate_n_s, scene.devices[0].max_force_rate_n_s * (1 + 1e-6)) << scene.name;
}

// The hand stayed out of the bunny and nothing reset.
void expect_hand_out(const world::SceneDesc& scene, const StallRun& r) {
  EXPECT_EQ(r.world_resets, 0) << scene.name;
  EXPECT_LE(r.deepest_m, 5e-3) << scene.name;
}

// The device pressed on the bunny for at least a second of the five: a precondition (the deformable
// bunny's 8 cm jumps at 200 ms steps press for exactly 1000 ticks, five whole steps, since a much
// longer step collides again).
void expect_pressed(const world::SceneDesc& scene, const StallRun& r) {
  EXPECT_GE(r.contact_ticks, 1000) << scene.name << ": the stylus pressed on the bunny";
}

// The stalls of 2, 3, 5 and 8 cm jumps (models 90, 30, 90 and 90 ms late) on `scene` at steps of
// `step_ticks`: pressed, safe forces, the hand out of the object.
void expect_stalls_safe(const world::SceneDesc& scene, int step_ticks) {
  for (const auto& [jump_m, late_ticks] :
       {std::pair{0.02, 90}, std::pair{0.03, 30}, std::pair{0.05, 90}, std::pair{0.08, 90}}) {
    const StallRun r = run_stalls(scene, jump_m, late_ticks, step_ticks);
    expect_pressed(scene, r);
    expect_safe_force(scene, r);
    expect_hand_out(scene, r);
  }
}

TEST(StalledServer, TwoThreeAndFiveCentimetreJumpsResetNothingAndKeepTheHandOutOfTheBunny) {
  for (bool movable : {true, false}) {
    const world::SceneDesc scene = bunny_scene(movable);
    for (const auto& [jump_m, late_ticks] : {std::pair{0.02, 90}, std::pair{0.03, 30}, std::pair{0.05, 90}}) {
      const StallRun r = run_stalls(scene, jump_m, late_ticks);
      expect_pressed(scene, r);
      expect_safe_force(scene, r);
      expect_hand_out(scene, r);
    }
  }
}

TEST(StalledServer, EightCentimetreJumpsResetNothingAndKeepTheHandOutOfTheBunny) {
  for (bool movable : {true, false}) {
    const world::SceneDesc scene = bunny_scene(movable);
    const StallRun r = run_stalls(scene, 0.08, 90);
    expect_pressed(scene, r);
    EXPECT_GT(r.bounded, 0) << scene.name << ": the stalls did not reach the travel bound";
    expect_safe_force(scene, r);
    expect_hand_out(scene, r);
  }
}

// The same stalls with the world's step at 150 ms (kMaxStep_s: a loaded world that keeps up with the
// clock) and, for a margin, 200 ms.
TEST(StalledServer, LongerStepsResetNothingAndKeepTheHandOutOfTheBunny) {
  for (const int step_ticks : {150, 200})
    for (bool movable : {true, false}) expect_stalls_safe(bunny_scene(movable), step_ticks);
}

// The same stalls on the deformable bunny (deformable_bunny.json, the hand placed as on the stylus
// bunny) at 100, 150 and 200 ms steps. While a hand met a deformable object only within 2 mm of it (no
// speculative rows, no clearance planes from it; 6847105) none reset, but the hand went 18-176 mm into
// it at 100 ms, 12-33 mm at 150 ms and 39-103 mm at 200 ms; since cbd33e2 at most 1.1 mm (1.7 mm
// since 2a49e32).
TEST(StalledServer, DeformableBunnyJumpsResetNothingAndKeepTheHandOutOfIt) {
  world::SceneDesc scene = press_scene("deformable_bunny");
  scene.name = "deformable bunny";
  for (const int step_ticks : {100, 150, 200}) expect_stalls_safe(scene, step_ticks);
}

}  // namespace
}  // namespace hapticd::offline
