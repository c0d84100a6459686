// Co-rotational FEM: invariances, stiffness against finite differences, patch
// test and the cantilever against Euler-Bernoulli beam theory.
#include <gtest/gtest.h>

#include <Eigen/Dense>
#include <Eigen/CholmodSupport>
#include <cmath>
#include <random>

#include "hand_models/box_mesh.hpp"
#include "hand_models/corotational_fem.hpp"

namespace hapticd::hand {
namespace {

Eigen::VectorXd rest_positions(const TetMesh& mesh) {
  Eigen::VectorXd x(3 * mesh.num_nodes());
  for (int i = 0; i < mesh.num_nodes(); ++i) x.segment<3>(3 * i) = mesh.X[i];
  return x;
}

Eigen::VectorXd forces(const CorotationalFem& fem, const Eigen::VectorXd& x) {
  std::vector<Eigen::Matrix3d> R;
  fem.compute_rotations(x, R);
  Eigen::VectorXd f = Eigen::VectorXd::Zero(x.size());
  fem.add_elastic_forces(x, R, f);
  return f;
}

// Warped stiffness sum_e R K_e R^T (df/dx ~ -K).
Eigen::SparseMatrix<double> warped_stiffness(const CorotationalFem& fem, const Eigen::VectorXd& x) {
  std::vector<Eigen::Matrix3d> R;
  fem.compute_rotations(x, R);
  std::vector<Eigen::Triplet<double>> t;
  for (int e = 0; e < fem.num_tets(); ++e)
    for (int a = 0; a < 4; ++a)
      for (int b = 0; b < 4; ++b) {
        const Eigen::Matrix3d B = fem.warped_block(e, a, b, R[e]);
        for (int r = 0; r < 3; ++r)
          for (int c = 0; c < 3; ++c) t.emplace_back(3 * fem.tets()[e][a] + r, 3 * fem.tets()[e][b] + c, B(r, c));
      }
  Eigen::SparseMatrix<double> K(x.size(), x.size());
  K.setFromTriplets(t.begin(), t.end());
  return K;
}

Eigen::Matrix3d random_rotation(std::mt19937& rng) {
  std::normal_distribution<double> n(0, 1);
  return Eigen::Quaterniond(n(rng), n(rng), n(rng), n(rng)).normalized().toRotationMatrix();
}

Eigen::VectorXd transformed(const TetMesh& mesh, const Eigen::Matrix3d& A, const Eigen::Vector3d& t) {
  Eigen::VectorXd x(3 * mesh.num_nodes());
  for (int i = 0; i < mesh.num_nodes(); ++i) x.segment<3>(3 * i) = A * mesh.X[i] + t;
  return x;
}

class CorotationalFemTest : public ::testing::Test {
 protected:
  TetMesh mesh = make_box_mesh({0.04, 0.03, 0.02}, {4, 3, 2});
  Material material;
  std::mt19937 rng{42};
  double force_scale() const { return material.youngs_modulus_pa * 0.02 * 0.02; }  // E * area, N
};

TEST_F(CorotationalFemTest, ZeroForceAtRest) {
  const CorotationalFem fem(mesh, material);
  EXPECT_LT(forces(fem, rest_positions(mesh)).cwiseAbs().maxCoeff(), 1e-12 * force_scale());
}

TEST_F(CorotationalFemTest, RigidMotionsOfTheRestShapeGiveZeroForce) {
  const CorotationalFem fem(mesh, material);
  for (int trial = 0; trial < 5; ++trial) {
    const Eigen::VectorXd x = transformed(mesh, random_rotation(rng), Eigen::Vector3d::Random());
    // Tolerance: rounding of the SVD and of E * strain, 1e-10 of E * area.
    EXPECT_LT(forces(fem, x).cwiseAbs().maxCoeff(), 1e-10 * force_scale()) << "trial " << trial;
  }
}

TEST_F(CorotationalFemTest, RotatingADeformedStateRotatesItsForces) {
  const CorotationalFem fem(mesh, material);
  Eigen::VectorXd x = rest_positions(mesh) + 2e-3 * Eigen::VectorXd::Random(3 * mesh.num_nodes());
  const Eigen::VectorXd f = forces(fem, x);
  const Eigen::Matrix3d Q = random_rotation(rng);
  Eigen::VectorXd xr(x.size()), fr_expected(x.size());
  for (int i = 0; i < mesh.num_nodes(); ++i) {
    xr.segment<3>(3 * i) = Q * x.segment<3>(3 * i) + Eigen::Vector3d(0.3, -0.2, 0.1);
    fr_expected.segment<3>(3 * i) = Q * f.segment<3>(3 * i);
  }
  EXPECT_LT((forces(fem, xr) - fr_expected).norm(), 1e-10 * f.norm());
  EXPECT_GT(f.norm(), 1e-3 * force_scale());  // the state is genuinely deformed
}

TEST_F(CorotationalFemTest, ExactTangentEqualsFiniteDifferencesOfForces) {
  const CorotationalFem fem(mesh, material);
  const Eigen::VectorXd x0 = transformed(mesh, random_rotation(rng), Eigen::Vector3d::Zero());
  double worst = 0;
  for (int e = 0; e < fem.num_tets(); e += 7) {
    Eigen::VectorXd x = x0 + 3e-3 * Eigen::VectorXd::Random(x0.size());  // 10 % strains
    const Matrix12d K = fem.element_exact_tangent(e, x);
    Matrix12d K_fd;
    const double eps = 1e-7;  // central differences: O(eps^2) truncation, O(1e-16/eps) rounding
    for (int c = 0; c < 12; ++c) {
      const int dof = 3 * fem.tets()[e][c / 3] + c % 3;
      Eigen::VectorXd xp = x, xm = x;
      xp[dof] += eps;
      xm[dof] -= eps;
      K_fd.col(c) = (fem.element_force(e, xp) - fem.element_force(e, xm)) / (2 * eps);
    }
    worst = std::max(worst, (K - K_fd).norm() / K_fd.norm());
  }
  EXPECT_LT(worst, 1e-6);
}

TEST_F(CorotationalFemTest, WarpedStiffnessEqualsFiniteDifferencesAtRotatedRest) {
  // At a rotated rest state the derivative of R multiplies a zero strain, so the
  // warped stiffness used by the solver is the exact tangent there.
  const CorotationalFem fem(mesh, material);
  const Eigen::VectorXd x = transformed(mesh, random_rotation(rng), Eigen::Vector3d(1, 2, 3));
  const Eigen::MatrixXd K = Eigen::MatrixXd(warped_stiffness(fem, x));
  const double eps = 1e-7;
  Eigen::MatrixXd K_fd(x.size(), x.size());
  for (int c = 0; c < x.size(); ++c) {
    Eigen::VectorXd xp = x, xm = x;
    xp[c] += eps;
    xm[c] -= eps;
    K_fd.col(c) = -(forces(fem, xp) - forces(fem, xm)) / (2 * eps);
  }
  EXPECT_LT((K - K_fd).norm() / K.norm(), 1e-6);
}

TEST_F(CorotationalFemTest, WarpedStiffnessIsSymmetricPositiveSemidefiniteAndBlindToTranslation) {
  const CorotationalFem fem(mesh, material);
  const Eigen::VectorXd x = rest_positions(mesh) + 3e-3 * Eigen::VectorXd::Random(3 * mesh.num_nodes());
  const Eigen::MatrixXd K = Eigen::MatrixXd(warped_stiffness(fem, x));
  EXPECT_LT((K - K.transpose()).norm(), 1e-12 * K.norm());
  const Eigen::VectorXd ev = Eigen::SelfAdjointEigenSolver<Eigen::MatrixXd>(K).eigenvalues();
  EXPECT_GT(ev.minCoeff(), -1e-9 * ev.maxCoeff());
  // Exactly three zero modes: rigid translations (rotations are not exact null
  // modes once the elements have different rotations).
  EXPECT_LT(std::abs(ev[2]), 1e-9 * ev.maxCoeff());
  EXPECT_GT(ev[3], 1e-9 * ev.maxCoeff());
  for (int axis = 0; axis < 3; ++axis) {
    Eigen::VectorXd t = Eigen::VectorXd::Zero(x.size());
    for (int i = 0; i < mesh.num_nodes(); ++i) t[3 * i + axis] = 1.0;
    EXPECT_LT((K * t).norm(), 1e-9 * K.norm());
  }
}

TEST_F(CorotationalFemTest, FastWarpedBlocksEqualRotatedRestStiffness) {
  const CorotationalFem fem(mesh, material);
  double worst = 0;
  for (int e = 0; e < fem.num_tets(); e += 5) {
    const Eigen::Matrix3d R = random_rotation(rng);
    Eigen::Matrix3d blocks[4][4];
    fem.warped_blocks(e, R, 2.5, blocks);
    for (int a = 0; a < 4; ++a)
      for (int b = 0; b < 4; ++b) {
        const Eigen::Matrix3d reference = 2.5 * fem.warped_block(e, a, b, R);
        worst = std::max(worst, (blocks[a][b] - reference).norm() / fem.rest_stiffness(e).norm());
      }
  }
  EXPECT_LT(worst, 1e-14);
}

TEST_F(CorotationalFemTest, InvertedAndFlatElementsGiveProperRotationsAndRestoringForces) {
  const CorotationalFem fem(mesh, material);
  const Eigen::Matrix3d flat = Eigen::Vector3d(1, 1, 0).asDiagonal();
  const Eigen::Matrix3d inverted = Eigen::Vector3d(1, 1, -0.5).asDiagonal();
  const Eigen::Matrix3d degenerate = Eigen::Matrix3d::Zero();
  for (const Eigen::Matrix3d& F : {flat, inverted, degenerate}) {
    const Eigen::Matrix3d R = rotation_of(F);
    EXPECT_NEAR(R.determinant(), 1.0, 1e-12);
    EXPECT_LT((R.transpose() * R - Eigen::Matrix3d::Identity()).norm(), 1e-12);
  }
  // Squash the whole box flat along z, and invert it: forces push the top back up.
  for (double scale_z : {0.0, -0.5}) {
    const Eigen::VectorXd x = transformed(mesh, Eigen::Vector3d(1, 1, scale_z).asDiagonal(), Eigen::Vector3d::Zero());
    const Eigen::VectorXd f = forces(fem, x);
    ASSERT_TRUE(f.allFinite());
    double top = 0;
    for (int i = 0; i < mesh.num_nodes(); ++i)
      if (mesh.X[i].z() > 0.019) top += f[3 * i + 2];
    EXPECT_GT(top, 0.01 * force_scale()) << "scale_z " << scale_z;
  }
}

// Static equilibrium with `fixed` DOFs prescribed: Newton with the warped
// stiffness, to a residual of `tolerance` times the load.
Eigen::VectorXd solve_static(const CorotationalFem& fem, Eigen::VectorXd x, const std::vector<bool>& fixed,
                             const Eigen::VectorXd& f_ext, double tolerance = 1e-11) {
  const int n = static_cast<int>(x.size());
  std::vector<int> free_index(n, -1);
  int nf = 0;
  for (int i = 0; i < n; ++i)
    if (!fixed[i]) free_index[i] = nf++;
  for (int it = 0; it < 30; ++it) {
    const Eigen::VectorXd r = forces(fem, x) + f_ext;
    Eigen::VectorXd r_free(nf);
    for (int i = 0; i < n; ++i)
      if (free_index[i] >= 0) r_free[free_index[i]] = r[i];
    if (r_free.norm() <= tolerance * f_ext.norm() + 1e-14) break;
    const Eigen::SparseMatrix<double> K = warped_stiffness(fem, x);
    std::vector<Eigen::Triplet<double>> t;
    for (int k = 0; k < K.outerSize(); ++k)
      for (Eigen::SparseMatrix<double>::InnerIterator e(K, k); e; ++e)
        if (free_index[e.row()] >= 0 && free_index[e.col()] >= 0)
          t.emplace_back(free_index[e.row()], free_index[e.col()], e.value());
    Eigen::SparseMatrix<double> K_free(nf, nf);
    K_free.setFromTriplets(t.begin(), t.end());
    Eigen::CholmodSupernodalLLT<Eigen::SparseMatrix<double>> ldlt(K_free);
    const Eigen::VectorXd dx = ldlt.solve(r_free);
    for (int i = 0; i < n; ++i)
      if (free_index[i] >= 0) x[i] += dx[free_index[i]];
  }
  return x;
}

TEST(CorotationalFemPatch, InteriorNodesReproduceAHomogeneousRotatedStrainExactly) {
  const TetMesh mesh = make_box_mesh({1, 1, 1}, {4, 4, 4});
  Material material;
  material.poisson_ratio = 0.3;
  const CorotationalFem fem(mesh, material);
  Eigen::Matrix3d eps;
  eps << 2e-3, 5e-4, -3e-4, 5e-4, -1e-3, 4e-4, -3e-4, 4e-4, 1.5e-3;
  const Eigen::Matrix3d Q = Eigen::AngleAxisd(0.7, Eigen::Vector3d(1, 2, 3).normalized()).toRotationMatrix();
  const Eigen::Matrix3d F = Q * (Eigen::Matrix3d::Identity() + eps);
  // Boundary nodes carry the exact field; interior nodes start at rest and must find it.
  const Eigen::VectorXd exact = transformed(mesh, F, Eigen::Vector3d(0.1, 0.2, 0.3));
  Eigen::VectorXd x = exact;
  std::vector<bool> fixed(x.size(), false);
  int interior = 0;
  for (int i = 0; i < mesh.num_nodes(); ++i) {
    const Eigen::Vector3d& X = mesh.X[i];
    const bool boundary = (X.array() < 1e-9).any() || (X.array() > 1 - 1e-9).any();
    for (int k = 0; k < 3; ++k) fixed[3 * i + k] = boundary;
    if (!boundary) {
      ++interior;
      x.segment<3>(3 * i) = Q * X;
    }
  }
  ASSERT_EQ(interior, 27);
  const Eigen::VectorXd x_eq = solve_static(fem, x, fixed, Eigen::VectorXd::Zero(x.size()));
  EXPECT_LT((x_eq - exact).cwiseAbs().maxCoeff(), 1e-10);
}

// Tip deflection of a clamped square beam under an end load, relative to
// Euler-Bernoulli delta = P L^3 / (3 E I).
double cantilever_relative_error(int cells_across) {
  const double L = 0.2, b = 0.02, E = 1e6, P = 1e-3;
  const TetMesh mesh = make_box_mesh({L, b, b}, {10 * cells_across, cells_across, cells_across});
  Material material;
  material.youngs_modulus_pa = E;
  material.poisson_ratio = 0.0;  // no anticlastic coupling: the beam-theory setting
  const CorotationalFem fem(mesh, material);
  Eigen::VectorXd x = rest_positions(mesh);
  std::vector<bool> fixed(x.size(), false);
  Eigen::VectorXd f_ext = Eigen::VectorXd::Zero(x.size());
  std::vector<int> tip;
  for (int i = 0; i < mesh.num_nodes(); ++i) {
    if (mesh.X[i].x() < 1e-9)
      for (int k = 0; k < 3; ++k) fixed[3 * i + k] = true;
    if (mesh.X[i].x() > L - 1e-9) tip.push_back(i);
  }
  for (int i : tip) f_ext[3 * i + 2] = -P / static_cast<double>(tip.size());
  const Eigen::VectorXd x_eq = solve_static(fem, x, fixed, f_ext, 1e-6);  // deflection to ~1e-6, far below the errors compared
  double deflection = 0;
  for (int i : tip) deflection += (x[3 * i + 2] - x_eq[3 * i + 2]) / static_cast<double>(tip.size());
  const double I = b * b * b * b / 12.0;
  const double beam = P * L * L * L / (3 * E * I);
  return std::abs(deflection - beam) / beam;
}

TEST(CorotationalFemCantilever, TipDeflectionConvergesToEulerBernoulli) {
  const double e2 = cantilever_relative_error(2);
  const double e4 = cantilever_relative_error(4);
  const double e6 = cantilever_relative_error(6);
  std::printf("cantilever relative error at 2, 4, 6 cells across: %.4f %.4f %.4f\n", e2, e4, e6);
  // Linear tets lock in bending and converge from the stiff side toward second
  // order (observed here: 1.4 from 2 to 4 cells, 1.8 from 4 to 6).
  const double order_24 = std::log(e2 / e4) / std::log(2.0);
  const double order_46 = std::log(e4 / e6) / std::log(1.5);
  EXPECT_GT(order_24, 1.2);
  EXPECT_GT(order_46, 1.5);
  EXPECT_GT(order_46, order_24);  // approaching the asymptotic rate
  EXPECT_LT(e6, 0.1);
}

}  // namespace
}  // namespace hapticd::hand
