#include "world_bench.hpp"

#include <spdlog/spdlog.h>

#include <Eigen/Geometry>
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <memory>
#include <numbers>
#include <string>
#include <vector>

#include "bench_common.hpp"
#include "clients/sim/glove_model.hpp"
#include "clients/sim/glove_trajectory.hpp"
#include "hand_models/skeleton/hand_skeleton.hpp"
#include "server/haptic/device_link.hpp"
#include "server/world/scene_loader.hpp"
#include "server/world/world.hpp"

namespace hapticd::bench {
namespace {

struct WorldBenchArgs {
  std::string scene;
  int steps = 240;
  std::string solver = "cholmod";
  std::string json;
};

struct RunStats {
  std::vector<double> total, collide, hands, contact, rigid, linearize, deformable, contacts;
  // |F of the model published before this step (the coming step's, as the server
  // builds it) at this step's end state - the coupling force at that state|, N:
  // what the haptic loop renders against what the step finds (hand 0, the force
  // part of the worst handle). The published model (ContactLinearization::unilateral: its
  // constraint contacts solved at that state, as the haptic tick does) and, a baseline in the same
  // run, the same linearization with the last step's contacts held bilaterally (GO09).
  std::vector<double> force_error_n, force_error_bilateral_n;
  double max_penetration_m = 0;
  long resets = 0;
};

// A hand driven by a glove device of the scene follows the glove's grasp (sim::GloveTrajectory::grasp:
// rest, close into the power grasp over 1 s, hold) from where its palm starts, its handles on the
// commanded frames as the glove's DeviceMap places them (no haptic loop: the handles' targets are the
// frames themselves).
Eigen::Vector3d to_eigen(sim::Vec3d v) { return {v.x, v.y, v.z}; }

struct GloveScript {
  int hand = -1;
  haptic::DeviceLink link;
  sim::GloveTrajectory trajectory = sim::GloveTrajectory::grasp();
};

std::vector<GloveScript> glove_scripts(const world::SceneDesc& scene, const world::World& world) {
  std::vector<GloveScript> out;
  for (const world::DeviceDesc& d : scene.devices) {
    if (d.kind != world::DeviceKind::glove) continue;
    GloveScript g;
    g.hand = world.find_hand(d.hand);
    g.link = haptic::make_device_link(world, d, 1000.0);
    const hand::HandleState& palm = world.hand(g.hand).handles()[0];
    Eigen::Vector3d palm_D;
    Eigen::Quaterniond q_D;
    g.link.map.to_device(0, {palm.p_WH, palm.q_WH}, palm_D, q_D);
    g.trajectory = sim::GloveTrajectory::grasp({palm_D.x(), palm_D.y(), palm_D.z()});
    g.trajectory.set_palm_orientation(q_D);
    out.push_back(std::move(g));
  }
  return out;
}

void set_glove_targets(const GloveScript& g, double t, hand::Hand& hand) {
  const sim::RigidPose palm{to_eigen(g.trajectory.palm_position(t)), g.trajectory.palm_orientation()};
  const auto frames = sim::glove_frame_poses(
      hand::skeleton_pose(hand::HandJointAngles::from_vector(g.trajectory.angles(t)), g.link.left), palm,
      g.link.handles);
  for (int j = 0; j < g.link.handles; ++j) {
    const haptic::HapticPose pose = g.link.map.to_world(j, frames[j].p_m, frames[j].q);
    hand::HandleTarget target;
    target.p_W = pose.p_W;
    target.q_W = pose.q_W;
    hand.set_target(j, target);
  }
}

// Every other hand's handles travel in the first second to 6 cm above the scene's
// first rigid or deformable object (file order), come down onto it in the next
// half second (palm centre 5 mm above its top surface, so the palm's skin
// presses into it), then stroke 2 cm along x with a 2 s period.
RunStats run(const world::SceneDesc& scene, world::WorldOptions options, int steps) {
  options.linearize = false;  // the model is the coming step's, built after each step as the server does
  world::World world(scene, options);
  const std::vector<GloveScript> gloves = glove_scripts(scene, world);
  hand::HandleLinearization model, model_bilateral;
  std::vector<std::vector<hand::HandleState>> start;
  for (int h = 0; h < world.num_hands(); ++h) start.push_back(world.hand(h).handles());
  Eigen::Vector3d goal = start.empty() ? Eigen::Vector3d::Zero() : start[0][0].p_WH;
  for (const world::ObjectDesc& o : scene.objects) {
    if (o.kind == world::BodyKind::deformable) {
      // The highest surface point within 1 cm of the vertical through the centre of its bounding box.
      const std::vector<Eigen::Vector3d>& surface =
          world.snapshot().deformables[world.find_deformable(o.name)].surface_W;
      Eigen::AlignedBox3d box;
      for (const Eigen::Vector3d& p : surface) box.extend(p);
      goal = Eigen::Vector3d(box.center().x(), box.center().y(), box.min().z());
      for (const Eigen::Vector3d& p : surface)
        if ((p - box.center()).head<2>().norm() < 0.01) goal.z() = std::max(goal.z(), p.z());
      goal.z() += 0.005;
      break;
    }
    if (o.kind == world::BodyKind::rigid && world.rigid()) {
      // The object's top surface under the centre of its bounding box.
      const int i = world.rigid()->find(o.name);
      dReal aabb[6];
      dGeomGetAABB(world.rigid()->geom(i), aabb);
      goal = Eigen::Vector3d(0.5 * (aabb[0] + aabb[1]), 0.5 * (aabb[2] + aabb[3]), aabb[5]);
      double depth;
      Eigen::Vector3d n;
      while (goal.z() > aabb[4] && !world.rigid()->penetration(i, goal, depth, n)) goal.z() -= 0.001;
      goal.z() += 0.005;
      break;
    }
  }
  const Eigen::Vector3d above = goal + Eigen::Vector3d(0, 0, 0.06);
  auto approach = [&](double t) -> Eigen::Vector3d {
    if (t < 1.0) return t * (above - start[0][0].p_WH);
    return above - start[0][0].p_WH + std::min(1.0, 2 * (t - 1.0)) * (goal - above);
  };
  RunStats r;
  for (int k = 0; k < steps; ++k) {
    const double t = (k + 1) * world.dt();
    const Eigen::Vector3d stroke(0.02 * std::sin(2 * std::numbers::pi * std::max(0.0, t - 1.5) / 2.0), 0, 0);
    for (int h = 0; h < world.num_hands(); ++h) {
      const auto glove = std::find_if(gloves.begin(), gloves.end(), [h](const GloveScript& g) { return g.hand == h; });
      if (glove != gloves.end()) {
        set_glove_targets(*glove, t, world.hand(h));
        continue;
      }
      for (size_t j = 0; j < start[h].size(); ++j) {
        hand::HandleTarget target;
        target.p_W = start[h][j].p_WH + approach(t) + stroke;
        target.q_W = start[h][j].q_WH;
        world.hand(h).set_target(static_cast<int>(j), target);
      }
    }
    const hand::HandleLinearization previous = model, previous_bilateral = model_bilateral;
    world.step();
    const auto t_model = std::chrono::steady_clock::now();
    for (int h = 0; h < world.num_hands(); ++h) {
      hand::HandleLinearization lin;
      world.hand(h).linearize_next_step(lin, hand::ContactLinearization::unilateral);
      if (h == 0) model = lin;
    }
    const double model_ms =
        std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t_model).count();
    if (world.num_hands() > 0) world.hand(0).linearize_next_step(model_bilateral, hand::ContactLinearization::held);
    const world::WorldSnapshot& s = world.snapshot();
    if (k < 10) continue;  // warm-up
    if (previous.K.size() > 0 && world.num_hands() > 0) {
      const Eigen::VectorXd actual = world.hand(0).coupling_wrench();
      auto worst_handle_error = [&](const hand::HandleLinearization& m) {
        const Eigen::VectorXd predicted = m.evaluate(world.hand(0).handles());
        double err = 0;
        for (int j = 0; j < predicted.size() / 6; ++j)
          err = std::max(err, (predicted.segment<3>(6 * j) - actual.segment<3>(6 * j)).norm());
        return err;
      };
      r.force_error_n.push_back(worst_handle_error(previous));
      r.force_error_bilateral_n.push_back(worst_handle_error(previous_bilateral));
    }
    r.total.push_back(s.timings.total_ms + model_ms);
    r.collide.push_back(s.timings.collide_ms);
    r.hands.push_back(s.timings.hands_ms);
    r.contact.push_back(s.timings.contact_ms);
    r.rigid.push_back(s.timings.rigid_ms);
    r.linearize.push_back(model_ms);
    r.deformable.push_back(s.timings.deformable_ms);
    r.contacts.push_back(static_cast<double>(s.contacts.size()));
    r.max_penetration_m = std::max(r.max_penetration_m, s.max_penetration_m);
    r.resets = s.resets;
  }
  return r;
}

nlohmann::json to_json(const RunStats& r) {
  return {
      {"step_ms_median", median(r.total)},
      {"step_ms_p99", percentile(r.total, 99)},
      {"collision_ms", median(r.collide)},
      {"hand_ms", median(r.hands)},
      {"contact_solve_ms", median(r.contact)},
      {"force_error_n_median", r.force_error_n.empty() ? 0.0 : median(r.force_error_n)},
      {"force_error_n_p99", r.force_error_n.empty() ? 0.0 : percentile(r.force_error_n, 99)},
      {"force_error_bilateral_n_median", r.force_error_bilateral_n.empty() ? 0.0 : median(r.force_error_bilateral_n)},
      {"force_error_bilateral_n_p99",
       r.force_error_bilateral_n.empty() ? 0.0 : percentile(r.force_error_bilateral_n, 99)},
      {"ode_ms", median(r.rigid)},
      {"linearization_ms", median(r.linearize)},
      {"deformable_ms", median(r.deformable)},
      {"contacts_median", median(r.contacts)},
      {"contacts_max", percentile(r.contacts, 100)},
      {"max_penetration_mm", 1e3 * r.max_penetration_m},
      {"resets", r.resets}};
}

void run_world_bench(const WorldBenchArgs& a) {
  const world::SceneDesc scene = world::load_scene(a.scene);
  world::WorldOptions options;
  options.solver = hand::parse_solver_kind(a.solver);
  const Machine machine = describe_machine();
  spdlog::info("world: {}, {} objects, {} hands, {} steps", scene.name, scene.objects.size(), scene.hands.size(),
               a.steps);
  options.contact = world::ContactModel::penalty;
  const RunStats penalty = run(scene, options, a.steps);
  options.contact = world::ContactModel::constraint;
  const RunStats constraint = run(scene, options, a.steps);
  options.hand_contacts = false;
  const RunStats without = run(scene, options, a.steps);
  nlohmann::json doc = {{"suite", "world"},
                        {"scene", scene.name},
                        {"solver", a.solver},
                        {"contact_cluster_m", options.contact_cluster_m},
                        {"steps", a.steps},
                        {"penalty", to_json(penalty)},
                        {"constraint", to_json(constraint)},
                        {"without_contact", to_json(without)},
                        {"penalty_cost_ratio", median(penalty.total) / median(without.total)},
                        {"constraint_cost_ratio", median(constraint.total) / median(without.total)},
                        {"threads", 1},
                        {"cpu", machine.cpu},
                        {"machine", to_json(machine)}};
  std::printf("%-18s %-10s %9s %9s %9s %9s %9s %9s %9s %9s %9s %9s %9s %9s\n", "scene", "contact", "step_med",
              "step_p99", "collide", "hand", "contact", "ode", "linearize", "deform", "contacts", "pen_mm", "ferr_N",
              "ferr_bil_N");
  for (const auto& [label, r] :
       {std::pair<const char*, const RunStats&>{"penalty", penalty}, {"constraint", constraint}, {"off", without}})
    std::printf("%-18s %-10s %9.3f %9.3f %9.3f %9.3f %9.3f %9.3f %9.3f %9.3f %9.0f %9.3f %9.4f %9.4f\n",
                scene.name.c_str(), label, median(r.total), percentile(r.total, 99), median(r.collide), median(r.hands),
                median(r.contact), median(r.rigid), median(r.linearize), median(r.deformable), median(r.contacts),
                1e3 * r.max_penetration_m, r.force_error_n.empty() ? 0.0 : median(r.force_error_n),
                r.force_error_bilateral_n.empty() ? 0.0 : median(r.force_error_bilateral_n));
  std::printf("machine: %s, %d cores, BLAS %s, revision %s (times in ms, one thread)\n", machine.cpu.c_str(),
              machine.cores, machine.blas.c_str(), machine.git_revision.c_str());
  if (!a.json.empty()) write_json(a.json, doc);
}

}  // namespace

void add_world_suite(CLI::App& app) {
  auto args = std::make_shared<WorldBenchArgs>();
  CLI::App* sub = app.add_subcommand(
      "world", "a scene's world under a scripted press and stroke (a glove's hand: its grasp), contact on and off");
  sub->add_option("--scene", args->scene, "scene file (scenes/*.json)")->required()->check(CLI::ExistingFile);
  sub->add_option("--steps", args->steps, "steps (the first 10 are not measured)")->check(CLI::Range(11, 1000000));
  sub->add_option("--solver", args->solver, "hand solver: monolithic | cg | cholmod | lagged")
      ->check(CLI::IsMember({"monolithic", "cg", "cholmod", "lagged"}));
  sub->add_option("--json", args->json, "write the results as JSON to this file");
  sub->callback([args] { run_world_bench(*args); });
}

}  // namespace hapticd::bench
