#pragma once
// Velocity-level frictional contact by projected Gauss-Seidel on the Delassus
// operator W = J A^-1 J^T (DESIGN.md section 3): find contact impulses
// lambda_i = (normal, tangent 1, tangent 2), N s, with
//   u = u_free + W lambda,  0 <= lambda_n  _|_  u_n - bias >= 0,
//   |lambda_t| <= mu lambda_n, and lambda_t opposing u_t when sliding
// (Coulomb, maximal dissipation). The building block of constraint contact;
// W comes from the implicit system's factorization (the Schur machinery).
#include <Eigen/Core>
#include <vector>

namespace hapticd::hand {

struct ContactProblem {
  Eigen::MatrixXd W;        // 3c x 3c, symmetric positive semi-definite, contact frames (n, t1, t2)
  Eigen::VectorXd u_free;   // 3c: relative velocities without contact impulses, m/s
  Eigen::VectorXd bias;     // c: least normal velocity (> 0 pushes penetrating points out), m/s
  std::vector<double> mu;   // c: friction coefficients
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

// `warm_start` (3c), when given, is the first iterate (the previous step's impulses).
PgsResult solve_contacts_pgs(const ContactProblem& problem, const PgsOptions& options = {},
                             const Eigen::VectorXd* warm_start = nullptr);

// Largest violation of the contact conditions by `lambda` (m/s for velocities,
// scaled by W's diagonal for impulses): 0 for an exact solution.
double contact_residual(const ContactProblem& problem, const Eigen::VectorXd& lambda);

}  // namespace hapticd::hand
