#include <gtest/gtest.h>

#include "file_test_util.hpp"
#include <unistd.h>

#include <Eigen/LU>
#include <algorithm>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <functional>
#include <map>
#include <random>
#include <stdexcept>
#include <string>
#include <vector>

#include "hand_models/box_mesh.hpp"
#include "hand_models/embedded_surface.hpp"
#include "hand_models/mesh_io.hpp"

namespace hapticd::hand {
namespace {

namespace fs = std::filesystem;
using Eigen::Vector3d;

const std::string kAssets = std::string(HAPTICD_TEST_DATA) + "/../../scenes/assets/";
constexpr double kPi = 3.14159265358979323846;

SurfaceMesh unit_cube_surface(const Vector3d& origin = Vector3d::Zero()) {
  const TetMesh box = make_box_mesh({1, 1, 1}, {1, 1, 1}, origin);
  return SurfaceMesh{box.X, box.surface};
}

// Icosahedron subdivided `levels` times, vertices projected onto the sphere; outward.
SurfaceMesh icosphere(double radius, int levels, const Vector3d& centre = Vector3d::Zero()) {
  const double t = (1.0 + std::sqrt(5.0)) / 2.0;
  std::vector<Vector3d> v = {{-1, t, 0}, {1, t, 0}, {-1, -t, 0}, {1, -t, 0}, {0, -1, t}, {0, 1, t},
                             {0, -1, -t}, {0, 1, -t}, {t, 0, -1}, {t, 0, 1}, {-t, 0, -1}, {-t, 0, 1}};
  std::vector<Triangle> f = {{0, 11, 5}, {0, 5, 1},  {0, 1, 7},   {0, 7, 10}, {0, 10, 11}, {1, 5, 9}, {5, 11, 4},
                             {11, 10, 2}, {10, 7, 6}, {7, 1, 8},  {3, 9, 4},  {3, 4, 2},   {3, 2, 6}, {3, 6, 8},
                             {3, 8, 9},  {4, 9, 5},  {2, 4, 11}, {6, 2, 10}, {8, 6, 7},   {9, 8, 1}};
  for (Vector3d& p : v) p.normalize();
  for (int l = 0; l < levels; ++l) {
    std::map<std::pair<int, int>, int> mid;
    auto midpoint = [&](int a, int b) {
      const auto key = std::minmax(a, b);
      auto [it, inserted] = mid.try_emplace(key, static_cast<int>(v.size()));
      if (inserted) v.push_back((v[a] + v[b]).normalized());
      return it->second;
    };
    std::vector<Triangle> next;
    for (const Triangle& tri : f) {
      const int ab = midpoint(tri[0], tri[1]), bc = midpoint(tri[1], tri[2]), ca = midpoint(tri[2], tri[0]);
      next.insert(next.end(), {{tri[0], ab, ca}, {tri[1], bc, ab}, {tri[2], ca, bc}, {ab, bc, ca}});
    }
    f = std::move(next);
  }
  for (Vector3d& p : v) p = centre + radius * p;
  return SurfaceMesh{v, f};
}

SurfaceMesh merged(const SurfaceMesh& a, const SurfaceMesh& b) {
  SurfaceMesh s = a;
  const int offset = static_cast<int>(a.vertices.size());
  s.vertices.insert(s.vertices.end(), b.vertices.begin(), b.vertices.end());
  for (const Triangle& t : b.triangles) s.triangles.push_back({t[0] + offset, t[1] + offset, t[2] + offset});
  return s;
}

Eigen::Vector4d barycentric(const TetMesh& m, const Tet& t, const Vector3d& p) {
  Eigen::Matrix3d A;
  A << m.X[t[1]] - m.X[t[0]], m.X[t[2]] - m.X[t[0]], m.X[t[3]] - m.X[t[0]];
  const Vector3d l = A.partialPivLu().solve(p - m.X[t[0]]);
  return {1.0 - l.sum(), l[0], l[1], l[2]};
}

bool covered(const TetMesh& m, const Vector3d& p) {
  for (const Tet& t : m.tets) {
    if (barycentric(m, t, p).minCoeff() >= -1e-9) return true;
  }
  return false;
}

// Every undirected edge in exactly two triangles, once in each direction.
testing::AssertionResult closed_and_consistent(const SurfaceMesh& s) {
  std::map<std::pair<int, int>, int> directed;
  for (const Triangle& t : s.triangles) {
    for (int k = 0; k < 3; ++k) ++directed[{t[k], t[(k + 1) % 3]}];
  }
  for (const auto& [edge, n] : directed) {
    const auto back = directed.find({edge.second, edge.first});
    if (n != 1 || back == directed.end() || back->second != 1) {
      return testing::AssertionFailure() << "edge " << edge.first << "-" << edge.second << " used " << n
                                         << " times, reverse " << (back == directed.end() ? 0 : back->second);
    }
  }
  return testing::AssertionSuccess();
}

// Weights valid, in range and reproducing every surface vertex.
void expect_valid_embedding(const EmbeddedBody& b, double tolerance) {
  ASSERT_EQ(b.surface_tet.size(), b.surface.vertices.size());
  ASSERT_EQ(b.surface_bary.size(), b.surface.vertices.size());
  double worst = 0.0;
  for (std::size_t v = 0; v < b.surface.vertices.size(); ++v) {
    const int e = b.surface_tet[v];
    ASSERT_GE(e, 0);
    ASSERT_LT(e, b.mesh.num_tets());
    const Eigen::Vector4d& w = b.surface_bary[v];
    EXPECT_GE(w.minCoeff(), -1e-9) << "vertex " << v;
    EXPECT_NEAR(w.sum(), 1.0, 1e-12) << "vertex " << v;
    Vector3d x = Vector3d::Zero();
    for (int k = 0; k < 4; ++k) x += w[k] * b.mesh.X[b.mesh.tets[e][k]];
    worst = std::max(worst, (x - b.surface.vertices[v]).norm());
  }
  EXPECT_LE(worst, tolerance);
}

// Kuhn tets of cubes of edge h all have volume h^3 / 6 and positive orientation.
void expect_grid_tets(const TetMesh& m, double h) {
  for (const Tet& t : m.tets) {
    EXPECT_NEAR(signed_volume(m.X[t[0]], m.X[t[1]], m.X[t[2]], m.X[t[3]]), h * h * h / 6, 1e-9 * h * h * h);
  }
}

double height(const SurfaceMesh& s) {
  double lo = INFINITY, hi = -INFINITY;
  for (const Vector3d& p : s.vertices) {
    lo = std::min(lo, p.z());
    hi = std::max(hi, p.z());
  }
  return hi - lo;
}

// ---- enclosed volume ----

TEST(EnclosedVolume, UnitCubeIsOne) {
  EXPECT_NEAR(enclosed_volume(unit_cube_surface()), 1.0, 1e-12);
  // Far from the origin too: no cancellation between large per-triangle terms.
  EXPECT_NEAR(enclosed_volume(unit_cube_surface(Vector3d(1e3, -2e3, 5e2))), 1.0, 1e-12);
}

TEST(EnclosedVolume, InwardSurfaceIsNegative) {
  SurfaceMesh s = unit_cube_surface();
  for (Triangle& t : s.triangles) std::swap(t[1], t[2]);
  EXPECT_NEAR(enclosed_volume(s), -1.0, 1e-12);
}

TEST(EnclosedVolume, IcosphereApproachesBall) {
  const double r = 0.05;
  const double ball = 4.0 / 3.0 * kPi * r * r * r;
  const double v3 = enclosed_volume(icosphere(r, 3, Vector3d(0.3, -0.1, 0.2)));
  const double v4 = enclosed_volume(icosphere(r, 4, Vector3d(0.3, -0.1, 0.2)));
  // Inscribed polyhedra: slightly below the ball, closer when finer.
  EXPECT_LT(v3, v4);
  EXPECT_LT(v4, ball);
  EXPECT_NEAR(v4 / ball, 1.0, 3e-3);
}

// ---- embedding ----

TEST(EmbedSurface, SphereIsReproducedAndCovered) {
  const SurfaceMesh sphere = icosphere(0.05, 3, Vector3d(0.01, -0.02, 0.1));
  const EmbeddedBody b = embed_surface(sphere, 300);
  EXPECT_NEAR(b.mesh.num_tets(), 300, 0.15 * 300);
  EXPECT_EQ(b.surface.vertices, sphere.vertices);
  EXPECT_EQ(b.surface.triangles, sphere.triangles);
  EXPECT_FALSE(b.mesh.surface.empty());
  expect_grid_tets(b.mesh, b.spacing);
  expect_valid_embedding(b, 1e-12);
  // Triangle interiors and edges, and the solid, are covered, not just the vertices.
  for (const Triangle& t : sphere.triangles) {
    const Vector3d& a = sphere.vertices[t[0]];
    const Vector3d& c = sphere.vertices[t[1]];
    const Vector3d& d = sphere.vertices[t[2]];
    EXPECT_TRUE(covered(b.mesh, (a + c + d) / 3));
    EXPECT_TRUE(covered(b.mesh, (a + c) / 2));
  }
  std::mt19937 rng(7);
  std::uniform_real_distribution<double> u(-0.05, 0.05);
  for (int i = 0; i < 500; ++i) {
    const Vector3d p(u(rng), u(rng), u(rng));
    if (p.norm() < 0.049) {
      EXPECT_TRUE(covered(b.mesh, Vector3d(0.01, -0.02, 0.1) + p)) << p.transpose();
    }
  }
}

TEST(EmbedSurface, TetCountFollowsTarget) {
  const SurfaceMesh sphere = icosphere(0.05, 2);
  for (int target : {60, 271, 1000, 5000}) {
    const EmbeddedBody b = embed_surface(sphere, target);
    EXPECT_NEAR(b.mesh.num_tets(), target, 0.15 * target) << "target " << target;
    expect_valid_embedding(b, 1e-12);
  }
  // A single cell when little is asked for.
  EXPECT_EQ(embed_surface(sphere, 1).mesh.num_tets(), 6);
}

TEST(EmbedSurface, SolidInteriorIsFilled) {
  // Fine grid: cells far inside the sphere are kept through the winding number, not the surface.
  const SurfaceMesh sphere = icosphere(0.05, 3);
  const EmbeddedBody b = embed_surface_with_spacing(sphere, 0.005);
  EXPECT_TRUE(covered(b.mesh, Vector3d::Zero()));
  EXPECT_GT(total_volume(b.mesh), enclosed_volume(sphere));
  EXPECT_EQ(b.spacing, 0.005);
  expect_grid_tets(b.mesh, 0.005);
  expect_valid_embedding(b, 1e-12);
}

TEST(EmbedSurface, SurfaceOnGridPlanesIsEmbedded) {
  // The grid starts (0.37, 0.21, 0.43) h below the box's low corner, so h = 1 / (k - f) puts the unit
  // cube's far faces on grid planes; the (1 +- 1e-13) variants put them within rounding of one.
  std::vector<double> spacings = {0.25, 1.0, 3.0};
  for (double f : {0.37, 0.21, 0.43}) {
    for (int k = 1; k <= 4; ++k) {
      for (double scale : {1.0, 1.0 + 1e-13, 1.0 - 1e-13}) spacings.push_back(scale / (k - f));
    }
  }
  for (double h : spacings) {
    const EmbeddedBody b = embed_surface_with_spacing(unit_cube_surface(), h);
    SCOPED_TRACE("h " + std::to_string(h));
    expect_valid_embedding(b, 1e-12);
    EXPECT_GE(total_volume(b.mesh), 1.0 - 1e-12);
  }
}

TEST(EmbedSurface, RejectsBadInput) {
  const SurfaceMesh sphere = icosphere(0.05, 1);
  EXPECT_THROW(embed_surface(sphere, 0), std::invalid_argument);
  EXPECT_THROW(embed_surface_with_spacing(sphere, 0.0), std::invalid_argument);
  EXPECT_THROW(embed_surface_with_spacing(sphere, NAN), std::invalid_argument);
  EXPECT_THROW(embed_surface_with_spacing(sphere, 1e-6), std::invalid_argument);  // ~10^15 cells
  EXPECT_THROW(embed_surface(SurfaceMesh{}, 100), MeshError);
  SurfaceMesh bad = sphere;
  bad.triangles[3][1] = static_cast<int>(bad.vertices.size());
  EXPECT_THROW(embed_surface(bad, 100), MeshError);
  bad = sphere;
  bad.vertices[2].x() = NAN;
  EXPECT_THROW(embed_surface(bad, 100), MeshError);
  bad = sphere;
  bad.triangles[0][2] = bad.triangles[0][0];
  EXPECT_THROW(embed_surface(bad, 100), MeshError);
}

TEST(EmbedSurface, SeparatePartsAreRejected) {
  // Two spheres 1 m apart: only the larger grid component survives, the other's vertices are uncovered.
  const SurfaceMesh two = merged(icosphere(0.05, 1), icosphere(0.04, 1, Vector3d(1, 0, 0)));
  try {
    embed_surface_with_spacing(two, 0.02);
    FAIL() << "no MeshError";
  } catch (const MeshError& e) {
    EXPECT_NE(std::string(e.what()).find("outside the kept cells"), std::string::npos) << e.what();
  }
}

// ---- shipped assets ----

TEST(Assets, BunnyIsClosedOutwardAndTwelveCentimetresTall) {
  const SurfaceMesh bunny = load_obj(kAssets + "bunny.obj");
  EXPECT_EQ(bunny.triangles.size(), 3674u);
  EXPECT_EQ(bunny.vertices.size(), 1839u);
  EXPECT_TRUE(closed_and_consistent(bunny));
  const double volume = enclosed_volume(bunny);
  EXPECT_GT(volume, 0.0);
  EXPECT_NEAR(volume, 3.73e-4, 0.05e-4);
  EXPECT_NEAR(height(bunny), 0.12, 1e-6);
  Vector3d lo = Vector3d::Constant(INFINITY), hi = -lo;
  for (const Vector3d& p : bunny.vertices) {
    lo = lo.cwiseMin(p);
    hi = hi.cwiseMax(p);
  }
  EXPECT_EQ(lo.z(), 0.0);
  EXPECT_NEAR(lo.x() + hi.x(), 0.0, 1e-6);
  EXPECT_NEAR(lo.y() + hi.y(), 0.0, 1e-6);
}

TEST(Assets, Bunny271MeshAndEmbeddingMatch) {
  const TetMesh mesh = load_tet_mesh(kAssets + "bunny_271");
  EXPECT_NEAR(mesh.num_tets(), 271, 0.15 * 271);
  const EmbeddedBody b = load_embedded_body(kAssets + "bunny.obj", kAssets + "bunny_271", kAssets + "bunny_271.embed");
  EXPECT_EQ(b.mesh.num_tets(), mesh.num_tets());
  EXPECT_GT(b.spacing, 0.0);
  expect_grid_tets(b.mesh, b.spacing);
  expect_valid_embedding(b, 1e-9);
}

TEST(Assets, LettersAreClosedAndEmbedded) {
  for (const char* letter : {"h", "a", "p"}) {
    SCOPED_TRACE(letter);
    const std::string base = kAssets + "letter_" + letter;
    const SurfaceMesh s = load_obj(base + ".obj");
    EXPECT_GE(s.triangles.size(), 100u);
    EXPECT_LE(s.triangles.size(), 200u);
    EXPECT_TRUE(closed_and_consistent(s));
    EXPECT_GT(enclosed_volume(s), 0.0);
    EXPECT_NEAR(height(s), 0.04, 1e-9);
    const EmbeddedBody b = load_embedded_body(base + ".obj", base + "_65", base + "_65.embed");
    EXPECT_NEAR(b.mesh.num_tets(), 65, 0.25 * 65);
    expect_grid_tets(b.mesh, b.spacing);
    expect_valid_embedding(b, 1e-9);
  }
}

// ---- files ----

class EmbeddedFilesTest : public testing_util::TempDirTest {};

using testing_util::throws_mesh_error;

TEST_F(EmbeddedFilesTest, ObjFormsAreRead) {
  const std::string path = write("forms.obj",
                                 "# a unit square pyramid\n"
                                 "o pyramid\n"
                                 "v 0 0 0\n"
                                 "v 1 0 0 1.0\n"
                                 "v 1 1 0 0.5 0.5 0.5\n"
                                 "v 0 1 0\n"
                                 "vt 0 0\n"
                                 "vn 0 0 1\n"
                                 "v +0.5 0.5 1e0  # apex\n"
                                 "f 1/1/1 4/1/1 3/1/1 2/1/1\n"
                                 "f 1//1 2//1 5//1\n"
                                 "f 2/1 3/1 5/1\n"
                                 "f -2 -1 -3\n"
                                 "f 4 1 5\r\n");
  const SurfaceMesh s = load_obj(path);
  ASSERT_EQ(s.vertices.size(), 5u);
  EXPECT_EQ(s.vertices[4], Vector3d(0.5, 0.5, 1.0));
  ASSERT_EQ(s.triangles.size(), 6u);  // the base quad is fan-split
  EXPECT_EQ(s.triangles[0], (Triangle{0, 3, 2}));
  EXPECT_EQ(s.triangles[1], (Triangle{0, 2, 1}));
  EXPECT_EQ(s.triangles[4], (Triangle{3, 4, 2}));
  EXPECT_TRUE(closed_and_consistent(s));
  EXPECT_NEAR(enclosed_volume(s), 1.0 / 3.0, 1e-15);
}

TEST_F(EmbeddedFilesTest, ObjForwardReferencesAreAllowed) {
  const SurfaceMesh s = load_obj(write("forward.obj", "f 1 2 3\nv 0 0 0\nv 1 0 0\nv 0 1 0\n"));
  EXPECT_EQ(s.triangles.size(), 1u);
}

TEST_F(EmbeddedFilesTest, ObjRoundTripIsExact) {
  const SurfaceMesh sphere = icosphere(0.0123, 2, Vector3d(0.1, 1.0 / 3.0, -0.7));
  const std::string path = (dir_ / "sphere.obj").string();
  save_obj(path, sphere);
  const SurfaceMesh back = load_obj(path);
  EXPECT_EQ(back.vertices, sphere.vertices);
  EXPECT_EQ(back.triangles, sphere.triangles);
}

TEST_F(EmbeddedFilesTest, ObjErrorsNameFileLineAndProblem) {
  const std::string head = "v 0 0 0\nv 1 0 0\nv 0 1 0\n";
  std::string p = write("word.obj", head + "v 0 zero 1\nf 1 2 3\n");
  EXPECT_TRUE(throws_mesh_error([&] { load_obj(p); }, p, 4, "'zero' is not a number"));
  p = write("nan.obj", head + "v 0 0 nan\nf 1 2 3\n");
  EXPECT_TRUE(throws_mesh_error([&] { load_obj(p); }, p, 4, "is not a finite number"));
  p = write("inf.obj", "v 0 0 0\n\nv 1 -inf 0\nf 1 2 3\n");
  EXPECT_TRUE(throws_mesh_error([&] { load_obj(p); }, p, 3, "is not a finite number"));
  p = write("short_vertex.obj", head + "v 1 2\nf 1 2 3\n");
  EXPECT_TRUE(throws_mesh_error([&] { load_obj(p); }, p, 4, "vertex needs 3 coordinates"));
  p = write("high.obj", head + "f 1 2 3\n# fine so far\nf 1 2 4\n");
  EXPECT_TRUE(throws_mesh_error([&] { load_obj(p); }, p, 6, "vertex index 4 is out of range"));
  p = write("relative.obj", head + "f -1 -2 -4\n");
  EXPECT_TRUE(throws_mesh_error([&] { load_obj(p); }, p, 4, "'-4' is out of range"));
  p = write("zero.obj", head + "f 0 1 2\n");
  EXPECT_TRUE(throws_mesh_error([&] { load_obj(p); }, p, 4, "'0' is out of range"));
  p = write("bad_index.obj", head + "f 1 2/7 x3\n");
  EXPECT_TRUE(throws_mesh_error([&] { load_obj(p); }, p, 4, "'x3' is not an integer"));
  p = write("two.obj", head + "f 1 2\n");
  EXPECT_TRUE(throws_mesh_error([&] { load_obj(p); }, p, 4, "face needs at least 3 vertices, found 2"));
  p = write("repeat.obj", head + "f 1 2 -3\n");
  EXPECT_TRUE(throws_mesh_error([&] { load_obj(p); }, p, 4, "repeats a vertex"));
  p = write("no_faces.obj", head + "# only vertices\n");
  EXPECT_TRUE(throws_mesh_error([&] { load_obj(p); }, p, 4, "no faces"));
  p = write("empty.obj", "");
  EXPECT_TRUE(throws_mesh_error([&] { load_obj(p); }, p, 0, "no faces"));
  p = (dir_ / "missing.obj").string();
  EXPECT_TRUE(throws_mesh_error([&] { load_obj(p); }, p, 0, "cannot open file"));
  p = dir_.string();
  EXPECT_TRUE(throws_mesh_error([&] { load_obj(p); }, p, 0, "it is a directory"));
  p = write("binary.obj", std::string(70000, '\0'));
  EXPECT_TRUE(throws_mesh_error([&] { load_obj(p); }, p, 1, "more than 65536 characters"));
}

TEST_F(EmbeddedFilesTest, EmbeddingRoundTripIsExact) {
  const EmbeddedBody b = embed_surface(icosphere(0.05, 2), 200);
  const std::string path = (dir_ / "sphere.embed").string();
  save_embedding(path, b);
  const EmbeddedBody back = load_embedding(path, b.mesh, b.surface);
  EXPECT_EQ(back.surface_tet, b.surface_tet);
  EXPECT_EQ(back.surface_bary, b.surface_bary);
  EXPECT_EQ(back.spacing, b.spacing);
  EXPECT_EQ(back.mesh.tets, b.mesh.tets);
  EXPECT_EQ(back.surface.vertices, b.surface.vertices);
}

TEST_F(EmbeddedFilesTest, EmbeddingErrorsNameFileLineAndProblem) {
  // Unit cube mesh (6 tets) with a 3-vertex "surface": vertex 0 at a corner, 1 and 2 inside tet 0 = (0, 1, 3, 7).
  const TetMesh cube = make_box_mesh({1, 1, 1}, {1, 1, 1});
  const SurfaceMesh s{{Vector3d(0, 0, 0), Vector3d(0.75, 0.5, 0.25), Vector3d(0.5, 0.25, 0.25)}, {{0, 1, 2}}};
  const std::string head = "hapticd-embedding 1\n3 6 1  # vertices tets spacing\n";
  const std::string good = head + "0 1 0 0 0\n0 0.25 0.25 0.25 0.25\n0 0.5 0.25 0 0.25\n";
  // Check the fixture itself: tet 0's nodes are corners 0, 1, 3, 7.
  ASSERT_EQ(cube.tets[0], (Tet{0, 1, 3, 7}));
  EXPECT_NO_THROW(load_embedding(write("good.embed", good), cube, s));

  auto expect_error = [&](const std::string& name, const std::string& text, long long line, const std::string& phrase) {
    const std::string p = write(name, text);
    EXPECT_TRUE(throws_mesh_error([&] { load_embedding(p, cube, s); }, p, line, phrase)) << name;
  };
  expect_error("header.embed", "hapticd-embedding 2\n", 1, "expected header 'hapticd-embedding 1'");
  expect_error("empty.embed", "", 0, "expected header");
  expect_error("counts.embed", "hapticd-embedding 1\n3 6\n", 2, "expected '<surface vertices> <tets> <spacing>'");
  expect_error("vertices.embed", "hapticd-embedding 1\n4 6 1\n", 2, "file is for 4 surface vertices");
  expect_error("tets.embed", "hapticd-embedding 1\n3 5 1\n", 2, "file is for 5 tets, the mesh has 6");
  expect_error("spacing.embed", "hapticd-embedding 1\n3 6 -1\n", 2, "is not positive");
  expect_error("tet_range.embed", head + "6 1 0 0 0\n", 3, "tet '6' is out of range");
  expect_error("weight_nan.embed", head + "0 1 0 0 nan\n", 3, "is not a finite number");
  expect_error("weight_negative.embed", head + "0 1.1 -0.1 0 0\n", 3, "is negative");
  expect_error("weight_sum.embed", head + "0 1 0 0 0.001\n", 3, "weights sum to");
  expect_error("fields.embed", head + "0 1 0 0\n", 3, "expected '<tet> <w0> <w1> <w2> <w3>'");
  expect_error("position.embed", head + "0 0 1 0 0\n", 3, "weights place surface vertex 0");
  expect_error("missing.embed", head + "0 1 0 0 0\n0 0.25 0.25 0.25 0.25\n", 4, "found end of file");
  expect_error("extra.embed", good + "0 1 0 0 0\n", 6, "expected end of file");
  const std::string missing = (dir_ / "none.embed").string();
  EXPECT_TRUE(throws_mesh_error([&] { load_embedding(missing, cube, s); }, missing, 0, "cannot open file"));
}

}  // namespace
}  // namespace hapticd::hand
