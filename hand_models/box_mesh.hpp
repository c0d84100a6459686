#pragma once
// A box split into a regular grid of cubes, six tets per cube (Kuhn / Freudenthal
// split along each cube's main diagonal, conforming between neighbours).
#include <array>

#include "hand_models/tet_mesh.hpp"

namespace hapticd::hand {

// Box [origin, origin + size] with cells[i] cells along axis i (each >= 1).
TetMesh make_box_mesh(const Eigen::Vector3d& size, const std::array<int, 3>& cells,
                      const Eigen::Vector3d& origin = Eigen::Vector3d::Zero());

// The six tets of the unit cube with corner index bits (x | y << 1 | z << 2).
const std::array<Tet, 6>& kuhn_cube_tets();

}  // namespace hapticd::hand
