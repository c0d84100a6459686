// Coupling springs and handles: every Jacobian of seed 004 eq. 4-5, 11 and 14
// against central finite differences.
#include <gtest/gtest.h>

#include <random>

#include "hand_models/box_mesh.hpp"
#include "hand_models/corotational_fem.hpp"
#include "hand_models/rigid_handle.hpp"

namespace hapticd::hand {
namespace {

struct SpringCase {
  Eigen::Vector3d x_A, v_A, r_B;
  HandleState h;
  double k = 750.0, d = 3.0;
};

SpringCase random_case(std::mt19937& rng) {
  std::uniform_real_distribution<double> u(-1, 1);
  auto vec = [&](double s) -> Eigen::Vector3d { return Eigen::Vector3d(u(rng), u(rng), u(rng)) * s; };
  SpringCase c;
  c.x_A = vec(0.05);
  c.v_A = vec(0.3);
  c.r_B = vec(0.03);
  c.h.p_WH = vec(0.05);
  c.h.q_WH = Eigen::Quaterniond(u(rng), u(rng), u(rng), u(rng)).normalized();
  c.h.v_WH = vec(0.2);
  c.h.w_WH = vec(8.0);
  return c;
}

// Force on the node and wrench on the handle as one 9-vector.
Eigen::Matrix<double, 9, 1> spring_output(const SpringCase& c) {
  const SpringTerms s = coupling_spring(c.x_A, c.v_A, c.h, c.r_B, c.k, c.d);
  Eigen::Matrix<double, 9, 1> out;
  out << s.F_A, s.W_B;
  return out;
}

// Perturbs coordinate i of (x_A, v_A, p_WH, theta, v_WH, w_WH) by eps.
SpringCase perturbed(SpringCase c, int i, double eps) {
  const Eigen::Vector3d e = eps * Eigen::Vector3d::Unit(i % 3);
  switch (i / 3) {
    case 0: c.x_A += e; break;
    case 1: c.v_A += e; break;
    case 2: c.h.p_WH += e; break;
    case 3: c.h.q_WH = rotate_by(c.h.q_WH, e); break;
    case 4: c.h.v_WH += e; break;
    case 5: c.h.w_WH += e; break;
  }
  return c;
}

TEST(CouplingSpring, ForceIsEquation4AndHandleWrenchBalancesIt) {
  std::mt19937 rng(1);
  const SpringCase c = random_case(rng);
  const SpringTerms s = coupling_spring(c.x_A, c.v_A, c.h, c.r_B, c.k, c.d);
  const Eigen::Vector3d rho = c.h.q_WH * c.r_B;
  const Eigen::Vector3d expected =
      -c.k * (c.x_A - c.h.p_WH - rho) - c.d * (c.v_A - c.h.v_WH - c.h.w_WH.cross(rho));
  EXPECT_LT((s.F_A - expected).norm(), 1e-12 * expected.norm());
  EXPECT_LT((s.W_B.head<3>() + s.F_A).norm(), 1e-14 * expected.norm());
  EXPECT_LT((s.W_B.tail<3>() - rho.cross(-s.F_A)).norm(), 1e-14 * expected.norm());
}

TEST(CouplingSpring, AllJacobiansMatchFiniteDifferences) {
  std::mt19937 rng(7);
  for (int trial = 0; trial < 20; ++trial) {
    const SpringCase c = random_case(rng);
    const SpringTerms s = coupling_spring(c.x_A, c.v_A, c.h, c.r_B, c.k, c.d);
    // Analytic 9 x 18 Jacobian of (F_A, W_B) w.r.t. (x_A, v_A, p, theta, v, w).
    Eigen::Matrix<double, 9, 18> J;
    J.setZero();
    J.block<3, 3>(0, 0) = -c.k * Eigen::Matrix3d::Identity();
    J.block<3, 3>(0, 3) = -c.d * Eigen::Matrix3d::Identity();
    J.block<3, 6>(0, 6) = s.dFA_dxh;
    J.block<3, 6>(0, 12) = s.dFA_dvh;
    J.block<6, 3>(3, 0) = s.dWB_dxA;
    J.block<6, 3>(3, 3) = s.dWB_dvA;
    J.block<6, 6>(3, 6) = s.dWB_dxh;
    J.block<6, 6>(3, 12) = s.dWB_dvh;
    Eigen::Matrix<double, 9, 18> J_fd;
    const double eps = 1e-6;
    for (int i = 0; i < 18; ++i)
      J_fd.col(i) = (spring_output(perturbed(c, i, eps)) - spring_output(perturbed(c, i, -eps))) / (2 * eps);
    // Central differences: truncation O(eps^2) ~ 1e-12 relative, rounding ~1e-16/eps.
    EXPECT_LT((J - J_fd).norm(), 1e-7 * J.norm()) << "trial " << trial << "\n" << (J - J_fd);
  }
}

TEST(QuaternionJacobian, Equation14MatchesFiniteDifferences) {
  std::mt19937 rng(3);
  std::uniform_real_distribution<double> u(-1, 1);
  for (int trial = 0; trial < 10; ++trial) {
    const Eigen::Vector4d q(u(rng), u(rng), u(rng), u(rng));  // (x, y, z, s), not normalised on purpose
    const Eigen::Vector3d r(u(rng), u(rng), u(rng));
    auto rotated = [&](const Eigen::Vector4d& c) -> Eigen::Vector3d {
      const Eigen::Quaterniond qq(c[3], c[0], c[1], c[2]);
      return (qq * Eigen::Quaterniond(0, r.x(), r.y(), r.z()) * qq.conjugate()).vec();
    };
    const Eigen::Matrix<double, 3, 4> J = d_rotated_d_quaternion(Eigen::Quaterniond(q[3], q[0], q[1], q[2]), r);
    Eigen::Matrix<double, 3, 4> J_fd;
    const double eps = 1e-6;
    for (int i = 0; i < 4; ++i) {
      const Eigen::Vector4d e = eps * Eigen::Vector4d::Unit(i);
      J_fd.col(i) = (rotated(q + e) - rotated(q - e)) / (2 * eps);
    }
    EXPECT_LT((J - J_fd).norm(), 1e-8 * J.norm()) << "trial " << trial;
  }
}

TEST(QuaternionJacobian, Equation14TimesGIsTheAngularVelocityCrossProduct) {
  // (d(R r)/dq) G w = w x (R r): the rotation-vector Jacobian -[R r]x used by the solver.
  std::mt19937 rng(5);
  std::uniform_real_distribution<double> u(-1, 1);
  for (int trial = 0; trial < 10; ++trial) {
    const Eigen::Quaterniond q = Eigen::Quaterniond(u(rng), u(rng), u(rng), u(rng)).normalized();
    const Eigen::Vector3d r(u(rng), u(rng), u(rng));
    const Eigen::Matrix3d JG = d_rotated_d_quaternion(q, r) * quaternion_rate_matrix(q);
    EXPECT_LT((JG + skew(q * r)).norm(), 1e-14 * (1 + r.norm()));
  }
}

TEST(QuaternionJacobian, RateMatrixMatchesIntegratedRotation) {
  const Eigen::Quaterniond q = Eigen::Quaterniond(0.3, -0.5, 0.2, 0.7).normalized();
  const Eigen::Vector3d w(1.5, -2.0, 0.5);
  const double h = 1e-7;
  const Eigen::Quaterniond q1 = rotate_by(q, h * w);
  const Eigen::Vector4d rate_fd = (q1.coeffs() - q.coeffs()) / h;  // coeffs() are (x, y, z, w)
  EXPECT_LT((quaternion_rate_matrix(q) * w - rate_fd).norm(), 1e-6);
}

TEST(RigidHandle, MassAndInertiaComeFromTheLumpedMassesOfNodesInTheSphere) {
  const TetMesh mesh = make_box_mesh({0.04, 0.04, 0.04}, {4, 4, 4}, Eigen::Vector3d(-0.02, -0.02, -0.02));
  const CorotationalFem fem(mesh, Material{});
  const RigidHandle h = make_handle(mesh, fem.lumped_mass(), Eigen::Vector3d::Zero(), 0.0101, {}, "palm");
  // Nodes within 1.01 cm of the centre on a 1 cm grid: the centre and its 6 axis neighbours.
  ASSERT_EQ(h.nodes.size(), 7u);
  double m = 0;
  for (int i : h.nodes) m += fem.lumped_mass()[i];
  EXPECT_DOUBLE_EQ(h.mass_kg, m);
  EXPECT_LT(h.p_WH_rest.norm(), 1e-15);
  // Inertia of the node set plus the regulariser 2/5 m (r/10)^2.
  Eigen::Matrix3d I = Eigen::Matrix3d::Zero();
  for (int i : h.nodes) {
    const Eigen::Vector3d r = mesh.X[i];
    I += fem.lumped_mass()[i] * (r.squaredNorm() * Eigen::Matrix3d::Identity() - r * r.transpose());
  }
  I += 0.4 * m * std::pow(0.00101, 2) * Eigen::Matrix3d::Identity();
  EXPECT_LT((h.inertia_B - I).norm(), 1e-12 * I.norm());
  EXPECT_THROW(make_handle(mesh, fem.lumped_mass(), Eigen::Vector3d(1, 1, 1), 0.01, {}, "far"), std::invalid_argument);
}

}  // namespace
}  // namespace hapticd::hand
