#pragma once
// The core the hand, solvers and resolution suites share: the procedural hand
// pressed into a floor by its handle(s) (hand_models/press_scenario.hpp),
// stepped with one solver, timed per phase, optionally checked step by step
// against the monolithic solve and recording the force the handles feel.
#include <Eigen/Core>
#include <vector>

#include "hand_models/coupled_solver.hpp"
#include "hand_models/hand_model.hpp"

namespace hapticd::bench {

struct HandPressOptions {
  int tets = 1700;  // target tet count of the procedural hand
  int handles = 1;
  hand::HandConfig config;  // make_press_scenario fills the handles, density and floor
  hand::SolverKind solver = hand::SolverKind::schur_cholmod;
  hand::SolverOptions solver_options;
  int steps = 200;  // measured steps
  int warmup = 10;  // unmeasured steps first (not timed, not compared, no force recorded)
  // Compare with the monolithic solve every K measured steps (0: never; never for the monolithic solver).
  int error_every = 1;
  bool record_force = false;  // fill HandPressRun::f_H_N
  bool progress = true;       // a line on stderr every 50 steps
};

struct HandPressRun {
  int tets = 0, nodes = 0, handles = 0, coupled_nodes_first_handle = 0;
  double dt_s = 0;
  // Per measured step, ms.
  std::vector<double> total, assembly, factor, schur, solve, iterations;
  // Per compared step whose step succeeded: the solver's own error on that step's system (eq. 7),
  //   sqrt(|v_h - v_h,mono|^2 + |v_t - v_t,mono|^2) / sqrt(|v_h,mono|^2 + |v_t,mono|^2),
  // (v_h, v_t) the solver's solution (handle and node velocities at the end of the step), mono: the
  // monolithic sparse LU's solution of the same system. Each solver runs its own trajectory.
  std::vector<double> errors;
  // Per measured step (record_force): the coupling force the flesh puts on the handles at the end
  // of the step (seed 004 eq. 5, summed over handles), N: what the haptic side is rendered.
  std::vector<Eigen::Vector3d> f_H_N;
  int factorizations = 0;  // steps that factored (CG: never counted)
  int floor_contacts_max = 0;
  long resets = 0;  // failed or diverged steps, warm-up included
};

HandPressRun run_hand_press(const HandPressOptions& options);

}  // namespace hapticd::bench
