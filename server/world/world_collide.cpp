// World, collision (world.hpp): hand skin and deformable surfaces against static and rigid
// geometry, hand skin against deformable objects and the other hands' flesh, clustered into
// constraint rows with reserves and warm-start impulses, for the next step.
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <unordered_map>

#include "server/world/world.hpp"

namespace hapticd::world {
namespace {

constexpr double kSpeculativeMargin_m = 0.002;
// The farthest a point is looked for ahead of a surface, whatever its speed (a teleport would
// otherwise make every point near every object a contact of the step).
constexpr double kMaxReach_m = 0.05;
// hand::kClearanceLook_m, how far ahead of a surface a hand's points are measured for their handles'
// clearance planes: 5 cm let a stylus that jumped 5 cm during a stall (10 cm in the world) through the
// bunny (StalledServer). Measured against 5 cm (haptic-bench world, 150 steps, three runs each, a
// temporary switch): collision 1.49 -> 1.61 ms on the glove grasp, unchanged on the stylus bunny
// (2.45 ms).
using hand::kClearanceLook_m;
// The least a clearance plane lets a handle come toward a surface within one visual step: thinner
// than any object it guards against passing through, more than the speculative margin.
constexpr double kClearanceFloor_m = 0.005;
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
Eigen::Vector3d embedded_at(const hand::TetMesh& mesh, const Eigen::VectorXd& x, int tet, const Eigen::Vector4d& w) {
  return hand::embedded_value(mesh.tets[tet], w, x);
}

// A bound on the speed of rigid object g's points (0 for a static one), from its AABB.
double speed_bound(const RigidWorld& rigid, int g, const dReal aabb[6]) {
  if (!rigid.is_dynamic(g)) return 0.0;
  const RigidBodyState body = rigid.state(g);
  const double radius = 0.5 * Eigen::Vector3d(aabb[1] - aabb[0], aabb[3] - aabb[2], aabb[5] - aabb[4]).norm();
  return body.v_WO.norm() + body.w_W.norm() * radius;
}

// Skin point i of the hand, at p, is `gap` from a surface with normal n (out of it) and not a
// contact: it becomes one of its handle's clearance planes (`clearance`, per handle) if it is the
// nearest in its direction.
void note_clearance(const hand::Hand& hand, std::vector<std::vector<hand::ClearancePlane>>& clearance, int i,
                    const Eigen::Vector3d& p, const Eigen::Vector3d& n, double gap) {
  const int j = hand.skin_handle(i);
  if (j < 0 || j >= static_cast<int>(clearance.size()) || !n.allFinite()) return;
  std::vector<hand::ClearancePlane>& planes = clearance[static_cast<std::size_t>(j)];
  // At least kClearanceFloor_m: a point just outside would otherwise hold its handle off the surface
  // it is about to touch (with penalty contact, which has no speculative rows, no step would find
  // it), and a hand closing faster than its gaps per visual step would lag its device.
  gap = std::max(gap, kClearanceFloor_m);
  const hand::ClearancePlane plane{n, p - hand.handles()[static_cast<std::size_t>(j)].p_WH, gap};
  hand::ClearancePlane* farthest = nullptr;
  for (hand::ClearancePlane& c : planes) {
    if (c.n_W.dot(n) > hand::kClearanceSpread) {  // the same direction: the nearer stays
      if (gap < c.gap_m) c = plane;
      return;
    }
    if (!farthest || c.gap_m > farthest->gap_m) farthest = &c;
  }
  if (static_cast<int>(planes.size()) < hand::kClearancePlanes)
    planes.push_back(plane);
  else if (gap < farthest->gap_m)
    *farthest = plane;
}

}  // namespace

void World::collide_all() {
  // Deformable objects first: a hand touching one takes the object's own contacts as its supports.
  for (int d = 0; d < num_deformables(); ++d) {
    DeformableObject& o = *deformables_[d];
    if (o.query) o.query->update(o.state.x), o.fit = detail::rigid_fit(o);
    o.surface_bounds.setEmpty();
    for (int v = 0; v < static_cast<int>(o.body.surface_tet.size()); ++v)
      o.surface_bounds.extend(detail::surface_point(o, v));
    collide(deformable_soft(d));
  }
  find_hand_hits();
  for (int h = 0; h < num_hands(); ++h)
    if (hand_soft_[h] >= 0) collide(soft_[hand_soft_[h]]);
  // The coming step's external forces as far as known now, for the model of the coming step.
  if (!constraint_contact_)
    for (int h = 0; h < num_hands(); ++h)
      if (hand_hand_) anchor_hand_contacts(h, dt_);
}

void World::add_contact(SoftBody& b, const hand::PointContact& c, int point, const Eigen::Vector3d& p_W, int other_key,
                        const DeformableTouch& touch, std::unordered_map<std::uint64_t, int>& cluster) {
  hand::HandState& s = *b.flesh.state;
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
  auto keep_in_reserve = [&](const hand::PointContact& r, int r_point, const Eigen::Vector3d& r_p_W) {
    if (!options_.contact_reserves || touch.object >= 0 || touch.hand >= 0) return;
    s.reserve_contacts.push_back(r);
    b.reserve_point.push_back(r_point);
    b.reserve_p_W.push_back(r_p_W);
  };
  const std::uint64_t key = cluster_key(other_key, p_W, options_.contact_cluster_m);
  hand::PointContact warm_started = c;
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
  hand::HandState& s = *b.flesh.state;
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
  const hand::TetMesh& mesh = b.flesh.model->mesh();
  const std::vector<int>& point_tet = *b.flesh.point_tet;
  const std::vector<Eigen::Vector4d>& point_bary = *b.flesh.point_bary;
  // A deformable object's point is looked for as far ahead of a surface as it can come over the
  // coming step (taken as long as the last): 2 mm, plus its speed and the object's, plus gravity's,
  // over the step. Within that reach it remembers the face it approaches, so that a step that
  // carries it deep (a slow visual loop: gravity alone moves 4.4 cm in a 67 ms step) pushes it back
  // out that face, not through a thin plate; constraint contacts also make it a speculative row if
  // it closes the gap within the step (penalty contacts act once it is inside). A hand's points,
  // driven by their handles, are rows within 2 mm, or farther if their approach closes the gap
  // within the step (no gravity; constraint contact). At 2 mm alone, a stylus at workspace scale 2
  // moving the hand 4 mm a 15 Hz step reached the bunny in a step that held no contact, ended it
  // 0.5 mm deeper than its pressed pose, and pushing it back out put +6.6e-4 J into the stylus
  // (Touch/SlowVisualPress). Rows for every point within 2 mm plus its step's motion raised the
  // stylus bunny's model error (p99 3.8 -> 4.8 N, scripts/bench-world), and more rows had slowed the
  // contact solve of a finger driven into the table (WorldGloveHardCases).
  const bool free_body = b.hand < 0;
  // Gravity's share: the speed it adds over the step, which the implicit (backward Euler) step moves
  // with for the step's whole length (h v_end), g h^2 from rest. A free body's reach is not capped by
  // kMaxReach_m (a teleport's guard; its motion is its own): a soft cube dropped 25 cm onto a 4 cm
  // table fell through it at 150 ms steps with the reach capped, and at 200 ms with half of g h^2.
  const double h = step_dt_, fall = gravity_m_s2_.norm() * h;
  // A hand's points farther than their reach are still measured up to kClearanceLook_m: the smallest
  // such gap per handle is how far the haptic tick may carry that handle before a contact the
  // model does not hold could begin (World::clearance).
  HandSlot* world_hand = free_body ? nullptr : &hands_[b.hand];
  if (world_hand) {
    world_hand->clearance.resize(world_hand->model->handles().size());
    for (std::vector<hand::ClearancePlane>& planes : world_hand->clearance) planes.clear();
  }
  std::vector<int> body_of_object(rigid_ ? rigid_->num_objects() : 0, -1);
  // Every point's position and velocity, the same against every object.
  std::vector<Eigen::Vector3d> points_p(point_tet.size(), Eigen::Vector3d::Zero()),
      points_v(point_tet.size(), Eigen::Vector3d::Zero());
  for (size_t v = 0; rigid_ && v < point_tet.size(); ++v) {
    const hand::Tet& t = mesh.tets[point_tet[v]];
    const Eigen::Vector4d& w = point_bary[v];
    for (int k = 0; k < 4; ++k)
      points_p[v] += w[k] * s.x.segment<3>(3 * t[k]), points_v[v] += w[k] * s.v.segment<3>(3 * t[k]);
  }
  for (int g = 0; rigid_ && g < rigid_->num_objects(); ++g) {
    dGeomID geom = rigid_->geom(g);
    dReal aabb[6];
    const bool bounded = dGeomGetClass(geom) != dPlaneClass;
    if (bounded) dGeomGetAABB(geom, aabb);
    const double object_speed = bounded ? speed_bound(*rigid_, g, aabb) : 0.0;
    for (size_t v = 0; v < point_tet.size(); ++v) {
      const Eigen::Vector3d &p = points_p[v], &p_v = points_v[v];
      const Eigen::Vector4d& w = point_bary[v];
      const double reach =
          free_body ? kSpeculativeMargin_m + (p_v.norm() + object_speed + fall) * h
                    : (constraint_contact_
                           ? std::min(std::max(kSpeculativeMargin_m, (p_v.norm() + object_speed) * h), kMaxReach_m)
                           : 0.0);
      const double look = world_hand ? kClearanceLook_m : reach;
      LastContact& last = b.last[v];
      // The point's distance to the object's box (0 inside it), a lower bound of its distance to
      // the object, and the direction from the box to it.
      Eigen::Vector3d box_offset = Eigen::Vector3d::Zero();
      if (bounded)
        for (int k = 0; k < 3; ++k)
          box_offset[k] = std::max(0.0, p[k] - aabb[2 * k + 1]) - std::max(0.0, aabb[2 * k] - p[k]);
      // Beyond `look` (>= reach) for certain, without the square root (most points, most objects).
      if (box_offset.squaredNorm() > (1 + 1e-6) * look * look) {
        if (last.object == g) last = LastContact{};
        continue;
      }
      const double box_gap = box_offset.norm();
      if (box_gap > reach) {
        if (last.object == g) last = LastContact{};
        if (world_hand && box_gap < look)
          note_clearance(*world_hand->model, world_hand->clearance, static_cast<int>(v), p, box_offset / box_gap,
                         box_gap);
        continue;
      }
      double depth;
      Eigen::Vector3d n;
      const Eigen::Vector3d entry = last.object == g ? last.n_W : Eigen::Vector3d::Zero();
      const bool near = rigid_->penetration(g, p, depth, n, entry, look);
      if (!near || depth <= -reach) {
        if (last.object == g) last = LastContact{};
        // A mesh's fine grid answers to 1.65 cm only: farther, its coarse one (StalledServer: with
        // no plane from the bunny a step carried the hand 84 mm down onto it).
        double gap = -depth;
        if (world_hand && (near || rigid_->far_clearance(g, p, gap, n)) && gap < look)
          note_clearance(*world_hand->model, world_hand->clearance, static_cast<int>(v), p, n, gap);
        continue;
      }
      last = LastContact{g, n};
      // A speculative row beyond the floor is a plane too: rows found at a fast hand's reach (up to
      // kMaxReach_m) were all that bounded the next step's target, and its hand went 11 mm in.
      if (world_hand && depth < -kClearanceFloor_m)
        note_clearance(*world_hand->model, world_hand->clearance, static_cast<int>(v), p, n, -depth);
      const Eigen::Vector3d v_other = rigid_->point_velocity(g, p);
      // Outside, with constraint contact: a deformable object's point is a row if it closes the gap
      // within the step (its mean velocity toward the surface over the step, under gravity, times
      // the step) but 2 mm, for what the step adds; a hand's point if it is within 2 mm or closes
      // the gap within the step.
      if (depth <= 0) {
        // How far it approaches the surface over the step (a free body's gravity counted).
        const Eigen::Vector3d v_rel =
            p_v - v_other + (free_body ? Eigen::Vector3d(h * gravity_m_s2_) : Eigen::Vector3d::Zero());
        const double closes = std::max(0.0, -v_rel.dot(n)) * h;
        const bool row = constraint_contact_ && (free_body ? -depth <= kSpeculativeMargin_m + closes
                                                           : -depth <= std::max(kSpeculativeMargin_m, closes));
        if (!row) continue;
      }
      hand::PointContact c;
      c.tet = point_tet[v];
      c.bary = w;
      c.n_W = n;
      c.depth_m = depth;
      c.v_other_W = v_other;
      c.body = implicit_body(s, body_of_object, g);
      c.stiffness_n_m = options_.contact_stiffness_n_m;
      c.damping_ns_m = options_.contact_damping_ns_m;
      c.friction = std::sqrt(b.flesh.friction * rigid_->friction(g));
      c.other = g;
      c.constraint = constraint_contact_;
      add_contact(b, c, static_cast<int>(v), p, g, DeformableTouch{}, cluster);
    }
  }
  if (b.hand >= 0) collide_with_deformables(b, cluster);
  if (b.hand >= 0 && hand_hand_) collide_with_hands(b, cluster);
  if (b.hand >= 0 && hands_[b.hand].query) collide_mesh_vertices(b, body_of_object, cluster);
  // The bodies touched bring their own contacts (table, other bodies) as supports: those found, and
  // those remembered while the gap the body lifted off them is one the coming step can close (its
  // speed and gravity over the step, as for a deformable object's points). With only 2 mm, a
  // bunny pressed by the hand that had bounced 2.4 mm off the table at a 67 ms step was solved, and
  // linearized for the haptic loop, with nothing under it: the hand drove it 1 cm into the table.
  std::vector<RigidWorld::BodyContact> found;
  for (int g = 0; rigid_ && g < rigid_->num_objects(); ++g) {
    if (body_of_object[g] < 0) continue;
    dReal aabb[6];
    dGeomGetAABB(rigid_->geom(g), aabb);
    // Gravity's share is not capped by kMaxReach_m (a teleport's guard): at a 200 ms step
    // a box the glove let go of 5 cm above the table falls up to 39 cm (g h^2) within the hand's solve,
    // and with the table out of reach it went through it to the floor (Touch/GraspRelease at 5 Hz).
    // The whole g h^2 (half of it until 2a49e32) gives the bunny under the stylus 4-5 more support
    // rows, and its model's force error went 0.08 / 3.8 -> 0.16 / 10.3 N (scripts/bench-world).
    const double reach = std::min(kSpeculativeMargin_m + speed_bound(*rigid_, g, aabb) * h, kMaxReach_m) + fall * h;
    rigid_->supports_of(g, found, reach);
    for (const RigidWorld::BodyContact& bc : found) {
      hand::BodySupport support;
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
  hand::HandState& s = *b.flesh.state;
  const double margin = constraint_contact_ ? kSpeculativeMargin_m : 0.0;
  const int first_key = rigid_ ? rigid_->num_objects() : 0;
  const int vertex_key = 2 * first_key + num_deformables() + 2 * num_hands();
  HandSlot& world_hand = hands_[b.hand];
  const double h = step_dt_;
  for (int d = 0; d < num_deformables(); ++d) {
    const DeformableObject& o = *deformables_[d];
    if (!o.query || o.query->empty() || o.surface_bounds.isEmpty()) continue;
    // As against a rigid object (collide()): a skin point is a row within 2 mm, or farther if its
    // approach closes the gap within the step, looked for up to its reach (the step's motion, its
    // own and the object's fastest node's); beyond that, its gap is one of its handle's clearance
    // planes, up to kClearanceLook_m. The query locates points a quarter of a tet outside the mesh;
    // farther, the rest surface carried by the object's rigid fit bounds the gap (far_clearance).
    // Without either a deep press at 5 Hz reached the bunny 12 mm past its surface in one step and
    // held the stylus 4.1 N toward it after the lift (SlowTouch/PressHoldLiftForces).
    double object_speed = 0;
    for (int i = 0; i < o.model->num_nodes(); ++i)
      object_speed = std::max(object_speed, o.state.v.segment<3>(3 * i).norm());
    const Eigen::AlignedBox3d& bounds = o.surface_bounds;
    int proxy = -1;  // constraint contacts: the object's index in s.bodies
    for (int v = 0; v < b.flesh.num_points(); ++v) {
      const Eigen::Vector3d p = b.flesh.point(v, s.x);
      // The point's distance to the surface's box (0 inside it), a lower bound of its gap.
      const Eigen::Vector3d box_offset = (p - bounds.max()).cwiseMax(0.0) - (bounds.min() - p).cwiseMax(0.0);
      if (box_offset.squaredNorm() > kClearanceLook_m * kClearanceLook_m) continue;
      const Eigen::Vector3d p_v = b.flesh.point(v, s.v);
      const double reach =
          constraint_contact_ ? std::min(std::max(margin, (p_v.norm() + object_speed) * h), kMaxReach_m) : 0.0;
      const double box_gap = box_offset.norm();
      if (box_gap > reach) {
        note_clearance(*world_hand.model, world_hand.clearance, v, p, box_offset / box_gap, box_gap);
        continue;
      }
      MeshPenetration pen;
      if (!o.query->penetration(p, kClearanceLook_m, pen)) {
        double gap;
        Eigen::Vector3d n;
        if (detail::far_clearance(o, p, gap, n) && gap < kClearanceLook_m)
          note_clearance(*world_hand.model, world_hand.clearance, v, p, n, gap);
        continue;
      }
      Eigen::Vector3d v_other = Eigen::Vector3d::Zero();
      const hand::Tet& ot = o.body.mesh.tets[pen.tet];
      for (int k = 0; k < 4; ++k) v_other += pen.bary[k] * o.state.v.segment<3>(3 * ot[k]);
      if (pen.depth_m <= -reach ||
          (pen.depth_m <= -margin && -pen.depth_m > std::max(0.0, -(p_v - v_other).dot(pen.n_W)) * h)) {
        note_clearance(*world_hand.model, world_hand.clearance, v, p, pen.n_W, -pen.depth_m);
        continue;
      }
      if (pen.depth_m < -kClearanceFloor_m)
        note_clearance(*world_hand.model, world_hand.clearance, v, p, pen.n_W, -pen.depth_m);
      hand::PointContact c;
      c.tet = (*b.flesh.point_tet)[v];
      c.bary = (*b.flesh.point_bary)[v];
      c.n_W = pen.n_W;
      c.depth_m = pen.depth_m;
      c.v_other_W = v_other;
      c.stiffness_n_m = options_.contact_stiffness_n_m;
      c.damping_ns_m = options_.contact_damping_ns_m;
      c.friction = std::sqrt(b.flesh.friction * o.friction);
      c.constraint = constraint_contact_;
      if (constraint_contact_) {
        if (proxy < 0) proxy = add_rigid_proxy(s, d);
        c.body = proxy;
      }
      add_contact(b, c, static_cast<int>(v), p, first_key + d, DeformableTouch{d, pen.tet, pen.bary}, cluster);
    }
    // The other way round, the object's surface points inside the hand's flesh (as a rigid mesh's
    // vertices, collide_mesh_vertices): contacts of the flesh where each lies, pushed along the
    // reversed skin normal, the reaction on the object at its point. The skin points alone let a
    // thin part between them: the deformable bunny pressed 3 cm deep with the palm at a 15 Hz step
    // had an ear inside the palm, whose side faced a skin point from below, and held the palm by it
    // as the user lifted (2.3 N toward the bunny against 1.1 N for the same lift in free space).
    const HandSlot& hand = world_hand;
    const Eigen::Vector3d grow_margin = Eigen::Vector3d::Constant(margin);
    if (!hand.query || !hand.query_current || hand.query->empty() ||
        !Eigen::AlignedBox3d(o.surface_bounds.min() - grow_margin, o.surface_bounds.max() + grow_margin)
             .intersects(hand.skin_bounds))
      continue;
    const Eigen::AlignedBox3d skin(hand.skin_bounds.min() - grow_margin, hand.skin_bounds.max() + grow_margin);
    for (int v = 0; v < static_cast<int>(o.body.surface_tet.size()); ++v) {
      const Eigen::Vector3d p = detail::surface_point(o, v);
      MeshPenetration pen;
      if (!skin.contains(p) || !hand.query->penetration(p, margin, pen)) continue;
      hand::PointContact c =
          flesh_contact(pen, embedded_at(o.body.mesh, o.state.v, o.body.surface_tet[v], o.body.surface_bary[v]),
                        b.flesh.friction, o.friction);
      if (constraint_contact_) {
        if (proxy < 0) proxy = add_rigid_proxy(s, d);
        c.body = proxy;
      }
      DeformableTouch touch{d, o.body.surface_tet[v], o.body.surface_bary[v]};
      touch.reversed = true;  // no skin point of the hand: the record names none
      // Keys of their own, past the rigid meshes' vertices' (collide_mesh_vertices).
      add_contact(b, c, -2 - v, p, vertex_key + d, touch, cluster);
    }
  }
}

bool World::mesh_overlaps(int g, const Eigen::AlignedBox3d& skin_bounds) const {
  const Eigen::Vector3d grow = Eigen::Vector3d::Constant(constraint_contact_ ? kSpeculativeMargin_m : 0.0);
  dReal aabb[6];
  dGeomGetAABB(rigid_->geom(g), aabb);
  return Eigen::AlignedBox3d(skin_bounds.min() - grow, skin_bounds.max() + grow)
      .intersects(
          Eigen::AlignedBox3d(Eigen::Vector3d(aabb[0], aabb[2], aabb[4]), Eigen::Vector3d(aabb[1], aabb[3], aabb[5])));
}

int World::implicit_body(hand::HandState& s, std::vector<int>& body_of_object, int g) {
  if (!rigid_->is_dynamic(g)) return -1;
  // Dynamic bodies join this body's implicit system for the step.
  if (body_of_object[g] < 0) {
    body_of_object[g] = static_cast<int>(s.bodies.size());
    s.bodies.push_back(rigid_->contact_body(g));
    s.bodies.back().gravity_W = gravity_m_s2_;
  }
  return body_of_object[g];
}

// A rigid mesh's vertices inside the hand's deformed flesh: contacts of the flesh where each one
// lies (the query's tet and weights), pushed along the reversed skin normal (the two surfaces face
// each other there), depth as deep as the vertex is inside the skin. The skin points alone let a
// thin part through between them: the scenes' bunny pressed with the palm at a 15 Hz step had its
// ear tips inside the palm, the skin points round them pushed sideways by up to 13 N each, and the
// palm held the bunny by their friction when the user lifted (3.3 N toward it, 2 s on).
void World::collide_mesh_vertices(SoftBody& b, std::vector<int>& body_of_object,
                                  std::unordered_map<std::uint64_t, int>& cluster) {
  hand::HandState& s = *b.flesh.state;
  const HandSlot& hand = hands_[b.hand];
  if (!hand.query || !hand.query_current || hand.query->empty() || hand.skin_bounds.isEmpty()) return;
  const double margin = constraint_contact_ ? kSpeculativeMargin_m : 0.0;
  const Eigen::Vector3d grow = Eigen::Vector3d::Constant(margin);
  const Eigen::AlignedBox3d skin(hand.skin_bounds.min() - grow, hand.skin_bounds.max() + grow);
  // Keys of their own: a cell's deepest skin point must not stand in for a vertex.
  const int first_key = (rigid_ ? rigid_->num_objects() : 0) + num_deformables() + 2 * num_hands();
  std::vector<Eigen::Vector3d> vertices;
  for (int g = 0; rigid_ && g < rigid_->num_objects(); ++g) {
    if (!rigid_->is_mesh(g) || !mesh_overlaps(g, hand.skin_bounds)) continue;
    rigid_->support_points(g, vertices);  // the mesh's vertices, world frame
    for (size_t v = 0; v < vertices.size(); ++v) {
      const Eigen::Vector3d& p = vertices[v];
      MeshPenetration pen;
      if (!skin.contains(p) || !hand.query->penetration(p, margin, pen)) continue;
      hand::PointContact c = flesh_contact(pen, rigid_->point_velocity(g, p), b.flesh.friction, rigid_->friction(g));
      c.other = g;
      c.body = implicit_body(s, body_of_object, g);
      DeformableTouch touch;
      touch.reversed = true;  // no skin point of the hand: the record names none
      add_contact(b, c, -2 - static_cast<int>(v), p, first_key + g, touch, cluster);
    }
  }
}

// Every pair of hands' skin points in the other's flesh, found once for both
// hands (collide_with_hands() makes their contacts), against every hand's
// flesh where it is now.
void World::find_hand_hits() {
  hand_hits_.clear();
  for (int h = 0; h < num_hands(); ++h) {
    HandSlot& hand = hands_[h];
    if (!hand.query) continue;
    const hand::Flesh& flesh = soft_[hand_soft_[h]].flesh;
    hand.skin_bounds.setEmpty();
    for (int v = 0; v < flesh.num_points(); ++v) hand.skin_bounds.extend(flesh.point(v, flesh.state->x));
    // Rebuilt (a few ms for a glove's flesh) only when it is asked: another hand, or a mesh or a
    // deformable object near.
    bool mesh_near = false;
    for (int g = 0; rigid_ && g < rigid_->num_objects() && !mesh_near; ++g)
      mesh_near = rigid_->is_mesh(g) && mesh_overlaps(g, hand.skin_bounds);
    const Eigen::Vector3d grow = Eigen::Vector3d::Constant(constraint_contact_ ? kSpeculativeMargin_m : 0.0);
    for (int d = 0; d < num_deformables() && !mesh_near; ++d) {
      const DeformableObject& o = *deformables_[d];
      mesh_near = o.query && !o.surface_bounds.isEmpty() &&
                  Eigen::AlignedBox3d(o.surface_bounds.min() - grow, o.surface_bounds.max() + grow)
                      .intersects(hand.skin_bounds);
    }
    hand.query_current = hand_hand_ || mesh_near;
    if (hand.query_current) hand.query->update(flesh.state->x);
  }
  if (!hand_hand_) return;  // the queries serve the mesh vertices only
  const double margin = constraint_contact_ ? kSpeculativeMargin_m : 0.0;
  const Eigen::Vector3d grow = Eigen::Vector3d::Constant(margin);
  for (int a = 0; a < num_hands(); ++a)
    for (int o = a + 1; o < num_hands(); ++o) {
      const HandSlot& A = hands_[a];
      const HandSlot& O = hands_[o];
      if (!A.query || !O.query || A.query->empty() || O.query->empty()) continue;
      // Only points in both skins' boxes (grown by the margin) can touch: none for hands apart.
      const Eigen::AlignedBox3d box_a(A.skin_bounds.min() - grow, A.skin_bounds.max() + grow);
      const Eigen::AlignedBox3d box_o(O.skin_bounds.min() - grow, O.skin_bounds.max() + grow);
      if (!box_a.intersects(box_o)) continue;
      const Eigen::AlignedBox3d both = box_a.intersection(box_o);
      for (const bool reversed : {false, true}) {
        const int skin = reversed ? o : a, flesh = reversed ? a : o;
        const hand::Flesh& S = soft_[skin].flesh;
        for (int v = 0; v < S.num_points(); ++v) {
          HandHit hit;
          hit.skin = skin, hit.flesh = flesh, hit.vertex = v;
          hit.p_W = S.point(v, S.state->x);
          if (both.contains(hit.p_W) && hands_[flesh].query->penetration(hit.p_W, margin, hit.pen))
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
    const hand::Flesh& skin = soft_[hit.skin].flesh;
    const hand::Flesh& flesh = soft_[hit.flesh].flesh;
    const int tet = (*skin.point_tet)[hit.vertex];
    const Eigen::Vector4d& w = (*skin.point_bary)[hit.vertex];
    const MeshPenetration& pen = hit.pen;
    hand::PointContact c;
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
    c.v_other_W = 0.5 * (skin.point(hit.vertex, skin.state->v) +
                         embedded_at(flesh.model->mesh(), flesh.state->v, pen.tet, pen.bary));
    c.depth_m = 0.5 * pen.depth_m;
    c.stiffness_n_m = 2 * options_.contact_stiffness_n_m;
    c.damping_ns_m = 2 * options_.contact_damping_ns_m;
    c.friction = std::sqrt(skin.friction * flesh.friction);
    c.constraint = constraint_contact_;
    add_contact(b, c, hit.vertex, hit.p_W, first_key + 2 * o + (reversed ? 1 : 0), touch, cluster);
  }
}

hand::PointContact World::flesh_contact(const MeshPenetration& pen, const Eigen::Vector3d& v_other_W,
                                        double hand_friction, double other_friction) const {
  hand::PointContact c;
  c.tet = pen.tet;
  c.bary = pen.bary;
  c.n_W = -pen.n_W;
  c.depth_m = pen.depth_m;
  c.v_other_W = v_other_W;
  c.stiffness_n_m = options_.contact_stiffness_n_m;
  c.damping_ns_m = options_.contact_damping_ns_m;
  c.friction = std::sqrt(hand_friction * other_friction);
  c.constraint = constraint_contact_;
  return c;
}

// A deformable object as the hand's constraint solve sees it: one rigid body
// (its mass, its inertia at its current shape, the velocities that carry its
// momentum) supported by the object's own contacts with static and rigid
// geometry, so an impulse from the hand is sized for the object's inertia and
// its support, as for a rigid body. Its solved motion is not used: the object's
// own step takes the hand's impulses (step_deformables()).
int World::add_rigid_proxy(hand::HandState& s, int d) {
  const int index = static_cast<int>(s.bodies.size());
  s.bodies.push_back(detail::rigid_proxy(*deformables_[d]));
  s.bodies.back().gravity_W = gravity_m_s2_;
  const SoftBody& own = deformable_soft(d);
  for (size_t k = 0; k < own.flesh.state->contacts.size(); ++k) {
    const hand::PointContact& c = own.flesh.state->contacts[k];
    hand::BodySupport support;
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

void World::remember_impulses(SoftBody& b) {
  // This step's impulses warm-start the next step's contacts in the same cells.
  b.warm_impulse.clear();
  for (size_t k = 0; k < b.keys.size(); ++k) b.warm_impulse[b.keys[k]] = b.flesh.state->contacts[k].f_W * step_dt_;
}

}  // namespace hapticd::world
