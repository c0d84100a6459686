#include "server/world/world.hpp"

#include <chrono>
#include <cmath>
#include <cstdint>
#include <stdexcept>
#include <unordered_map>

namespace hapticd {
namespace {

using Clock = std::chrono::steady_clock;
double ms_since(Clock::time_point t0) {
  return std::chrono::duration<double, std::milli>(Clock::now() - t0).count();
}

constexpr double kSpeculativeMargin_m = 0.002;

// The cluster cell of a contact: object and integer cell coordinates packed in 64 bits.
std::uint64_t cluster_key(int object, const Eigen::Vector3d& p_W, double cell_m) {
  std::uint64_t key = static_cast<std::uint64_t>(object) & 0xffff;
  for (int k = 0; k < 3; ++k) {
    const auto cell = static_cast<std::int64_t>(std::floor(p_W[k] / cell_m));
    key = (key << 16) | (static_cast<std::uint64_t>(cell) & 0xffff);
  }
  return key;
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
      gravity_m_s2_(scene.gravity_m_s2),
      constraint_contact_(options.contact.value_or(scene.contact) == ContactModel::constraint),
      options_(options) {
  if (scene.needs_deformable_objects())
    throw std::runtime_error(scene.path + ": deformable objects are not simulated yet (scene loads; world refuses)");
  bool has_geometry = false;
  for (const ObjectDesc& o : scene.objects) has_geometry = has_geometry || o.kind != BodyKind::deformable;
  if (has_geometry) rigid_ = std::make_unique<RigidWorld>(scene);
  for (const HandDesc& d : scene.hands) {
    if (d.model != HandModelKind::fem)
      throw std::runtime_error("hands." + d.name + ": only the fem hand model is built so far");
    auto h = std::make_unique<WorldHand>();
    h->name = d.name;
    ProceduralHandOptions shape_options;
    shape_options.target_tets = d.resolution_tets;
    shape_options.left = d.side == HandSide::left;
    h->shape = make_procedural_hand(shape_options);
    HandConfig config;
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
    config.drive = options.drive;
    h->friction = d.material.friction;
    h->model = std::make_unique<HandModel>(h->shape.mesh, config);
    h->state = make_rest_state(*h->model);
    // The hand frame's pose places the rest mesh: handle 0 goes where it sits in that frame.
    const Eigen::Vector3d p_handle = d.pose.p_W + d.pose.q_W * h->model->handles()[0].p_WH_rest;
    place_hand(*h->model, h->state, p_handle, d.pose.q_W, 0);
    h->solver = make_solver(options.solver);
    hands_.push_back(std::move(h));
  }
  contact_points_.resize(hands_.size());
  contact_keys_.resize(hands_.size());
  warm_impulse_.resize(hands_.size());
  last_contact_.resize(hands_.size());
  for (size_t h = 0; h < hands_.size(); ++h) last_contact_[h].resize(hands_[h]->shape.skin_vertices.size());
  for (int h = 0; h < num_hands(); ++h) collide(h);
  publish();
}

int World::find_hand(const std::string& name) const {
  for (size_t i = 0; i < hands_.size(); ++i)
    if (hands_[i]->name == name) return static_cast<int>(i);
  return -1;
}

void World::collide(int hi) {
  WorldHand& h = *hands_[hi];
  h.state.contacts.clear();
  h.state.bodies.clear();
  h.state.supports.clear();
  contact_keys_[hi].clear();
  std::unordered_map<std::uint64_t, int> cluster;
  std::vector<int> body_of_object(rigid_ ? rigid_->num_objects() : 0, -1);
  contact_points_[hi].clear();
  if (!rigid_ || !options_.hand_contacts) return;
  const TetMesh& mesh = h.model->mesh();
  for (int g = 0; g < rigid_->num_objects(); ++g) {
    dGeomID geom = rigid_->geom(g);
    dReal aabb[6];
    const bool bounded = dGeomGetClass(geom) != dPlaneClass;
    if (bounded) dGeomGetAABB(geom, aabb);
    for (size_t v = 0; v < h.shape.skin_vertices.size(); ++v) {
      const Tet& t = mesh.tets[h.shape.skin_tet[v]];
      const Eigen::Vector4d& w = h.shape.skin_bary[v];
      Eigen::Vector3d p = Eigen::Vector3d::Zero();
      for (int k = 0; k < 4; ++k) p += w[k] * h.state.x.segment<3>(3 * t[k]);
      if (bounded && (p.x() < aabb[0] || p.x() > aabb[1] || p.y() < aabb[2] || p.y() > aabb[3] ||
                      p.z() < aabb[4] || p.z() > aabb[5])) {
        if (last_contact_[hi][v].object == g) last_contact_[hi][v] = LastContact{};
        continue;
      }
      double depth;
      Eigen::Vector3d n;
      LastContact& last = last_contact_[hi][v];
      const Eigen::Vector3d entry = last.object == g ? last.n_W : Eigen::Vector3d::Zero();
      // Constraint contacts also take points just outside (speculative: the step may not cross the gap).
      const double margin = constraint_contact_ ? kSpeculativeMargin_m : 0.0;
      if (!rigid_->penetration(g, p, depth, n, entry, margin)) {
        if (last.object == g) last = LastContact{};
        continue;
      }
      if (depth > 0) last = LastContact{g, n};
      PointContact c;
      c.tet = h.shape.skin_tet[v];
      c.bary = w;
      c.n_W = n;
      c.depth_m = depth;
      c.v_other_W = rigid_->point_velocity(g, p);
      if (rigid_->is_dynamic(g)) {
        // Dynamic bodies join this hand's implicit system for the step.
        if (body_of_object[g] < 0) {
          body_of_object[g] = static_cast<int>(h.state.bodies.size());
          h.state.bodies.push_back(rigid_->contact_body(g));
        }
        c.body = body_of_object[g];
      }
      c.stiffness_n_m = options_.contact_stiffness_n_m;
      c.damping_ns_m = options_.contact_damping_ns_m;
      c.friction = std::sqrt(h.friction * rigid_->friction(g));
      c.other = g;
      c.constraint = constraint_contact_;
      if (!constraint_contact_) {
        h.state.contacts.push_back(c);
        contact_points_[hi].push_back(p);
        continue;
      }
      // Constraint contacts are reduced to the deepest point per object and
      // cluster cell: a patch of skin on a face needs a few non-penetration
      // rows, not one per skin vertex (each row costs a column of A^-1 J^T).
      const std::uint64_t key = cluster_key(g, p, options_.contact_cluster_m);
      const auto warm = warm_impulse_[hi].find(key);
      if (warm != warm_impulse_[hi].end()) c.warm_impulse_W = warm->second;
      const auto [it, fresh] = cluster.try_emplace(key, static_cast<int>(h.state.contacts.size()));
      if (!fresh) {
        if (h.state.contacts[it->second].depth_m >= depth) continue;
        h.state.contacts[it->second] = c;
        contact_points_[hi][it->second] = p;
        continue;
      }
      h.state.contacts.push_back(c);
      contact_points_[hi].push_back(p);
      contact_keys_[hi].push_back(key);
    }
  }
  // The bodies the hand touches bring their own contacts (table, other bodies) as supports.
  std::vector<RigidWorld::BodyContact> found;
  for (int g = 0; g < rigid_->num_objects(); ++g) {
    if (body_of_object[g] < 0) continue;
    rigid_->contacts_of(g, found);
    for (const RigidWorld::BodyContact& bc : found) {
      BodySupport support;
      support.body = body_of_object[g];
      support.p_W = bc.p_W;
      support.n_W = bc.n_W;
      support.depth_m = bc.depth_m;
      support.friction = bc.friction;
      support.v_other_W = rigid_->point_velocity(bc.other, bc.p_W);
      h.state.supports.push_back(support);
    }
  }
}

void World::step() {
  // Contacts were detected at the end of the previous step.
  const auto t0 = Clock::now();
  WorldTimings timings;
  snapshot_.linear_models.resize(hands_.size());
  snapshot_.linear_model_valid.assign(hands_.size(), false);
  for (int h = 0; h < num_hands(); ++h) {
    WorldHand& hand = *hands_[h];
    hapticd::step(*hand.model, hand.state, *hand.solver, &snapshot_.linear_models[h]);
    snapshot_.linear_model_valid[h] = snapshot_.linear_models[h].K.size() > 0;
    timings.linearize_ms += hand.state.timings.linearize_ms;
    timings.contact_ms += hand.state.timings.contact_ms;
    // This step's impulses warm-start the next step's contacts in the same cells.
    warm_impulse_[h].clear();
    for (size_t k = 0; k < contact_keys_[h].size(); ++k)
      warm_impulse_[h][contact_keys_[h][k]] = hand.state.contacts[k].f_W * dt_;
  }
  timings.hands_ms = ms_since(t0) - timings.linearize_ms - timings.contact_ms;
  const auto t1 = Clock::now();
  if (rigid_) {
    apply_reactions();
    rigid_->step(dt_);
  }
  timings.rigid_ms = ms_since(t1);
  const auto t2 = Clock::now();
  for (int h = 0; h < num_hands(); ++h) collide(h);
  timings.collide_ms = ms_since(t2);
  timings.total_ms = ms_since(t0);
  ++steps_;
  publish();
  snapshot_.timings = timings;
}

void World::apply_reactions() {
  // Each body a hand touched was solved implicitly with that hand, with its
  // gravity and supports: its end-of-step velocity is the result, handed to ODE
  // less the gravity ODE adds again (ODE's own contacts then find nothing to
  // correct where the hand's solve already satisfied them).
  for (int h = 0; h < num_hands(); ++h) {
    const HandState& s = hands_[h]->state;
    std::vector<int> object_of_body(s.bodies.size(), -1);
    for (const PointContact& c : s.contacts)
      if (c.body >= 0) object_of_body[c.body] = c.other;
    for (size_t b = 0; b < s.bodies.size(); ++b) {
      if (object_of_body[b] < 0) continue;
      const ContactBody& B = s.bodies[b];
      rigid_->add_velocity(object_of_body[b], B.dv_W - dt_ * gravity_m_s2_, B.dw_W);
    }
  }
}

void World::publish() {
  snapshot_.step = steps_;
  snapshot_.t_s = static_cast<double>(steps_) * dt_;
  snapshot_.handles.resize(hands_.size());
  snapshot_.contacts.clear();
  snapshot_.max_penetration_m = 0;
  snapshot_.resets = 0;
  for (int h = 0; h < num_hands(); ++h) {
    const HandState& s = hands_[h]->state;
    snapshot_.handles[h] = s.handles;
    snapshot_.resets += s.resets;
    for (size_t k = 0; k < s.contacts.size(); ++k) {
      const PointContact& c = s.contacts[k];
      snapshot_.contacts.push_back({h, c.other, contact_points_[h][k], c.n_W, c.f_W, c.depth_m});
      snapshot_.max_penetration_m = std::max(snapshot_.max_penetration_m, c.depth_m);  // gaps are < 0
    }
  }
  snapshot_.bodies.clear();
  if (rigid_)
    for (int i = 0; i < rigid_->num_objects(); ++i) snapshot_.bodies.push_back(rigid_->state(i));
}

}  // namespace hapticd
