#include "server/world/world.hpp"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <stdexcept>
#include <unordered_map>

namespace hapticd::world {
namespace {

using Clock = std::chrono::steady_clock;
double ms_since(Clock::time_point t0) {
  return std::chrono::duration<double, std::milli>(Clock::now() - t0).count();
}

int handle_count(HandleSet set) {
  switch (set) {
    case HandleSet::palm: return 1;
    case HandleSet::fingertips: return 6;
    case HandleSet::phalanges: return 16;
  }
  return 1;
}

}  // namespace

World::World(const SceneDesc& scene, const WorldOptions& options)
    : dt_(scene.dt_s),
      step_dt_(scene.dt_s),
      gravity_m_s2_(scene.gravity_m_s2),
      constraint_contact_(options.contact.value_or(scene.contact) == ContactModel::constraint),
      options_(options) {
  bool has_geometry = false;
  for (const ObjectDesc& o : scene.objects) has_geometry = has_geometry || o.kind != BodyKind::deformable;
  if (has_geometry) {
    rigid_ = std::make_unique<RigidWorld>(scene);
    rigid_->set_bounds(options.body_bounds);
  }
  for (const HandDesc& d : scene.hands) {
    if (d.model != HandModelKind::fem)
      throw std::runtime_error("hands." + d.name + ": only the fem hand model is built so far");
    auto h = std::make_unique<WorldHand>();
    h->name = d.name;
    hand::ProceduralHandOptions shape_options;
    shape_options.target_tets = d.resolution_tets;
    shape_options.left = d.side == HandSide::left;
    h->left_side = shape_options.left;
    // A hand driven by more than its palm (a glove) needs fingers that move on their own.
    shape_options.separate_fingers = d.handles != HandleSet::palm;
    h->shape = make_procedural_hand(shape_options);
    hand::HandConfig config;
    config.dt_s = scene.dt_s;
    config.gravity_m_s2 = options.hand_gravity ? scene.gravity_m_s2 : Eigen::Vector3d::Zero();
    config.material.youngs_modulus_pa = d.material.youngs_modulus_pa;
    config.material.poisson_ratio = d.material.poisson_ratio;
    config.material.density_kg_m3 = embedding_density(h->shape, d.material.density_kg_m3);
    config.material.rayleigh_alpha_per_s = d.material.rayleigh_alpha_per_s;
    config.material.rayleigh_beta_s = d.material.rayleigh_beta_s;
    config.coupling.stiffness_n_m = d.coupling_stiffness_n_m;
    config.coupling.damping_ns_m = d.coupling_damping_ns_m;
    config.handles = procedural_handles(h->shape, handle_count(d.handles));
    // A glove hand's joints are soft flesh between its bones: bending a finger costs little work.
    config.element_stiffness =
        procedural_joint_stiffness(h->shape, handle_count(d.handles), hand::kGloveJointStiffness);
    config.drive = options.drive;
    h->friction = d.material.friction;
    h->model = std::make_unique<hand::HandModel>(h->shape.mesh, config);
    h->skin_handles = procedural_skin_handles(h->shape, handle_count(d.handles));
    h->state = make_rest_state(*h->model);
    // The hand frame's pose places the rest mesh: handle 0 goes where it sits in that frame.
    const Eigen::Vector3d p_handle = d.pose.p_W + d.pose.q_W * h->model->handles()[0].p_WH_rest;
    place_hand(*h->model, h->state, p_handle, d.pose.q_W, 0);
    h->solver = make_solver(options.solver);
    hands_.push_back(std::move(h));
  }
  // Deformable objects only when the scene names them; their hand-contact query only when a hand can touch them.
  DeformableBuild build;
  build.gravity_m_s2 = scene.gravity_m_s2;
  build.dt_s = scene.dt_s;
  build.solver = options.solver;
  build.touched_by_hands = !hands_.empty() && options.hand_contacts;
  for (const ObjectDesc& o : scene.objects)
    if (o.kind == BodyKind::deformable) deformables_.push_back(make_deformable_object(o, build));
  // Cluster keys hold 16 bits of the other body: objects, deformable objects, then two per hand (hand-hand contact).
  if ((rigid_ ? rigid_->num_objects() : 0) + num_deformables() + 2 * num_hands() > 0xffff)
    throw std::runtime_error(scene.path + ": more than 65535 objects");
  // Hands collide with their skin points, deformable objects with their surface points.
  auto add_soft = [&](const hand::HandModel* model, hand::HandState* state, const std::vector<int>* tets,
                      const std::vector<Eigen::Vector4d>* barys, double friction, int hand, int deformable) {
    SoftBody b;
    b.model = model;
    b.state = state;
    b.point_tet = tets;
    b.point_bary = barys;
    b.friction = friction;
    b.hand = hand;
    b.deformable = deformable;
    b.last.resize(tets->size());
    soft_.push_back(std::move(b));
  };
  for (int h = 0; h < num_hands(); ++h) {
    WorldHand& hand = *hands_[h];
    add_soft(hand.model.get(), &hand.state, &hand.shape.skin_tet, &hand.shape.skin_bary, hand.friction, h, -1);
  }
  for (int d = 0; d < num_deformables(); ++d) {
    DeformableObject& o = *deformables_[d];
    add_soft(o.model.get(), &o.state, &o.body.surface_tet, &o.body.surface_bary, o.friction, -1, d);
  }
  // Hand-hand contact only when the scene has two hands or more: each hand's
  // flesh as a point-location query on its deformed tets, depths from the
  // signed distance of its rest skin (3 mm cells as for the deformable
  // objects; exact within 1.8 cm of the skin, deeper than half the palm is thick).
  // The same query finds the vertices of rigid meshes and the surface points of deformable objects
  // in a hand's flesh.
  hand_hand_ = num_hands() >= 2 && options.hand_contacts && options.hand_hand_contacts;
  bool meshes = false;
  for (int g = 0; rigid_ && g < rigid_->num_objects(); ++g) meshes = meshes || rigid_->is_mesh(g);
  if (hand_hand_ || ((meshes || !deformables_.empty()) && options.hand_contacts)) {
    for (const std::unique_ptr<WorldHand>& h : hands_) {
      const hand::SurfaceMesh skin{h->shape.skin_vertices, h->shape.skin_triangles};
      Eigen::AlignedBox3d box;
      for (const Eigen::Vector3d& v : skin.vertices) box.extend(v);
      const double cell = std::clamp(box.sizes().maxCoeff() / 40, 0.001, 0.003);
      h->query = std::make_unique<DeformedMeshQuery>(h->model->mesh(), skin, cell, 6);
      h->f_hands_W = Eigen::VectorXd::Zero(3 * h->model->num_nodes());
    }
  }
  // Each hand's element rotations start at its placement (the polar factors of
  // its rigidly placed rest shape). Started at the identity, a hand placed half
  // a turn round (a left hand turned palm up to face a right hand) has F = R,
  // symmetric, which the polar decomposition keeps as a stretch: its first step
  // flung the flesh at 11 m/s.
  for (size_t h = 0; h < hands_.size(); ++h)
    hands_[h]->state.R.assign(hands_[h]->state.R.size(), scene.hands[h].pose.q_W.normalized().toRotationMatrix());
  collide_all();
  record_contacts();
  publish();
}

int World::find_hand(const std::string& name) const {
  for (size_t i = 0; i < hands_.size(); ++i)
    if (hands_[i]->name == name) return static_cast<int>(i);
  return -1;
}

int World::find_deformable(const std::string& name) const {
  for (size_t i = 0; i < deformables_.size(); ++i)
    if (deformables_[i]->name == name) return static_cast<int>(i);
  return -1;
}

void World::step(double dt_s) {
  // Contacts were detected at the end of the previous step.
  const auto t0 = Clock::now();
  step_dt_ = dt_s > 0 && std::isfinite(dt_s) ? dt_s : dt_;
  for (SoftBody& b : soft_) b.state->dt_s = step_dt_;
  WorldTimings timings;
  snapshot_.linear_models.resize(hands_.size());
  snapshot_.linear_model_valid.assign(hands_.size(), false);
  for (int h = 0; h < num_hands(); ++h) {
    WorldHand& hand = *hands_[h];
    if (hand_hand_ && constraint_contact_) {
      take_hand_reactions(h);  // in index order: the impulses of the hands that stepped before this one
    } else if (hand_hand_) {
      anchor_hand_contacts(h, step_dt_);
    }
    hand.step(options_.linearize ? &snapshot_.linear_models[h] : nullptr);
    snapshot_.linear_model_valid[h] = snapshot_.linear_models[h].K.size() > 0;
    timings.linearize_ms += hand.state.timings.linearize_ms;
    timings.contact_ms += hand.state.timings.contact_ms;
    if (hand_hand_) sum_hand_forces(h);
    remember_impulses(soft_[h]);
  }
  timings.hands_ms = ms_since(t0) - timings.linearize_ms - timings.contact_ms;
  const auto t_deformable = Clock::now();
  step_deformables();
  timings.deformable_ms = ms_since(t_deformable);
  const auto t1 = Clock::now();
  if (rigid_) {
    apply_reactions();
    rigid_->step(step_dt_);
    place_solved_bodies();
  }
  timings.rigid_ms = ms_since(t1);
  record_contacts();
  const auto t2 = Clock::now();
  collide_all();
  timings.collide_ms = ms_since(t2);
  timings.total_ms = ms_since(t0);
  ++steps_;
  t_s_ += step_dt_;
  publish();
  snapshot_.timings = timings;
}

}  // namespace hapticd::world
