#pragma once
// Where a world point lies in a deformed tet mesh and how deep it is inside the
// body's closed surface: the query behind hand-vs-deformable contact.
//
// A uniform grid over the deformed tets' bounding boxes (rebuilt by update()
// each step) finds the tet holding the point; its barycentric coordinates map
// the point back to the rest shape X, where a signed distance grid of the rest
// surface (MeshSdf) gives the distance phi and its unit gradient g. Through the
// tet's deformation gradient F (dX = F^-1 dx),
//   phi(X + dX) ~ phi + (F^-T g) . dx,
// so the deformed depth is -phi / |F^-T g| along n = F^-T g / |F^-T g|: exact
// for an affinely deformed planar face, first order elsewhere.
#include <Eigen/Core>
#include <Eigen/Geometry>
#include <vector>

#include "hand_models/embedded_surface.hpp"
#include "hand_models/tet_mesh.hpp"
#include "server/world/mesh_sdf.hpp"

namespace hapticd::world {

struct MeshPenetration {
  int tet = -1;                                      // the tet holding the point
  Eigen::Vector4d bary{1, 0, 0, 0};                  // its barycentric coordinates there (deformed = rest)
  Eigen::Vector3d p_rest = Eigen::Vector3d::Zero();  // the point mapped to the rest shape
  double depth_m = 0;                                // > 0 inside the surface, < 0 a gap (within the margin)
  Eigen::Vector3d n_W = Eigen::Vector3d::UnitZ();    // unit, out of the body
};

class DeformedMeshQuery {
 public:
  // Points this far outside the mesh, in barycentric units of the nearest tet,
  // are still located (extrapolated): a surface that is the mesh's own boundary
  // then still has speculative contacts just outside it.
  static constexpr double kBarycentricSlack = 0.25;

  DeformedMeshQuery() = default;
  // `surface`: closed and outward, in the coordinates of mesh.X (the rest shape).
  // Its signed distance grid has cells of `sdf_cell_m` and is exact within
  // `sdf_band_cells` cells of the surface (deeper points keep that depth).
  DeformedMeshQuery(const hand::TetMesh& mesh, const hand::SurfaceMesh& surface, double sdf_cell_m,
                    int sdf_band_cells = 6);

  // Rebuilds the grid at deformed node positions x (3n); allocates only when the
  // grid outgrows its largest earlier size.
  void update(const Eigen::VectorXd& x);
  bool empty() const { return tets_.empty(); }
  // Bounding box of the deformed tets at the last update (empty before).
  const Eigen::AlignedBox3d& bounds() const { return bounds_; }
  // The rest surface's signed distance grid.
  const MeshSdf& rest_sdf() const { return sdf_; }

  // The tet holding p (or, within kBarycentricSlack outside the mesh, the
  // nearest) and p's barycentric coordinates in it; false when none.
  bool locate(const Eigen::Vector3d& p_W, int& tet, Eigen::Vector4d& bary) const;
  // Depth and normal of p inside the deformed surface; false when p is not in
  // the mesh, outside the distance grid, or more than margin_m outside the surface.
  bool penetration(const Eigen::Vector3d& p_W, double margin_m, MeshPenetration& out) const;

 private:
  int cell_of(const Eigen::Vector3d& p, int axis) const;

  std::vector<hand::Tet> tets_;
  std::vector<Eigen::Vector3d> X_;     // rest nodes
  std::vector<Eigen::Matrix3d> Dm_T_;  // per tet, Dm^T (rest edge matrix, transposed)
  MeshSdf sdf_;
  Eigen::VectorXd x_;  // deformed nodes at the last update
  Eigen::AlignedBox3d bounds_;
  Eigen::Vector3d origin_ = Eigen::Vector3d::Zero();
  double cell_ = 1;
  int dims_[3] = {0, 0, 0};
  std::vector<int> cell_start_, cell_tets_, fill_;
  std::vector<Eigen::Matrix3d> Ds_inv_;  // per tet, the inverse deformed edge matrix at the last update
  std::vector<char> invertible_;
  std::vector<Eigen::AlignedBox3d> tet_boxes_;  // per tet, its grown bounding box at the last update
  std::vector<Eigen::AlignedBox3i> tet_cells_;  // per tet, its range of grid cells
};

}  // namespace hapticd::world
