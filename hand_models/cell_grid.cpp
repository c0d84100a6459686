#include "hand_models/cell_grid.hpp"

#include <cstddef>
#include <cstdint>
#include <limits>
#include <unordered_map>
#include <unordered_set>

namespace hapticd::hand::detail {

using Eigen::Vector3i;

int label_components(const CellGrid& g, const std::vector<char>& mask, std::vector<int>& label,
                     std::vector<int>& sizes) {
  label.assign(mask.size(), -1);
  sizes.clear();
  std::vector<int> queue;
  for (int start = 0; start < g.num_cells(); ++start) {
    if (!mask[start] || label[start] >= 0) continue;
    const int l = static_cast<int>(sizes.size());
    queue.assign(1, start);
    label[start] = l;
    for (std::size_t q = 0; q < queue.size(); ++q) {
      const Vector3i c = g.cell_coords(queue[q]);
      for (int a = 0; a < 3; ++a) {
        for (int dir = -1; dir <= 1; dir += 2) {
          Vector3i nb = c;
          nb[a] += dir;
          if (nb[a] < 0 || nb[a] >= g.n[a]) continue;
          const int id = g.cell_id(nb);
          if (mask[id] && label[id] < 0) {
            label[id] = l;
            queue.push_back(id);
          }
        }
      }
    }
    sizes.push_back(static_cast<int>(queue.size()));
  }
  return static_cast<int>(sizes.size());
}

void keep_largest_component(const CellGrid& g, std::vector<char>& keep) {
  std::vector<int> label, sizes;
  label_components(g, keep, label, sizes);
  const int best = static_cast<int>(std::max_element(sizes.begin(), sizes.end()) - sizes.begin());
  for (int id = 0; id < g.num_cells(); ++id) keep[id] = label[id] == best ? 1 : 0;
}

CellMesh mesh_cells(const CellGrid& g, const std::vector<char>& keep, const std::array<Tet, 6>& cube_tets) {
  CellMesh out;
  TetMesh& mesh = out.mesh;
  const Vector3i nn = g.n + Vector3i::Ones();
  std::vector<int> node_of(static_cast<std::size_t>(nn.x()) * nn.y() * nn.z(), -1);
  for (int id = 0; id < g.num_cells(); ++id) {
    if (!keep[id]) continue;
    out.cells.push_back(id);
    const Vector3i cell = g.cell_coords(id);
    std::array<int, 8> corner_node;
    for (int c = 0; c < 8; ++c) {
      const Vector3i v = cell + cube_corner(c);
      int& node = node_of[(static_cast<std::size_t>(v.z()) * nn.y() + v.y()) * nn.x() + v.x()];
      if (node < 0) {
        node = mesh.num_nodes();
        mesh.X.push_back(g.corner(v));
      }
      corner_node[c] = node;
    }
    for (const Tet& t : cube_tets) {
      mesh.tets.push_back({corner_node[t[0]], corner_node[t[1]], corner_node[t[2]], corner_node[t[3]]});
    }
  }
  finalize_mesh(mesh);
  return out;
}

CellMesh mesh_cells_by_part(const CellGrid& g, const std::vector<char>& keep, const std::vector<int>& part,
                            int shared, const std::array<Tet, 6>& cube_tets) {
  CellMesh out;
  TetMesh& mesh = out.mesh;
  const Vector3i nn = g.n + Vector3i::Ones();
  auto grid_node = [&](const Vector3i& v) {
    return static_cast<std::int64_t>((static_cast<std::size_t>(v.z()) * nn.y() + v.y()) * nn.x() + v.x());
  };
  // Grid nodes on a cell of the shared part: one node for every cell there.
  std::unordered_set<std::int64_t> merged;
  for (int id = 0; id < g.num_cells(); ++id) {
    if (!keep[id] || part[id] != shared) continue;
    for (int c = 0; c < 8; ++c) merged.insert(grid_node(g.cell_coords(id) + cube_corner(c)));
  }
  // Node of (grid node, part); merged grid nodes are keyed with the shared part.
  std::unordered_map<std::int64_t, int> node_of;
  const std::int64_t parts = 1 + *std::max_element(part.begin(), part.end());
  for (int id = 0; id < g.num_cells(); ++id) {
    if (!keep[id]) continue;
    out.cells.push_back(id);
    const Vector3i cell = g.cell_coords(id);
    std::array<int, 8> corner_node;
    for (int c = 0; c < 8; ++c) {
      const Vector3i v = cell + cube_corner(c);
      const std::int64_t gn = grid_node(v);
      const int copy = merged.count(gn) ? shared : part[id];
      const auto [it, inserted] = node_of.try_emplace(gn * parts + copy, mesh.num_nodes());
      if (inserted) {
        mesh.X.push_back(g.corner(v));
        out.node_part.push_back(copy);
      }
      corner_node[c] = it->second;
    }
    for (const Tet& t : cube_tets) {
      mesh.tets.push_back({corner_node[t[0]], corner_node[t[1]], corner_node[t[2]], corner_node[t[3]]});
    }
  }
  finalize_mesh(mesh);
  return out;
}

double spacing_for_tets(int target_tets, double volume, double h_min, double h_max, bool scan_if_stalled,
                        const std::function<int(double)>& count_tets) {
  const double target = target_tets;
  double best_h = h_max;
  double best_err = std::numeric_limits<double>::infinity();
  auto count = [&](double h) {
    const int c = count_tets(h);
    const double err = std::abs(c - target);
    if (err < best_err || (err == best_err && h > best_h)) {
      best_err = err;
      best_h = h;
    }
    return c;
  };
  double lo = std::clamp(std::cbrt(6.0 * volume / target), h_min, h_max);
  double hi = lo;
  if (count(lo) >= target) {
    while (hi < h_max) {
      hi = std::min(hi * 1.3, h_max);
      if (count(hi) < target) break;
      lo = hi;
    }
  } else {
    while (lo > h_min) {
      lo = std::max(lo / 1.3, h_min);
      if (count(lo) >= target) break;
      hi = lo;
    }
  }
  for (int it = 0; it < 40 && best_err > 0.01 * target && hi / lo > 1.0 + 1e-6; ++it) {
    const double mid = std::sqrt(lo * hi);
    if (count(mid) >= target) lo = mid; else hi = mid;
  }
  if (scan_if_stalled && best_err > 0.01 * target) {
    const double centre = best_h;
    for (int i = -24; i <= 24 && best_err > 0.01 * target; ++i) {
      const double h = centre * std::pow(1.15, i / 24.0);
      if (h >= h_min && h <= h_max) count(h);
    }
  }
  return best_h;
}

}  // namespace hapticd::hand::detail
