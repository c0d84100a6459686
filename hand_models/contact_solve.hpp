#pragma once
// Internal to hand_models (hand_model.cpp's step): the constraint-contact solve of one implicit hand
// step (DESIGN.md section 3: non-penetration and the Coulomb cone by projected Gauss-Seidel on the
// Delassus operator of the step's system).
#include <vector>

#include "hand_models/coupled_solver.hpp"
#include "hand_models/hand_model.hpp"

namespace hapticd::hand {

// Constraint contacts on the solved free velocities: J (contact frames of the relative velocity,
// sparse), A^-1 J^T by one block solve through the step's factorization, W = J A^-1 J^T, projected
// Gauss-Seidel warm-started from each contact's guess, V = V_free + A^-1 J^T lambda. The rows are the
// hand's constraint contacts and the implicit bodies' supports; reserve contacts the solution would
// carry deeper than kReserveDepth_m join as further rows for a few rounds. Hand impulses go to
// `impulses` (world frame, per active contact); the pushing rows become s.held for the
// linearization. False when the solve fails.
bool solve_constraint_contacts(const HandModel& model, HandState& s, CoupledSolver& solver,
                               std::vector<Eigen::Vector3d>& impulses);

}  // namespace hapticd::hand
