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
// The constraint rows of the coming step as solve_constraint_contacts builds them, for the haptic
// loop's contact model: the hand's constraint contacts in s.active_contacts, the valid supports of
// its implicit bodies, then its reserve contacts (rows the step may promote); at most `max_contacts`,
// in that order and the deepest first within each (a gap is a negative depth); when there are more,
// the supports keep up to a third of the rows and the reserves two.
struct ContactRows {
  Eigen::SparseMatrix<double> Jt;        // (handle + body + tool DOFs) x 3c, contact frames
  Eigen::VectorXd u_known;               // 3c: the kinematic other side's part of the relative velocity, m/s
  Eigen::VectorXd bias;                  // c: least normal velocity, m/s (ContactProblem::bias)
  std::vector<double> mu;                // c: friction coefficients
  Eigen::VectorXd warm;                  // 3c: the contacts' warm-start impulses in their frames, N s
  std::vector<Eigen::Matrix3d> frames;   // c: (n, t1, t2) in world axes
  int count() const { return static_cast<int>(mu.size()); }
};
void contact_rows(const HandModel& model, const HandState& s, int max_contacts, ContactRows& out);

bool solve_constraint_contacts(const HandModel& model, HandState& s, CoupledSolver& solver,
                               std::vector<Eigen::Vector3d>& impulses);

}  // namespace hapticd::hand
