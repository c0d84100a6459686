#include "hand_models/coupled_solver.hpp"

#include <Eigen/CholmodSupport>
#include <Eigen/Dense>
#include <Eigen/IterativeLinearSolvers>
#include <Eigen/SparseLU>
#include <chrono>
#include <stdexcept>
#include <vector>

namespace hapticd {
namespace {

using Clock = std::chrono::steady_clock;
double ms_since(Clock::time_point t0) {
  return std::chrono::duration<double, std::milli>(Clock::now() - t0).count();
}

// Handle solve of eq. 13: S = A_h - A_ht Y, r = b_h - A_ht y0 (S is small and, with
// the rotational terms, not symmetric: LU with partial pivoting).
bool solve_handles(const CoupledSystem& s, const Eigen::MatrixXd& Y, const Eigen::VectorXd& y0, Eigen::VectorXd& v_h) {
  const Eigen::MatrixXd S = s.A_h - s.A_ht * Y;
  const Eigen::VectorXd r = s.b_h - s.A_ht * y0;
  const Eigen::PartialPivLU<Eigen::MatrixXd> lu(S);
  v_h = lu.solve(r);
  // A singular S shows as a non-finite or inaccurate solution.
  return v_h.allFinite() && (S * v_h - r).norm() <= 1e-8 * (r.norm() + S.norm() * v_h.norm());
}

class MonolithicSolver final : public CoupledSolver {
 public:
  SolverKind kind() const override { return SolverKind::monolithic; }
  bool solve(const CoupledSystem& s, Eigen::VectorXd& v_h, Eigen::VectorXd& v_t, SolveReport& report) override {
    const auto t0 = Clock::now();
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
    lu_.compute(A);
    report.factor_ms = ms_since(t0);
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
  explicit SchurCholmodSolver(const SolverOptions& o) : options_(o) {
    chol_.setMode(o.supernodal ? Eigen::CholmodSupernodalLLt : Eigen::CholmodSimplicialLLt);
    cholmod_common& c = chol_.cholmod();
    switch (o.ordering) {
      case Ordering::automatic:
        break;
      case Ordering::amd:
        c.nmethods = 1, c.method[0].ordering = CHOLMOD_AMD;
        break;
      case Ordering::metis:
        c.nmethods = 1, c.method[0].ordering = CHOLMOD_METIS;
        break;
      case Ordering::nesdis:
        c.nmethods = 1, c.method[0].ordering = CHOLMOD_NESDIS;
        break;
      case Ordering::natural:
        c.nmethods = 1, c.method[0].ordering = CHOLMOD_NATURAL;
        break;
    }
  }
  SolverKind kind() const override { return SolverKind::schur_cholmod; }

  bool solve(const CoupledSystem& s, Eigen::VectorXd& v_h, Eigen::VectorXd& v_t, SolveReport& report) override {
    const auto t0 = Clock::now();
    const int nh = s.handle_dofs(), nt = s.tool_dofs();
    // Symbolic analysis once per pattern (the pattern is fixed per mesh).
    if (analyzed_nnz_ != s.A_t.nonZeros() || analyzed_rows_ != nt) {
      chol_.analyzePattern(s.A_t);
      analyzed_nnz_ = s.A_t.nonZeros();
      analyzed_rows_ = nt;
    }
    chol_.factorize(s.A_t);
    report.factor_ms = ms_since(t0);
    if (chol_.info() != Eigen::Success) return false;
    // All 1 + 6m right-hand sides [b_t, A_th] in one block solve.
    const auto t1 = Clock::now();
    rhs_.resize(nt, nh + 1);
    rhs_.col(0) = s.b_t;
    rhs_.rightCols(nh) = s.A_th;
    Y_ = chol_.solve(rhs_);
    report.schur_ms = ms_since(t1);
    const auto t2 = Clock::now();
    if (!solve_handles(s, Y_.rightCols(nh), Y_.col(0), v_h)) return false;
    // eq. 12 without another solve: A_t^-1 (b_t - A_th v_h) = y0 - Y v_h.
    v_t = Y_.col(0) - Y_.rightCols(nh) * v_h;
    report.solve_ms = ms_since(t2);
    return v_t.allFinite();
  }

 private:
  SolverOptions options_;
  Eigen::CholmodDecomposition<Eigen::SparseMatrix<double>, Eigen::Lower> chol_;
  long analyzed_nnz_ = -1;
  long analyzed_rows_ = -1;
  Eigen::MatrixXd rhs_, Y_;
};

}  // namespace

std::unique_ptr<CoupledSolver> make_solver(SolverKind kind, const SolverOptions& options) {
  switch (kind) {
    case SolverKind::monolithic:
      return std::make_unique<MonolithicSolver>();
    case SolverKind::schur_cg:
      return std::make_unique<SchurCgSolver>(options);
    case SolverKind::schur_cholmod:
      return std::make_unique<SchurCholmodSolver>(options);
  }
  throw std::invalid_argument("unknown solver kind");
}

SolverKind parse_solver_kind(const std::string& name) {
  if (name == "monolithic") return SolverKind::monolithic;
  if (name == "cg") return SolverKind::schur_cg;
  if (name == "cholmod") return SolverKind::schur_cholmod;
  throw std::invalid_argument("unknown solver '" + name + "' (expected monolithic, cg or cholmod)");
}

const char* to_string(SolverKind kind) {
  switch (kind) {
    case SolverKind::monolithic:
      return "monolithic";
    case SolverKind::schur_cg:
      return "cg";
    case SolverKind::schur_cholmod:
      return "cholmod";
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

}  // namespace hapticd
