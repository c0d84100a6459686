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

struct HandleLinearization {
  Eigen::VectorXd F0;  // 6m: force (N) and torque (N m) on each handle at (x0, v0)
  Eigen::MatrixXd K;   // 6m x 6m: d F / d (position, rotation vector), N/m and N m/rad
  Eigen::MatrixXd D;   // 6m x 6m: d F / d (velocity, angular velocity), N s/m and N m s/rad
  std::vector<HandleState> x0;  // the handles' poses and velocities at the linearization point

  // F*(x, v) for end-of-step handle states (position difference and the
  // rotation vector of q q0^-1 for the pose).
  Eigen::VectorXd evaluate(const std::vector<HandleState>& handles) const;
};

// Builds the model of the step whose system `state` holds (assembled at the
// state's current positions); step() calls it right after its solve, while the
// solver's factorization is current. `solver` provides A_t^-1. With `held`, the
// flesh and bodies answer a handle displacement with those contact rows held
// at their solved relative velocities (bilateral, by their Lagrange
// multipliers), so the model keeps the contacts of the step (GO09). False if a solve fails.
bool linearize_handles(const HandModel& model, const HandState& state, CoupledSolver& solver,
                       HandleLinearization& out, const HeldContacts* held = nullptr);

// The model of the step about to be taken from `state` (GO09: the haptic loop
// needs the force over the coming interval, which the flesh's current momentum
// shapes, not the step just taken): assembles the system at the state as it is
// (contacts as set for the next step), solves it so the solver's factorization is
// current (the step that follows reuses it when nothing changed), and linearizes,
// holding the last step's held contacts. The model is anchored at the handles'
// current state. False (and `out` cleared) if the solve fails.
bool linearize_next_step(const HandModel& model, HandState& state, CoupledSolver& solver, HandleLinearization& out);

// The coupling wrench on each handle at a given state, exactly (seed 004 eq. 4-5), 6m.
Eigen::VectorXd coupling_wrench(const HandModel& model, const Eigen::VectorXd& x_t, const Eigen::VectorXd& v_t,
                                const std::vector<HandleState>& handles);

}  // namespace hapticd::hand
