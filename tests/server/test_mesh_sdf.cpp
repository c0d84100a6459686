// The mesh signed distance grid against the exact distance to a sphere.
#include <gtest/gtest.h>

#include <cmath>
#include <numbers>

#include "server/world/mesh_sdf.hpp"

namespace hapticd::world {
namespace {

// A UV sphere of radius r, outward triangles.
hand::SurfaceMesh uv_sphere(double r, int rings, int segments) {
  hand::SurfaceMesh m;
  m.vertices.push_back({0, 0, r});
  for (int i = 1; i < rings; ++i) {
    const double th = std::numbers::pi * i / rings;
    for (int j = 0; j < segments; ++j) {
      const double ph = 2 * std::numbers::pi * j / segments;
      m.vertices.push_back({r * std::sin(th) * std::cos(ph), r * std::sin(th) * std::sin(ph), r * std::cos(th)});
    }
  }
  m.vertices.push_back({0, 0, -r});
  const int south = static_cast<int>(m.vertices.size()) - 1;
  auto ring = [&](int i, int j) { return 1 + (i - 1) * segments + (j % segments); };
  for (int j = 0; j < segments; ++j) m.triangles.push_back({0, ring(1, j), ring(1, j + 1)});
  for (int i = 1; i < rings - 1; ++i)
    for (int j = 0; j < segments; ++j) {
      m.triangles.push_back({ring(i, j), ring(i + 1, j), ring(i + 1, j + 1)});
      m.triangles.push_back({ring(i, j), ring(i + 1, j + 1), ring(i, j + 1)});
    }
  for (int j = 0; j < segments; ++j) m.triangles.push_back({south, ring(rings - 1, j + 1), ring(rings - 1, j)});
  return m;
}

TEST(MeshSdf, SignedDistanceAndNormalMatchASphereWithinTheGridError) {
  const double r = 0.05, cell = 0.003;
  const hand::SurfaceMesh sphere = uv_sphere(r, 48, 96);
  const MeshSdf sdf(sphere, cell, 6);
  double worst_distance = 0, worst_normal = 0;
  int inside = 0, outside = 0;
  for (int k = 0; k < 400; ++k) {
    // Points from 1.5 cm inside to 1.5 cm outside, in every direction.
    const Eigen::Vector3d dir = Eigen::Vector3d(std::sin(1.3 * k), std::cos(2.1 * k), std::sin(0.7 * k + 1)).normalized();
    const double radius = r + 0.015 * std::sin(3.7 * k);
    double d;
    Eigen::Vector3d n;
    ASSERT_TRUE(sdf.query(radius * dir, d, n));
    worst_distance = std::max(worst_distance, std::abs(d - (radius - r)));
    worst_normal = std::max(worst_normal, (n - dir).norm());
    (radius < r ? inside : outside) += (d < 0) == (radius < r);
  }
  EXPECT_EQ(inside + outside, 400);  // the sign is right everywhere
  // Trilinear interpolation of a curved distance on 3 mm cells, plus the facets (sagitta ~0.1 mm).
  EXPECT_LT(worst_distance, 0.5e-3);
  EXPECT_LT(worst_normal, 0.1);
  double d;
  Eigen::Vector3d n;
  EXPECT_FALSE(sdf.query(Eigen::Vector3d(1, 0, 0), d, n));  // outside the grid: no contact
  // Inside the grid but beyond the exact band (1.8 cm): no answer. The clamped field answered 1.8 cm
  // with any normal there (-z at points 1.8 cm beside the bunny, which gave the spring hand's stylus
  // rows pulling it down).
  const Eigen::Vector3d diagonal = Eigen::Vector3d::Ones().normalized();
  EXPECT_TRUE(sdf.query((r + 0.012) * diagonal, d, n));
  EXPECT_NEAR(d, 0.012, 0.5e-3);
  EXPECT_FALSE(sdf.query((r + 0.019) * diagonal, d, n));
  EXPECT_FALSE(sdf.query(Eigen::Vector3d(r + 0.019, 0, 0), d, n));
}

}  // namespace
}  // namespace hapticd::world
