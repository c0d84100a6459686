#include "server/world/world.hpp"

#include <algorithm>
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
// A cell's constraint contact moves to another point only when that one is deeper by this much.
constexpr double kClusterHysteresis_m = 1e-4;

// The cluster cell of a contact: object and integer cell coordinates packed in 64 bits.
// The cells sit uneven fractions of a cell off the origin: scenes are written
// in round numbers, and a row of surface points on a cell boundary would change
// cells (and contacts) with every micrometre of jitter.
std::uint64_t cluster_key(int object, const Eigen::Vector3d& p_W, double cell_m) {
  static constexpr double kCellShift[3] = {0.37, 0.21, 0.43};
  std::uint64_t key = static_cast<std::uint64_t>(object) & 0xffff;
  for (int k = 0; k < 3; ++k) {
    const auto cell = static_cast<std::int64_t>(std::floor(p_W[k] / cell_m + kCellShift[k]));
    key = (key << 16) | (static_cast<std::uint64_t>(cell) & 0xffff);
  }
  return key;
}

// A point embedded in a tet of `mesh` by barycentric weights w, at nodal values x (positions or velocities).
Eigen::Vector3d embedded_at(const TetMesh& mesh, const Eigen::VectorXd& x, int tet, const Eigen::Vector4d& w) {
  const Tet& t = mesh.tets[tet];
  Eigen::Vector3d p = Eigen::Vector3d::Zero();
  for (int k = 0; k < 4; ++k) p += w[k] * x.segment<3>(3 * t[k]);
  return p;
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
    ProceduralHandOptions shape_options;
    shape_options.target_tets = d.resolution_tets;
    shape_options.left = d.side == HandSide::left;
    h->left_side = shape_options.left;
    // A hand driven by more than its palm (a glove) needs fingers that move on their own.
    shape_options.separate_fingers = d.handles != HandleSet::palm;
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
    // A glove hand's joints are soft flesh between its bones: bending a finger costs little work.
    config.element_stiffness = procedural_joint_stiffness(h->shape, handle_count(d.handles), kGloveJointStiffness);
    config.drive = options.drive;
    h->friction = d.material.friction;
    h->model = std::make_unique<HandModel>(h->shape.mesh, config);
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
  auto add_soft = [&](const HandModel* model, HandState* state, const std::vector<int>* tets,
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
  if (num_hands() >= 2 && options.hand_contacts && options.hand_hand_contacts) {
    for (const std::unique_ptr<WorldHand>& h : hands_) {
      const SurfaceMesh skin{h->shape.skin_vertices, h->shape.skin_triangles};
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

void World::collide_all() {
  // Deformable objects first: a hand touching one takes the object's own contacts as its supports.
  for (int d = 0; d < num_deformables(); ++d) {
    DeformableObject& o = *deformables_[d];
    if (o.query) o.query->update(o.state.x);
    o.surface_bounds.setEmpty();
    for (int v = 0; v < static_cast<int>(o.body.surface_tet.size()); ++v) o.surface_bounds.extend(surface_point(o, v));
    collide(soft_[num_hands() + d]);
  }
  find_hand_hits();
  for (int h = 0; h < num_hands(); ++h) collide(soft_[h]);
  // The coming step's external forces as far as known now, for the model of the coming step.
  if (!constraint_contact_)
    for (int h = 0; h < num_hands(); ++h)
      if (hands_[h]->query) anchor_hand_contacts(h, dt_);
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

void World::add_contact(SoftBody& b, const PointContact& c, int point, const Eigen::Vector3d& p_W, int other_key,
                        const DeformableTouch& touch, std::unordered_map<std::uint64_t, int>& cluster) {
  HandState& s = *b.state;
  if (!constraint_contact_) {
    s.contacts.push_back(c);
    b.points.push_back(p_W);
    b.touches.push_back(touch);
    b.point_of.push_back(point);
    return;
  }
  // Constraint contacts are reduced to the deepest point per other body and
  // cluster cell: a patch of skin on a face needs a few non-penetration rows,
  // not one per skin vertex (each row costs a column of A^-1 J^T). The other
  // points of the cell stay in reserve: the step makes a row of any it would
  // carry too deep (HandState::reserve_contacts). Against deformable objects
  // and other hands the reaction must be handed over, so those points are not kept.
  auto keep_in_reserve = [&](const PointContact& r, int r_point, const Eigen::Vector3d& r_p_W) {
    if (!options_.contact_reserves || touch.object >= 0 || touch.hand >= 0) return;
    s.reserve_contacts.push_back(r);
    b.reserve_point.push_back(r_point);
    b.reserve_p_W.push_back(r_p_W);
  };
  const std::uint64_t key = cluster_key(other_key, p_W, options_.contact_cluster_m);
  PointContact warm_started = c;
  const auto warm = b.warm_impulse.find(key);
  if (warm != b.warm_impulse.end()) warm_started.warm_impulse_W = warm->second;
  const auto [it, fresh] = cluster.try_emplace(key, static_cast<int>(s.contacts.size()));
  if (!fresh) {
    // The point the cell kept last step stays unless another is deeper by a
    // margin: on a flat face the deepest point changes with every micrometre of
    // jitter, and a contact that moves each step rocks a resting body.
    const auto kept = b.kept_point.find(key);
    const int current = b.point_of[it->second];
    double advantage = c.depth_m - s.contacts[it->second].depth_m;
    if (kept != b.kept_point.end() && kept->second == current) advantage -= kClusterHysteresis_m;
    if (kept != b.kept_point.end() && kept->second == point) advantage += kClusterHysteresis_m;
    if (advantage <= 0) {
      keep_in_reserve(c, point, p_W);
      return;
    }
    keep_in_reserve(s.contacts[it->second], current, b.points[it->second]);
    s.contacts[it->second] = warm_started;
    b.points[it->second] = p_W;
    b.touches[it->second] = touch;
    b.point_of[it->second] = point;
    return;
  }
  s.contacts.push_back(warm_started);
  b.points.push_back(p_W);
  b.touches.push_back(touch);
  b.point_of.push_back(point);
  b.keys.push_back(key);
}

// The same for hands and deformable objects: the body's points against every
// static and rigid object (then, for hands, against the deformable objects),
// rigid bodies touched joining the body's implicit system with their supports.
void World::collide(SoftBody& b) {
  HandState& s = *b.state;
  s.contacts.clear();
  s.reserve_contacts.clear();
  b.reserve_point.clear();
  b.reserve_p_W.clear();
  s.bodies.clear();
  s.supports.clear();
  b.kept_point.clear();
  for (size_t k = 0; k < b.keys.size(); ++k) b.kept_point[b.keys[k]] = b.point_of[k];
  b.keys.clear();
  b.point_of.clear();
  b.points.clear();
  b.touches.clear();
  std::unordered_map<std::uint64_t, int> cluster;
  if (b.hand >= 0 && !options_.hand_contacts) return;
  const TetMesh& mesh = b.model->mesh();
  const std::vector<int>& point_tet = *b.point_tet;
  const std::vector<Eigen::Vector4d>& point_bary = *b.point_bary;
  // Constraint contacts also take points just outside (speculative: the step may not cross the gap).
  const double margin = constraint_contact_ ? kSpeculativeMargin_m : 0.0;
  std::vector<int> body_of_object(rigid_ ? rigid_->num_objects() : 0, -1);
  for (int g = 0; rigid_ && g < rigid_->num_objects(); ++g) {
    dGeomID geom = rigid_->geom(g);
    dReal aabb[6];
    const bool bounded = dGeomGetClass(geom) != dPlaneClass;
    if (bounded) dGeomGetAABB(geom, aabb);
    for (size_t v = 0; v < point_tet.size(); ++v) {
      const Tet& t = mesh.tets[point_tet[v]];
      const Eigen::Vector4d& w = point_bary[v];
      Eigen::Vector3d p = Eigen::Vector3d::Zero();
      for (int k = 0; k < 4; ++k) p += w[k] * s.x.segment<3>(3 * t[k]);
      LastContact& last = b.last[v];
      // The box grown by the margin: a point just above a face is a speculative contact.
      if (bounded && (p.x() < aabb[0] - margin || p.x() > aabb[1] + margin || p.y() < aabb[2] - margin ||
                      p.y() > aabb[3] + margin || p.z() < aabb[4] - margin || p.z() > aabb[5] + margin)) {
        if (last.object == g) last = LastContact{};
        continue;
      }
      double depth;
      Eigen::Vector3d n;
      const Eigen::Vector3d entry = last.object == g ? last.n_W : Eigen::Vector3d::Zero();
      if (!rigid_->penetration(g, p, depth, n, entry, margin)) {
        if (last.object == g) last = LastContact{};
        continue;
      }
      if (depth > 0) last = LastContact{g, n};
      PointContact c;
      c.tet = point_tet[v];
      c.bary = w;
      c.n_W = n;
      c.depth_m = depth;
      c.v_other_W = rigid_->point_velocity(g, p);
      if (rigid_->is_dynamic(g)) {
        // Dynamic bodies join this body's implicit system for the step.
        if (body_of_object[g] < 0) {
          body_of_object[g] = static_cast<int>(s.bodies.size());
          s.bodies.push_back(rigid_->contact_body(g));
          s.bodies.back().gravity_W = gravity_m_s2_;
        }
        c.body = body_of_object[g];
      }
      c.stiffness_n_m = options_.contact_stiffness_n_m;
      c.damping_ns_m = options_.contact_damping_ns_m;
      c.friction = std::sqrt(b.friction * rigid_->friction(g));
      c.other = g;
      c.constraint = constraint_contact_;
      add_contact(b, c, static_cast<int>(v), p, g, DeformableTouch{}, cluster);
    }
  }
  if (b.hand >= 0) collide_with_deformables(b, cluster);
  if (b.hand >= 0 && hands_[b.hand]->query) collide_with_hands(b, cluster);
  // The bodies touched bring their own contacts (table, other bodies) as supports.
  std::vector<RigidWorld::BodyContact> found;
  for (int g = 0; rigid_ && g < rigid_->num_objects(); ++g) {
    if (body_of_object[g] < 0) continue;
    rigid_->supports_of(g, found, kSpeculativeMargin_m);
    for (const RigidWorld::BodyContact& bc : found) {
      BodySupport support;
      support.body = body_of_object[g];
      support.p_W = bc.p_W;
      support.n_W = bc.n_W;
      support.depth_m = bc.depth_m;
      support.friction = bc.friction;
      support.v_other_W = rigid_->point_velocity(bc.other, bc.p_W);
      s.supports.push_back(support);
    }
  }
}

// Hand skin points inside a deformable object's deformed surface (DeformedMeshQuery).
// How the two bodies share a contact is in step_deformables().
void World::collide_with_deformables(SoftBody& b, std::unordered_map<std::uint64_t, int>& cluster) {
  HandState& s = *b.state;
  const TetMesh& mesh = b.model->mesh();
  const double margin = constraint_contact_ ? kSpeculativeMargin_m : 0.0;
  const int first_key = rigid_ ? rigid_->num_objects() : 0;
  for (int d = 0; d < num_deformables(); ++d) {
    const DeformableObject& o = *deformables_[d];
    if (!o.query || o.query->empty() || o.surface_bounds.isEmpty()) continue;
    const Eigen::Vector3d grow = Eigen::Vector3d::Constant(margin);
    const Eigen::AlignedBox3d box(o.surface_bounds.min() - grow, o.surface_bounds.max() + grow);
    int proxy = -1;  // constraint contacts: the object's index in s.bodies
    for (size_t v = 0; v < b.point_tet->size(); ++v) {
      const Tet& t = mesh.tets[(*b.point_tet)[v]];
      const Eigen::Vector4d& w = (*b.point_bary)[v];
      Eigen::Vector3d p = Eigen::Vector3d::Zero();
      for (int k = 0; k < 4; ++k) p += w[k] * s.x.segment<3>(3 * t[k]);
      MeshPenetration pen;
      if (!box.contains(p) || !o.query->penetration(p, margin, pen)) continue;
      PointContact c;
      c.tet = (*b.point_tet)[v];
      c.bary = w;
      c.n_W = pen.n_W;
      c.depth_m = pen.depth_m;
      const Tet& ot = o.body.mesh.tets[pen.tet];
      for (int k = 0; k < 4; ++k) c.v_other_W += pen.bary[k] * o.state.v.segment<3>(3 * ot[k]);
      c.stiffness_n_m = options_.contact_stiffness_n_m;
      c.damping_ns_m = options_.contact_damping_ns_m;
      c.friction = std::sqrt(b.friction * o.friction);
      c.constraint = constraint_contact_;
      if (constraint_contact_) {
        if (proxy < 0) proxy = add_rigid_proxy(s, d);
        c.body = proxy;
      }
      add_contact(b, c, static_cast<int>(v), p, first_key + d, DeformableTouch{d, pen.tet, pen.bary}, cluster);
    }
  }
}

// Every pair of hands' skin points in the other's flesh, found once for both
// hands (collide_with_hands() makes their contacts), against every hand's
// flesh where it is now.
void World::find_hand_hits() {
  hand_hits_.clear();
  for (int h = 0; h < num_hands(); ++h) {
    WorldHand& hand = *hands_[h];
    if (!hand.query) continue;
    hand.query->update(hand.state.x);
    hand.skin_bounds.setEmpty();
    for (size_t v = 0; v < hand.shape.skin_tet.size(); ++v)
      hand.skin_bounds.extend(
          embedded_at(hand.model->mesh(), hand.state.x, hand.shape.skin_tet[v], hand.shape.skin_bary[v]));
  }
  const double margin = constraint_contact_ ? kSpeculativeMargin_m : 0.0;
  const Eigen::Vector3d grow = Eigen::Vector3d::Constant(margin);
  for (int a = 0; a < num_hands(); ++a)
    for (int o = a + 1; o < num_hands(); ++o) {
      const WorldHand& A = *hands_[a];
      const WorldHand& O = *hands_[o];
      if (!A.query || !O.query || A.query->empty() || O.query->empty()) continue;
      // Only points in both skins' boxes (grown by the margin) can touch: none for hands apart.
      const Eigen::AlignedBox3d box_a(A.skin_bounds.min() - grow, A.skin_bounds.max() + grow);
      const Eigen::AlignedBox3d box_o(O.skin_bounds.min() - grow, O.skin_bounds.max() + grow);
      if (!box_a.intersects(box_o)) continue;
      const Eigen::AlignedBox3d both = box_a.intersection(box_o);
      for (const bool reversed : {false, true}) {
        const int skin = reversed ? o : a, flesh = reversed ? a : o;
        const WorldHand& S = *hands_[skin];
        for (size_t v = 0; v < S.shape.skin_tet.size(); ++v) {
          HandHit hit;
          hit.skin = skin, hit.flesh = flesh, hit.vertex = static_cast<int>(v);
          hit.p_W = embedded_at(S.model->mesh(), S.state.x, S.shape.skin_tet[v], S.shape.skin_bary[v]);
          if (both.contains(hit.p_W) && hands_[flesh]->query->penetration(hit.p_W, margin, hit.pen))
            hand_hits_.push_back(hit);
        }
      }
    }
}

// Hand-hand contact of hand a with another hand o, both ways: a's skin points
// in o's deformed flesh, and o's skin points in a's flesh (each hand's
// DeformedMeshQuery), the latter a contact of a's flesh where the point is (the
// query's tet and weights in a), normal reversed: the two surfaces face each
// other there. The reaction of the first lies at o's tet and weights of a's
// skin point, that of the second at o's skin point.
// a meets o as two bodies of like inertia at the point meet (the hands are
// mirror images of one flesh): at the midpoint of the two points, moving at
// their mean velocity at the start of the step (the pair's centre of mass for
// equal masses, which their contact cannot move), half the depth deep. The
// other hand as a kinematic body instead (infinite inertia, as deformable
// objects' penalty contacts have it) stopped a dead against it: o, taking the
// whole impulse, was thrown back, or, answering implicitly, barely moved while
// a bounced off; momentum was lost either way.
//  - penalty contacts: o holds the same pairs the other way round, with twice
//    the stiffness and damping over the half depth (the same force k d, and,
//    for equal inertia, the force of one implicit solve of both hands): each
//    hand's step is implicit in its own motion, and o's forces are the
//    reactions of a's when the pair's mean velocity stays as it was (equal
//    inertia at the point; exactly at rest). Handed over to o as external
//    forces instead, a's forces left o's answer explicit in o, any mismatch
//    between the inertias amplified k h^2 / m >> 1 times: the contacts
//    chattered and never settled. See also anchor_hand_contacts().
//  - constraint contacts: the lower-numbered hand a holds both ways of the
//    pair, each point stopped at the mean velocity, and o takes the impulses
//    whole (take_hand_reactions()): momentum passes exactly, the meeting is
//    inelastic for equal inertia at the point, and the interface settles
//    where the two hands' pushes balance (o gives way where a's impulse is
//    more than it answers). Held by both hands, each against the midpoint as
//    a wall, it stays wherever it is, the forces unbalanced. A point twice as
//    heavy on a's side as on o's throws o back as fast as a came.
void World::collide_with_hands(SoftBody& b, std::unordered_map<std::uint64_t, int>& cluster) {
  const int a = b.hand;
  const int first_key = (rigid_ ? rigid_->num_objects() : 0) + num_deformables();
  for (const HandHit& hit : hand_hits_) {
    if (hit.skin != a && hit.flesh != a) continue;
    const bool reversed = hit.flesh == a;  // the other hand's skin point, in a's flesh
    const int o = reversed ? hit.skin : hit.flesh;
    if (constraint_contact_ && o < a) continue;  // the lower-numbered hand holds them
    const WorldHand& skin = *hands_[hit.skin];
    const WorldHand& flesh = *hands_[hit.flesh];
    const int tet = skin.shape.skin_tet[hit.vertex];
    const Eigen::Vector4d& w = skin.shape.skin_bary[hit.vertex];
    const MeshPenetration& pen = hit.pen;
    PointContact c;
    DeformableTouch touch;  // the reaction's point in o
    touch.hand = o;
    touch.reversed = reversed;
    if (!reversed) {  // a's skin point in o's flesh
      c.tet = tet, c.bary = w, c.n_W = pen.n_W;
      touch.tet = pen.tet, touch.bary = pen.bary;
    } else {  // o's skin point in a's flesh
      c.tet = pen.tet, c.bary = pen.bary, c.n_W = -pen.n_W;
      touch.tet = tet, touch.bary = w;
    }
    // The two points, one in each hand, meet at their midpoint: it moves at their mean velocity.
    c.v_other_W = 0.5 * (embedded_at(skin.model->mesh(), skin.state.v, tet, w) +
                         embedded_at(flesh.model->mesh(), flesh.state.v, pen.tet, pen.bary));
    c.depth_m = 0.5 * pen.depth_m;
    c.stiffness_n_m = 2 * options_.contact_stiffness_n_m;
    c.damping_ns_m = 2 * options_.contact_damping_ns_m;
    c.friction = std::sqrt(skin.friction * flesh.friction);
    c.constraint = constraint_contact_;
    add_contact(b, c, hit.vertex, hit.p_W, first_key + 2 * o + (reversed ? 1 : 0), touch, cluster);
  }
}

// A deformable object as the hand's constraint solve sees it: one rigid body
// (its mass, its inertia at its current shape, the velocities that carry its
// momentum) supported by the object's own contacts with static and rigid
// geometry, so an impulse from the hand is sized for the object's inertia and
// its support, as for a rigid body. Its solved motion is not used: the object's
// own step takes the hand's impulses (step_deformables()).
int World::add_rigid_proxy(HandState& s, int d) {
  const int index = static_cast<int>(s.bodies.size());
  s.bodies.push_back(rigid_proxy(*deformables_[d]));
  s.bodies.back().gravity_W = gravity_m_s2_;
  const SoftBody& own = soft_[num_hands() + d];
  for (size_t k = 0; k < own.state->contacts.size(); ++k) {
    const PointContact& c = own.state->contacts[k];
    BodySupport support;
    support.body = index;
    support.p_W = own.points[k];
    support.n_W = c.n_W;  // out of the support, into the object
    support.depth_m = c.depth_m;
    support.friction = c.friction;
    support.v_other_W = c.body >= 0 ? rigid_->point_velocity(c.other, own.points[k]) : c.v_other_W;
    s.supports.push_back(support);
  }
  return index;
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
    if (hand.query && constraint_contact_) {
      take_hand_reactions(h);  // in index order: the impulses of the hands that stepped before this one
    } else if (hand.query) {
      anchor_hand_contacts(h, step_dt_);
    }
    hand.step(options_.linearize ? &snapshot_.linear_models[h] : nullptr);
    snapshot_.linear_model_valid[h] = snapshot_.linear_models[h].K.size() > 0;
    timings.linearize_ms += hand.state.timings.linearize_ms;
    timings.contact_ms += hand.state.timings.contact_ms;
    if (hand.query) sum_hand_forces(h);
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

void World::remember_impulses(SoftBody& b) {
  // This step's impulses warm-start the next step's contacts in the same cells.
  b.warm_impulse.clear();
  for (size_t k = 0; k < b.keys.size(); ++k) b.warm_impulse[b.keys[k]] = b.state->contacts[k].f_W * step_dt_;
}

// Hand-deformable contact by operator splitting. A rigid body a hand touches
// joins the hand's system as one 6-DOF block; a deformable object would bring
// its whole A_t (and make the hand's factorization depend on every object it
// brushes), so the hand steps first, against the object as it was, and the
// object then steps with the hand's contact forces (f_W, the force on the
// hand), reversed, spread over the nodes of its tet by the contact point's
// barycentric weights, together with its own contacts against static and rigid
// geometry. It answers one step behind the hand's solve.
//  - constraint contacts: the hand met the object as a rigid proxy with the
//    object's supports (add_rigid_proxy); the object takes the impulses / h as
//    external forces. Momentum passes exactly (the weights sum to 1 and keep
//    the point of application). A kinematic object (the hand's impulse sized
//    to stop the hand against it) launched a light object: a hand at 0.3 m/s
//    drove the 0.2 kg bunny 3 cm into the table in one step.
//  - penalty contacts: the hand met the object as a kinematic body moving with
//    the object's node velocities interpolated at the contact. The reaction of
//    a stiff spring applied explicitly to a light object diverges
//    (k h^2 / m >> 1), so, as for every force in the step (Baraff-Witkin), its
//    dependence on the object's own velocity over the step is taken
//    implicitly: the object meets the hand's contact mirrored (a penalty
//    contact, normal reversed, same depth, the hand point moving at its solved
//    velocity), whose force is -f_W - (h K_c + D_c) (u_end - u_start) at the
//    object's point velocity u: -f_W when the object's point keeps the
//    velocity the hand's step assumed (up to the regularized friction, which
//    each side evaluates at its own relative velocity).
void World::step_deformables() {
  for (int d = 0; d < num_deformables(); ++d) {
    DeformableObject& o = *deformables_[d];
    o.state.f_ext.setZero();
    mirrored_.clear();
    for (int h = 0; h < num_hands(); ++h) {
      const SoftBody& b = soft_[h];
      for (size_t k = 0; k < b.touches.size(); ++k) {
        const DeformableTouch& touch = b.touches[k];
        if (touch.object != d) continue;
        const PointContact& c = b.state->contacts[k];
        const Tet& t = o.body.mesh.tets[touch.tet];
        if (c.constraint) {
          for (int a = 0; a < 4; ++a) o.state.f_ext.segment<3>(3 * t[a]) -= touch.bary[a] * c.f_W;
          continue;
        }
        PointContact mirror = c;
        mirror.tet = touch.tet;
        mirror.bary = touch.bary;
        mirror.n_W = -c.n_W;
        mirror.v_other_W.setZero();
        const Tet& ht = b.model->mesh().tets[c.tet];
        for (int a = 0; a < 4; ++a) mirror.v_other_W += c.bary[a] * b.state->v.segment<3>(3 * ht[a]);
        mirror.body = -1;
        mirror.other = -1;
        mirrored_.push_back(mirror);
      }
    }
    // The mirrored contacts join the object's own for this step only.
    HandState& s = o.state;
    const size_t own = s.contacts.size();
    s.contacts.insert(s.contacts.end(), mirrored_.begin(), mirrored_.end());
    hapticd::step(*o.model, s, *o.solver);
    // What the hands did to the object over the step, per node.
    o.f_hands_W = s.f_ext;
    for (size_t k = own; k < s.contacts.size(); ++k) {
      const Tet& t = o.body.mesh.tets[s.contacts[k].tet];
      for (int a = 0; a < 4; ++a) o.f_hands_W.segment<3>(3 * t[a]) += s.contacts[k].bary[a] * s.contacts[k].f_W;
    }
    s.contacts.resize(own);
    remember_impulses(soft_[num_hands() + d]);
  }
}

// Constraint contacts: hand h takes the impulses of the hands before it that
// hold contacts with it (collide_with_hands()), reversed, as external forces.
// They stay in f_ext after its step, so the model of its coming step (the
// visual loop's linearize_next_step) predicts them unchanged: as a force,
// without the contacts' stiffness.
void World::take_hand_reactions(int h) {
  HandState& s = hands_[h]->state;
  const TetMesh& mesh = hands_[h]->model->mesh();
  s.f_ext.setZero();
  for (int g = 0; g < h; ++g) {
    const SoftBody& from = soft_[g];
    for (size_t k = 0; k < from.touches.size(); ++k) {
      const DeformableTouch& touch = from.touches[k];
      if (touch.hand != h) continue;
      const Tet& t = mesh.tets[touch.tet];
      for (int a = 0; a < 4; ++a) s.f_ext.segment<3>(3 * t[a]) -= touch.bary[a] * from.state->contacts[k].f_W;
    }
  }
}

// Penalty contacts: hand_models' penalty contact takes the far end of its
// spring as still over the step (only its damping and friction see
// v_other_W): the spring's force k (d - h n . (v_end - v_other)) misses
// k h (n . v_other) n, known before the step, which comes in as an external
// force. Against the midpoint of two hands moving along n it is not small:
// both hands' springs pulled the pair toward rest, and a hand meeting another
// at 0.3 m/s lost nearly all their momentum within five steps. The recorded contact
// forces (f_W) have it: they take the relative velocity.
void World::anchor_hand_contacts(int h, double dt) {
  HandState& s = hands_[h]->state;
  const SoftBody& b = soft_[h];
  const TetMesh& mesh = hands_[h]->model->mesh();
  s.f_ext.setZero();
  for (size_t k = 0; k < b.touches.size(); ++k) {
    const PointContact& c = s.contacts[k];
    if (b.touches[k].hand < 0 || c.constraint) continue;
    const Eigen::Vector3d f = c.stiffness_n_m * dt * c.n_W.dot(c.v_other_W) * c.n_W;
    const Tet& t = mesh.tets[c.tet];
    for (int a = 0; a < 4; ++a) s.f_ext.segment<3>(3 * t[a]) += c.bary[a] * f;
  }
}

// What the other hands did to hand h over the step, per node: the impulses it
// took and its own hand-hand contacts' forces.
void World::sum_hand_forces(int h) {
  WorldHand& hand = *hands_[h];
  const SoftBody& b = soft_[h];
  const TetMesh& mesh = hand.model->mesh();
  if (constraint_contact_) {
    hand.f_hands_W = hand.state.f_ext;  // the impulses taken
  } else {
    hand.f_hands_W.setZero();  // f_ext holds part of the contacts' own forces (anchor_hand_contacts())
  }
  for (size_t k = 0; k < b.touches.size(); ++k) {
    if (b.touches[k].hand < 0) continue;
    const PointContact& c = hand.state.contacts[k];
    const Tet& t = mesh.tets[c.tet];
    for (int a = 0; a < 4; ++a) hand.f_hands_W.segment<3>(3 * t[a]) += c.bary[a] * c.f_W;
  }
}

void World::apply_reactions() {
  // Each body a hand or a deformable object touched was solved implicitly with
  // it, with its gravity and supports: its end-of-step velocity is the result,
  // handed to ODE less the gravity ODE adds again (ODE's own contacts then find
  // nothing to correct where the soft body's solve already satisfied them).
  for (const SoftBody& b : soft_) {
    const HandState& s = *b.state;
    std::vector<int> object_of_body(s.bodies.size(), -1);
    for (const PointContact& c : s.contacts)
      if (c.body >= 0) object_of_body[c.body] = c.other;
    for (size_t i = 0; i < s.bodies.size(); ++i) {
      if (object_of_body[i] < 0) continue;
      const ContactBody& B = s.bodies[i];
      rigid_->add_velocity(object_of_body[i], B.dv_W - step_dt_ * gravity_m_s2_, B.dw_W);
    }
  }
}

// The contacts the bodies hold, with the forces of the step that solved them
// (before collide() replaces them with the next step's).
void World::record_contacts() {
  snapshot_.contacts.clear();
  snapshot_.max_penetration_m = 0;
  for (const SoftBody& b : soft_) {
    const HandState& s = *b.state;
    for (size_t k = 0; k < s.contacts.size(); ++k) {
      const PointContact& c = s.contacts[k];
      const DeformableTouch& touch = b.touches[k];
      ContactRecord r;
      r.hand = b.hand;
      r.deformable = b.deformable;
      r.object = c.other;
      r.point = b.point_of[k];
      r.other_deformable = touch.object;
      r.other_hand = touch.hand;
      r.p_W = b.points[k];
      r.n_W = c.n_W;
      r.f_W = c.f_W;
      r.depth_m = c.depth_m;
      if (touch.hand >= 0) r.depth_m = 2 * c.depth_m;  // held at half depth (collide_with_hands())
      if (touch.reversed) r.point = -1;                // the other hand's skin point, in this hand's flesh
      snapshot_.contacts.push_back(r);
      snapshot_.max_penetration_m = std::max(snapshot_.max_penetration_m, r.depth_m);  // gaps are < 0
      if (touch.hand >= 0 && c.constraint) {
        // The other hand took this impulse reversed: its record too.
        r.hand = touch.hand;
        r.other_hand = b.hand;
        r.point = touch.reversed ? b.point_of[k] : -1;
        r.n_W = -c.n_W;
        r.f_W = -c.f_W;
        snapshot_.contacts.push_back(r);
      }
    }
    // Reserve points the step made rows of (the others carry no force).
    for (size_t k = 0; k < s.reserve_contacts.size(); ++k) {
      const PointContact& c = s.reserve_contacts[k];
      if (c.f_W.isZero()) continue;
      ContactRecord r;
      r.hand = b.hand;
      r.deformable = b.deformable;
      r.object = c.other;
      r.point = b.reserve_point[k];
      r.p_W = b.reserve_p_W[k];
      r.n_W = c.n_W;
      r.f_W = c.f_W;
      r.depth_m = c.depth_m;
      snapshot_.contacts.push_back(r);
      snapshot_.max_penetration_m = std::max(snapshot_.max_penetration_m, r.depth_m);
    }
  }
}

void World::publish() {
  snapshot_.step = steps_;
  snapshot_.t_s = t_s_;
  snapshot_.handles.resize(hands_.size());
  snapshot_.resets = 0;
  for (int h = 0; h < num_hands(); ++h) snapshot_.handles[h] = hands_[h]->state.handles;
  for (const SoftBody& b : soft_) snapshot_.resets += b.state->resets;
  snapshot_.body_resets = rigid_ ? rigid_->resets() : 0;
  snapshot_.deformables.resize(deformables_.size());
  for (int d = 0; d < num_deformables(); ++d) {
    const DeformableObject& o = *deformables_[d];
    DeformableSnapshot& out = snapshot_.deformables[d];
    out.surface_W.resize(o.body.surface_tet.size());
    for (size_t v = 0; v < out.surface_W.size(); ++v) out.surface_W[v] = surface_point(o, static_cast<int>(v));
    out.nodes_W.resize(o.model->num_nodes());
    for (int i = 0; i < o.model->num_nodes(); ++i) out.nodes_W[i] = o.state.x.segment<3>(3 * i);
  }
  snapshot_.bodies.clear();
  if (rigid_)
    for (int i = 0; i < rigid_->num_objects(); ++i) snapshot_.bodies.push_back(rigid_->state(i));
}

}  // namespace hapticd
