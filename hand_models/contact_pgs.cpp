#include "hand_models/contact_pgs.hpp"

#include <algorithm>
#include <cmath>

namespace hapticd::hand {
namespace {

// Projects an impulse onto the friction cone: normal >= 0, |tangent| <= mu normal.
Eigen::Vector3d project_to_cone(Eigen::Vector3d l, double mu) {
  l[0] = std::max(0.0, l[0]);
  const double t = l.tail<2>().norm(), limit = mu * l[0];
  if (t > limit) l.tail<2>() *= t > 0 ? limit / t : 0.0;
  return l;
}

}  // namespace

PgsResult solve_contacts_pgs(const ContactProblem& p, const PgsOptions& options, const Eigen::VectorXd* warm) {
  const int c = static_cast<int>(p.mu.size());
  PgsResult r;
  r.lambda = warm && warm->size() == 3 * c ? *warm : Eigen::VectorXd::Zero(3 * c);
  for (int i = 0; i < c; ++i) r.lambda.segment<3>(3 * i) = project_to_cone(r.lambda.segment<3>(3 * i), p.mu[i]);
  // Per contact: the normal row first with its own diagonal, then the tangent
  // with a scalar step 1 / lambda_max(W_tt), each followed by its projection. A
  // scalar step (not the 2x2 block's inverse) makes every fixed point on the cone
  // oppose the slide (maximal dissipation) even when W_tt is anisotropic.
  std::vector<double> tangent_step(c, 0.0);
  for (int i = 0; i < c; ++i) {
    const Eigen::Matrix2d Wtt = p.W.block<2, 2>(3 * i + 1, 3 * i + 1);
    const double mean = 0.5 * Wtt.trace(), spread = std::hypot(0.5 * (Wtt(0, 0) - Wtt(1, 1)), Wtt(0, 1));
    if (mean + spread > 0) tangent_step[i] = 1.0 / (mean + spread);
  }
  Eigen::VectorXd u = p.u_free + p.W * r.lambda;
  for (r.iterations = 1; r.iterations <= options.max_iterations; ++r.iterations) {
    double change = 0, largest = 0;
    for (int i = 0; i < c; ++i) {
      const Eigen::Vector3d old = r.lambda.segment<3>(3 * i);
      Eigen::Vector3d l = old;
      const double Wnn = p.W(3 * i, 3 * i);
      if (Wnn > 0) l[0] = std::max(0.0, l[0] - (u[3 * i] - p.bias[i]) / Wnn);
      // Tangential: the impulse that would stop sliding, clipped to the cone of the new normal.
      const Eigen::Vector2d u_t = u.segment<2>(3 * i + 1) + p.W.block<2, 1>(3 * i + 1, 3 * i) * (l[0] - old[0]);
      l.tail<2>() -= tangent_step[i] * u_t;
      l = project_to_cone(l, p.mu[i]);
      const Eigen::Vector3d delta = l - old;
      if (delta.squaredNorm() > 0) {
        u.noalias() += p.W.middleCols<3>(3 * i) * delta;
        r.lambda.segment<3>(3 * i) = l;
      }
      change = std::max(change, delta.cwiseAbs().maxCoeff());
      largest = std::max(largest, l.cwiseAbs().maxCoeff());
    }
    if (change <= options.tolerance * std::max(largest, 1e-300)) {
      r.converged = true;
      break;
    }
  }
  r.iterations = std::min(r.iterations, options.max_iterations);
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
