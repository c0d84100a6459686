#include "server/world/world.hpp"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <stdexcept>
#include <unordered_map>

#include "server/world/hand_factory.hpp"

namespace hapticd::world {
namespace {

using Clock = std::chrono::steady_clock;
double ms_since(Clock::time_point t0) { return std::chrono::duration<double, std::milli>(Clock::now() - t0).count(); }

}  // namespace

World::World(const SceneDesc& scene, const WorldOptions& options)
    : dt_(scene.dt_s),
      step_dt_(scene.dt_s),
      gravity_m_s2_(scene.gravity_m_s2),
      constraint_contact_(options.contact.value_or(scene.contact) == ContactModel::constraint),
      options_(options) {
  bool has_geometry = false, ode_hands = false;
  for (const ObjectDesc& o : scene.objects) has_geometry = has_geometry || o.kind != BodyKind::deformable;
  for (const HandDesc& d : scene.hands)
    ode_hands = ode_hands || d.model == HandModelKind::spring || d.model == HandModelKind::contact_point;
  if (has_geometry || ode_hands) {
    rigid_ = std::make_unique<RigidWorld>(scene, ode_hands);
    rigid_->set_bounds(options.body_bounds);
  }
  HandBuild hand_build;
  hand_build.dt_s = scene.dt_s;
  hand_build.gravity_m_s2 = options.hand_gravity ? scene.gravity_m_s2 : Eigen::Vector3d::Zero();
  hand_build.solver = options.solver;
  hand_build.drive = options.drive;
  hand_build.palm_mass_scale = options.palm_hand_mass_scale;
  if (rigid_) hand_build.ode_world = rigid_->ode_world(), hand_build.ode_space = rigid_->space();
  hand_build.spring_body_step_model = options.spring_body_step_model;
  hand_build.hand_contacts = options.hand_contacts;
  for (const HandDesc& d : scene.hands) {
    HandSlot slot;
    slot.name = d.name;
    slot.model = make_hand(d, hand_build);
    if (auto* ode_hand = dynamic_cast<hand::OdeHand*>(slot.model.get())) {
      rigid_->add_hand(ode_hand, static_cast<int>(hands_.size()));
      if (!options.hand_contacts)
        for (int i = 0; i < ode_hand->num_geoms(); ++i) dGeomSetCollideBits(ode_hand->geom(i), 0);
    } else if (!slot.model->flesh()) {
      throw std::runtime_error("hands." + d.name +
                               ": the world's collision needs a hand with flesh or ODE bodies "
                               "(model \"" +
                               std::string(slot.model->model_name()) + "\" has neither)");
    }
    hands_.push_back(std::move(slot));
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
  auto add_soft = [&](const hand::Flesh& flesh, int hand, int deformable) {
    SoftBody b;
    b.flesh = flesh;
    b.hand = hand;
    b.deformable = deformable;
    b.last.resize(flesh.point_tet->size());
    soft_.push_back(std::move(b));
  };
  for (int h = 0; h < num_hands(); ++h) {
    hand::Flesh* flesh = hands_[h].model->flesh();
    hand_soft_.push_back(flesh ? static_cast<int>(soft_.size()) : -1);
    if (flesh) add_soft(*flesh, h, -1);
  }
  flesh_hands_ = static_cast<int>(soft_.size());
  for (int d = 0; d < num_deformables(); ++d) add_soft(detail::flesh_of(*deformables_[d]), -1, d);
  // Hand-hand contact only when the scene has two hands or more: each hand's
  // flesh as a point-location query on its deformed tets, depths from the
  // signed distance of its rest skin (3 mm cells as for the deformable
  // objects; exact within 1.8 cm of the skin, deeper than half the palm is thick).
  // The same query finds the vertices of rigid meshes and the surface points of deformable objects
  // in a hand's flesh.
  // Between hands with flesh only (then hand h's body is soft_[h]).
  hand_hand_ = num_hands() >= 2 && flesh_hands_ == num_hands() && options.hand_contacts && options.hand_hand_contacts;
  bool meshes = false;
  for (int g = 0; rigid_ && g < rigid_->num_objects(); ++g) meshes = meshes || rigid_->is_mesh(g);
  if (hand_hand_ || ((meshes || !deformables_.empty()) && options.hand_contacts)) {
    for (int i = 0; i < num_hands(); ++i) {
      if (hand_soft_[i] < 0) continue;
      HandSlot& h = hands_[i];
      const hand::Flesh& f = soft_[hand_soft_[i]].flesh;
      const hand::SurfaceMesh skin{*f.rest_surface_vertices, *f.surface_triangles};
      Eigen::AlignedBox3d box;
      for (const Eigen::Vector3d& v : skin.vertices) box.extend(v);
      const double cell = std::clamp(box.sizes().maxCoeff() / 40, 0.001, 0.003);
      h.query = std::make_unique<DeformedMeshQuery>(f.model->mesh(), skin, cell, 6);
      h.f_hands_W = Eigen::VectorXd::Zero(3 * f.model->num_nodes());
    }
  }
  collide_all();
  record_contacts();
  publish();
}

int World::find_hand(const std::string& name) const {
  for (size_t i = 0; i < hands_.size(); ++i)
    if (hands_[i].name == name) return static_cast<int>(i);
  return -1;
}

int World::find_deformable(const std::string& name) const {
  for (size_t i = 0; i < deformables_.size(); ++i)
    if (deformables_[i]->name == name) return static_cast<int>(i);
  return -1;
}

void World::step(double dt_s) {
  // Contacts were detected at the end of the previous step, each point looked for as far ahead as a
  // step of that one's length carries it. A step much longer (the first after a stall, or the first
  // of a loaded visual loop) looks again: a soft cube falling onto a 4 cm table at 60 Hz went through
  // it in one 200 ms step with the contacts found for 17 ms.
  const auto t0 = Clock::now();
  const double last_dt = step_dt_;
  step_dt_ = dt_s > 0 && std::isfinite(dt_s) ? dt_s : dt_;
  if (step_dt_ > kLongerStepRecollides * last_dt) collide_all();
  for (SoftBody& b : soft_) b.flesh.state->dt_s = step_dt_;
  WorldTimings timings;
  snapshot_.linear_models.resize(hands_.size());
  snapshot_.linear_model_valid.assign(hands_.size(), false);
  for (int h = 0; h < num_hands(); ++h) {
    hand::Hand& hand = *hands_[h].model;
    if (hand_soft_[h] < 0) {  // ODE bodies: the rigid world steps them; finish_ode_hands() models them
      hand.set_step_length(step_dt_);
      hand.step(nullptr);
      continue;
    }
    if (hand_hand_ && constraint_contact_) {
      take_hand_reactions(h);  // in index order: the impulses of the hands that stepped before this one
    } else if (hand_hand_) {
      anchor_hand_contacts(h, step_dt_);
    }
    hand.step(options_.linearize ? &snapshot_.linear_models[h] : nullptr);
    snapshot_.linear_model_valid[h] = snapshot_.linear_models[h].K.size() > 0;
    SoftBody& body = soft_[hand_soft_[h]];
    timings.linearize_ms += body.flesh.state->timings.linearize_ms;
    timings.contact_ms += body.flesh.state->timings.contact_ms;
    if (hand_hand_) sum_hand_forces(h);
    remember_impulses(body);
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
  if (rigid_) {
    const auto t_ode_hands = Clock::now();
    finish_ode_hands();
    timings.linearize_ms += ms_since(t_ode_hands);
  }
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

void World::finish_ode_hands() {
  if (flesh_hands_ == num_hands()) return;
  rigid_->hand_contacts(ode_hand_contacts_);
  std::vector<hand::OdeHandContact> mine;
  for (int h = 0; h < num_hands(); ++h) {
    if (hand_soft_[h] >= 0) continue;
    mine.clear();
    for (const RigidWorld::HandContact& c : ode_hand_contacts_)
      if (c.hand == h) mine.push_back({c.handle, c.p_W, c.n_W, c.depth_m, c.mu, c.geom});
    static_cast<hand::OdeHand&>(*hands_[h].model).set_contacts(mine);
    if (!options_.linearize) continue;
    snapshot_.linear_model_valid[h] =
        hands_[h].model->linearize_next_step(snapshot_.linear_models[h], hand::ContactLinearization::unilateral);
  }
}

}  // namespace hapticd::world
