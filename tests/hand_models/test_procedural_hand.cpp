#include "hand_models/embedded_surface.hpp"
#include "hand_models/procedural_hand.hpp"

#include <gtest/gtest.h>

#include <Eigen/Geometry>
#include <algorithm>
#include <array>
#include <cmath>
#include <map>
#include <numeric>
#include <random>
#include <stdexcept>
#include <string>

namespace hapticd::hand {
namespace {

constexpr double kCm = 0.01;
constexpr double kCm3 = 1e-6;
constexpr std::array<int, 4> kTargets = {350, 1700, 5000, 20000};

// Generation at 20k takes a noticeable fraction of a second: build each hand once.
const ProceduralHand& hand_for(int target, bool left = false) {
  static std::map<std::pair<int, bool>, ProceduralHand> cache;
  auto it = cache.find({target, left});
  if (it == cache.end()) {
    ProceduralHandOptions options;
    options.target_tets = target;
    options.left = left;
    it = cache.emplace(std::make_pair(target, left), make_procedural_hand(options)).first;
  }
  return it->second;
}

// Volume of {sdf < 0}: cubes the 1-Lipschitz bound shows to be all in or all out count whole,
// the rest split down to 1 mm and counted by the sign at their centre.
double sdf_volume_in(const Eigen::Vector3d& centre, double size) {
  const double f = procedural_hand_sdf(centre);
  const double reach = 0.8660254037844386 * size;
  if (f <= -reach) return size * size * size;
  if (f >= reach) return 0.0;
  if (size < 0.0011) return f < 0.0 ? size * size * size : 0.0;
  double v = 0.0;
  for (int c = 0; c < 8; ++c) {
    const Eigen::Vector3d offset((c & 1) ? 1.0 : -1.0, (c & 2) ? 1.0 : -1.0, (c & 4) ? 1.0 : -1.0);
    v += sdf_volume_in(centre + 0.25 * size * offset, 0.5 * size);
  }
  return v;
}

double sdf_volume() {
  static const double volume = [] {
    double v = 0.0;
    const double size = 0.016;  // 1 mm * 2^4
    for (double x = -0.12; x < 0.08; x += size) {
      for (double y = -0.06; y < 0.16; y += size) {
        for (double z = -0.04; z < 0.03; z += size) v += sdf_volume_in(Eigen::Vector3d(x, y, z), size);
      }
    }
    return v;
  }();
  return volume;
}

double skin_volume(const ProceduralHand& hand) {
  double v = 0.0;
  for (const Triangle& t : hand.skin_triangles) {
    v += hand.skin_vertices[t[0]].dot(hand.skin_vertices[t[1]].cross(hand.skin_vertices[t[2]])) / 6.0;
  }
  return v;
}

struct Box {
  Eigen::Vector3d lo = Eigen::Vector3d::Constant(1e9);
  Eigen::Vector3d hi = Eigen::Vector3d::Constant(-1e9);
  void add(const Eigen::Vector3d& p) {
    lo = lo.cwiseMin(p);
    hi = hi.cwiseMax(p);
  }
  Eigen::Vector3d size() const { return hi - lo; }
};

Box box_of(const std::vector<Eigen::Vector3d>& points) {
  Box b;
  for (const Eigen::Vector3d& p : points) b.add(p);
  return b;
}

Eigen::Vector4d barycentric(const TetMesh& mesh, int e, const Eigen::Vector3d& p) {
  const Tet& t = mesh.tets[e];
  Eigen::Matrix3d A;
  for (int k = 0; k < 3; ++k) A.col(k) = mesh.X[t[k + 1]] - mesh.X[t[0]];
  const Eigen::Vector3d w = A.inverse() * (p - mesh.X[t[0]]);
  return Eigen::Vector4d(1.0 - w.sum(), w.x(), w.y(), w.z());
}

bool inside_mesh(const TetMesh& mesh, const Eigen::Vector3d& p) {
  for (int e = 0; e < mesh.num_tets(); ++e) {
    if (barycentric(mesh, e, p).minCoeff() >= -1e-9) return true;
  }
  return false;
}

int find_root(std::vector<int>& parent, int i) {
  while (parent[i] != i) i = parent[i] = parent[parent[i]];
  return i;
}

// Components of tets joined through shared faces.
int face_connected_components(const TetMesh& mesh) {
  std::vector<int> parent(mesh.num_tets());
  std::iota(parent.begin(), parent.end(), 0);
  std::map<std::array<int, 3>, int> first_with_face;
  for (int e = 0; e < mesh.num_tets(); ++e) {
    for (int skip = 0; skip < 4; ++skip) {
      std::array<int, 3> f;
      for (int k = 0, m = 0; k < 4; ++k) {
        if (k != skip) f[m++] = mesh.tets[e][k];
      }
      std::sort(f.begin(), f.end());
      auto [it, inserted] = first_with_face.try_emplace(f, e);
      if (!inserted) parent[find_root(parent, e)] = find_root(parent, it->second);
    }
  }
  int roots = 0;
  for (int e = 0; e < mesh.num_tets(); ++e) roots += find_root(parent, e) == e ? 1 : 0;
  return roots;
}

double degrees_between(const Eigen::Vector3d& a, const Eigen::Vector3d& b) {
  return std::acos(std::clamp(a.normalized().dot(b.normalized()), -1.0, 1.0)) * 180.0 / 3.14159265358979323846;
}

TEST(ProceduralHand, TetCountIsWithinFifteenPercentOfTarget) {
  for (int target : kTargets) {
    const ProceduralHand& hand = hand_for(target);
    SCOPED_TRACE(target);
    EXPECT_NEAR(hand.mesh.num_tets(), target, 0.15 * target);
    EXPECT_EQ(hand.mesh.num_tets() % 6, 0);  // whole Kuhn cells
  }
  EXPECT_EQ(hand_for(350).spacing, hand_spacing_for_tets(350));
  // Finer target, finer grid.
  EXPECT_GT(hand_for(350).spacing, hand_for(1700).spacing);
  EXPECT_GT(hand_for(1700).spacing, hand_for(5000).spacing);
  EXPECT_GT(hand_for(5000).spacing, hand_for(20000).spacing);
}

TEST(ProceduralHand, ExplicitSpacingIsUsedAndBadOptionsThrow) {
  ProceduralHandOptions options;
  options.spacing = 0.012;
  const ProceduralHand hand = make_procedural_hand(options);
  EXPECT_EQ(hand.spacing, 0.012);
  for (const Eigen::Vector3d& x : hand.mesh.X) {
    // Nodes sit on one regular grid: every coordinate difference is a whole number of cells.
    const Eigen::Vector3d cells = (x - hand.mesh.X[0]) / 0.012;
    EXPECT_LT((cells - cells.array().round().matrix()).cwiseAbs().maxCoeff(), 1e-9);
  }
  EXPECT_THROW(hand_spacing_for_tets(0), std::invalid_argument);
  options.spacing = std::nan("");
  EXPECT_THROW(make_procedural_hand(options), std::invalid_argument);
  options.spacing = 1e-5;
  EXPECT_THROW(make_procedural_hand(options), std::invalid_argument);
  options.spacing = 0.5;
  EXPECT_THROW(make_procedural_hand(options), std::invalid_argument);
  options.spacing = 0.0;
  options.target_tets = -5;
  EXPECT_THROW(make_procedural_hand(options), std::invalid_argument);
}

TEST(ProceduralHand, MeshIsOneComponentWithoutOrphansAndHoldsEveryFinger) {
  for (int target : kTargets) {
    const ProceduralHand& hand = hand_for(target);
    SCOPED_TRACE(target);
    EXPECT_EQ(face_connected_components(hand.mesh), 1);
    std::vector<char> used(hand.mesh.num_nodes(), 0);
    for (const Tet& t : hand.mesh.tets) {
      for (int v : t) used[v] = 1;
    }
    EXPECT_EQ(std::count(used.begin(), used.end(), 0), 0);
    for (const HandFrame& f : hand.phalanges) {
      EXPECT_TRUE(inside_mesh(hand.mesh, f.p)) << f.name;
    }
    for (const auto& finger : hand.joints) {
      for (const Eigen::Vector3d& j : finger) EXPECT_TRUE(inside_mesh(hand.mesh, j));
    }
  }
}

TEST(ProceduralHand, TetsArePositiveKuhnTets) {
  for (int target : kTargets) {
    const ProceduralHand& hand = hand_for(target);
    SCOPED_TRACE(target);
    const double kuhn_volume = std::pow(hand.spacing, 3) / 6.0;
    double min_volume = 1e9;
    double max_volume = 0.0;
    for (const Tet& t : hand.mesh.tets) {
      const double v = signed_volume(hand.mesh.X[t[0]], hand.mesh.X[t[1]], hand.mesh.X[t[2]], hand.mesh.X[t[3]]);
      min_volume = std::min(min_volume, v);
      max_volume = std::max(max_volume, v);
    }
    EXPECT_GT(min_volume, 0.1 * kuhn_volume);
    EXPECT_NEAR(min_volume, kuhn_volume, 1e-9 * kuhn_volume);
    EXPECT_NEAR(max_volume, kuhn_volume, 1e-9 * kuhn_volume);
    EXPECT_FALSE(hand.mesh.surface.empty());
  }
}

TEST(ProceduralHand, SizeIsAdult) {
  for (int target : kTargets) {
    const ProceduralHand& hand = hand_for(target);
    SCOPED_TRACE(target);
    const Box skin = box_of(hand.skin_vertices);
    EXPECT_GT(skin.size().y(), 17.0 * kCm);  // wrist to middle fingertip
    EXPECT_LT(skin.size().y(), 20.0 * kCm);
    EXPECT_GT(skin.size().x(), 12.0 * kCm);  // little finger to abducted thumb
    EXPECT_LT(skin.size().x(), 17.0 * kCm);
    EXPECT_GT(skin.size().z(), 2.5 * kCm);
    EXPECT_LT(skin.size().z(), 4.5 * kCm);
    // Palm across, between the knuckles and the thumb's reach (the thumb is beyond x = -7 cm there).
    Box palm;
    for (const Eigen::Vector3d& v : hand.skin_vertices) {
      if (v.y() > 2.0 * kCm && v.y() < 3.0 * kCm && v.x() > -7.0 * kCm) palm.add(v);
    }
    EXPECT_GT(palm.size().x(), 7.5 * kCm);
    EXPECT_LT(palm.size().x(), 9.0 * kCm);
    EXPECT_GT(palm.size().z(), 2.3 * kCm);
    EXPECT_LT(palm.size().z(), 2.7 * kCm);
    // The mesh covers the skin and overhangs it by at most about a cell per side.
    const Box mesh = box_of(hand.mesh.X);
    EXPECT_TRUE((mesh.lo.array() <= skin.lo.array()).all());
    EXPECT_TRUE((mesh.hi.array() >= skin.hi.array()).all());
    EXPECT_LT((skin.lo - mesh.lo).maxCoeff(), 1.3 * hand.spacing);
    EXPECT_LT((mesh.hi - skin.hi).maxCoeff(), 1.3 * hand.spacing);
  }
}

TEST(ProceduralHand, VolumeIsAdultAndConvergesToTheSdfVolume) {
  const double v_sdf = sdf_volume();
  EXPECT_GT(v_sdf, 250.0 * kCm3);
  EXPECT_LT(v_sdf, 500.0 * kCm3);
  double previous = 1e9;
  for (int target : kTargets) {
    const double v = total_volume(hand_for(target).mesh);
    SCOPED_TRACE(target);
    EXPECT_GT(v, v_sdf);  // the cells cover the shape
    EXPECT_LT(v, previous);
    previous = v;
  }
  const double v_fine = total_volume(hand_for(20000).mesh);
  EXPECT_LT(v_fine, 500.0 * kCm3);
  EXPECT_LT(v_fine - v_sdf, 0.2 * (total_volume(hand_for(350).mesh) - v_sdf));
}

TEST(ProceduralHand, SkinIsAClosedOutwardManifold) {
  const double v_sdf = sdf_volume();
  for (int target : kTargets) {
    const ProceduralHand& hand = hand_for(target);
    SCOPED_TRACE(target);
    ASSERT_FALSE(hand.skin_triangles.empty());
    std::map<std::pair<int, int>, int> directed;
    for (const Triangle& t : hand.skin_triangles) {
      for (int k = 0; k < 3; ++k) {
        ASSERT_GE(t[k], 0);
        ASSERT_LT(t[k], static_cast<int>(hand.skin_vertices.size()));
        ++directed[{t[k], t[(k + 1) % 3]}];
      }
    }
    int bad = 0;
    for (const auto& [edge, count] : directed) {
      // Closed and consistently oriented: each edge once in each direction.
      const auto reverse = directed.find({edge.second, edge.first});
      if (count != 1 || reverse == directed.end() || reverse->second != 1) ++bad;
    }
    EXPECT_EQ(bad, 0);
    EXPECT_EQ(directed.size(), 3 * hand.skin_triangles.size());
    const double v = skin_volume(hand);
    EXPECT_GT(v, 0.0);
    EXPECT_NEAR(v, v_sdf, 0.05 * v_sdf);
    // On the zero level up to the error of linear interpolation over <= 6 mm samples (largest at creases).
    double worst = 0.0;
    double sum = 0.0;
    for (const Eigen::Vector3d& p : hand.skin_vertices) {
      const double d = std::abs(procedural_hand_sdf(p));
      worst = std::max(worst, d);
      sum += d;
    }
    EXPECT_LT(worst, 3e-3);
    EXPECT_LT(sum / static_cast<double>(hand.skin_vertices.size()), 0.3e-3);
    // No finger is missing from the skin, however coarse the mesh.
    for (const auto& finger : hand.joints) {
      double nearest = 1e9;
      for (const Eigen::Vector3d& p : hand.skin_vertices) nearest = std::min(nearest, (p - finger[3]).norm());
      EXPECT_LT(nearest, 6e-3);
    }
  }
  EXPECT_NEAR(skin_volume(hand_for(5000)), v_sdf, 0.1 * v_sdf);
}

TEST(ProceduralHand, SkinBarycentricWeightsReproduceVertices) {
  for (int target : kTargets) {
    const ProceduralHand& hand = hand_for(target);
    SCOPED_TRACE(target);
    const size_t n = hand.skin_vertices.size();
    ASSERT_EQ(hand.skin_tet.size(), n);
    ASSERT_EQ(hand.skin_bary.size(), n);
    double worst = 0.0;
    for (size_t i = 0; i < n; ++i) {
      const int e = hand.skin_tet[i];
      ASSERT_GE(e, 0);
      ASSERT_LT(e, hand.mesh.num_tets());
      const Eigen::Vector4d& w = hand.skin_bary[i];
      EXPECT_NEAR(w.sum(), 1.0, 1e-12);
      EXPECT_GE(w.minCoeff(), -1e-9);
      Eigen::Vector3d p = Eigen::Vector3d::Zero();
      for (int k = 0; k < 4; ++k) p += w[k] * hand.mesh.X[hand.mesh.tets[e][k]];
      worst = std::max(worst, (p - hand.skin_vertices[i]).norm());
    }
    EXPECT_LT(worst, 1e-12);
  }
}

TEST(ProceduralHand, LeftHandIsTheMirrorImage) {
  const ProceduralHand& right = hand_for(1700);
  const ProceduralHand& left = hand_for(1700, true);
  EXPECT_EQ(left.spacing, right.spacing);
  ASSERT_EQ(left.mesh.num_nodes(), right.mesh.num_nodes());
  ASSERT_EQ(left.mesh.num_tets(), right.mesh.num_tets());
  EXPECT_EQ(left.mesh.surface.size(), right.mesh.surface.size());
  ASSERT_EQ(left.skin_vertices.size(), right.skin_vertices.size());
  EXPECT_EQ(left.skin_triangles.size(), right.skin_triangles.size());
  const Eigen::Vector3d m(-1.0, 1.0, 1.0);
  for (int i = 0; i < left.mesh.num_nodes(); ++i) {
    EXPECT_EQ(left.mesh.X[i], right.mesh.X[i].cwiseProduct(m));
  }
  const Box bl = box_of(left.mesh.X);
  const Box br = box_of(right.mesh.X);
  EXPECT_EQ(bl.lo.x(), -br.hi.x());
  EXPECT_EQ(bl.hi.x(), -br.lo.x());
  EXPECT_EQ(bl.lo.y(), br.lo.y());
  EXPECT_EQ(bl.hi.z(), br.hi.z());
  for (const Tet& t : left.mesh.tets) {
    EXPECT_GT(signed_volume(left.mesh.X[t[0]], left.mesh.X[t[1]], left.mesh.X[t[2]], left.mesh.X[t[3]]), 0.0);
  }
  EXPECT_NEAR(total_volume(left.mesh), total_volume(right.mesh), 1e-12);
  EXPECT_NEAR(skin_volume(left), skin_volume(right), 1e-12);
  for (int k = 0; k < 4; ++k) {
    EXPECT_GT(left.joints[0][k].x(), 0.0);  // thumb on +x
    EXPECT_LT(right.joints[0][k].x(), 0.0);
  }
  for (size_t i = 0; i < left.skin_vertices.size(); ++i) {
    Eigen::Vector3d p = Eigen::Vector3d::Zero();
    for (int k = 0; k < 4; ++k) p += left.skin_bary[i][k] * left.mesh.X[left.mesh.tets[left.skin_tet[i]][k]];
    EXPECT_LT((p - left.skin_vertices[i]).norm(), 1e-12);
    EXPECT_EQ(left.skin_vertices[i], right.skin_vertices[i].cwiseProduct(m));
  }
  for (int s = 0; s < 15; ++s) {
    const HandFrame& fl = left.phalanges[s];
    const HandFrame& fr = right.phalanges[s];
    EXPECT_EQ(fl.name, fr.name);
    EXPECT_EQ(fl.p, fr.p.cwiseProduct(m));
    EXPECT_NEAR(fl.R.determinant(), 1.0, 1e-12);
    EXPECT_LT((fl.R.col(1) - fr.R.col(1).cwiseProduct(m)).norm(), 1e-15);  // bone axis mirrored
    EXPECT_LT((fl.R.col(2) - fr.R.col(2).cwiseProduct(m)).norm(), 1e-15);  // dorsal mirrored
  }
}

TEST(ProceduralHand, FramesFollowTheSkeleton) {
  const ProceduralHand& hand = hand_for(1700);
  EXPECT_EQ(hand.palm.name, "palm");
  EXPECT_EQ(hand.palm.p, Eigen::Vector3d::Zero());
  EXPECT_EQ(hand.palm.R, Eigen::Matrix3d::Identity());
  EXPECT_GT(hand.palm.radius, 0.5 * kCm);
  EXPECT_LT(procedural_hand_sdf(hand.palm.p), -hand.palm.radius);
  const std::array<std::string, 5> fingers = {"thumb", "index", "middle", "ring", "little"};
  const std::array<std::string, 3> phalanges = {"proximal", "middle", "distal"};
  for (int f = 0; f < 5; ++f) {
    EXPECT_EQ(finger_index(fingers[f]), f);
    double distance = 0.0;
    for (int k = 0; k < 4; ++k) {
      const double d = hand.joints[f][k].norm();
      EXPECT_GT(d, distance) << fingers[f] << " joint " << k;
      distance = d;
    }
    distance = 0.0;
    for (int k = 0; k < 3; ++k) {
      const HandFrame& frame = hand.phalanges[3 * f + k];
      SCOPED_TRACE(frame.name);
      EXPECT_EQ(frame.name, fingers[f] + "_" + phalanges[k]);
      EXPECT_GT(frame.p.norm(), distance);
      distance = frame.p.norm();
      EXPECT_LT((frame.R.transpose() * frame.R - Eigen::Matrix3d::Identity()).norm(), 1e-12);
      EXPECT_NEAR(frame.R.determinant(), 1.0, 1e-12);
      const Eigen::Vector3d bone = hand.joints[f][k + 1] - hand.joints[f][k];
      EXPECT_LT(degrees_between(frame.R.col(1), bone), 1e-6);
      EXPECT_LT((frame.p - 0.5 * (hand.joints[f][k] + hand.joints[f][k + 1])).norm(), 1e-12);
      EXPECT_GT(frame.R.col(2).z(), 0.5);  // dorsal side up, even for the pronated thumb
      EXPECT_GT(frame.radius, 0.3 * kCm);
      EXPECT_LT(procedural_hand_sdf(frame.p), -frame.radius);  // the handle sphere stays under the skin
    }
    // The fingertip is on the skin.
    EXPECT_NEAR(procedural_hand_sdf(hand.joints[f][3]), 0.0, 1e-9);
  }
  EXPECT_EQ(finger_index("pinky"), -1);
  EXPECT_EQ(finger_index(""), -1);
  // Long fingers point along +y, the thumb leaves the radial side near the wrist and points
  // 40-50 degrees away from the index, a little toward palmar.
  for (int f = 1; f < 5; ++f) EXPECT_GT(hand.phalanges[3 * f].R.col(1).y(), 0.9);
  const Eigen::Vector3d thumb = hand.phalanges[0].R.col(1);
  const Eigen::Vector3d index = hand.phalanges[3].R.col(1);
  EXPECT_GT(degrees_between(thumb, index), 40.0);
  EXPECT_LT(degrees_between(thumb, index), 50.0);
  EXPECT_LT(thumb.x(), -0.5);
  EXPECT_LT(thumb.z(), 0.0);
  EXPECT_GT(thumb.z(), -0.2);
  EXPECT_LT(hand.joints[0][0].y(), -2.0 * kCm);
  for (int f = 1; f < 5; ++f) EXPECT_GT(hand.joints[f][0].y(), 3.0 * kCm);
  for (int f = 1; f < 4; ++f) EXPECT_LT(hand.joints[f][0].x(), hand.joints[f + 1][0].x());
  // Middle finger is the longest: 4.5 + 3.0 + 2.2 cm.
  double middle = 0.0;
  for (int k = 0; k < 3; ++k) middle += (hand.joints[2][k + 1] - hand.joints[2][k]).norm();
  EXPECT_NEAR(middle, 9.7 * kCm, 1e-12);
}

TEST(ProceduralHand, SdfIsOneLipschitzSoTheCoverIsConservative) {
  std::mt19937 rng(7);
  std::uniform_real_distribution<double> u(-0.12, 0.16);
  std::normal_distribution<double> step(0.0, 0.01);
  double worst = 0.0;
  for (int i = 0; i < 20000; ++i) {
    const Eigen::Vector3d p(u(rng) * 0.8, u(rng), u(rng) * 0.3);
    const Eigen::Vector3d q = p + Eigen::Vector3d(step(rng), step(rng), step(rng));
    const double d = (p - q).norm();
    if (d > 0.0) worst = std::max(worst, std::abs(procedural_hand_sdf(p) - procedural_hand_sdf(q)) / d);
  }
  EXPECT_LE(worst, 1.0 + 1e-9);
  EXPECT_GT(worst, 0.9);
  EXPECT_LT(procedural_hand_sdf(Eigen::Vector3d::Zero()), -1.0 * kCm);
  EXPECT_GT(procedural_hand_sdf(Eigen::Vector3d(0.0, 0.0, 0.1)), 0.08);
  EXPECT_EQ(procedural_hand_sdf(Eigen::Vector3d(0.03, 0.05, 0.001), true),
            procedural_hand_sdf(Eigen::Vector3d(-0.03, 0.05, 0.001)));
}

TEST(ProceduralHand, EmbeddingDensityGivesTheMeshTheMassOfTheHand) {
  for (int target : {350, 1700}) {
    ProceduralHandOptions options;
    options.target_tets = target;
    const ProceduralHand hand = make_procedural_hand(options);
    const double rho = embedding_density(hand, 1070.0);
    const double skin = enclosed_volume(SurfaceMesh{hand.skin_vertices, hand.skin_triangles});
    EXPECT_NEAR(rho * total_volume(hand.mesh), 1070.0 * skin, 1e-9);
    // An adult hand weighs 0.25-0.5 kg; the covering mesh at plain density would weigh 2-5x that.
    EXPECT_GT(rho * total_volume(hand.mesh), 0.25);
    EXPECT_LT(rho * total_volume(hand.mesh), 0.5);
    EXPECT_LT(rho, 0.7 * 1070.0);
  }
}

}  // namespace
}  // namespace hapticd::hand
