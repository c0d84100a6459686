#include "hand_models/contact_pgs.hpp"

#include <algorithm>
#include <cmath>

namespace hapticd::hand {
PgsResult solve_contacts_pgs(const ContactProblem& p, const PgsOptions& options, const Eigen::VectorXd* warm) {
  const int c = static_cast<int>(p.mu.size());
  PgsResult r;
  r.lambda = warm && warm->size() == 3 * c ? *warm : Eigen::VectorXd::Zero(3 * c);
  for (int i = 0; i < c; ++i) r.lambda.segment<3>(3 * i) = project_to_cone(r.lambda.segment<3>(3 * i), p.mu[i]);
  std::vector<double> tangent_step(c, 0.0);
  for (int i = 0; i < c; ++i) tangent_step[i] = pgs_tangent_step(p.W, i);
  Eigen::VectorXd u = p.u_free + p.W * r.lambda;
  r.iterations = pgs_sweeps(p.W, p.bias, p.mu.data(), tangent_step.data(), c, u, r.lambda, options.max_iterations,
                            options.tolerance, r.converged);
  return r;
}

double contact_residual(const ContactProblem& p, const Eigen::VectorXd& lambda) {
  const int c = static_cast<int>(p.mu.size());
  const Eigen::VectorXd u = p.u_free + p.W * lambda;
  double worst = 0;
  for (int i = 0; i < c; ++i) {
    const double ln = lambda[3 * i], un = u[3 * i] - p.bias[i];
    const Eigen::Vector2d lt = lambda.segment<2>(3 * i + 1), ut = u.segment<2>(3 * i + 1);
    const double scale = std::max(p.W(3 * i, 3 * i), 1e-300);
    worst = std::max({worst, std::max(0.0, -ln) * scale, std::max(0.0, -un), std::min(ln * scale, std::abs(un))});
    // Friction: inside the cone the contact sticks (u_t = 0); on its boundary it opposes the slide.
    const double slack = p.mu[i] * ln - lt.norm();
    worst = std::max(worst, std::max(0.0, -slack) * scale);
    if (slack > 1e-9 * (1 + ln)) {
      worst = std::max(worst, ut.norm());
    } else if (ut.norm() > 0 && lt.norm() > 0) {
      worst = std::max(worst, (lt / lt.norm() + ut / ut.norm()).norm() * ut.norm());
    }
  }
  return worst;
}

}  // namespace hapticd::hand
