// Projected Gauss-Seidel frictional contact against closed forms: a frictionless
// contact, a particle on an incline (stick and slide), a box on four corners.
#include <gtest/gtest.h>

#include <Eigen/Dense>
#include <cmath>
#include <random>

#include "hand_models/contact_pgs.hpp"

namespace hapticd::hand {
namespace {

constexpr double kG = 9.81, kH = 1.0 / 60.0;

TEST(ContactPgs, FrictionlessContactStopsTheApproachExactly) {
  ContactProblem p;
  p.W = 2.0 * Eigen::Matrix3d::Identity();
  p.u_free = Eigen::Vector3d(-1.0, 0.5, 0.0);
  p.bias = Eigen::VectorXd::Zero(1);
  p.mu = {0.0};
  const PgsResult r = solve_contacts_pgs(p);
  ASSERT_TRUE(r.converged);
  EXPECT_NEAR(r.lambda[0], 0.5, 1e-14);  // -u_n / W_nn
  EXPECT_EQ(r.lambda.tail<2>(), Eigen::Vector2d::Zero());
  EXPECT_LT(contact_residual(p, r.lambda), 1e-12);
  p.u_free[0] = 0.3;  // separating: no impulse
  EXPECT_EQ(solve_contacts_pgs(p).lambda, Eigen::Vector3d::Zero());
}

// A point mass on an incline of angle theta, one step of gravity, in the contact frame (n, down-slope, side).
ContactProblem particle_on_incline(double theta, double mu, double m) {
  ContactProblem p;
  p.W = Eigen::Matrix3d::Identity() / m;
  p.u_free = Eigen::Vector3d(-kG * std::cos(theta) * kH, kG * std::sin(theta) * kH, 0);
  p.bias = Eigen::VectorXd::Zero(1);
  p.mu = {mu};
  return p;
}

TEST(ContactPgs, ParticleOnAnInclineSticksBelowTheFrictionAngleAndSlidesAboveIt) {
  const double m = 0.1, theta = 0.4;
  const ContactProblem stick = particle_on_incline(theta, 1.2 * std::tan(theta), m);
  const PgsResult s = solve_contacts_pgs(stick);
  ASSERT_TRUE(s.converged);
  const Eigen::Vector3d u_stick = stick.u_free + stick.W * s.lambda;
  EXPECT_LT(u_stick.norm(), 1e-12);  // at rest
  EXPECT_NEAR(s.lambda[0], m * kG * std::cos(theta) * kH, 1e-14);
  const double mu = 0.5 * std::tan(theta);
  const ContactProblem slide = particle_on_incline(theta, mu, m);
  const PgsResult r = solve_contacts_pgs(slide);
  ASSERT_TRUE(r.converged);
  const Eigen::Vector3d u = slide.u_free + slide.W * r.lambda;
  EXPECT_NEAR(u[0], 0.0, 1e-14);
  EXPECT_NEAR(u[1] / kH, kG * (std::sin(theta) - mu * std::cos(theta)), 1e-10);  // Coulomb acceleration
  EXPECT_NEAR(r.lambda[1], -mu * r.lambda[0], 1e-14);                          // on the cone, opposing
  EXPECT_LT(contact_residual(slide, r.lambda), 1e-12);
}

// A 10 cm cube of mass m on four corner contacts (z = 0 floor), pushed along x
// with `push` N for one step: the Delassus operator of a rigid body.
struct BoxOnCorners {
  double m = 0.5, side = 0.1;
  Eigen::MatrixXd J;  // 12 x 6: contact frame rows (n = z, t1 = x, t2 = y) per corner
  Eigen::Matrix<double, 6, 6> M_inv;
  ContactProblem problem;
  Eigen::Matrix<double, 6, 1> v_free;

  BoxOnCorners(double mu, double push) : J(12, 6) {
    const double I = m * side * side / 6;
    M_inv.setZero();
    M_inv.diagonal() << 1 / m, 1 / m, 1 / m, 1 / I, 1 / I, 1 / I;
    const Eigen::Vector3d axes[3] = {Eigen::Vector3d::UnitZ(), Eigen::Vector3d::UnitX(), Eigen::Vector3d::UnitY()};
    for (int c = 0; c < 4; ++c) {
      const Eigen::Vector3d r(c & 1 ? 0.05 : -0.05, c & 2 ? 0.05 : -0.05, -0.05);  // corner from the centre
      for (int k = 0; k < 3; ++k) J.row(3 * c + k) << axes[k].transpose(), r.cross(axes[k]).transpose();
    }
    v_free << push / m * kH, 0, -kG * kH, 0, 0, 0;
    problem.W = J * M_inv * J.transpose();
    problem.u_free = J * v_free;
    problem.bias = Eigen::VectorXd::Zero(4);
    problem.mu.assign(4, mu);
  }
  Eigen::Matrix<double, 6, 1> velocity(const Eigen::VectorXd& lambda) const {
    return v_free + M_inv * J.transpose() * lambda;
  }
};

TEST(ContactPgs, BoxOnFourCornersCarriesItsWeightAndHoldsBelowMuMg) {
  const double mu = 0.5;
  const BoxOnCorners box(mu, 0.8 * mu * 0.5 * kG);  // pushed with 80 % of mu m g
  PgsOptions options;
  options.max_iterations = 2000;
  const PgsResult r = solve_contacts_pgs(box.problem, options);
  ASSERT_TRUE(r.converged) << r.iterations;
  const Eigen::Matrix<double, 6, 1> v = box.velocity(r.lambda);
  EXPECT_LT(v.norm(), 1e-8);  // m/s: it stays put
  double normal = 0;
  for (int c = 0; c < 4; ++c) normal += r.lambda[3 * c];
  EXPECT_NEAR(normal, box.m * kG * kH, 1e-9);
}

TEST(ContactPgs, BoxOnFourCornersSlidesAboveMuMgWithCoulombAcceleration) {
  const double mu = 0.5, push = 1.5 * mu * 0.5 * kG;
  const BoxOnCorners box(mu, push);
  PgsOptions options;
  options.max_iterations = 5000;
  const PgsResult r = solve_contacts_pgs(box.problem, options);
  ASSERT_TRUE(r.converged) << r.iterations;
  const Eigen::Matrix<double, 6, 1> v = box.velocity(r.lambda);
  // The push beyond mu m g accelerates it: a = (F - mu m g) / m, no lift, no spin.
  EXPECT_NEAR(v[0] / kH, (push - mu * box.m * kG) / box.m, 1e-6);
  EXPECT_NEAR(v[2], 0.0, 1e-9);
  EXPECT_LT(v.tail<3>().norm(), 1e-6);
}

TEST(ContactPgs, RandomProblemsConvergeToTheContactConditions) {
  std::mt19937 rng(3);
  std::normal_distribution<double> n(0, 1);
  for (int trial = 0; trial < 20; ++trial) {
    const int c = 6, dofs = 30;  // more DOFs than constraints: W positive definite
    Eigen::MatrixXd J(3 * c, dofs);
    for (int i = 0; i < J.size(); ++i) J.data()[i] = n(rng);
    ContactProblem p;
    p.W = J * J.transpose() / dofs;
    p.u_free = Eigen::VectorXd::NullaryExpr(3 * c, [&] { return n(rng); });
    p.bias = Eigen::VectorXd::Zero(c);
    for (int i = 0; i < c; ++i) p.mu.push_back(std::abs(n(rng)));
    PgsOptions options;
    options.max_iterations = 5000;
    options.tolerance = 1e-13;
    const PgsResult r = solve_contacts_pgs(p, options);
    EXPECT_TRUE(r.converged) << "trial " << trial;
    EXPECT_LT(contact_residual(p, r.lambda), 1e-8) << "trial " << trial;
  }
}

}  // namespace
}  // namespace hapticd::hand
