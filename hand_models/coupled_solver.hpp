#pragma once
// Three interchangeable solvers for the coupled step (seed 004 eq. 7):
//  - monolithic: one sparse LU of the whole system, the reference;
//  - schur_cg: the paper's Schur complement of A_t (eq. 12-13) with 6m + 2
//    Jacobi-preconditioned CG solves, warm-started from the previous step;
//  - schur_cholmod: the same Schur complement with one CHOLMOD factorization of
//    A_t per step (symbolic analysis once per pattern) and all right-hand sides
//    solved as one block;
//  - schur_lagged: GMRES on eq. 7 preconditioned by the exact Schur solve of an
//    earlier step (factorization reused across steps, refactored when the
//    iterations' estimated cost, counted not timed, grows), converged to a residual tolerance.
//    Its decisions use counts only, never a clock: the same steps give the same
//    result, bit for bit, on any machine under any load.
#include <Eigen/Core>
#include <memory>
#include <string>

#include "hand_models/coupled_system.hpp"

namespace hapticd::hand {

enum class SolverKind { monolithic, schur_cg, schur_cholmod, schur_lagged };
// Fill-reducing ordering for CHOLMOD; `automatic` lets CHOLMOD try AMD and METIS and keep the best.
enum class Ordering { automatic, amd, metis, nesdis, natural };

struct SolverOptions {
  double cg_tolerance = 1e-10;  // relative residual of each CG solve
  int cg_max_iterations = 0;    // 0: 3n (CG's exact-arithmetic bound)
  Ordering ordering = Ordering::automatic;
  bool supernodal = true;       // CHOLMOD supernodal (BLAS-3) or simplicial factorization
  double lagged_tolerance = 1e-12;      // relative residual of eq. 7 for schur_lagged
  int lagged_max_iterations = 30;       // beyond this, refactor and solve exactly
  int lagged_refactor_iterations = 20;  // a solve needing more always refactors on the next step
};

// Times are measurements for the stats only: no solver decision reads them.
struct SolveReport {
  double factor_ms = 0;    // numeric factorization (or preconditioner set-up)
  double schur_ms = 0;     // A_t solves for the Schur complement and its right-hand side
  double solve_ms = 0;     // handle solve and tool back-substitution
  long iterations = 0;     // CG or GMRES iterations summed over all solves
  int factorizations = 0;  // numeric factorizations this solve made (sparse LU or CHOLMOD)
  // schur_lagged: the solve's cost as its refactoring rule counts it, in flops of sparse
  // products and triangular solves estimated from counts (nnz(L) of CHOLMOD's analysis, the
  // nonzeros of eq. 7, iterations; the factorization itself as a fixed number of solve pairs);
  // a step that factors counts the factorization, its Schur set-up and any GMRES it gave up.
  // 0 for the other solvers.
  double work_flops = 0;
};

class CoupledSolver {
 public:
  virtual ~CoupledSolver() = default;
  virtual SolverKind kind() const = 0;
  // Solves eq. 7; false (outputs unspecified) when the system is not solvable
  // as assumed (A_t not SPD, singular Schur complement, CG not converged).
  virtual bool solve(const CoupledSystem& system, Eigen::VectorXd& v_h, Eigen::VectorXd& v_t,
                     SolveReport& report) = 0;
  // X = A_t^-1 B (the handle-space linearization needs it): CG to a relative
  // residual of 1e-10 per column, preconditioned by the solver's factorization
  // where it has one (one iteration when it is this system's), else by Jacobi.
  virtual bool solve_tool(const CoupledSystem& system, const Eigen::MatrixXd& B, Eigen::MatrixXd& X);
  // X = A^-1 R for the whole eq. 7 matrix (rows: handle DOFs, then tool DOFs):
  // directly with the solver's factorization when it is this system's, else by
  // a sparse LU of the whole system.
  virtual bool solve_block(const CoupledSystem& system, const Eigen::MatrixXd& R, Eigen::MatrixXd& X);
  // solve_block in the Schur complement's own form, X = [X_h; X_t - Y X_h] with Y the handle
  // columns (1 ... nh) of *Y_tool = tool_solution(system): what X is needed for (J X, X lambda)
  // then takes no nt x nh x cols product. Y_tool null (no such solution kept): X_t is X's tool part.
  virtual bool solve_block_parts(const CoupledSystem& system, const Eigen::MatrixXd& R, Eigen::MatrixXd& X_h,
                                 Eigen::MatrixXd& X_t, const Eigen::MatrixXd*& Y_tool);
  // A_t^-1 [b_t, A_th] (the Schur complement's tool solves) when the solver
  // keeps them and `system` is the one it last solved, else null.
  virtual const Eigen::MatrixXd* tool_solution(const CoupledSystem& /*system*/) const { return nullptr; }
};

// The whole eq. 7 matrix [A_h A_ht; A_th A_t] as one sparse matrix.
Eigen::SparseMatrix<double> full_matrix(const CoupledSystem& system);

std::unique_ptr<CoupledSolver> make_solver(SolverKind kind, const SolverOptions& options = {});

// Debian's CHOLMOD opens OpenMP regions with a compiled-in thread count; the
// visual loop owns one core (the haptic loop needs the other), so no region
// may fork. libgomp keeps this per thread: a thread that steps a world calls it.
void single_threaded_cholmod();

// "monolithic" | "cg" | "cholmod" | "lagged"; throws std::invalid_argument otherwise.
SolverKind parse_solver_kind(const std::string& name);
const char* to_string(SolverKind kind);
// "auto" | "amd" | "metis" | "nesdis" | "natural"; throws std::invalid_argument otherwise.
Ordering parse_ordering(const std::string& name);
const char* to_string(Ordering ordering);

}  // namespace hapticd::hand
