#include "hand_models/procedural_hand.hpp"

#include "hand_models/cell_grid.hpp"
#include "hand_models/embedded_surface.hpp"
#include "hand_models/skeleton/hand_skeleton.hpp"

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <stdexcept>
#include <unordered_map>
#include <vector>

namespace hapticd::hand {
namespace {

using Eigen::Vector3d;
using Eigen::Vector3i;
using detail::CellGrid;
using detail::cube_corner;

constexpr double kCm = 0.01;
constexpr double kPi = 3.14159265358979323846;
constexpr double kHalfDiagonal = 0.86602540378443864676;  // sqrt(3)/2: centre-to-corner distance of a unit cube

double sign(double x) { return x > 0.0 ? 1.0 : (x < 0.0 ? -1.0 : 0.0); }

// Tapered capsule: convex hull of a sphere (a, ra) and a sphere (b, rb); exact SDF (Quilez's round cone).
struct RoundCone {
  Vector3d a, b;
  double ra, rb;
  Vector3d ba;
  double l2, rr, a2, il2;
  Vector3d centre;   // of a ball containing the cone: the SDF is at least |p - centre| - bound
  double bound;

  RoundCone() = default;
  RoundCone(const Vector3d& a_in, const Vector3d& b_in, double ra_in, double rb_in)
      : a(a_in), b(b_in), ra(ra_in), rb(rb_in), ba(b_in - a_in) {
    l2 = ba.squaredNorm();
    rr = ra - rb;
    a2 = l2 - rr * rr;
    il2 = 1.0 / l2;
    centre = 0.5 * (a + b);
    bound = 0.5 * std::sqrt(l2) + std::max(ra, rb);
  }

  double sdf(const Vector3d& p) const {
    const Vector3d pa = p - a;
    const double y = pa.dot(ba);
    const double z = y - l2;
    const double x2 = (pa * l2 - ba * y).squaredNorm();
    const double y2 = y * y * l2;
    const double z2 = z * z * l2;
    const double k = sign(rr) * rr * rr * x2;
    if (sign(z) * a2 * z2 > k) return std::sqrt(x2 + z2) * il2 - rb;
    if (sign(y) * a2 * y2 < k) return std::sqrt(x2 + y2) * il2 - ra;
    return (std::sqrt(x2 * a2 * il2) + y * rr) * il2 - ra;
  }
};

// Exact 2D SDF of an isosceles trapezoid: half width r1 at y = -he, r2 at y = +he.
double sd_trapezoid(double px, double py, double r1, double r2, double he) {
  const Eigen::Vector2d k1(r2, he);
  const Eigen::Vector2d k2(r2 - r1, 2.0 * he);
  const Eigen::Vector2d p(std::abs(px), py);
  const Eigen::Vector2d ca(p.x() - std::min(p.x(), p.y() < 0.0 ? r1 : r2), std::abs(p.y()) - he);
  const Eigen::Vector2d cb = p - k1 + k2 * std::clamp((k1 - p).dot(k2) / k2.squaredNorm(), 0.0, 1.0);
  const double s = (cb.x() < 0.0 && ca.y() < 0.0) ? -1.0 : 1.0;
  return s * std::sqrt(std::min(ca.squaredNorm(), cb.squaredNorm()));
}

// Quadratic smooth minimum; its gradient is a convex combination, so it stays 1-Lipschitz.
double smooth_min(double a, double b, double k) {
  const double h = std::max(k - std::abs(a - b), 0.0) / k;
  return std::min(a, b) - h * h * k * 0.25;
}

// Palm, blend and handle sizes in cm.
constexpr double kPalmHalfLength = 4.5;   // along y
constexpr double kPalmHalfWidthWrist = 3.4;
constexpr double kPalmHalfWidthKnuckles = 4.0;
constexpr double kPalmHalfThickness = 1.25;
constexpr double kPalmCornerRadius = 1.2;  // rounding of the outline seen from above
constexpr double kPalmEdgeRadius = 1.0;    // rounding of the dorsal and palmar rims
constexpr double kBlend = 1.0;             // finger-palm blend width: webs and thenar, not between fingers
constexpr double kPalmHandleRadius = 1.0;
constexpr double kPhalanxHandleFraction = 0.6;  // of the segment's smaller radius

constexpr double kSkinSampling = 0.006;  // m: largest edge of the grid the skin is extracted on

struct HandShape {
  std::array<std::array<Vector3d, 4>, 5> joints;  // m
  std::array<std::array<Eigen::Matrix3d, 3>, 5> frames;
  std::array<RoundCone, 15> cones;                // m
  Vector3d lo, hi;                                // bounding box of the shape, m

  // The palm alone: a rounded trapezoidal slab.
  double palm_sdf(const Vector3d& p) const {
    const double d2 = sd_trapezoid(p.x(), p.y(), (kPalmHalfWidthWrist - kPalmCornerRadius) * kCm,
                                   (kPalmHalfWidthKnuckles - kPalmCornerRadius) * kCm,
                                   (kPalmHalfLength - kPalmCornerRadius) * kCm) -
                      kPalmCornerRadius * kCm;
    const double wx = d2 + kPalmEdgeRadius * kCm;
    const double wy = std::abs(p.z()) - (kPalmHalfThickness - kPalmEdgeRadius) * kCm;
    return std::min(std::max(wx, wy), 0.0) + std::hypot(std::max(wx, 0.0), std::max(wy, 0.0)) -
           kPalmEdgeRadius * kCm;
  }

  // Finger f alone: the union of its three cones.
  double finger_sdf(int f, const Vector3d& p) const {
    return std::min({cones[3 * f].sdf(p), cones[3 * f + 1].sdf(p), cones[3 * f + 2].sdf(p)});
  }

  // The part (finger 0-4 or kHandPalmPart) whose own SDF is smallest at p: the one p lies in or is
  // nearest to (the palm on ties).
  int nearest_part(const Vector3d& p) const {
    int best = kHandPalmPart;
    double d = palm_sdf(p);
    for (int f = 0; f < 5; ++f) {
      const double df = finger_sdf(f, p);
      if (df < d) d = df, best = f;
    }
    return best;
  }

  double sdf(const Vector3d& p) const {
    const double palm = palm_sdf(p);
    // Fingers farther than palm + blend width leave the result at palm: start there and skip
    // every cone whose bounding ball is already farther (the result is unchanged, just faster).
    double fingers = palm + kBlend * kCm;
    for (const RoundCone& c : cones) {
      if ((p - c.centre).norm() - c.bound < fingers) fingers = std::min(fingers, c.sdf(p));
    }
    return smooth_min(palm, fingers, kBlend * kCm);
  }
};

HandShape build_right_shape() {
  // The standard skeleton in its rest posture gives the bones (hand_skeleton.hpp).
  const SkeletonPose pose = skeleton_pose(rest_joint_angles());
  HandShape s;
  s.lo = Vector3d(-kPalmHalfWidthKnuckles, -kPalmHalfLength, -kPalmHalfThickness) * kCm;
  s.hi = -s.lo;
  s.joints = pose.joints;
  for (int f = 0; f < 5; ++f) {
    const FingerGeometry& g = finger_geometry()[f];
    for (int k = 0; k < 3; ++k) {
      s.frames[f][k] = pose.R[3 * f + k];
      const Vector3d& joint = pose.joints[f][k];
      const Vector3d& next = pose.joints[f][k + 1];
      // The distal bone stops one tip radius short so the rounded cap ends at the fingertip.
      const Vector3d end = k == 2 ? Vector3d(next - g.radius[3] * pose.R[3 * f + k].col(1)) : next;
      s.cones[3 * f + k] = RoundCone(joint, end, g.radius[k], g.radius[k + 1]);
    }
    for (int k = 0; k < 3; ++k) {
      const RoundCone& c = s.cones[3 * f + k];
      const double r = std::max(c.ra, c.rb);
      s.lo = s.lo.cwiseMin(c.a.cwiseMin(c.b) - Vector3d::Constant(r));
      s.hi = s.hi.cwiseMax(c.a.cwiseMax(c.b) + Vector3d::Constant(r));
    }
  }
  // The blend can push the surface out by up to a quarter of its width.
  s.lo -= Vector3d::Constant(0.25 * kBlend * kCm);
  s.hi += Vector3d::Constant(0.25 * kBlend * kCm);
  return s;
}

const HandShape& right_shape() {
  static const HandShape shape = build_right_shape();
  return shape;
}

constexpr double kMinSpacing = 0.001;  // ~2M tets already; finer grids would exhaust memory
constexpr double kMaxSpacing = 0.1;    // a few cells hold the whole hand

// Planes at anchor + i h whatever the shape's extent, so nearby spacings give comparable grids.
CellGrid make_grid(const HandShape& shape, double h) {
  CellGrid g;
  g.h = h;
  const Vector3d anchor = detail::grid_shift(h);
  const Vector3d lo = shape.lo - Vector3d::Constant(1.5 * h);
  const Vector3d hi = shape.hi + Vector3d::Constant(1.5 * h);
  for (int a = 0; a < 3; ++a) {
    const double i0 = std::floor((lo[a] - anchor[a]) / h);
    g.origin[a] = anchor[a] + i0 * h;
    g.n[a] = static_cast<int>(std::ceil((hi[a] - g.origin[a]) / h));
  }
  return g;
}

// Conservative: false only if the cube (centre c, edge size) provably misses the shape, using
// the SDF's Lipschitz bound at the centre and, when undecided, at sub-cubes.
bool may_touch(const HandShape& shape, const Vector3d& c, double size, int depth) {
  const double f = shape.sdf(c);
  if (f < 0.0) return true;
  if (f >= kHalfDiagonal * size) return false;
  if (depth == 0) return true;
  const double q = 0.25 * size;
  for (int corner = 0; corner < 8; ++corner) {
    const Vector3d offset((corner & 1) ? q : -q, (corner & 2) ? q : -q, (corner & 4) ? q : -q);
    if (may_touch(shape, c + offset, 0.5 * size, depth - 1)) return true;
  }
  return false;
}

constexpr int kCoverDepth = 2;  // sub-cubes of h/4: kept cells come within ~h/4 of the shape, not 0.87 h

// Calls visit(cell id) for the cells the cone's axis passes through, from a to b, as a face-connected
// chain (a cell may come more than once).
template <typename Visit>
void for_each_axis_cell(const CellGrid& g, const RoundCone& cone, Visit visit) {
  const int steps = static_cast<int>(std::ceil((cone.b - cone.a).norm() / (0.125 * g.h))) + 1;
  Vector3i prev = g.cell_of(cone.a);
  visit(g.cell_id(prev));
  for (int s = 1; s <= steps; ++s) {
    const Vector3i cur = g.cell_of(cone.a + (cone.b - cone.a) * (static_cast<double>(s) / steps));
    // Step one axis at a time so consecutive cells share a face.
    while (cur != prev) {
      for (int a = 0; a < 3; ++a) {
        if (cur[a] != prev[a]) {
          prev[a] += cur[a] > prev[a] ? 1 : -1;
          break;
        }
      }
      visit(g.cell_id(prev));
    }
  }
}

// Kept cells: all that may touch the shape plus every cell a bone axis passes through, reduced
// to the largest face-connected component.
std::vector<char> cover_cells(const HandShape& shape, const CellGrid& g) {
  std::vector<char> keep(g.num_cells(), 0);
  for (int k = 0; k < g.n.z(); ++k) {
    for (int j = 0; j < g.n.y(); ++j) {
      for (int i = 0; i < g.n.x(); ++i) {
        const Vector3i c(i, j, k);
        if (may_touch(shape, g.centre(c), g.h, kCoverDepth)) keep[g.cell_id(c)] = 1;
      }
    }
  }
  for (const RoundCone& cone : shape.cones) for_each_axis_cell(g, cone, [&](int id) { keep[id] = 1; });
  detail::keep_largest_component(g, keep);
  return keep;
}

// Skeleton-aware split (separate_fingers): the part of every kept cell (finger 0-4 or kHandPalmPart),
// -1 elsewhere. A cell takes the part nearest its centre. Then, so that every finger is one piece
// hanging from the palm by faces: the knuckle cells (base joints) become palm, the cells a finger's
// bone axes pass through that are not palm become that finger's (a face-connected chain from the
// palm to the tip; a cell two fingers' bones pass through becomes palm), and any other island of a
// finger's cells (a cell nearer to it but cut off by a neighbour's cells, at coarse grids) joins
// the part most of its face neighbours have.
std::vector<int> label_parts(const HandShape& shape, const CellGrid& g, const std::vector<char>& keep) {
  std::vector<int> part(g.num_cells(), -1);
  for (int id = 0; id < g.num_cells(); ++id) {
    if (keep[id]) part[id] = shape.nearest_part(g.centre(g.cell_coords(id)));
  }
  std::vector<char> axis(g.num_cells(), 0);
  for (int f = 0; f < 5; ++f) part[g.cell_id(g.cell_of(shape.joints[f][0]))] = kHandPalmPart;
  for (int f = 0; f < 5; ++f) {
    for (int k = 0; k < 3; ++k) {
      for_each_axis_cell(g, shape.cones[3 * f + k], [&](int id) {
        if (part[id] == kHandPalmPart) return;
        if (axis[id] && part[id] != f) {
          // Two fingers' bones in one cell (coarse grids): it cannot separate them, so it is shared
          // flesh, and both chains stay attached through it.
          part[id] = kHandPalmPart;
          axis[id] = 0;
          return;
        }
        part[id] = f;
        axis[id] = 1;
      });
    }
  }
  std::vector<char> mask(g.num_cells());
  std::vector<int> label, sizes;
  for (int round = 0; round < 16; ++round) {
    bool changed = false;
    for (int f = 0; f < 5; ++f) {
      for (int id = 0; id < g.num_cells(); ++id) mask[id] = part[id] == f ? 1 : 0;
      const int n = detail::label_components(g, mask, label, sizes);
      std::vector<char> rooted(n, 0);
      std::vector<std::vector<int>> members(n);
      for (int id = 0; id < g.num_cells(); ++id) {
        if (label[id] < 0) continue;
        members[label[id]].push_back(id);
        if (axis[id]) rooted[label[id]] = 1;
      }
      for (int l = 0; l < n; ++l) {
        if (rooted[l]) continue;
        // Votes of the island's face neighbours outside it (kept cells only).
        std::array<int, kHandPalmPart + 1> votes{};
        for (int id : members[l]) {
          const Vector3i c = g.cell_coords(id);
          for (int a = 0; a < 3; ++a) {
            for (int dir = -1; dir <= 1; dir += 2) {
              Vector3i nb = c;
              nb[a] += dir;
              if (nb[a] < 0 || nb[a] >= g.n[a]) continue;
              const int q = part[g.cell_id(nb)];
              if (q >= 0 && q != f) ++votes[q];
            }
          }
        }
        // The palm wins ties, then the higher finger index.
        int best = kHandPalmPart;
        for (int q = kHandPalmPart; q >= 0; --q) {
          if (votes[q] > votes[best]) best = q;
        }
        for (int id : members[l]) part[id] = best;
        changed = true;
      }
    }
    if (!changed) break;
  }
  return part;
}

int count_tets(const HandShape& shape, double h) {
  return detail::kept_tet_count(cover_cells(shape, make_grid(shape, h)));
}

// Kuhn subdivision of the unit cube along its main diagonal: tet p walks 000 -> +e[p0] -> +e[p1] -> 111.
constexpr int kPerm[6][3] = {{0, 1, 2}, {1, 2, 0}, {2, 0, 1}, {0, 2, 1}, {1, 0, 2}, {2, 1, 0}};

// Cube corners (bit a = offset along axis a) of Kuhn tet p, positively oriented.
constexpr Tet kuhn_corners(int p) {
  const int c1 = 1 << kPerm[p][0];
  const int c2 = c1 | (1 << kPerm[p][1]);
  // The last three permutations are odd: swapping two nodes restores positive orientation.
  return p < 3 ? Tet{0, c1, c2, 7} : Tet{0, c1, 7, c2};
}

// The hand's own tet order (not box_mesh's): its node numbering and skin weights depend on it.
constexpr std::array<Tet, 6> kKuhnTets = {kuhn_corners(0), kuhn_corners(1), kuhn_corners(2),
                                          kuhn_corners(3), kuhn_corners(4), kuhn_corners(5)};

// Weights of the corners (kuhn_corners order) of Kuhn tet p for local point u of the unit cube: the
// affine coordinates, so outside the tet some are negative.
Eigen::Vector4d kuhn_weights(int p, const Vector3d& u) {
  const double w0 = 1.0 - u[kPerm[p][0]];
  const double w1 = u[kPerm[p][0]] - u[kPerm[p][1]];
  const double w2 = u[kPerm[p][1]] - u[kPerm[p][2]];
  const double w3 = u[kPerm[p][2]];
  return p < 3 ? Eigen::Vector4d(w0, w1, w2, w3) : Eigen::Vector4d(w0, w1, w3, w2);
}

// Kuhn tet of the unit cube containing local point u, with the weights of its corners (kuhn_corners order).
std::pair<int, Eigen::Vector4d> locate_in_cube(const Vector3d& u_in) {
  const Vector3d u = u_in.cwiseMax(0.0).cwiseMin(1.0);
  int p = 0;
  for (; p < 5; ++p) {
    if (u[kPerm[p][0]] >= u[kPerm[p][1]] && u[kPerm[p][1]] >= u[kPerm[p][2]]) break;
  }
  return {p, kuhn_weights(p, u)};
}

// Corner weights w (kuhn_corners(perm) order) of the cell with low corner cell_min, moved to the node
// order of mesh tet `tet` (finalize_mesh may have reordered its nodes): matched by position.
Eigen::Vector4d weights_in_tet_order(const TetMesh& mesh, int tet, const Vector3d& cell_min, double h, int perm,
                                     const Eigen::Vector4d& w) {
  const Tet& corners = kKuhnTets[perm];
  Eigen::Vector4d bary = Eigen::Vector4d::Zero();
  for (int q = 0; q < 4; ++q) {
    const int c = corners[q];
    const Vector3d xc = cell_min + h * cube_corner(c).cast<double>();
    for (int m = 0; m < 4; ++m) {
      if ((mesh.X[mesh.tets[tet][m]] - xc).squaredNorm() < 1e-6 * h * h) bary[m] = w[q];
    }
  }
  return bary;
}

// Parity of the permutation (a, b, c, d) of (0, 1, 2, 3).
bool odd_permutation(const std::array<int, 4>& q) {
  int inversions = 0;
  for (int i = 0; i < 4; ++i) {
    for (int j = i + 1; j < 4; ++j) inversions += q[i] > q[j] ? 1 : 0;
  }
  return inversions % 2 == 1;
}

struct Skin {
  std::vector<Vector3d> vertices;
  std::vector<Triangle> triangles;
  std::vector<int> tet;
  std::vector<Eigen::Vector4d> bary;
};

// Marching tetrahedra on the Kuhn tets of the grid refined n times inside every kept cell. The
// refined Kuhn tets nest in the coarse ones, so each vertex has exact weights in a mesh tet.
Skin extract_skin(const HandShape& shape, const CellGrid& g, const std::vector<int>& kept_cells, const TetMesh& mesh) {
  Skin skin;
  const int n = std::max(1, static_cast<int>(std::ceil(g.h / kSkinSampling - 1e-9)));
  const double hf = g.h / n;
  const Vector3i nf = g.n * n + Vector3i::Ones();  // fine nodes per axis
  auto fine_id = [&](const Vector3i& c) {
    return (static_cast<int64_t>(c.z()) * nf.y() + c.y()) * nf.x() + c.x();
  };
  auto fine_pos = [&](const Vector3i& c) -> Vector3d { return g.origin + hf * c.cast<double>(); };
  std::unordered_map<int64_t, double> value;
  auto sdf_at = [&](const Vector3i& c) {
    auto [it, inserted] = value.try_emplace(fine_id(c), 0.0);
    if (inserted) it->second = shape.sdf(fine_pos(c));
    return it->second;
  };
  std::unordered_map<int64_t, int> edge_vertex;
  const int64_t num_fine = static_cast<int64_t>(nf.x()) * nf.y() * nf.z();

  for (size_t kc = 0; kc < kept_cells.size(); ++kc) {
    const Vector3i cell = g.cell_coords(kept_cells[kc]);
    const Vector3d cell_min = g.corner(cell);
    auto vertex_on_edge = [&](const Vector3i& fu, double f_u, const Vector3i& fv, double f_v) {
      const int64_t iu = fine_id(fu);
      const int64_t iv = fine_id(fv);
      auto [it, inserted] = edge_vertex.try_emplace(std::min(iu, iv) * num_fine + std::max(iu, iv), 0);
      if (!inserted) return it->second;
      const double t = f_u / (f_u - f_v);
      const Vector3d p = (1.0 - t) * fine_pos(fu) + t * fine_pos(fv);
      const auto [perm, w] = locate_in_cube((p - cell_min) / g.h);
      const int tet = static_cast<int>(6 * kc) + perm;
      const Eigen::Vector4d bary = weights_in_tet_order(mesh, tet, cell_min, g.h, perm, w);
      it->second = static_cast<int>(skin.vertices.size());
      skin.vertices.push_back(p);
      skin.tet.push_back(tet);
      skin.bary.push_back(bary);
      return it->second;
    };

    for (int sk = 0; sk < n; ++sk) {
      for (int sj = 0; sj < n; ++sj) {
        for (int si = 0; si < n; ++si) {
          const Vector3i base = cell * n + Vector3i(si, sj, sk);
          std::array<Vector3i, 8> fc;
          std::array<double, 8> fv;
          int inside = 0;
          for (int c = 0; c < 8; ++c) {
            fc[c] = base + cube_corner(c);
            fv[c] = sdf_at(fc[c]);
            inside += fv[c] < 0.0 ? 1 : 0;
          }
          if (inside == 0 || inside == 8) continue;
          for (int p = 0; p < 6; ++p) {
            const Tet& tc = kKuhnTets[p];
            std::array<int, 4> in{}, out{};
            int ni = 0, no = 0;
            for (int q = 0; q < 4; ++q) {
              if (fv[tc[q]] < 0.0) in[ni++] = q; else out[no++] = q;
            }
            if (ni == 0 || ni == 4) continue;
            auto e = [&](int q0, int q1) {
              return vertex_on_edge(fc[tc[q0]], fv[tc[q0]], fc[tc[q1]], fv[tc[q1]]);
            };
            if (ni == 1 || ni == 3) {
              // Lone node first, the rest ordered so the tet stays positive; the face opposite the
              // lone node then points away from it.
              const int lone = ni == 1 ? in[0] : out[0];
              std::array<int, 4> q{lone, 0, 0, 0};
              for (int r = 0, m = 1; r < 4; ++r) {
                if (r != lone) q[m++] = r;
              }
              if (odd_permutation(q)) std::swap(q[2], q[3]);
              const int v1 = e(q[0], q[1]), v2 = e(q[0], q[2]), v3 = e(q[0], q[3]);
              skin.triangles.push_back(ni == 1 ? Triangle{v1, v2, v3} : Triangle{v1, v3, v2});
            } else {
              std::array<int, 4> q{in[0], in[1], out[0], out[1]};
              if (odd_permutation(q)) std::swap(q[2], q[3]);
              const int ia = e(q[0], q[2]), ib = e(q[0], q[3]), jb = e(q[1], q[3]), ja = e(q[1], q[2]);
              // Quad ia-ib-jb-ja faces outward; split along its shorter diagonal.
              const double d1 = (skin.vertices[ia] - skin.vertices[jb]).squaredNorm();
              const double d2 = (skin.vertices[ib] - skin.vertices[ja]).squaredNorm();
              if (d1 <= d2) {
                skin.triangles.push_back({ia, ib, jb});
                skin.triangles.push_back({ia, jb, ja});
              } else {
                skin.triangles.push_back({ia, ib, ja});
                skin.triangles.push_back({ib, jb, ja});
              }
            }
          }
        }
      }
    }
  }
  return skin;
}

// separate_fingers: a skin vertex must follow the flesh of its own part (the part nearest it), not
// the copy of a neighbouring finger that shares its grid cell. A tet is part P's when each of its
// nodes is a copy of P or shared (palm flesh, which every part reaches). A vertex whose tet is not its
// part's moves to the tet of its part, among the cells within two of its own, that holds it with the
// least extrapolation (largest smallest weight): the cell across a face when the vertex lies on one
// (weights >= 0); otherwise the part's flesh stops short of the vertex (a cell nearer to the
// neighbour took the gap) and the weights extrapolate a fraction of a cell.
void embed_skin_in_parts(const HandShape& shape, const CellGrid& g, const std::vector<int>& kept_cells,
                         const TetMesh& mesh, const std::vector<int>& node_part, Skin& skin) {
  std::vector<int> kc_of(g.num_cells(), -1);
  for (size_t kc = 0; kc < kept_cells.size(); ++kc) kc_of[kept_cells[kc]] = static_cast<int>(kc);
  auto tet_is_of = [&](int tet, int part) {
    for (int v : mesh.tets[tet]) {
      if (node_part[v] != part && node_part[v] != kHandPalmPart) return false;
    }
    return true;
  };
  for (size_t i = 0; i < skin.vertices.size(); ++i) {
    const Vector3d& p = skin.vertices[i];
    const int part = shape.nearest_part(p);
    if (tet_is_of(skin.tet[i], part)) continue;
    const Vector3i home = g.cell_coords(kept_cells[skin.tet[i] / 6]);
    double best = -std::numeric_limits<double>::infinity();
    for (int dz = -2; dz <= 2; ++dz) {
      for (int dy = -2; dy <= 2; ++dy) {
        for (int dx = -2; dx <= 2; ++dx) {
          const Vector3i c = home + Vector3i(dx, dy, dz);
          if ((c.array() < 0).any() || (c.array() >= g.n.array()).any()) continue;
          const int kc = kc_of[g.cell_id(c)];
          if (kc < 0) continue;
          const Vector3d u = (p - g.corner(c)) / g.h;
          for (int perm = 0; perm < 6; ++perm) {
            const int tet = 6 * kc + perm;
            const Eigen::Vector4d w = kuhn_weights(perm, u);
            if (w.minCoeff() <= best || !tet_is_of(tet, part)) continue;
            best = w.minCoeff();
            skin.tet[i] = tet;
            skin.bary[i] = weights_in_tet_order(mesh, tet, g.corner(c), g.h, perm, w);
          }
        }
      }
    }
  }
}

void mirror(ProceduralHand& hand) {
  const Eigen::Matrix3d M = Eigen::Vector3d(-1.0, 1.0, 1.0).asDiagonal();
  for (Vector3d& x : hand.mesh.X) x.x() = -x.x();
  for (Tet& t : hand.mesh.tets) std::swap(t[2], t[3]);
  for (Vector3d& x : hand.skin_vertices) x.x() = -x.x();
  for (Eigen::Vector4d& w : hand.skin_bary) std::swap(w[2], w[3]);
  for (Triangle& t : hand.skin_triangles) std::swap(t[1], t[2]);
  // M R M keeps the frame right-handed: y and z mirror, x = y cross z flips with them.
  auto mirror_frame = [&](HandFrame& f) {
    f.p.x() = -f.p.x();
    f.R = M * f.R * M;
  };
  mirror_frame(hand.palm);
  for (HandFrame& f : hand.phalanges) mirror_frame(f);
  for (auto& finger : hand.joints) {
    for (Vector3d& j : finger) j.x() = -j.x();
  }
  finalize_mesh(hand.mesh);
}

}  // namespace

double procedural_hand_sdf(const Eigen::Vector3d& p, bool left) {
  return right_shape().sdf(left ? Vector3d(-p.x(), p.y(), p.z()) : p);
}

int procedural_hand_nearest_part(const Eigen::Vector3d& p, bool left) {
  return right_shape().nearest_part(left ? Vector3d(-p.x(), p.y(), p.z()) : p);
}

int finger_index(const std::string& finger) {
  for (int f = 0; f < 5; ++f) {
    if (finger == finger_name(f)) return f;
  }
  return -1;
}

double hand_spacing_for_tets(int target_tets) {
  if (target_tets <= 0) {
    throw std::invalid_argument("procedural hand: target_tets must be positive, got " + std::to_string(target_tets));
  }
  const HandShape& shape = right_shape();
  // Volume guess (including the cover's margin) gives the first spacing; the count falls with h.
  return detail::spacing_for_tets(target_tets, 3.5e-4, kMinSpacing, kMaxSpacing, false,
                                  [&](double h) { return count_tets(shape, h); });
}

ProceduralHand make_procedural_hand(const ProceduralHandOptions& options) {
  if (!std::isfinite(options.spacing) || (options.spacing > 0.0 && options.spacing < kMinSpacing) ||
      options.spacing > kMaxSpacing) {
    throw std::invalid_argument("procedural hand: spacing " + std::to_string(options.spacing) +
                                " m is outside [0.001, 0.1] (or <= 0 to use target_tets)");
  }
  const double h = options.spacing > 0.0 ? options.spacing : hand_spacing_for_tets(options.target_tets);
  const HandShape& shape = right_shape();
  const CellGrid g = make_grid(shape, h);
  const std::vector<char> keep = cover_cells(shape, g);
  std::vector<int> part;
  detail::CellMesh cells;
  if (options.separate_fingers) {
    part = label_parts(shape, g, keep);
    cells = detail::mesh_cells_by_part(g, keep, part, kHandPalmPart, kKuhnTets);
  } else {
    cells = detail::mesh_cells(g, keep, kKuhnTets);
  }

  ProceduralHand hand;
  hand.spacing = h;
  hand.mesh = std::move(cells.mesh);

  Skin skin = extract_skin(shape, g, cells.cells, hand.mesh);
  if (options.separate_fingers) {
    embed_skin_in_parts(shape, g, cells.cells, hand.mesh, cells.node_part, skin);
    hand.node_part = std::move(cells.node_part);
    for (int id : cells.cells) hand.tet_part.insert(hand.tet_part.end(), 6, part[id]);
  }
  hand.skin_vertices = std::move(skin.vertices);
  hand.skin_triangles = std::move(skin.triangles);
  hand.skin_tet = std::move(skin.tet);
  hand.skin_bary = std::move(skin.bary);

  hand.joints = shape.joints;
  hand.palm = HandFrame{"palm", Vector3d::Zero(), Eigen::Matrix3d::Identity(), kPalmHandleRadius * kCm};
  for (int f = 0; f < 5; ++f) {
    for (int k = 0; k < 3; ++k) {
      const RoundCone& c = shape.cones[3 * f + k];
      hand.phalanges[3 * f + k] = HandFrame{std::string(finger_name(f)) + "_" + phalanx_name(k),
                                            0.5 * (shape.joints[f][k] + shape.joints[f][k + 1]),
                                            shape.frames[f][k], kPhalanxHandleFraction * std::min(c.ra, c.rb)};
    }
  }
  if (options.left) mirror(hand);
  return hand;
}

double embedding_density(const ProceduralHand& hand, double density_kg_m3) {
  const double skin = enclosed_volume(SurfaceMesh{hand.skin_vertices, hand.skin_triangles});
  return density_kg_m3 * skin / total_volume(hand.mesh);
}

}  // namespace hapticd::hand
