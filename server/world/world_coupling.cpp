// World, coupling (world.hpp): the deformable objects' steps with the hands' reactions, hand-hand
// reactions, and the contact impulses onto the ODE bodies.
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <unordered_map>

#include "server/world/world.hpp"

namespace hapticd::world {

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
        const hand::PointContact& c = b.flesh.state->contacts[k];
        const hand::Tet& t = o.body.mesh.tets[touch.tet];
        if (c.constraint) {
          for (int a = 0; a < 4; ++a) o.state.f_ext.segment<3>(3 * t[a]) -= touch.bary[a] * c.f_W;
          continue;
        }
        hand::PointContact mirror = c;
        mirror.tet = touch.tet;
        mirror.bary = touch.bary;
        mirror.n_W = -c.n_W;
        mirror.v_other_W.setZero();
        const hand::Tet& ht = b.flesh.model->mesh().tets[c.tet];
        for (int a = 0; a < 4; ++a) mirror.v_other_W += c.bary[a] * b.flesh.state->v.segment<3>(3 * ht[a]);
        mirror.body = -1;
        mirror.other = -1;
        mirrored_.push_back(mirror);
      }
    }
    // The mirrored contacts join the object's own for this step only.
    hand::HandState& s = o.state;
    const size_t own = s.contacts.size();
    s.contacts.insert(s.contacts.end(), mirrored_.begin(), mirrored_.end());
    hand::step(*o.model, s, *o.solver);
    // What the hands did to the object over the step, per node.
    o.f_hands_W = s.f_ext;
    for (size_t k = own; k < s.contacts.size(); ++k) {
      const hand::Tet& t = o.body.mesh.tets[s.contacts[k].tet];
      for (int a = 0; a < 4; ++a) o.f_hands_W.segment<3>(3 * t[a]) += s.contacts[k].bary[a] * s.contacts[k].f_W;
    }
    s.contacts.resize(own);
    remember_impulses(deformable_soft(d));
  }
}

// Constraint contacts: hand h takes the impulses of the hands before it that
// hold contacts with it (collide_with_hands()), reversed, as external forces.
// They stay in f_ext after its step, so the model of its coming step (the
// visual loop's linearize_next_step) predicts them unchanged: as a force,
// without the contacts' stiffness.
void World::take_hand_reactions(int h) {
  hand::HandState& s = *soft_[h].flesh.state;
  const hand::TetMesh& mesh = soft_[h].flesh.model->mesh();
  s.f_ext.setZero();
  for (int g = 0; g < h; ++g) {
    const SoftBody& from = soft_[g];
    for (size_t k = 0; k < from.touches.size(); ++k) {
      const DeformableTouch& touch = from.touches[k];
      if (touch.hand != h) continue;
      const hand::Tet& t = mesh.tets[touch.tet];
      for (int a = 0; a < 4; ++a) s.f_ext.segment<3>(3 * t[a]) -= touch.bary[a] * from.flesh.state->contacts[k].f_W;
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
  hand::HandState& s = *soft_[h].flesh.state;
  const SoftBody& b = soft_[h];
  const hand::TetMesh& mesh = soft_[h].flesh.model->mesh();
  s.f_ext.setZero();
  for (size_t k = 0; k < b.touches.size(); ++k) {
    const hand::PointContact& c = s.contacts[k];
    if (b.touches[k].hand < 0 || c.constraint) continue;
    const Eigen::Vector3d f = c.stiffness_n_m * dt * c.n_W.dot(c.v_other_W) * c.n_W;
    const hand::Tet& t = mesh.tets[c.tet];
    for (int a = 0; a < 4; ++a) s.f_ext.segment<3>(3 * t[a]) += c.bary[a] * f;
  }
}

// What the other hands did to hand h over the step, per node: the impulses it
// took and its own hand-hand contacts' forces.
void World::sum_hand_forces(int h) {
  HandSlot& hand = hands_[h];
  const SoftBody& b = soft_[h];
  const hand::TetMesh& mesh = soft_[h].flesh.model->mesh();
  const hand::HandState& s = *soft_[h].flesh.state;
  if (constraint_contact_) {
    hand.f_hands_W = s.f_ext;  // the impulses taken
  } else {
    hand.f_hands_W.setZero();  // f_ext holds part of the contacts' own forces (anchor_hand_contacts())
  }
  for (size_t k = 0; k < b.touches.size(); ++k) {
    if (b.touches[k].hand < 0) continue;
    const hand::PointContact& c = s.contacts[k];
    const hand::Tet& t = mesh.tets[c.tet];
    for (int a = 0; a < 4; ++a) hand.f_hands_W.segment<3>(3 * t[a]) += c.bary[a] * c.f_W;
  }
}

void World::apply_reactions() {
  // Each body a hand or a deformable object touched was solved implicitly with
  // it, with its gravity and supports: its end-of-step velocity is the result,
  // handed to ODE less the gravity ODE adds again in the step's first substep,
  // the only one that adds it (ODE's own contacts then find nothing to correct
  // where the soft body's solve already satisfied them). Less the whole step's
  // gravity, RigidWorld's substeps saw the body move into its supports at g h
  // and bounce: the bunny at rest jumped 1.5 cm as a hand's first contact
  // reached it at a 15 Hz step.
  const double first_substep_s = step_dt_ / RigidWorld::substeps(step_dt_);
  solved_bodies_.clear();
  for (const SoftBody& b : soft_) {
    const hand::HandState& s = *b.flesh.state;
    std::vector<int> object_of_body(s.bodies.size(), -1);
    for (const hand::PointContact& c : s.contacts)
      if (c.body >= 0) object_of_body[c.body] = c.other;
    for (size_t i = 0; i < s.bodies.size(); ++i) {
      const int g = object_of_body[i];
      if (g < 0) continue;
      const hand::ContactBody& B = s.bodies[i];
      auto solved = std::find_if(solved_bodies_.begin(), solved_bodies_.end(),
                                 [g](const SolvedBody& sb) { return sb.object == g; });
      if (solved == solved_bodies_.end()) {
        solved_bodies_.push_back({g, rigid_->state(g), B.p_com_W, B.v_W + step_dt_ * gravity_m_s2_, B.w_W});
        solved = solved_bodies_.end() - 1;
      }
      // Each solve's change has the step's gravity in it: counted once (a box both hands hold).
      solved->v_W += B.dv_W - step_dt_ * gravity_m_s2_, solved->w_W += B.dw_W;
      rigid_->add_velocity(g, B.dv_W - first_substep_s * gravity_m_s2_, B.dw_W);
      rigid_->hold_gravity_for_next_step(g);
    }
  }
}

void World::place_solved_bodies() {
  // ODE stepped the bodies the soft bodies solved as it steps any (so the other bodies they touch
  // feel them); each of those then ends where its solve took it (implicit Euler with its solved
  // end-of-step velocity, as the hand's nodes), so the step the published model describes is the
  // step the world takes. Left to ODE, whose contacts and substeps do not know the hand, the bunny
  // pressed hard at 15 Hz landed on one foot with the spin the solve gave it and rocked 1-2 degrees
  // from one step to the next, an ear tip 2-3 mm into the palm; the stylus press on the movable bunny
  // at 30 Hz rendered 0.42 N RMS from the world stepped every tick where it now renders 0.29 N.
  const double h = step_dt_;
  for (const SolvedBody& sb : solved_bodies_) {
    RigidBodyState end;
    end.v_WO = sb.v_W;
    end.w_W = sb.w_W;
    const double angle = h * sb.w_W.norm();
    const Eigen::Quaterniond turn =
        angle > 0 ? Eigen::Quaterniond(Eigen::AngleAxisd(angle, sb.w_W.normalized())) : Eigen::Quaterniond::Identity();
    end.q_WO = (turn * sb.start.q_WO).normalized();
    const Eigen::Vector3d com_offset = sb.com_W - sb.start.p_WO;  // world, at the start
    end.p_WO = sb.com_W + h * sb.v_W - turn * com_offset;
    if (!end.p_WO.allFinite() || !end.q_WO.coeffs().allFinite()) continue;
    rigid_->set_state(sb.object, end);
  }
}

}  // namespace hapticd::world
