#include "server/world/deformed_mesh_query.hpp"

#include <Eigen/LU>
#include <algorithm>
#include <cmath>
#include <limits>

namespace hapticd::world {
namespace {

// The grid has about one tet-sized cell per tet bounding box, but never more
// than this many cells along an axis (a few flattened, far-flung tets must not
// make it huge).
constexpr int kMaxCellsPerAxis = 64;

// Barycentric coordinates of p in the tet with corner x0 and inverse edge matrix Ds^-1.
Eigen::Vector4d barycentric(const Eigen::Matrix3d& Ds_inv, const Eigen::Vector3d& x0, const Eigen::Vector3d& p) {
  const Eigen::Vector3d w = Ds_inv * (p - x0);
  return {1 - w.sum(), w[0], w[1], w[2]};
}

}  // namespace

DeformedMeshQuery::DeformedMeshQuery(const hand::TetMesh& mesh, const hand::SurfaceMesh& surface, double sdf_cell_m,
                                     int sdf_band_cells)
    : tets_(mesh.tets), X_(mesh.X), sdf_(surface, sdf_cell_m, sdf_band_cells) {
  Dm_T_.reserve(tets_.size());
  for (const hand::Tet& t : tets_) {
    Eigen::Matrix3d Dm;
    Dm << X_[t[1]] - X_[t[0]], X_[t[2]] - X_[t[0]], X_[t[3]] - X_[t[0]];
    Dm_T_.push_back(Dm.transpose());
  }
  tet_cells_.resize(tets_.size());
  tet_boxes_.resize(tets_.size());
  Ds_inv_.resize(tets_.size());
  invertible_.resize(tets_.size());
}

int DeformedMeshQuery::cell_of(const Eigen::Vector3d& p, int axis) const {
  return static_cast<int>(std::floor((p[axis] - origin_[axis]) / cell_));
}

void DeformedMeshQuery::update(const Eigen::VectorXd& x) {
  x_ = x;
  bounds_.setEmpty();
  if (tets_.empty() || !x.allFinite()) {
    dims_[0] = dims_[1] = dims_[2] = 0;
    return;
  }
  // Each tet is filed under every cell its box, grown by the extrapolation slack, touches.
  double extent_sum = 0;
  for (size_t e = 0; e < tets_.size(); ++e) {
    const hand::Tet& t = tets_[e];
    const Eigen::Vector3d x0 = x_.segment<3>(3 * t[0]);
    Eigen::Matrix3d Ds;
    Ds << x_.segment<3>(3 * t[1]) - x0, x_.segment<3>(3 * t[2]) - x0, x_.segment<3>(3 * t[3]) - x0;
    bool invertible;
    Ds.computeInverseWithCheck(Ds_inv_[e], invertible, 1e-30);
    invertible_[e] = invertible;  // a flattened tet holds no volume to be inside of
    Eigen::AlignedBox3d box;
    for (int k = 0; k < 4; ++k) box.extend(Eigen::Vector3d(x_.segment<3>(3 * t[k])));
    const Eigen::Vector3d grow = Eigen::Vector3d::Constant(kBarycentricSlack * box.sizes().maxCoeff());
    box = Eigen::AlignedBox3d(box.min() - grow, box.max() + grow);
    extent_sum += box.sizes().maxCoeff();
    bounds_.extend(box);
    tet_boxes_[e] = box;
  }
  const Eigen::Vector3d size = bounds_.sizes();
  cell_ = std::max(extent_sum / static_cast<double>(tets_.size()), size.maxCoeff() / kMaxCellsPerAxis);
  if (!(cell_ > 0)) cell_ = 1;
  origin_ = bounds_.min();
  for (int a = 0; a < 3; ++a) dims_[a] = std::min(kMaxCellsPerAxis, static_cast<int>(size[a] / cell_) + 1);
  const int cells = dims_[0] * dims_[1] * dims_[2];
  cell_start_.assign(cells + 1, 0);
  for (size_t e = 0; e < tets_.size(); ++e) {
    Eigen::AlignedBox3i& range = tet_cells_[e];
    for (int a = 0; a < 3; ++a) {
      range.min()[a] = std::clamp(cell_of(tet_boxes_[e].min(), a), 0, dims_[a] - 1);
      range.max()[a] = std::clamp(cell_of(tet_boxes_[e].max(), a), 0, dims_[a] - 1);
    }
    for (int k = range.min().z(); k <= range.max().z(); ++k)
      for (int j = range.min().y(); j <= range.max().y(); ++j)
        for (int i = range.min().x(); i <= range.max().x(); ++i) ++cell_start_[1 + i + dims_[0] * (j + dims_[1] * k)];
  }
  for (int c = 0; c < cells; ++c) cell_start_[c + 1] += cell_start_[c];
  cell_tets_.resize(cell_start_[cells]);
  fill_.assign(cell_start_.begin(), cell_start_.end() - 1);
  for (size_t e = 0; e < tets_.size(); ++e) {
    const Eigen::AlignedBox3i& range = tet_cells_[e];
    for (int k = range.min().z(); k <= range.max().z(); ++k)
      for (int j = range.min().y(); j <= range.max().y(); ++j)
        for (int i = range.min().x(); i <= range.max().x(); ++i)
          cell_tets_[fill_[i + dims_[0] * (j + dims_[1] * k)]++] = static_cast<int>(e);
  }
}

bool DeformedMeshQuery::locate(const Eigen::Vector3d& p, int& tet, Eigen::Vector4d& bary) const {
  if (dims_[0] == 0 || !bounds_.contains(p)) return false;
  int c[3];
  for (int a = 0; a < 3; ++a) c[a] = std::clamp(cell_of(p, a), 0, dims_[a] - 1);
  const int cell = c[0] + dims_[0] * (c[1] + dims_[1] * c[2]);
  // The tet whose smallest coordinate is largest: the one holding p, or the
  // nearest in barycentric terms (points on shared faces pick either).
  double best = -std::numeric_limits<double>::infinity();
  for (int k = cell_start_[cell]; k < cell_start_[cell + 1]; ++k) {
    const int e = cell_tets_[k];
    if (!invertible_[e]) continue;
    const Eigen::Vector4d w = barycentric(Ds_inv_[e], x_.segment<3>(3 * tets_[e][0]), p);
    if (w.minCoeff() > best) best = w.minCoeff(), tet = e, bary = w;
  }
  return best >= -kBarycentricSlack;
}

bool DeformedMeshQuery::penetration(const Eigen::Vector3d& p, double margin_m, MeshPenetration& out) const {
  if (!locate(p, out.tet, out.bary)) return false;
  const hand::Tet& t = tets_[out.tet];
  out.p_rest.setZero();
  for (int k = 0; k < 4; ++k) out.p_rest += out.bary[k] * X_[t[k]];
  double phi;
  Eigen::Vector3d g;
  if (!sdf_.query(out.p_rest, phi, g)) return false;
  // n = F^-T g with F = Ds Dm^-1, i.e. F^-T = Ds^-T Dm^T.
  const Eigen::Vector3d n = Ds_inv_[out.tet].transpose() * (Dm_T_[out.tet] * g);
  const double stretch = n.norm();
  if (!(stretch > 0) || !std::isfinite(stretch)) return false;
  out.depth_m = -phi / stretch;
  out.n_W = n / stretch;
  return out.depth_m > -margin_m;
}

}  // namespace hapticd::world
