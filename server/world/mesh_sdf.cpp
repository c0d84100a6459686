#include "server/world/mesh_sdf.hpp"

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>

namespace hapticd::world {
namespace {

// The coarse distance grid of a mesh's far clearance: 1.5 cm cells, exact to 7 of them, and the
// trilinear interpolant's largest error in cells: a distance field is 1-Lipschitz, so the
// interpolant is within the weighted distance to the cell's corners, at most sqrt(3) / 2 at its centre.
constexpr double kFarCell_m = 0.015;
constexpr int kFarBandCells = 7;
constexpr double kFarError = 0.8660254037844386;

// Closest point on triangle abc to p (Ericson, Real-Time Collision Detection 5.1.5).
Eigen::Vector3d closest_on_triangle(const Eigen::Vector3d& p, const Eigen::Vector3d& a, const Eigen::Vector3d& b,
                                    const Eigen::Vector3d& c) {
  const Eigen::Vector3d ab = b - a, ac = c - a, ap = p - a;
  const double d1 = ab.dot(ap), d2 = ac.dot(ap);
  if (d1 <= 0 && d2 <= 0) return a;
  const Eigen::Vector3d bp = p - b;
  const double d3 = ab.dot(bp), d4 = ac.dot(bp);
  if (d3 >= 0 && d4 <= d3) return b;
  const double vc = d1 * d4 - d3 * d2;
  if (vc <= 0 && d1 >= 0 && d3 <= 0) return a + d1 / (d1 - d3) * ab;
  const Eigen::Vector3d cp = p - c;
  const double d5 = ab.dot(cp), d6 = ac.dot(cp);
  if (d6 >= 0 && d5 <= d6) return c;
  const double vb = d5 * d2 - d1 * d6;
  if (vb <= 0 && d2 >= 0 && d6 <= 0) return a + d2 / (d2 - d6) * ac;
  const double va = d3 * d6 - d5 * d4;
  if (va <= 0 && (d4 - d3) >= 0 && (d5 - d6) >= 0) return b + (d4 - d3) / ((d4 - d3) + (d5 - d6)) * (c - b);
  const double denom = 1.0 / (va + vb + vc);
  return a + ab * (vb * denom) + ac * (vc * denom);
}

}  // namespace

MeshSdf::MeshSdf(const hand::SurfaceMesh& mesh, double cell, int band) : cell_(cell) {
  Eigen::Vector3d lo = Eigen::Vector3d::Constant(INFINITY), hi = -lo;
  for (const Eigen::Vector3d& v : mesh.vertices) lo = lo.cwiseMin(v), hi = hi.cwiseMax(v);
  if (mesh.vertices.empty() || !lo.allFinite() || !hi.allFinite()) return;  // no surface: every query misses
  // A scaled-up mesh keeps its grid small: 10 m at 3 mm cells would be 3e10 values.
  cell = std::max(cell, (hi - lo).maxCoeff() / kMaxCellsPerAxis);
  cell_ = cell;
  origin_ = lo - Eigen::Vector3d::Constant(band * cell);
  for (int d = 0; d < 3; ++d) dims_[d] = static_cast<int>(std::ceil((hi[d] - lo[d]) / cell)) + 2 * band + 2;
  const double far = band * cell;
  far_ = far;
  values_.assign(static_cast<size_t>(dims_[0]) * dims_[1] * dims_[2], far);
  auto node = [&](int i, int j, int k) -> Eigen::Vector3d { return origin_ + cell * Eigen::Vector3d(i, j, k); };
  auto index = [&](int i, int j, int k) { return i + dims_[0] * (j + dims_[1] * k); };
  // Unsigned distance in a band around each triangle.
  std::vector<std::vector<double>> crossings(static_cast<size_t>(dims_[0]) * dims_[1]);
  for (const hand::Triangle& t : mesh.triangles) {
    const Eigen::Vector3d &a = mesh.vertices[t[0]], &b = mesh.vertices[t[1]], &c = mesh.vertices[t[2]];
    const Eigen::Vector3d tlo = a.cwiseMin(b).cwiseMin(c), thi = a.cwiseMax(b).cwiseMax(c);
    int i0[3], i1[3];
    for (int d = 0; d < 3; ++d) {
      i0[d] = std::max(0, static_cast<int>(std::floor((tlo[d] - origin_[d]) / cell)) - band);
      i1[d] = std::min(dims_[d] - 1, static_cast<int>(std::ceil((thi[d] - origin_[d]) / cell)) + band);
    }
    for (int k = i0[2]; k <= i1[2]; ++k)
      for (int j = i0[1]; j <= i1[1]; ++j)
        for (int i = i0[0]; i <= i1[0]; ++i) {
          double& v = values_[index(i, j, k)];
          v = std::min(v, (node(i, j, k) - closest_on_triangle(node(i, j, k), a, b, c)).norm());
        }
    // Where the vertical line through each grid column crosses the triangle (for the sign).
    const Eigen::Vector2d A = a.head<2>(), B = b.head<2>(), C = c.head<2>();
    const double area = (B - A).x() * (C - A).y() - (B - A).y() * (C - A).x();
    if (std::abs(area) < 1e-300) continue;  // vertical triangle: no line crosses its interior
    for (int j = std::max(0, i0[1]); j <= i1[1]; ++j)
      for (int i = std::max(0, i0[0]); i <= i1[0]; ++i) {
        // A tiny irrational offset keeps the lines off edges and vertices.
        const Eigen::Vector2d q = node(i, j, 0).head<2>() + Eigen::Vector2d(1.3e-9, 0.7e-9);
        const double w0 = ((B - q).x() * (C - q).y() - (B - q).y() * (C - q).x()) / area;
        const double w1 = ((C - q).x() * (A - q).y() - (C - q).y() * (A - q).x()) / area;
        const double w2 = 1 - w0 - w1;
        if (w0 < 0 || w1 < 0 || w2 < 0) continue;
        crossings[i + dims_[0] * j].push_back(w0 * a.z() + w1 * b.z() + w2 * c.z());
      }
  }
  // Inside where an odd number of crossings lie below the node.
  for (int j = 0; j < dims_[1]; ++j)
    for (int i = 0; i < dims_[0]; ++i) {
      std::vector<double>& z = crossings[i + dims_[0] * j];
      std::sort(z.begin(), z.end());
      size_t below = 0;
      for (int k = 0; k < dims_[2]; ++k) {
        const double zk = node(i, j, k).z();
        while (below < z.size() && z[below] < zk) ++below;
        if (below % 2 == 1) values_[index(i, j, k)] *= -1;
      }
    }
}

bool MeshSdf::query(const Eigen::Vector3d& p, double& distance, Eigen::Vector3d& normal) const {
  if (values_.empty()) return false;
  const Eigen::Vector3d u = (p - origin_) / cell_;
  int c[3];
  double f[3];
  for (int d = 0; d < 3; ++d) {
    if (!(u[d] >= 0) || u[d] > dims_[d] - 1.000001) return false;
    c[d] = std::min(static_cast<int>(u[d]), dims_[d] - 2);
    f[d] = u[d] - c[d];
  }
  distance = 0;
  Eigen::Vector3d grad = Eigen::Vector3d::Zero();
  for (int corner = 0; corner < 8; ++corner) {
    const int di = corner & 1, dj = (corner >> 1) & 1, dk = (corner >> 2) & 1;
    const double wx = di ? f[0] : 1 - f[0], wy = dj ? f[1] : 1 - f[1], wz = dk ? f[2] : 1 - f[2];
    const double v = at(c[0] + di, c[1] + dj, c[2] + dk);
    distance += wx * wy * wz * v;
    grad.x() += (di ? 1 : -1) * wy * wz * v;
    grad.y() += (dj ? 1 : -1) * wx * wz * v;
    grad.z() += (dk ? 1 : -1) * wx * wy * v;
  }
  // Within half a cell of the clamp the field is mostly clamped nodes: no distance, no normal.
  if (distance > far_ - 0.5 * cell_) return false;
  const double g = grad.norm();
  normal = g > 0 ? Eigen::Vector3d(grad / g) : Eigen::Vector3d::UnitZ();
  return true;
}

MeshSdf far_clearance_sdf(const hand::SurfaceMesh& mesh) { return MeshSdf(mesh, kFarCell_m, kFarBandCells); }

bool clearance(const MeshSdf& fine, const MeshSdf& far, const Eigen::Vector3d& p, double& gap, Eigen::Vector3d& n) {
  if (far.empty()) return false;
  double distance;
  if (fine.query(p, distance, n)) {  // within the fine grid's reach: its own answer
    if (distance <= 0) return false;
    gap = distance;
    return true;
  }
  // Beyond it the point is at least that far from the surface.
  if (!far.query(p, distance, n) || distance <= 0) return false;
  gap = std::max(fine.reach(), distance - kFarError * far.cell());
  return true;
}

}  // namespace hapticd::world
