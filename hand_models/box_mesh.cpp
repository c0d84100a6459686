#include "hand_models/box_mesh.hpp"

#include <stdexcept>

namespace hapticd::hand {

const std::array<Tet, 6>& kuhn_cube_tets() {
  // One tet per path 0 -> 7 along the cube's edges (one axis at a time).
  static const std::array<Tet, 6> tets = {{{0, 1, 3, 7}, {0, 1, 5, 7}, {0, 2, 3, 7},
                                           {0, 2, 6, 7}, {0, 4, 5, 7}, {0, 4, 6, 7}}};
  return tets;
}

TetMesh make_box_mesh(const Eigen::Vector3d& size, const std::array<int, 3>& cells, const Eigen::Vector3d& origin) {
  if (cells[0] < 1 || cells[1] < 1 || cells[2] < 1) throw std::invalid_argument("box mesh: cells must be >= 1");
  if (!(size.array() > 0).all() || !origin.allFinite()) throw std::invalid_argument("box mesh: size must be > 0");
  TetMesh mesh;
  const int nx = cells[0] + 1, ny = cells[1] + 1, nz = cells[2] + 1;
  auto node = [&](int i, int j, int k) { return i + nx * (j + ny * k); };
  for (int k = 0; k < nz; ++k)
    for (int j = 0; j < ny; ++j)
      for (int i = 0; i < nx; ++i)
        mesh.X.push_back(origin + Eigen::Vector3d(size.x() * i / cells[0], size.y() * j / cells[1],
                                                  size.z() * k / cells[2]));
  for (int k = 0; k < cells[2]; ++k)
    for (int j = 0; j < cells[1]; ++j)
      for (int i = 0; i < cells[0]; ++i) {
        std::array<int, 8> corner;
        for (int c = 0; c < 8; ++c) corner[c] = node(i + (c & 1), j + ((c >> 1) & 1), k + ((c >> 2) & 1));
        for (const Tet& t : kuhn_cube_tets()) mesh.tets.push_back({corner[t[0]], corner[t[1]], corner[t[2]], corner[t[3]]});
      }
  finalize_mesh(mesh);
  return mesh;
}

}  // namespace hapticd::hand
