// World, publishing (world.hpp): the solved contacts as records and the snapshot.
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <unordered_map>

#include "server/world/world.hpp"

namespace hapticd::world {

// The contacts the bodies hold, with the forces of the step that solved them
// (before collide() replaces them with the next step's).
void World::record_contacts() {
  snapshot_.contacts.clear();
  snapshot_.max_penetration_m = 0;
  for (const SoftBody& b : soft_) {
    const hand::HandState& s = *b.flesh.state;
    for (size_t k = 0; k < s.contacts.size(); ++k) {
      const hand::PointContact& c = s.contacts[k];
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
      const hand::PointContact& c = s.reserve_contacts[k];
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
  // Hands of ODE bodies: their contacts of the last substep, at the first skin point on the touching
  // part's handle (a 6-frame glove's frame 2, the index's distal phalanx, is not skin point 2's).
  for (const RigidWorld::HandContact& c : ode_hand_contacts_) {
    ContactRecord r;
    r.hand = c.hand;
    r.object = c.object;
    const hand::Hand& hand = *hands_[c.hand].model;
    r.point = 0;
    for (int i = 0; i < hand.num_skin_points(); ++i)
      if (hand.skin_handle(i) == c.handle) {
        r.point = i;
        break;
      }
    r.p_W = c.p_W;
    r.n_W = c.n_W;
    r.f_W = c.f_W;
    r.depth_m = c.depth_m;
    snapshot_.contacts.push_back(r);
    snapshot_.max_penetration_m = std::max(snapshot_.max_penetration_m, r.depth_m);
  }
}

void World::publish() {
  snapshot_.step = steps_;
  snapshot_.t_s = t_s_;
  snapshot_.handles.resize(hands_.size());
  snapshot_.resets = 0;
  for (int h = 0; h < num_hands(); ++h) snapshot_.handles[h] = hands_[h].model->handles();
  for (const SoftBody& b : soft_) snapshot_.resets += b.flesh.state->resets;
  for (int h = 0; h < num_hands(); ++h)
    if (hand_soft_[h] < 0) snapshot_.resets += hands_[h].model->resets();
  snapshot_.body_resets = rigid_ ? rigid_->resets() : 0;
  snapshot_.deformables.resize(deformables_.size());
  for (int d = 0; d < num_deformables(); ++d) {
    const DeformableObject& o = *deformables_[d];
    DeformableSnapshot& out = snapshot_.deformables[d];
    out.surface_W.resize(o.body.surface_tet.size());
    for (size_t v = 0; v < out.surface_W.size(); ++v) out.surface_W[v] = detail::surface_point(o, static_cast<int>(v));
    out.nodes_W.resize(o.model->num_nodes());
    for (int i = 0; i < o.model->num_nodes(); ++i) out.nodes_W[i] = o.state.x.segment<3>(3 * i);
  }
  snapshot_.bodies.clear();
  if (rigid_)
    for (int i = 0; i < rigid_->num_objects(); ++i) snapshot_.bodies.push_back(rigid_->state(i));
}

}  // namespace hapticd::world
