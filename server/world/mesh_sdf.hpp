#pragma once
// Signed distance to a closed triangle mesh on a regular grid (negative inside),
// for hand-vs-mesh contact: sign by ray parity along z per grid column, exact
// distance in a band of `band_cells` around each triangle, clamped beyond it.
// Queries interpolate trilinearly; the normal is the interpolant's gradient.
#include <Eigen/Core>
#include <vector>

#include "hand_models/embedded_surface.hpp"

namespace hapticd::world {

class MeshSdf {
 public:
  // Cells are cell_m, or coarser for a mesh wider than kMaxCellsPerAxis of them, so the grid
  // holds at most (kMaxCellsPerAxis + 2 band_cells + 2)^3 values whatever the mesh's scale.
  static constexpr int kMaxCellsPerAxis = 128;

  MeshSdf() = default;
  MeshSdf(const hand::SurfaceMesh& mesh, double cell_m, int band_cells = 3);

  // Signed distance (m) and unit outward normal at p (mesh frame); false outside the grid, and outside
  // the mesh within half a cell of the clamp (band_cells cells), where the interpolant is mostly
  // clamped nodes and its gradient no normal.
  bool query(const Eigen::Vector3d& p, double& distance, Eigen::Vector3d& normal) const;
  bool empty() const { return values_.empty(); }
  double cell() const { return cell_; }
  // How far outside the surface query() answers: half a cell short of the clamp.
  double reach() const { return far_ - 0.5 * cell_; }

 private:
  double at(int i, int j, int k) const { return values_[i + dims_[0] * (j + dims_[1] * k)]; }
  Eigen::Vector3d origin_ = Eigen::Vector3d::Zero();
  double cell_ = 0, far_ = 0;  // far_: the clamp, band_cells cells
  int dims_[3] = {0, 0, 0};
  std::vector<double> values_;
};

// A mesh's clearance far from it (clearance planes, never contacts), from its fine grid and a coarse
// one: `far_clearance_sdf` builds the coarse grid, 1.5 cm cells exact to 7 of them (10 cm,
// hand::kClearanceLook_m). `clearance` gives an outside point's distance from the fine grid where it
// answers, else a lower bound from the coarse one (its trilinear error taken off), and the direction
// out of the mesh; false inside the mesh and beyond the coarse grid's reach. The bound is short of the
// surface by up to twice that error (2.6 cm).
MeshSdf far_clearance_sdf(const hand::SurfaceMesh& mesh);
bool clearance(const MeshSdf& fine, const MeshSdf& far, const Eigen::Vector3d& p, double& gap_m, Eigen::Vector3d& n);

}  // namespace hapticd::world
