#pragma once
// Internal: the regular cell grid that the procedural hand and embedded surfaces
// mesh on. Each keeps the cells covering its shape, reduces them to the largest
// face-connected component and splits them into six Kuhn tets with shared nodes;
// the spacing is searched for a target tet count.
#include <Eigen/Core>
#include <algorithm>
#include <array>
#include <cmath>
#include <functional>
#include <utility>
#include <vector>

#include "hand_models/tet_mesh.hpp"

namespace hapticd::hand::detail {

// Cell (i, j, k) spans origin + h * [i, i+1] x [j, j+1] x [k, k+1].
struct CellGrid {
  double h = 0.0;
  Eigen::Vector3d origin;
  Eigen::Vector3i n;  // cells per axis

  int num_cells() const { return n.x() * n.y() * n.z(); }
  int cell_id(const Eigen::Vector3i& c) const { return (c.z() * n.y() + c.y()) * n.x() + c.x(); }
  Eigen::Vector3i cell_coords(int id) const {
    return Eigen::Vector3i(id % n.x(), (id / n.x()) % n.y(), id / (n.x() * n.y()));
  }
  Eigen::Vector3d corner(const Eigen::Vector3i& c) const { return origin + h * c.cast<double>(); }
  Eigen::Vector3d centre(const Eigen::Vector3i& c) const { return corner(c) + Eigen::Vector3d::Constant(0.5 * h); }
  // The cell containing p, clamped to the grid.
  Eigen::Vector3i cell_of(const Eigen::Vector3d& p) const {
    const Eigen::Vector3d u = (p - origin) / h;
    Eigen::Vector3i c;
    for (int a = 0; a < 3; ++a) c[a] = std::clamp(static_cast<int>(std::floor(u[a])), 0, n[a] - 1);
    return c;
  }
  // Cells, per axis [first, last], whose box enlarged by slack cells may meet the box [lo, hi].
  std::pair<Eigen::Vector3i, Eigen::Vector3i> cell_range(const Eigen::Vector3d& lo, const Eigen::Vector3d& hi,
                                                         double slack) const {
    Eigen::Vector3i first, last;
    for (int a = 0; a < 3; ++a) {
      first[a] = std::clamp(static_cast<int>(std::floor((lo[a] - origin[a]) / h - slack)), 0, n[a] - 1);
      last[a] = std::clamp(static_cast<int>(std::floor((hi[a] - origin[a]) / h + slack)), 0, n[a] - 1);
    }
    return {first, last};
  }
};

// Uneven fractions of a cell to shift a grid off its anchor: a symmetric placement would add cells in
// symmetric groups (and put flat faces on grid planes), so the tet count would jump in large steps with h.
inline Eigen::Vector3d grid_shift(double h) { return h * Eigen::Vector3d(0.37, 0.21, 0.43); }

// Offset of cube corner c (bit a set: +1 along axis a), the corner numbering of every cube tet table.
inline Eigen::Vector3i cube_corner(int c) { return Eigen::Vector3i(c & 1, (c >> 1) & 1, (c >> 2) & 1); }

// Face-connected components of the cells where mask is set; label -1 elsewhere. Returns the
// component count; sizes[l] is the number of cells of component l. Labels follow cell id order.
int label_components(const CellGrid& g, const std::vector<char>& mask, std::vector<int>& label,
                     std::vector<int>& sizes);

// Clears every kept cell outside the largest face-connected component (the first one on ties).
void keep_largest_component(const CellGrid& g, std::vector<char>& keep);

struct CellMesh {
  TetMesh mesh;                // finalize_mesh applied
  std::vector<int> cells;      // kept cell ids in increasing order; cells[i] owns tets 6i .. 6i+5
  std::vector<int> node_part;  // mesh_cells_by_part only: the part of each node's copy (`shared` if merged)
};

// Splits each kept cell into cube_tets (corners numbered as cube_corner), sharing nodes between
// neighbouring cells; nodes are numbered in order of first use, so the table's order fixes the numbering.
CellMesh mesh_cells(const CellGrid& g, const std::vector<char>& keep, const std::array<Tet, 6>& cube_tets);

// Same, but each kept cell belongs to a part (part[cell id] >= 0) and a grid node gets one copy per
// part among its kept cells, each used only by that part's cells; a grid node that also belongs to
// a cell of part `shared` gets one node that all its cells use. Parts then meet only through the
// shared part (cells of different parts that touch elsewhere are free to separate there). Numbering
// as mesh_cells, copies in order of first use; with a single part it is mesh_cells' mesh.
CellMesh mesh_cells_by_part(const CellGrid& g, const std::vector<char>& keep, const std::vector<int>& part,
                            int shared, const std::array<Tet, 6>& cube_tets);

// Tets of a Kuhn split of the kept cells.
inline int kept_tet_count(const std::vector<char>& keep) {
  return 6 * static_cast<int>(std::count(keep.begin(), keep.end(), 1));
}

// Spacing in [h_min, h_max] whose count_tets(h) is nearest target_tets (the coarser on ties), stopping
// within 1 %. The count must fall with h (roughly); volume (m^3) gives the first guess at h^3 / 6 per tet.
// scan_if_stalled: when bisection ends on a large step, also try 49 spacings within 15 % of the best,
// for counts that are far from monotone.
double spacing_for_tets(int target_tets, double volume, double h_min, double h_max, bool scan_if_stalled,
                        const std::function<int(double)>& count_tets);

}  // namespace hapticd::hand::detail
