#include "server/offline/multirate.hpp"

#include <algorithm>
#include <cmath>
#include <stdexcept>
#include <utility>

#include "clients/sim/glove_trajectory.hpp"
#include "clients/sim/trajectory.hpp"

namespace hapticd::offline {
namespace {

Eigen::Vector3d to_eigen(sim::Vec3d v) { return {v.x, v.y, v.z}; }

}  // namespace

Interaction stylus_press(world::SceneDesc scene, double seconds) {
  Interaction in;
  in.name = "stylus_press";
  in.scene = std::move(scene);
  in.seconds = seconds;
  in.device = [](const OfflineLoops& loops) -> std::unique_ptr<OfflineDevice> {
    Eigen::Vector3d start_D;
    Eigen::Quaterniond q_D;
    loops.frame_pose_at_handle(0, start_D, q_D);
    // The trajectory's start (kApproachHeightM above its origin) is the handle.
    const sim::Trajectory press = sim::Trajectory::press();
    const Eigen::Vector3d p0 = to_eigen(press.position(0.0));
    return std::make_unique<SimulatedStylus>(
        start_D, [press, p0](double t) { return Eigen::Vector3d(to_eigen(press.position(t)) - p0); },
        loops.options().haptic_period_s);
  };
  return in;
}

world::SceneDesc with_rigid_bodies_fixed(world::SceneDesc scene) {
  for (world::ObjectDesc& o : scene.objects)
    if (o.kind == world::BodyKind::rigid) {
      o.kind = world::BodyKind::static_body;
      o.linear_velocity.setZero();
      o.angular_velocity.setZero();
    }
  return scene;
}

Interaction stylus_press_fixed(world::SceneDesc scene, double seconds) {
  Interaction in = stylus_press(with_rigid_bodies_fixed(std::move(scene)), seconds);
  in.name = "stylus_press_fixed";
  return in;
}

Interaction glove_grasp(world::SceneDesc scene, double seconds, int frames) {
  if (frames != sim::kGloveFramesAll && frames != sim::kGloveFramesTips)
    throw std::invalid_argument("glove_grasp: 16 or 6 frames, not " + std::to_string(frames));
  if (scene.hands.empty()) throw std::invalid_argument("glove_grasp: " + scene.name + " has no hand");
  scene.hands[0].handles = frames == sim::kGloveFramesAll ? world::HandleSet::phalanges : world::HandleSet::fingertips;
  Interaction in;
  in.name = frames == sim::kGloveFramesAll ? "glove_grasp" : "glove_grasp_tips";
  in.scene = std::move(scene);
  in.seconds = seconds;
  const bool left = in.scene.hands[0].side == world::HandSide::left;
  in.device = [frames, left](const OfflineLoops& loops) -> std::unique_ptr<OfflineDevice> {
    Eigen::Vector3d palm_D;
    Eigen::Quaterniond q_D;
    loops.frame_pose_at_handle(0, palm_D, q_D);
    sim::GloveTrajectory grasp = sim::GloveTrajectory::grasp({palm_D.x(), palm_D.y(), palm_D.z()});
    grasp.set_palm_orientation(q_D);
    return std::make_unique<SimulatedGlove>(std::move(grasp), frames, left, loops.options().haptic_period_s);
  };
  return in;
}

ForceError force_error(const OfflineTrace& run, const OfflineTrace& reference, int visual_ticks) {
  ForceError e;
  const std::size_t n = std::min(run.replies.size(), reference.replies.size());
  // The visual steps come at ticks 0, P, 2P, ... (OfflineLoops::tick).
  const long period = visual_ticks, eighth = period / 8;
  double sum2 = 0, near2 = 0, mid2 = 0;
  long near = 0, mid = 0;
  for (std::size_t k = 0; k < n; ++k) {
    const DeviceReply &a = run.replies[k], &b = reference.replies[k];
    double e2 = 0;
    for (int j = 0; j < std::min(a.frames, b.frames); ++j) e2 += (a.wrench[j].f_D - b.wrench[j].f_D).squaredNorm();
    sum2 += e2;
    e.max_n = std::max(e.max_n, std::sqrt(e2));
    if (period < 4) continue;
    const long phase = static_cast<long>(k) % period, from_step = std::min(phase, period - phase);
    if (from_step <= eighth) near2 += e2, ++near;
    if (std::abs(2 * phase - period) <= 2 * eighth) mid2 += e2, ++mid;
  }
  e.rms_n = n ? std::sqrt(sum2 / static_cast<double>(n)) : 0.0;
  if (near) e.rms_near_steps_n = std::sqrt(near2 / static_cast<double>(near));
  if (mid) e.rms_mid_period_n = std::sqrt(mid2 / static_cast<double>(mid));
  return e;
}

double rms_force(const OfflineTrace& trace) {
  double sum2 = 0;
  for (const DeviceReply& r : trace.replies)
    for (int j = 0; j < r.frames; ++j) sum2 += r.wrench[j].f_D.squaredNorm();
  return trace.replies.empty() ? 0.0 : std::sqrt(sum2 / static_cast<double>(trace.replies.size()));
}

MultirateRuns run_multirate(const Interaction& interaction, const std::vector<int>& visual_ticks,
                            const std::vector<haptic::HandleModelKind>& models, double haptic_period_s) {
  const long ticks = std::lround(interaction.seconds / haptic_period_s);
  MultirateRuns out;
  OfflineOptions options;
  options.haptic_period_s = haptic_period_s;
  options.visual_every_ticks = 1;
  options.settle_s = interaction.settle_s;
  options.passivity_control = false;  // the models' own rendering, unguarded
  {
    OfflineLoops loops(interaction.scene, options);
    const std::unique_ptr<OfflineDevice> device = interaction.device(loops);
    out.reference = run_offline(loops, *device, ticks);
  }
  for (int k : visual_ticks)
    for (haptic::HandleModelKind model : models) {
      MultirateRow row;
      row.interaction = interaction.name;
      row.visual_ticks = k;
      row.visual_hz = 1.0 / (k * haptic_period_s);
      row.model = model;
      if (k == 1 && model == haptic::HandleModelKind::linearized) {
        row.timings = out.reference.timings;
        row.resets = out.reference.resets;
      } else {
        options.visual_every_ticks = k;
        options.model = model;
        OfflineLoops loops(interaction.scene, options);
        RecordedDevice replay(out.reference.poses);
        const OfflineTrace trace = run_offline(loops, replay, ticks);
        row.error = force_error(trace, out.reference, k);
        row.timings = trace.timings;
        row.resets = trace.resets;
      }
      out.rows.push_back(row);
    }
  return out;
}

}  // namespace hapticd::offline
