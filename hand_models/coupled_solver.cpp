#include "hand_models/coupled_solver.hpp"

#include <Eigen/CholmodSupport>
#include <Eigen/Dense>
#include <Eigen/IterativeLinearSolvers>
#include <Eigen/SparseLU>
#include <array>
#include <chrono>
#include <stdexcept>
#include <vector>

// libgomp (CHOLMOD's OpenMP runtime); declared here so the project itself builds without -fopenmp.
extern "C" void omp_set_max_active_levels(int levels);
extern "C" void omp_set_num_threads(int threads);

namespace hapticd::hand {
namespace {

using Clock = std::chrono::steady_clock;
double ms_since(Clock::time_point t0) {
  return std::chrono::duration<double, std::milli>(Clock::now() - t0).count();
}

// Handle solve of eq. 13 given S = A_h - A_ht Y (Y = A_t^-1 A_th), its LU, and y0 = A_t^-1 b_t:
// r = b_h - A_ht y0 (S is small and, with the rotational terms, not symmetric: LU with partial
// pivoting; a singular S shows as an inaccurate solution, checked against S).
bool solve_schur(const CoupledSystem& s, const Eigen::MatrixXd& S, const Eigen::PartialPivLU<Eigen::MatrixXd>& lu,
                 const Eigen::VectorXd& y0, Eigen::VectorXd& v_h) {
  // A free body (no handles, no bodies in contact): eq. 7 is A_t v_t = b_t alone.
  if (s.handle_dofs() == 0) {
    v_h.resize(0);
    return true;
  }
  const Eigen::VectorXd r = s.b_h - s.A_ht * y0;
  v_h = lu.solve(r);
  return v_h.allFinite() && (S * v_h - r).norm() <= 1e-8 * (r.norm() + S.norm() * v_h.norm());
}

// The same, forming S and its LU from Y.
bool solve_handles(const CoupledSystem& s, const Eigen::MatrixXd& Y, const Eigen::VectorXd& y0, Eigen::VectorXd& v_h) {
  const Eigen::MatrixXd S = s.A_h - s.A_ht * Y;
  return solve_schur(s, S, S.partialPivLu(), y0, v_h);
}

}  // namespace

void single_threaded_cholmod() {
  // Per thread in libgomp: every thread that factors must say it.
  omp_set_max_active_levels(0);
  omp_set_num_threads(1);
}

namespace {

void configure_cholmod(Eigen::CholmodDecomposition<Eigen::SparseMatrix<double>, Eigen::Lower>& chol,
                       const SolverOptions& o) {
  single_threaded_cholmod();
  chol.setMode(o.supernodal ? Eigen::CholmodSupernodalLLt : Eigen::CholmodSimplicialLLt);
  cholmod_common& c = chol.cholmod();
  const int ordering[] = {0, CHOLMOD_AMD, CHOLMOD_METIS, CHOLMOD_NESDIS, CHOLMOD_NATURAL};
  if (o.ordering != Ordering::automatic) {
    c.nmethods = 1;
    c.method[0].ordering = ordering[static_cast<int>(o.ordering)];
  }
}

// The exact Schur machinery of one system (eq. 12-13 with a CHOLMOD factor of A_t):
// factor A_t, Y = A_t^-1 [b_t, A_th] as one block solve, S = A_h - A_ht Y.
class CholmodSchur {
 public:
  explicit CholmodSchur(const SolverOptions& o) { configure_cholmod(chol_, o); }

  // `reuse`: keep the current factor when A_t is the one it factors (the same
  // state assembled again, e.g. the step after the visual loop's model of it).
  bool factor(const CoupledSystem& s, SolveReport& report, bool reuse = false) {
    const auto t0 = Clock::now();
    const int nh = s.handle_dofs(), nt = s.tool_dofs();
    if (!reuse || !factors(s.A_t)) {
      // Symbolic analysis once per pattern (the pattern is fixed per mesh).
      if (analyzed_nnz_ != s.A_t.nonZeros() || analyzed_rows_ != nt) {
        chol_.analyzePattern(s.A_t);
        analyzed_nnz_ = s.A_t.nonZeros();
        analyzed_rows_ = nt;
        // The analysis's count for the ordering it kept (the same on any machine).
        factor_nnz_ = chol_.cholmod().lnz;
      }
      chol_.factorize(s.A_t);
      report.factor_ms += ms_since(t0);
      ++report.factorizations;
      fingerprint_ = fingerprint(s.A_t);
    }
    if (chol_.info() != Eigen::Success) return false;
    // The same state assembled again (the server's step after the model of it)
    // has the same couplings and tool RHS too: Y, S and its LU stand.
    if (reuse && schur_fingerprint(s) == schur_fingerprint_ && s.A_h == A_h_) return Y_.allFinite();
    const auto t1 = Clock::now();
    rhs_.resize(nt, nh + 1);
    rhs_.col(0) = s.b_t;
    rhs_.rightCols(nh) = s.A_th;
    Y_ = chol_.solve(rhs_);
    schur_fingerprint_ = schur_fingerprint(s);
    A_h_ = s.A_h;
    A_ht_ = s.A_ht;
    S_ = s.A_h - A_ht_ * Y_.rightCols(nh);
    if (nh > 0) lu_.compute(S_);
    report.schur_ms += ms_since(t1);
    return Y_.allFinite();
  }

  // Solution of the factored system itself; eq. 12 needs no further A_t solve:
  // A_t^-1 (b_t - A_th v_h) = y0 - Y v_h.
  bool solve_factored(const CoupledSystem& s, Eigen::VectorXd& v_h, Eigen::VectorXd& v_t) const {
    const int nh = s.handle_dofs();
    if (!solve_schur(s, S_, lu_, Y_.col(0), v_h)) return false;  // factor() formed S and its LU
    v_t = Y_.col(0) - Y_.rightCols(nh) * v_h;
    return v_t.allFinite();
  }

  Eigen::MatrixXd solve_tool(const Eigen::MatrixXd& B) const { return chol_.solve(B); }

  // nnz(L) for the analysed pattern (cholmod_common::lnz).
  double factor_nnz() const { return factor_nnz_; }

  // Whether the current factorization is of exactly this A_t (same pattern and values).
  bool factors(const Eigen::SparseMatrix<double>& A) const { return fingerprint(A) == fingerprint_; }

  // A_t^-1 [b_t, A_th] of the last factored system when `s` is that system, else null.
  const Eigen::MatrixXd* tool_solution(const CoupledSystem& s) const {
    if (!factors(s.A_t)) return nullptr;
    return schur_fingerprint(s) == schur_fingerprint_ && Y_.cols() == s.handle_dofs() + 1 ? &Y_ : nullptr;
  }

  // A_t^-1 B: directly when the factorization is this A_t's, else CG preconditioned by it.
  bool solve_tool(const Eigen::SparseMatrix<double>& A, const Eigen::MatrixXd& B, Eigen::MatrixXd& X) const;

  // z = P^-1 r with P the factored system: one A_t solve and the small Schur solve.
  template <class In, class Out>
  void apply(const In& r, Out& z) const {
    const Eigen::Index nh = S_.rows(), n = r.rows();
    Eigen::MatrixXd z_h, y;
    apply_parts(r, z_h, y);
    if (nh == 0) {
      z = y;
      return;
    }
    z.resize(n, r.cols());
    z.topRows(nh) = z_h;
    z.bottomRows(n - nh) = y - Y_.rightCols(nh) * z_h;
  }

  // apply() without its last product: z = [z_h; y - Y z_h], Y = A_t^-1 A_th.
  template <class In>
  void apply_parts(const In& r, Eigen::MatrixXd& z_h, Eigen::MatrixXd& y) const {
    const Eigen::Index nh = S_.rows(), n = r.rows();
    y = chol_.solve(Eigen::MatrixXd(r.bottomRows(n - nh)));
    z_h = nh == 0 ? Eigen::MatrixXd(0, r.cols()) : Eigen::MatrixXd(lu_.solve(Eigen::MatrixXd(r.topRows(nh) - A_ht_ * y)));
  }

 private:
  // Two weighted sums of the values and the size: equal for the same matrix.
  template <class Values>
  static std::array<double, 3> fingerprint_of(const Values* values, Eigen::Index size) {
    std::array<double, 3> f{0, 0, static_cast<double>(size)};
    for (Eigen::Index k = 0; k < size; ++k) {
      f[0] += values[k];
      f[1] += values[k] * static_cast<double>(k + 1);
    }
    return f;
  }
  static std::array<double, 3> fingerprint(const Eigen::SparseMatrix<double>& A) {
    return fingerprint_of(A.valuePtr(), A.nonZeros());
  }
  // Of what Y and S are made of besides A_t and A_h: A_th, A_ht and b_t.
  static std::array<double, 9> schur_fingerprint(const CoupledSystem& s) {
    const std::array<double, 3> th = fingerprint(s.A_th), ht = fingerprint_of(s.A_ht.valuePtr(), s.A_ht.nonZeros()),
                                b = fingerprint_of(s.b_t.data(), s.b_t.size());
    return {th[0], th[1], th[2], ht[0], ht[1], ht[2], b[0], b[1], b[2]};
  }

  std::array<double, 3> fingerprint_{0, 0, -1};
  std::array<double, 9> schur_fingerprint_{0, 0, -1, 0, 0, -1, 0, 0, -1};  // of the system Y_ and S_ belong to
  Eigen::MatrixXd A_h_;
  Eigen::CholmodDecomposition<Eigen::SparseMatrix<double>, Eigen::Lower> chol_;
  long analyzed_nnz_ = -1;
  long analyzed_rows_ = -1;
  double factor_nnz_ = 0;
  Eigen::MatrixXd rhs_, Y_, S_;
  Eigen::SparseMatrix<double, Eigen::RowMajor> A_ht_;
  Eigen::PartialPivLU<Eigen::MatrixXd> lu_;
};

// y = A v for the whole eq. 7 matrix, v = (v_h, v_t).
void multiply(const CoupledSystem& s, const Eigen::VectorXd& v, Eigen::VectorXd& y) {
  const int nh = s.handle_dofs(), nt = s.tool_dofs();
  y.resize(nh + nt);
  y.head(nh).noalias() = s.A_h * v.head(nh);
  y.head(nh).noalias() += s.A_ht * v.tail(nt);
  y.tail(nt).noalias() = s.A_t * v.tail(nt);
  y.tail(nt).noalias() += s.A_th * v.head(nh);
}

// Preconditioned CG on A_t for all columns of B at once (each column its own
// CG; the preconditioner and the product run on the whole block, so a
// factorization's triangular solves are block solves). `precondition` maps a
// block R to P^-1 R.
template <class Precondition>
bool pcg_columns(const Eigen::SparseMatrix<double>& A, const Eigen::MatrixXd& B, Eigen::MatrixXd& X,
                 Precondition precondition) {
  constexpr double kTolerance = 1e-10;  // ample for a force model; 1e-13 can sit below rounding
  const Eigen::Index n = B.rows(), c = B.cols();
  const Eigen::RowVectorXd b_norm = B.colwise().norm();
  X = Eigen::MatrixXd::Zero(n, c);
  Eigen::MatrixXd R = B, Z = precondition(R), P = Z, AP(n, c);
  Eigen::RowVectorXd rz = (R.cwiseProduct(Z)).colwise().sum();
  for (int it = 0; it < 4 * n; ++it) {
    const Eigen::RowVectorXd r_norm = R.colwise().norm();
    if (((r_norm.array() <= kTolerance * b_norm.array()) || (b_norm.array() == 0)).all()) return X.allFinite();
    AP.noalias() = A * P;
    const Eigen::RowVectorXd pAp = (P.cwiseProduct(AP)).colwise().sum();
    for (Eigen::Index j = 0; j < c; ++j) {
      if (r_norm[j] <= kTolerance * b_norm[j] || pAp[j] == 0) continue;  // this column has converged
      const double alpha = rz[j] / pAp[j];
      X.col(j) += alpha * P.col(j);
      R.col(j) -= alpha * AP.col(j);
    }
    Z = precondition(R);
    const Eigen::RowVectorXd rz_next = (R.cwiseProduct(Z)).colwise().sum();
    for (Eigen::Index j = 0; j < c; ++j) P.col(j) = Z.col(j) + (rz[j] != 0 ? rz_next[j] / rz[j] : 0.0) * P.col(j);
    rz = rz_next;
  }
  return false;
}

bool CholmodSchur::solve_tool(const Eigen::SparseMatrix<double>& A, const Eigen::MatrixXd& B,
                              Eigen::MatrixXd& X) const {
  if (factors(A)) {
    X = chol_.solve(B);
    return X.allFinite();
  }
  return pcg_columns(A, B, X, [&](const Eigen::MatrixXd& r) -> Eigen::MatrixXd { return chol_.solve(r); });
}

class MonolithicSolver final : public CoupledSolver {
 public:
  SolverKind kind() const override { return SolverKind::monolithic; }
  bool solve(const CoupledSystem& s, Eigen::VectorXd& v_h, Eigen::VectorXd& v_t, SolveReport& report) override {
    const auto t0 = Clock::now();
    const int nh = s.handle_dofs(), nt = s.tool_dofs();
    const Eigen::SparseMatrix<double> A = full_matrix(s);
    lu_.compute(A);
    report.factor_ms = ms_since(t0);
    report.factorizations = 1;
    if (lu_.info() != Eigen::Success) return false;
    const auto t1 = Clock::now();
    Eigen::VectorXd b(nh + nt);
    b << s.b_h, s.b_t;
    const Eigen::VectorXd v = lu_.solve(b);
    v_h = v.head(nh);
    v_t = v.tail(nt);
    report.solve_ms = ms_since(t1);
    return v.allFinite();
  }

 private:
  Eigen::SparseLU<Eigen::SparseMatrix<double>, Eigen::COLAMDOrdering<int>> lu_;
};

class SchurCgSolver final : public CoupledSolver {
 public:
  explicit SchurCgSolver(const SolverOptions& o) : options_(o) {}
  SolverKind kind() const override { return SolverKind::schur_cg; }

  bool solve(const CoupledSystem& s, Eigen::VectorXd& v_h, Eigen::VectorXd& v_t, SolveReport& report) override {
    const auto t0 = Clock::now();
    const int nh = s.handle_dofs(), nt = s.tool_dofs();
    cg_.setTolerance(options_.cg_tolerance);
    cg_.setMaxIterations(options_.cg_max_iterations > 0 ? options_.cg_max_iterations : 3 * nt);
    cg_.compute(s.A_t);
    if (guess_.rows() != nt || guess_.cols() != nh + 2) guess_ = Eigen::MatrixXd::Zero(nt, nh + 2);
    report.factor_ms = ms_since(t0);
    bool ok = true;
    // Each A_t solve, warm-started from the same solve of the previous step.
    auto solve_column = [&](const Eigen::VectorXd& rhs, int slot) {
      guess_.col(slot) = cg_.solveWithGuess(rhs, guess_.col(slot));
      report.iterations += cg_.iterations();
      ok = ok && cg_.info() == Eigen::Success;
      return guess_.col(slot);
    };
    // seed 004 section 6 pseudocode: 1 + 6m solves to form eq. 13, then one for eq. 12.
    const auto t1 = Clock::now();
    const Eigen::VectorXd y0 = solve_column(s.b_t, 0);
    const Eigen::MatrixXd A_th = s.A_th;
    Eigen::MatrixXd Y(nt, nh);
    for (int c = 0; c < nh; ++c) Y.col(c) = solve_column(A_th.col(c), 1 + c);
    report.schur_ms = ms_since(t1);
    const auto t2 = Clock::now();
    ok = ok && solve_handles(s, Y, y0, v_h);
    if (ok) v_t = solve_column(s.b_t - s.A_th * v_h, nh + 1);
    report.solve_ms = ms_since(t2);
    return ok && v_t.allFinite();
  }

 private:
  SolverOptions options_;
  Eigen::ConjugateGradient<Eigen::SparseMatrix<double>, Eigen::Lower | Eigen::Upper,
                           Eigen::DiagonalPreconditioner<double>>
      cg_;
  Eigen::MatrixXd guess_;
};

class SchurCholmodSolver final : public CoupledSolver {
 public:
  explicit SchurCholmodSolver(const SolverOptions& o) : schur_(o) {}
  SolverKind kind() const override { return SolverKind::schur_cholmod; }

  bool solve_block(const CoupledSystem& s, const Eigen::MatrixXd& R, Eigen::MatrixXd& X) override {
    if (!factored_ || !schur_.factors(s.A_t)) return CoupledSolver::solve_block(s, R, X);
    schur_.apply(R, X);
    return X.allFinite();
  }

  bool solve_block_parts(const CoupledSystem& s, const Eigen::MatrixXd& R, Eigen::MatrixXd& X_h, Eigen::MatrixXd& X_t,
                         const Eigen::MatrixXd*& Y_tool) override {
    Y_tool = factored_ ? schur_.tool_solution(s) : nullptr;
    if (Y_tool == nullptr) return CoupledSolver::solve_block_parts(s, R, X_h, X_t, Y_tool);
    schur_.apply_parts(R, X_h, X_t);
    return X_h.allFinite() && X_t.allFinite();
  }

  // Its factorization preconditions CG on the given A_t: one iteration when it
  // is that system's, a few when the system has moved on.
  bool solve_tool(const CoupledSystem& s, const Eigen::MatrixXd& B, Eigen::MatrixXd& X) override {
    if (!factored_) return CoupledSolver::solve_tool(s, B, X);
    return schur_.solve_tool(s.A_t, B, X);
  }

  const Eigen::MatrixXd* tool_solution(const CoupledSystem& s) const override {
    return factored_ ? schur_.tool_solution(s) : nullptr;
  }

  bool solve(const CoupledSystem& s, Eigen::VectorXd& v_h, Eigen::VectorXd& v_t, SolveReport& report) override {
    factored_ = schur_.factor(s, report, factored_);
    if (!factored_) return false;
    const auto t0 = Clock::now();
    const bool ok = schur_.solve_factored(s, v_h, v_t);
    report.solve_ms = ms_since(t0);
    return ok;
  }

 private:
  CholmodSchur schur_;
  bool factored_ = false;
};

// The lagged solver's costs, estimated from counts only: nnz(L) for A_t's pattern, the nonzeros
// of eq. 7's blocks and its handle DOFs, in flops of sparse products and triangular solves. Every
// number is the same on any machine under any load, so the refactoring schedule (and with it the
// result, bit for bit) is too. A triangular solve pair with L and L^T is a multiply-add per entry
// of each: 4 nnz(L) flops per column.
//
// A numeric factorization counts as kFactorSolvePairs solve pairs, not as its flops
// (cholmod_common::fl): a supernodal factorization's dense kernels run its flops faster than a
// solve runs its own, the more so the larger the supernodes. On the bench's pressed hands of 350
// to 12,000 tets fl / (4 nnz(L)) grew from 11 to 74 while a numeric factorization took 14 to 25
// solve pairs' time; with 14, a factor step's counted work and a GMRES step's ran at the same
// rate within 10 % from 350 to 5,000 tets (AMD EPYC, OpenBLAS serial), where counting fl made a
// factor step look 2.4x (5,000 tets) to 4x (12,000) dearer than it was. The constant sets only
// how often the solver refactors, never what it converges to.
constexpr double kFactorSolvePairs = 14;

struct LaggedWork {
  double factor = 0;    // a step that factors: A_t = L L^T, the Schur set-up and the exact solve
  double apply = 0;     // P^-1 r: one A_t solve pair and the handle solve
  double multiply = 0;  // A v with the whole eq. 7 matrix
  double n = 0;         // rows of eq. 7

  static LaggedWork of(const CoupledSystem& s, double factor_nnz) {
    const double nh = s.handle_dofs(), nt = s.tool_dofs(), solve_pair = 4 * factor_nnz;
    const double ht = static_cast<double>(s.A_ht.nonZeros()), th = static_cast<double>(s.A_th.nonZeros());
    // seed 004 eq. 13 then eq. 12: r_h - A_ht y, the LU solve with S, y - Y z_h.
    const double handle_solve = 2 * ht + 2 * nh * nh + 2 * nt * nh;
    LaggedWork w;
    w.n = nh + nt;
    w.multiply = 2 * (static_cast<double>(s.A_t.nonZeros()) + th + ht + nh * nh);
    w.apply = solve_pair + handle_solve;
    // seed 004 eq. 13: Y = A_t^-1 [b_t, A_th] (nh + 1 solve pairs), S = A_h - A_ht Y, S's LU.
    w.factor = (kFactorSolvePairs + nh + 1) * solve_pair + 2 * ht * nh + 2.0 / 3.0 * nh * nh * nh + handle_solve;
    return w;
  }
  // GMRES's start: the previous solution corrected by one application, two products.
  double start() const { return apply + 2 * multiply; }
  // Iteration k (from 0): an application, a product, Gram-Schmidt twice against k + 1 vectors.
  double iteration(int k) const { return apply + multiply + 8 * n * (k + 1); }
  // Closing after k iterations: x += Z y and the product for the true residual.
  double finish(int k) const { return 2 * n * k + multiply; }
};

// GMRES on the whole of eq. 7, right-preconditioned by the exact Schur solve of
// an earlier step's system (its CHOLMOD factor, Y and S kept). Element rotations
// and contacts change little between visual steps, so a handful of iterations
// (one A_t triangular solve each) replace a factorization. When to refactor is
// decided on LaggedWork's counts, never on measured times: the same sequence of
// systems gives the same schedule and the same solutions, bit for bit.
class SchurLaggedSolver final : public CoupledSolver {
 public:
  explicit SchurLaggedSolver(const SolverOptions& o) : options_(o), schur_(o) {}
  SolverKind kind() const override { return SolverKind::schur_lagged; }

  // The factorization (current or lagged) preconditions CG on the current A_t.
  bool solve_tool(const CoupledSystem& s, const Eigen::MatrixXd& B, Eigen::MatrixXd& X) override {
    if (factored_size_ < 0) return CoupledSolver::solve_tool(s, B, X);
    return schur_.solve_tool(s.A_t, B, X);
  }

  bool solve(const CoupledSystem& s, Eigen::VectorXd& v_h, Eigen::VectorXd& v_t, SolveReport& report) override {
    const int nh = s.handle_dofs(), nt = s.tool_dofs();
    if (refactor_ || factored_size_ != nh + nt) return factor_and_solve(s, v_h, v_t, report);
    const auto t0 = Clock::now();
    Eigen::VectorXd b(nh + nt), v;
    b << s.b_h, s.b_t;
    int iterations = 0;
    double work = 0;
    const bool converged = gmres(s, b, v, iterations, work);
    report.iterations += iterations;
    report.work_flops += work;
    report.solve_ms = ms_since(t0);
    // Not converged within the budget: factor this system and solve it exactly.
    if (!converged) return factor_and_solve(s, v_h, v_t, report);
    // Refactor once this step's solve costs more than the mean step since the last
    // factorization, factorization included: with costs that grow as the factor ages,
    // that is when the mean cost per step stops falling.
    ++steps_since_factor_;
    work_since_factor_ += work;
    refactor_ = work > work_since_factor_ / steps_since_factor_ || iterations > options_.lagged_refactor_iterations;
    v_h = v.head(nh);
    v_t = v.tail(nt);
    previous_ = v;
    return v.allFinite();
  }

 private:
  bool factor_and_solve(const CoupledSystem& s, Eigen::VectorXd& v_h, Eigen::VectorXd& v_t, SolveReport& report) {
    const int nh = s.handle_dofs(), nt = s.tool_dofs();
    refactor_ = false;
    factored_size_ = -1;
    if (!schur_.factor(s, report)) return false;
    factored_size_ = nh + nt;
    work_ = LaggedWork::of(s, schur_.factor_nnz());
    const auto t0 = Clock::now();
    const bool ok = schur_.solve_factored(s, v_h, v_t);
    report.solve_ms += ms_since(t0);
    // The cycle's cost starts with this step's, a GMRES it gave up included.
    report.work_flops += work_.factor;
    steps_since_factor_ = 1;
    work_since_factor_ = report.work_flops;
    if (ok) previous_ = (Eigen::VectorXd(nh + nt) << v_h, v_t).finished();
    return ok;
  }

  // Right-preconditioned GMRES (no restarts: the Krylov space stays small). True
  // when the relative residual reached the tolerance; `iterations` and `work` (in
  // LaggedWork's count) are what it spent. It gives up after lagged_max_iterations or
  // once it has spent a factor step's work (then refactoring is cheaper).
  bool gmres(const CoupledSystem& s, const Eigen::VectorXd& b, Eigen::VectorXd& x, int& iterations, double& work) {
    const int max_it = options_.lagged_max_iterations, n = static_cast<int>(b.size());
    const double b_norm = b.norm();
    iterations = 0;
    work = work_.start();
    // Start from the previous step's velocities corrected by one preconditioner application.
    Eigen::VectorXd Ax, r, z, w;
    x = previous_;
    multiply(s, x, Ax);
    schur_.apply(b - Ax, z);
    x += z;
    multiply(s, x, Ax);
    r = b - Ax;
    double beta = r.norm();
    if (b_norm == 0 || beta <= options_.lagged_tolerance * b_norm) return true;
    V_.resize(n, max_it + 1);
    Z_.resize(n, max_it);
    H_.setZero(max_it + 1, max_it);
    Eigen::VectorXd g = Eigen::VectorXd::Zero(max_it + 1), cs(max_it), sn(max_it);
    V_.col(0) = r / beta;
    g[0] = beta;
    for (int k = 0; k < max_it; ++k) {
      schur_.apply(V_.col(k), z);
      Z_.col(k) = z;
      multiply(s, z, w);
      // Modified Gram-Schmidt, twice for orthogonality at tight tolerances.
      for (int pass = 0; pass < 2; ++pass)
        for (int i = 0; i <= k; ++i) {
          const double hik = V_.col(i).dot(w);
          H_(i, k) += hik;
          w -= hik * V_.col(i);
        }
      const double h_next = w.norm();  // 0: the Krylov space holds the exact solution
      H_(k + 1, k) = h_next;
      if (h_next > 0) V_.col(k + 1) = w / h_next;
      for (int i = 0; i < k; ++i) {  // apply earlier Givens rotations
        const double t = cs[i] * H_(i, k) + sn[i] * H_(i + 1, k);
        H_(i + 1, k) = -sn[i] * H_(i, k) + cs[i] * H_(i + 1, k);
        H_(i, k) = t;
      }
      const double d = std::hypot(H_(k, k), H_(k + 1, k));
      cs[k] = H_(k, k) / d;
      sn[k] = H_(k + 1, k) / d;
      H_(k, k) = d;
      H_(k + 1, k) = 0;
      g[k + 1] = -sn[k] * g[k];
      g[k] = cs[k] * g[k];
      work += work_.iteration(k);
      const bool over_budget = work > work_.factor;
      if (std::abs(g[k + 1]) <= options_.lagged_tolerance * b_norm || h_next == 0 || k + 1 == max_it ||
          over_budget) {
        const Eigen::VectorXd y =
            H_.topLeftCorner(k + 1, k + 1).triangularView<Eigen::Upper>().solve(g.head(k + 1));
        x += Z_.leftCols(k + 1) * y;
        multiply(s, x, Ax);
        iterations = k + 1;
        work += work_.finish(k + 1);
        return (b - Ax).norm() <= options_.lagged_tolerance * b_norm;
      }
    }
    return false;
  }

  SolverOptions options_;
  CholmodSchur schur_;
  LaggedWork work_;  // of the system last factored
  bool refactor_ = true;
  int factored_size_ = -1;
  int steps_since_factor_ = 0;
  double work_since_factor_ = 0;  // LaggedWork of the steps since the last factorization, it included
  Eigen::VectorXd previous_;
  Eigen::MatrixXd V_, Z_, H_;
};

}  // namespace

Eigen::SparseMatrix<double> full_matrix(const CoupledSystem& s) {
  const int nh = s.handle_dofs(), nt = s.tool_dofs();
  std::vector<Eigen::Triplet<double>> entries;
  entries.reserve(s.A_t.nonZeros() + 2 * s.A_th.nonZeros() + nh * nh);
  for (int r = 0; r < nh; ++r)
    for (int c = 0; c < nh; ++c) entries.emplace_back(r, c, s.A_h(r, c));
  for (int k = 0; k < s.A_ht.outerSize(); ++k)
    for (Eigen::SparseMatrix<double, Eigen::RowMajor>::InnerIterator it(s.A_ht, k); it; ++it)
      entries.emplace_back(it.row(), nh + it.col(), it.value());
  for (int k = 0; k < s.A_th.outerSize(); ++k)
    for (Eigen::SparseMatrix<double>::InnerIterator it(s.A_th, k); it; ++it)
      entries.emplace_back(nh + it.row(), it.col(), it.value());
  for (int k = 0; k < s.A_t.outerSize(); ++k)
    for (Eigen::SparseMatrix<double>::InnerIterator it(s.A_t, k); it; ++it)
      entries.emplace_back(nh + it.row(), nh + it.col(), it.value());
  Eigen::SparseMatrix<double> A(nh + nt, nh + nt);
  A.setFromTriplets(entries.begin(), entries.end());
  A.makeCompressed();
  return A;
}

bool CoupledSolver::solve_block(const CoupledSystem& s, const Eigen::MatrixXd& R, Eigen::MatrixXd& X) {
  Eigen::SparseLU<Eigen::SparseMatrix<double>, Eigen::COLAMDOrdering<int>> lu(full_matrix(s));
  if (lu.info() != Eigen::Success) return false;
  X = lu.solve(R);
  return X.allFinite();
}

bool CoupledSolver::solve_block_parts(const CoupledSystem& s, const Eigen::MatrixXd& R, Eigen::MatrixXd& X_h,
                                      Eigen::MatrixXd& X_t, const Eigen::MatrixXd*& Y_tool) {
  Y_tool = nullptr;
  Eigen::MatrixXd X;
  if (!solve_block(s, R, X)) return false;
  X_h = X.topRows(s.handle_dofs());
  X_t = X.bottomRows(s.tool_dofs());
  return true;
}

bool CoupledSolver::solve_tool(const CoupledSystem& s, const Eigen::MatrixXd& B, Eigen::MatrixXd& X) {
  const Eigen::VectorXd inv_diag = s.A_t.diagonal().cwiseInverse();
  return pcg_columns(s.A_t, B, X,
                     [&](const Eigen::MatrixXd& r) -> Eigen::MatrixXd { return inv_diag.asDiagonal() * r; });
}

std::unique_ptr<CoupledSolver> make_solver(SolverKind kind, const SolverOptions& options) {
  switch (kind) {
    case SolverKind::monolithic:
      return std::make_unique<MonolithicSolver>();
    case SolverKind::schur_cg:
      return std::make_unique<SchurCgSolver>(options);
    case SolverKind::schur_cholmod:
      return std::make_unique<SchurCholmodSolver>(options);
    case SolverKind::schur_lagged:
      return std::make_unique<SchurLaggedSolver>(options);
  }
  throw std::invalid_argument("unknown solver kind");
}

SolverKind parse_solver_kind(const std::string& name) {
  if (name == "monolithic") return SolverKind::monolithic;
  if (name == "cg") return SolverKind::schur_cg;
  if (name == "cholmod") return SolverKind::schur_cholmod;
  if (name == "lagged") return SolverKind::schur_lagged;
  throw std::invalid_argument("unknown solver '" + name + "' (expected monolithic, cg, cholmod or lagged)");
}

const char* to_string(SolverKind kind) {
  switch (kind) {
    case SolverKind::monolithic:
      return "monolithic";
    case SolverKind::schur_cg:
      return "cg";
    case SolverKind::schur_cholmod:
      return "cholmod";
    case SolverKind::schur_lagged:
      return "lagged";
  }
  return "?";
}

Ordering parse_ordering(const std::string& name) {
  if (name == "auto") return Ordering::automatic;
  if (name == "amd") return Ordering::amd;
  if (name == "metis") return Ordering::metis;
  if (name == "nesdis") return Ordering::nesdis;
  if (name == "natural") return Ordering::natural;
  throw std::invalid_argument("unknown ordering '" + name + "' (expected auto, amd, metis, nesdis or natural)");
}

const char* to_string(Ordering ordering) {
  switch (ordering) {
    case Ordering::automatic:
      return "auto";
    case Ordering::amd:
      return "amd";
    case Ordering::metis:
      return "metis";
    case Ordering::nesdis:
      return "nesdis";
    case Ordering::natural:
      return "natural";
  }
  return "?";
}

double relative_residual(const CoupledSystem& s, const Eigen::VectorXd& v_h, const Eigen::VectorXd& v_t) {
  const Eigen::VectorXd r_h = s.A_h * v_h + s.A_ht * v_t - s.b_h;
  const Eigen::VectorXd r_t = s.A_th * v_h + s.A_t * v_t - s.b_t;
  const double b = std::sqrt(s.b_h.squaredNorm() + s.b_t.squaredNorm());
  return std::sqrt(r_h.squaredNorm() + r_t.squaredNorm()) / (b > 0 ? b : 1.0);
}

}  // namespace hapticd::hand
