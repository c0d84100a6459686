#pragma once
// A tetrahedral mesh in its rest configuration: the constant part of every
// deformable body (hand, deformable object). Units: metres.
#include <Eigen/Core>
#include <array>
#include <stdexcept>
#include <string>
#include <vector>

namespace hapticd::hand {

// Any problem with a mesh (file syntax, inconsistent counts, degenerate
// elements). The message names the file and line where one applies.
class MeshError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

using Tet = std::array<int, 4>;
using Triangle = std::array<int, 3>;

struct TetMesh {
  std::vector<Eigen::Vector3d> X;  // rest node positions, m
  std::vector<Tet> tets;           // node indices, positively oriented
  std::vector<Triangle> surface;   // boundary faces, counter-clockwise seen from outside

  int num_nodes() const { return static_cast<int>(X.size()); }
  int num_tets() const { return static_cast<int>(tets.size()); }
};

// Signed volume of tet (a, b, c, d): positive when (b-a, c-a, d-a) is right-handed.
double signed_volume(const Eigen::Vector3d& a, const Eigen::Vector3d& b,
                     const Eigen::Vector3d& c, const Eigen::Vector3d& d);

// Makes every tet positively oriented (swaps two indices where needed), then
// rebuilds the boundary surface. Throws MeshError naming the first element that
// is out of range, repeats a node, has a non-finite node, or is degenerate
// (|volume| below min_volume_ratio times the mean element volume).
void finalize_mesh(TetMesh& mesh, double min_volume_ratio = 1e-9);

// Faces that belong to exactly one tet, oriented outward.
std::vector<Triangle> extract_surface(const std::vector<Tet>& tets);

// Sum of element volumes, m^3.
double total_volume(const TetMesh& mesh);

// A point embedded in tet t by barycentric weights w: the weighted sum of a 3n nodal vector v over
// the tet's nodes (the point's position for node positions, its velocity for node velocities).
inline Eigen::Vector3d embedded_value(const Tet& t, const Eigen::Vector4d& w, const Eigen::VectorXd& v) {
  Eigen::Vector3d u = Eigen::Vector3d::Zero();
  for (int k = 0; k < 4; ++k) u += w[k] * v.segment<3>(3 * t[k]);
  return u;
}

}  // namespace hapticd::hand
