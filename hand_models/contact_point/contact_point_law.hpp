#pragma once
// The contact force of seed 001 (Hoell et al.) section 3.3 for one contact point, as functions:
//   f = gamma (C - p)                                   (eq. 1)
//   f_n = (f . n) n,  f_t = f - f_n                     (eqs. 2, 3)
//   inside = f . n > 0  and  |f_t| <= mu_st (f . n)     (eq. 4)
//   f_T = f_t inside the cone, else the kinetic share   (eq. 5)
// C is the contact point on the object's surface, n the object's outward normal there, p the hand
// point the contact follows (a sample on the phalanx's surface, section 3.2). f is the force on the
// hand: it points out of the object while p is inside it; the object takes -f at C.
//
// Two readings of the paper, both chosen so that a hand never pulls and friction is Coulomb's:
//  - eq. 2's normal force is applied only while f . n > 0 (p inside the object); a hand point outside
//    exerts nothing (the paper applies f_n "directly", which would pull for f . n < 0);
//  - eq. 5's dynamic branch is printed as mu_dyn f_t, a pure number times a force that grows with
//    the hand's tangential travel; it is taken as Coulomb's kinetic friction mu_dyn (f . n) along
//    f_t, the force "during dynamic contact state" that section 3.3's Fig. 6 describes.
// In the dynamic state the contact point slides (section 3.5): slide_target() says where to.
#include <Eigen/Core>

namespace hapticd::hand::contact_point {

enum class ContactState {
  separated,  // f . n <= 0: the hand point is outside the object, no force
  stuck,      // inside the friction cone (eq. 4): f_T = f_t
  sliding,    // outside it: f_T = mu_dyn (f . n) f_t / |f_t|
};

struct ContactForce {
  ContactState state = ContactState::separated;
  Eigen::Vector3d f_n = Eigen::Vector3d::Zero();  // eq. 2, on the hand
  Eigen::Vector3d f_T = Eigen::Vector3d::Zero();  // eq. 5, on the hand
  Eigen::Vector3d total() const { return f_n + f_T; }
};

// Eqs. 1-5 for contact point C_W with outward unit normal n_W and hand point p_W.
ContactForce contact_force(double gamma_n_m, double mu_static, double mu_dynamic, const Eigen::Vector3d& C_W,
                           const Eigen::Vector3d& n_W, const Eigen::Vector3d& p_W);

// Where a sliding contact point goes: along the tangent plane toward p's foot, until the tangential
// spring gamma |C - p|_t equals the kinetic force mu_dyn gamma (C - p) . n (the point the next step's
// eq. 5 starts from; the caller puts it back on a curved surface, section 3.5's ray). C itself for
// a contact that is not sliding.
Eigen::Vector3d slide_target(double mu_dynamic, const Eigen::Vector3d& C_W, const Eigen::Vector3d& n_W,
                             const Eigen::Vector3d& p_W);

}  // namespace hapticd::hand::contact_point
