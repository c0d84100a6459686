#pragma once
// Velocity-level frictional contact by projected Gauss-Seidel on the Delassus
// operator W = J A^-1 J^T (DESIGN.md section 3): find contact impulses
// lambda_i = (normal, tangent 1, tangent 2), N s, with
//   u = u_free + W lambda,  0 <= lambda_n  _|_  u_n - bias >= 0,
//   |lambda_t| <= mu lambda_n, and lambda_t opposing u_t when sliding
// (Coulomb, maximal dissipation). The building block of constraint contact;
// W comes from the implicit system's factorization (the Schur machinery).
#include <Eigen/Core>
#include <algorithm>
#include <cmath>
#include <vector>

namespace hapticd::hand {

struct ContactProblem {
  Eigen::MatrixXd W;       // 3c x 3c, symmetric positive semi-definite, contact frames (n, t1, t2)
  Eigen::VectorXd u_free;  // 3c: relative velocities without contact impulses, m/s
  Eigen::VectorXd bias;    // c: least normal velocity (> 0 pushes penetrating points out), m/s
  std::vector<double> mu;  // c: friction coefficients
};

struct PgsOptions {
  int max_iterations = 200;
  double tolerance = 1e-10;  // on the largest impulse change in a sweep, relative to the largest impulse
};

struct PgsResult {
  Eigen::VectorXd lambda;  // 3c
  int iterations = 0;
  bool converged = false;
};

// Projects an impulse (normal, tangent 1, tangent 2) onto the friction cone: normal >= 0,
// |tangent| <= mu normal.
inline Eigen::Vector3d project_to_cone(Eigen::Vector3d l, double mu) {
  l[0] = std::max(0.0, l[0]);
  const double t = l.tail<2>().norm(), limit = mu * l[0];
  if (t > limit) l.tail<2>() *= t > 0 ? limit / t : 0.0;
  return l;
}

// Contact i's tangential step of the sweeps: 1 / lambda_max(W_tt), 0 when W_tt vanishes. A scalar
// step (not the 2x2 block's inverse) makes every fixed point on the cone oppose the slide (maximal
// dissipation) even when W_tt is anisotropic.
template <class MatW>
double pgs_tangent_step(const MatW& W, int i) {
  const Eigen::Matrix2d Wtt = W.template block<2, 2>(3 * i + 1, 3 * i + 1);
  const double mean = 0.5 * Wtt.trace(), spread = std::hypot(0.5 * (Wtt(0, 0) - Wtt(1, 1)), Wtt(0, 1));
  return mean + spread > 0 ? 1.0 / (mean + spread) : 0.0;
}

// The sweeps of solve_contacts_pgs on the caller's storage, so that the haptic tick (fixed-capacity
// matrices, its Delassus operator dense or in low-rank form) and the hand step (dynamic ones) run one
// implementation and neither allocates here. `op` is the Delassus operator W together with the rows'
// velocities u = u_free + W lambda, kept so: op.block(i) is W's 3x3 diagonal block of contact i,
// op.velocity(i) contact i's three rows of u, op.add(i, delta) moves u by W's three columns of
// contact i times delta. c contacts; bias (c), mu (c), tangent_step (c, pgs_tangent_step); lambda (3c)
// the first iterate (inside the cone) and the answer. Per contact: the normal row with its own
// diagonal, then the tangent, each followed by its projection. Stops when a sweep changes no impulse
// by more than `tolerance` times the largest. Returns the sweeps run.
template <class Op, class VecB, class VecL>
int pgs_sweeps_on(Op& op, const VecB& bias, const double* mu, const double* tangent_step, int c, VecL& lambda,
                  int max_iterations, double tolerance, bool& converged) {
  converged = false;
  int sweep = 1;
  for (; sweep <= max_iterations; ++sweep) {
    double change = 0, largest = 0;
    for (int i = 0; i < c; ++i) {
      const Eigen::Vector3d old = lambda.template segment<3>(3 * i);
      Eigen::Vector3d l = old;
      const Eigen::Matrix3d W_ii = op.block(i);
      const Eigen::Vector3d u = op.velocity(i);
      if (W_ii(0, 0) > 0) l[0] = std::max(0.0, l[0] - (u[0] - bias[i]) / W_ii(0, 0));
      // Tangential: the impulse that would stop sliding, clipped to the cone of the new normal.
      const Eigen::Vector2d u_t = u.tail<2>() + W_ii.block<2, 1>(1, 0) * (l[0] - old[0]);
      l.tail<2>() -= tangent_step[i] * u_t;
      l = project_to_cone(l, mu[i]);
      const Eigen::Vector3d delta = l - old;
      if (delta.squaredNorm() > 0) {
        op.add(i, delta);
        lambda.template segment<3>(3 * i) = l;
      }
      change = std::max(change, delta.cwiseAbs().maxCoeff());
      largest = std::max(largest, l.cwiseAbs().maxCoeff());
    }
    if (change <= tolerance * std::max(largest, 1e-300)) {
      converged = true;
      break;
    }
  }
  return std::min(sweep, max_iterations);
}

// u += W's columns first .. first + 2 times delta: one pass over u where no delta is 0, each row's
// three products added in the order three passes add them (the same bits, for a third of the
// memory traffic: the haptic tick's sweeps run this on up to 72 rows).
template <class MatW, class VecU>
void add_columns(const MatW& W, int first, const Eigen::Vector3d& delta, VecU&& u) {
  const Eigen::Index n = u.size();
  if (delta[0] != 0 && delta[1] != 0 && delta[2] != 0) {
    u = ((u + W.col(first).head(n) * delta[0]) + W.col(first + 1).head(n) * delta[1]) +
        W.col(first + 2).head(n) * delta[2];
    return;
  }
  for (int d = 0; d < 3; ++d)
    if (delta[d] != 0) u += W.col(first + d).head(n) * delta[d];
}

// A dense Delassus operator for pgs_sweeps_on: W (3c x 3c) and u (3c) held by reference.
template <class MatW, class VecU>
struct DenseDelassus {
  const MatW& W;
  VecU& u;
  int c;
  Eigen::Matrix3d block(int i) const { return W.template block<3, 3>(3 * i, 3 * i); }
  Eigen::Vector3d velocity(int i) const { return u.template segment<3>(3 * i); }
  void add(int i, const Eigen::Vector3d& delta) { add_columns(W, 3 * i, delta, u.head(3 * c)); }
};

// pgs_sweeps_on a dense W, u = u_free + W lambda on entry and kept so.
template <class MatW, class VecB, class VecU, class VecL>
int pgs_sweeps(const MatW& W, const VecB& bias, const double* mu, const double* tangent_step, int c, VecU& u,
               VecL& lambda, int max_iterations, double tolerance, bool& converged) {
  DenseDelassus<MatW, VecU> op{W, u, c};
  return pgs_sweeps_on(op, bias, mu, tangent_step, c, lambda, max_iterations, tolerance, converged);
}

// `warm_start` (3c), when given, is the first iterate (the previous step's impulses).
PgsResult solve_contacts_pgs(const ContactProblem& problem, const PgsOptions& options = {},
                             const Eigen::VectorXd* warm_start = nullptr);

// Largest violation of the contact conditions by `lambda` (m/s for velocities,
// scaled by W's diagonal for impulses): 0 for an exact solution.
double contact_residual(const ContactProblem& problem, const Eigen::VectorXd& lambda);

}  // namespace hapticd::hand
