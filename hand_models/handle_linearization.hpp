#pragma once
// The handle-space linearized coupling force (seed 004 section 3, after GO09):
// what the haptic loop evaluates at 1 kHz instead of the FEM. For the step the
// visual loop is about to take from `state`, the coupling wrench the flesh puts
// on the handles, as an affine function of the handles' end-of-step pose x and
// velocity v (the haptic proxy's), all 6m handle DOFs at once:
//   F*(x, v) = F0 + K (x - x0) + D (v - v0).
// Time-implicit: the flesh answers through A_t^-1, so F* holds the flesh's
// compliance and inertia, its contacts (held as they are) and any rigid bodies
// solved with the hand, condensed through the Schur complement.
#include <Eigen/Core>
#include <vector>

#include "hand_models/coupled_solver.hpp"
#include "hand_models/hand_model.hpp"

namespace hapticd::hand {

struct ContactRows;  // contact_solve.hpp

// The contacts the coming step may make or break, for the haptic loop's complementarity solve:
// the step's constraint rows (contact_rows: the hand's active and speculative contacts, its bodies'
// supports) in contact frames (n, t1, t2). With row impulses lambda (N s over the step), the model is
//   F*(x, v) = F0 + K dx + D (v - v0) + G lambda                 (the wrench on the handles)
//   u(x, v)  = u0 + U_K dx + U_D (v - v0) + W lambda             (the rows' relative velocities)
// with 0 <= lambda_n _|_ u_n - bias_n >= 0 and |lambda_t| <= mu lambda_n (Coulomb): F0, K, D are then
// the model with no impulse on these rows, and W = J A^-1 J^T is the Delassus operator of the rows
// with the handles prescribed (the flesh's and the bodies' compliance behind each contact), all
// through the step's Schur factorization. A contact that would pull releases; a gap that closes
// engages.
struct HandleContactModel {
  Eigen::MatrixXd G;         // 6m x 3c: handle wrench per unit row impulse, N / (N s)
  Eigen::MatrixXd W;         // 3c x 3c, m/s per N s
  Eigen::VectorXd u0;        // 3c, m/s, at the anchor (x0, v0) without impulses
  Eigen::MatrixXd U_K, U_D;  // 3c x 6m: d u / d (pose), d u / d (velocity)
  Eigen::VectorXd bias;      // c, m/s
  std::vector<double> mu;    // c
  Eigen::VectorXd lambda0;   // 3c: the solution at the anchor, N s
  int count() const { return static_cast<int>(mu.size()); }
};

// The most contact rows a model carries (the deepest first; contact_rows): the haptic tick's
// complementarity problem stays small enough for 1 kHz.
constexpr int kMaxLinearizedContacts = 24;

// How linearize_next_step treats the constraint contacts of the coming step.
enum class ContactLinearization {
  held,        // the last step's pushing rows held bilaterally (GO09): F0, K, D say it all
  unilateral,  // the coming step's rows as a HandleContactModel, solved by the haptic tick
};

struct HandleLinearization {
  Eigen::VectorXd F0;  // 6m: force (N) and torque (N m) on each handle at (x0, v0)
  Eigen::MatrixXd K;   // 6m x 6m: d F / d (position, rotation vector), N/m and N m/rad
  Eigen::MatrixXd D;   // 6m x 6m: d F / d (velocity, angular velocity), N s/m and N m s/rad
  std::vector<HandleState> x0;  // the handles' poses and velocities at the linearization point
  HandleContactModel contacts;  // empty unless linearized ContactLinearization::unilateral with constraint rows

  // F*(x, v) for end-of-step handle states (position difference and the
  // rotation vector of q q0^-1 for the pose), contacts solved when the model has them (up to 10000
  // sweeps, to 1e-12 of the largest impulse where they get there: on the stylus bunny's press, 58
  // of 473 evaluations; 40000 sweeps moved `haptic-bench world`'s force error by at most 0.03 N).
  Eigen::VectorXd evaluate(const std::vector<HandleState>& handles) const;
};

// Builds the model of the step whose system `state` holds (assembled at the
// state's current positions); step() calls it right after its solve, while the
// solver's factorization is current. `solver` provides A_t^-1. With `held`, the
// flesh and bodies answer a handle displacement with those contact rows held
// at their solved relative velocities (bilateral, by their Lagrange
// multipliers), so the model keeps the contacts of the step (GO09). With `rows` instead, those rows
// become out.contacts (no impulse on them in F0, K, D). False if a solve fails.
bool linearize_handles(const HandModel& model, const HandState& state, CoupledSolver& solver,
                       HandleLinearization& out, const HeldContacts* held = nullptr,
                       const ContactRows* rows = nullptr);

// The model of the step about to be taken from `state` (GO09: the haptic loop
// needs the force over the coming interval, which the flesh's current momentum
// shapes, not the step just taken): assembles the system at the state as it is
// (contacts as set for the next step), solves it so the solver's factorization is
// current (the step that follows reuses it when nothing changed), and linearizes,
// with the constraint contacts as `contacts` says. The model is anchored at the handles'
// current state. False (and `out` cleared) if the solve fails.
bool linearize_next_step(const HandModel& model, HandState& state, CoupledSolver& solver, HandleLinearization& out,
                         ContactLinearization contacts = ContactLinearization::held);

// The coupling wrench on each handle at a given state, exactly (seed 004 eq. 4-5), 6m.
Eigen::VectorXd coupling_wrench(const HandModel& model, const Eigen::VectorXd& x_t, const Eigen::VectorXd& v_t,
                                const std::vector<HandleState>& handles);

}  // namespace hapticd::hand
