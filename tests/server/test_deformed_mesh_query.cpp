// The hand-vs-deformable query against closed forms: a cube, undeformed and
// affinely deformed (x = A X + b), whose faces stay planes with normal
// A^-T n_rest and whose distances scale by 1 / |A^-T n_rest|; point location
// checked against a brute-force search over every tet.
#include <gtest/gtest.h>

#include <Eigen/LU>
#include <cmath>
#include <random>

#include "hand_models/box_mesh.hpp"
#include "server/world/deformed_mesh_query.hpp"

namespace hapticd::world {
namespace {

constexpr double kHalf = 0.02;  // the cube is [-2 cm, 2 cm]^3

hand::TetMesh cube_mesh() {
  return hand::make_box_mesh({2 * kHalf, 2 * kHalf, 2 * kHalf}, {4, 4, 4}, -Eigen::Vector3d::Constant(kHalf));
}

hand::SurfaceMesh boundary(const hand::TetMesh& mesh) { return hand::SurfaceMesh{mesh.X, mesh.surface}; }

Eigen::VectorXd deformed(const hand::TetMesh& mesh, const Eigen::Matrix3d& A, const Eigen::Vector3d& b) {
  Eigen::VectorXd x(3 * mesh.num_nodes());
  for (int i = 0; i < mesh.num_nodes(); ++i) x.segment<3>(3 * i) = A * mesh.X[i] + b;
  return x;
}

// Rest points near each face (depth -4..+1.5 mm, > 8 mm from the face's edges,
// so that face alone is nearest and the distance grid is exact there), with
// their face's outward normal and signed depth.
struct Probe {
  Eigen::Vector3d X, n;
  double depth;
};
std::vector<Probe> probes() {
  std::vector<Probe> out;
  for (int axis = 0; axis < 3; ++axis)
    for (double sign : {-1.0, 1.0})
      for (double depth : {-0.0015, -0.0004, 0.0003, 0.002, 0.004})
        for (double u : {-0.011, 0.0, 0.0073})
          for (double v : {-0.009, 0.0052, 0.011}) {
            Eigen::Vector3d X;
            X[axis] = sign * (kHalf - depth);
            X[(axis + 1) % 3] = u;
            X[(axis + 2) % 3] = v;
            out.push_back({X, sign * Eigen::Vector3d::Unit(axis), depth});
          }
  return out;
}

void expect_closed_form(const Eigen::Matrix3d& A, const Eigen::Vector3d& b) {
  const hand::TetMesh mesh = cube_mesh();
  // 1 mm cells, exact within 6 mm of the surface.
  DeformedMeshQuery query(mesh, boundary(mesh), 0.001, 6);
  query.update(deformed(mesh, A, b));
  const Eigen::Matrix3d A_inv_T = A.inverse().transpose();
  for (const Probe& probe : probes()) {
    const Eigen::Vector3d p = A * probe.X + b;
    const Eigen::Vector3d n = A_inv_T * probe.n;
    const double expected_depth = probe.depth / n.norm();
    MeshPenetration pen;
    ASSERT_TRUE(query.penetration(p, 0.002, pen)) << "rest point " << probe.X.transpose();
    // 1e-12 m: the distance field is linear near a face, so its trilinear
    // interpolation is exact up to rounding, and so is its affine image.
    EXPECT_NEAR(pen.depth_m, expected_depth, 1e-12) << "rest point " << probe.X.transpose();
    EXPECT_LT((pen.n_W - n.normalized()).norm(), 1e-9) << "rest point " << probe.X.transpose();
    EXPECT_LT((pen.p_rest - probe.X).norm(), 1e-12);
    Eigen::Vector3d back = Eigen::Vector3d::Zero();
    const hand::Tet& t = mesh.tets[pen.tet];
    for (int k = 0; k < 4; ++k) back += pen.bary[k] * (A * mesh.X[t[k]] + b);
    EXPECT_LT((back - p).norm(), 1e-12);
  }
  // Beyond the margin, and far away, nothing.
  MeshPenetration pen;
  EXPECT_FALSE(query.penetration(A * Eigen::Vector3d(0, 0, kHalf + 0.003) + b, 0.002, pen));
  EXPECT_FALSE(query.penetration(A * Eigen::Vector3d(0, 0, kHalf + 0.0015) + b, 0.0, pen));
  EXPECT_FALSE(query.penetration(A * Eigen::Vector3d(0.5, 0, 0) + b, 0.002, pen));
}

TEST(DeformedMeshQuery, UndeformedCubeGivesTheDistanceToTheNearestFace) {
  expect_closed_form(Eigen::Matrix3d::Identity(), Eigen::Vector3d::Zero());
}

TEST(DeformedMeshQuery, AffinelyDeformedCubeGivesTheDistanceToTheMappedFacePlanes) {
  // Stretched 30 % along x, squashed 20 % along z, sheared, turned and moved.
  Eigen::Matrix3d S;
  S << 1.3, 0.15, 0.0, 0.0, 1.0, -0.1, 0.05, 0.0, 0.8;
  const Eigen::Matrix3d R = Eigen::AngleAxisd(0.6, Eigen::Vector3d(1, -2, 0.5).normalized()).toRotationMatrix();
  ASSERT_GT(S.determinant(), 0);
  expect_closed_form(R * S, Eigen::Vector3d(0.3, -0.1, 0.7));
}

TEST(DeformedMeshQuery, LocatesEveryPointLikeABruteForceSearch) {
  const hand::TetMesh mesh = cube_mesh();
  DeformedMeshQuery query(mesh, boundary(mesh), 0.002, 3);
  // A non-affine deformation: each node pushed by a smooth field.
  Eigen::VectorXd x(3 * mesh.num_nodes());
  for (int i = 0; i < mesh.num_nodes(); ++i) {
    const Eigen::Vector3d& X = mesh.X[i];
    x.segment<3>(3 * i) = X + 0.004 * Eigen::Vector3d(std::sin(80 * X.y()), std::cos(60 * X.z()), std::sin(70 * X.x()));
  }
  query.update(x);
  std::mt19937 rng(7);
  std::uniform_real_distribution<double> coordinate(-0.03, 0.03);
  int inside = 0;
  for (int k = 0; k < 3000; ++k) {
    const Eigen::Vector3d p(coordinate(rng), coordinate(rng), coordinate(rng));
    double brute_best = -1e300;
    for (const hand::Tet& t : mesh.tets) {
      Eigen::Matrix3d Ds;
      const Eigen::Vector3d x0 = x.segment<3>(3 * t[0]);
      Ds << x.segment<3>(3 * t[1]) - x0, x.segment<3>(3 * t[2]) - x0, x.segment<3>(3 * t[3]) - x0;
      const Eigen::Vector3d w = Ds.inverse() * (p - x0);
      brute_best = std::max(brute_best, std::min(1 - w.sum(), w.minCoeff()));
    }
    int tet = -1;
    Eigen::Vector4d bary;
    const bool found = query.locate(p, tet, bary);
    if (brute_best >= 0) {
      ++inside;
      ASSERT_TRUE(found) << p.transpose();
      // 1e-12: on a shared face either tet will do; the point is inside the one found.
      EXPECT_GE(bary.minCoeff(), -1e-12) << p.transpose();
    }
    if (found) {
      EXPECT_NEAR(bary.sum(), 1.0, 1e-12);
      Eigen::Vector3d back = Eigen::Vector3d::Zero();
      for (int j = 0; j < 4; ++j) back += bary[j] * x.segment<3>(3 * mesh.tets[tet][j]);
      EXPECT_LT((back - p).norm(), 1e-12);
      EXPECT_GE(bary.minCoeff(), -DeformedMeshQuery::kBarycentricSlack);
    }
  }
  EXPECT_GT(inside, 500);  // the sample did cover the body
}

}  // namespace
}  // namespace hapticd::world
