#include "wall_press.hpp"

#include <algorithm>
#include <cmath>
#include <limits>
#include <numbers>
#include <stdexcept>

#include "hand_models/fem_hand.hpp"
#include "server/world/scene_loader.hpp"
#include "server/world/world.hpp"

namespace hapticd::bench {
namespace {

// 0 -> 1 over [0, 1] with zero slope at both ends.
double half_cosine(double s) { return 0.5 - 0.5 * std::cos(std::numbers::pi * std::clamp(s, 0.0, 1.0)); }

}  // namespace

Eigen::Vector3d PressProfile::offset(double t_s) const {
  const double down = half_cosine((t_s - settle_s) / ramp_s);
  const double up = half_cosine((t_s - settle_s - ramp_s - hold_s) / ramp_s);
  return {0, 0, -depth_m * (down - up)};
}

PressProfile default_press() { return {}; }
PressProfile tiny_press() { return {0.05, 0.5, 0.1, 0.05, 0.02}; }

world::SceneDesc wall_scene(const std::string& path, int hand_tets, double gap_m) {
  world::SceneDesc scene = world::load_scene(path);
  if (scene.hands.empty() || scene.devices.empty())
    throw std::runtime_error(path + ": the press needs a hand and a device");
  if (hand_tets > 0)
    for (world::HandDesc& h : scene.hands) h.resolution_tets = hand_tets;
  scene.objects.clear();
  scene.joints.clear();
  double lowest = std::numeric_limits<double>::infinity();
  {
    // The hand as the world builds it at its pose (nothing else in the scene yet).
    const world::World probe(scene, world::WorldOptions{});
    const Eigen::VectorXd& x = hand::as_fem(probe.hand(0)).state.x;
    for (Eigen::Index i = 2; i < x.size(); i += 3) lowest = std::min(lowest, x(i));
  }
  world::ObjectDesc wall;
  wall.name = "wall";
  wall.kind = world::BodyKind::static_body;
  wall.shape.type = world::ShapeType::box;
  wall.shape.size = {0.3, 0.3, 0.04};
  wall.pose.p_W = scene.hands[0].pose.p_W;
  wall.pose.p_W.z() = lowest - gap_m - 0.5 * wall.shape.size.z();
  if (const world::MaterialDesc* wood = scene.find_material("wood")) wall.material = *wood;
  scene.objects.push_back(wall);
  return scene;
}

offline::SimulatedStylus press_stylus(const offline::OfflineLoops& loops, const PressProfile& press,
                                      const sim::DeviceParams& params) {
  Eigen::Vector3d start_D;
  Eigen::Quaterniond q_D;
  loops.frame_pose_at_handle(0, start_D, q_D);
  return offline::SimulatedStylus(
      start_D, [press](double t) { return press.offset(t); }, loops.options().haptic_period_s, params);
}

PressRun run_press(offline::OfflineLoops& loops, offline::OfflineDevice& device, long ticks,
                   const PressProfile& press) {
  PressRun run;
  const int every = loops.options().visual_every_ticks;
  double sum2 = 0;
  long pressed_steps = 0;
  run.trace = offline::run_offline(loops, device, ticks, [&](long tick) {
    if (tick % every != 0) return;  // no visual step at this tick
    const double depth = std::max(0.0, loops.world().snapshot().max_penetration_m);
    run.penetration_max_m = std::max(run.penetration_max_m, depth);
    const double t_end = loops.time_s() + (every - 1) * loops.options().haptic_period_s;
    if (t_end >= press.pressed_from_s() && t_end <= press.pressed_to_s()) sum2 += depth * depth, ++pressed_steps;
  });
  run.penetration_rms_m = pressed_steps ? std::sqrt(sum2 / static_cast<double>(pressed_steps)) : 0.0;
  return run;
}

}  // namespace hapticd::bench
