#include "hand_models/tet_mesh.hpp"

#include <Eigen/Geometry>

#include <algorithm>
#include <cmath>
#include <map>
#include <sstream>

namespace hapticd::hand {

double signed_volume(const Eigen::Vector3d& a, const Eigen::Vector3d& b,
                     const Eigen::Vector3d& c, const Eigen::Vector3d& d) {
  return (b - a).cross(c - a).dot(d - a) / 6.0;
}

void finalize_mesh(TetMesh& mesh, double min_volume_ratio) {
  const int n = mesh.num_nodes();
  if (n < 4) throw MeshError("mesh has " + std::to_string(n) + " nodes; a tet mesh needs at least 4");
  if (mesh.tets.empty()) throw MeshError("mesh has no tetrahedra");
  for (int i = 0; i < n; ++i) {
    if (!mesh.X[i].allFinite()) throw MeshError("node " + std::to_string(i) + " has a non-finite coordinate");
  }
  double sum = 0.0;
  std::vector<double> vol(mesh.tets.size());
  for (size_t e = 0; e < mesh.tets.size(); ++e) {
    Tet& t = mesh.tets[e];
    for (int k = 0; k < 4; ++k) {
      if (t[k] < 0 || t[k] >= n) {
        std::ostringstream msg;
        msg << "tet " << e << " references node " << t[k] << ", outside [0, " << n - 1 << "]";
        throw MeshError(msg.str());
      }
      for (int j = 0; j < k; ++j) {
        if (t[j] == t[k]) throw MeshError("tet " + std::to_string(e) + " repeats node " + std::to_string(t[k]));
      }
    }
    vol[e] = signed_volume(mesh.X[t[0]], mesh.X[t[1]], mesh.X[t[2]], mesh.X[t[3]]);
    if (vol[e] < 0) {
      std::swap(t[2], t[3]);
      vol[e] = -vol[e];
    }
    sum += vol[e];
  }
  const double mean = sum / static_cast<double>(mesh.tets.size());
  for (size_t e = 0; e < vol.size(); ++e) {
    if (!(vol[e] > min_volume_ratio * mean)) {
      std::ostringstream msg;
      msg << "tet " << e << " is degenerate: volume " << vol[e] << " m^3 vs mean " << mean << " m^3";
      throw MeshError(msg.str());
    }
  }
  mesh.surface = extract_surface(mesh.tets);
}

std::vector<Triangle> extract_surface(const std::vector<Tet>& tets) {
  // Faces of a positively oriented tet (a,b,c,d), each counter-clockwise seen from outside.
  static constexpr int kFace[4][3] = {{0, 2, 1}, {0, 1, 3}, {0, 3, 2}, {1, 2, 3}};
  std::map<std::array<int, 3>, std::pair<Triangle, int>> faces;
  for (const Tet& t : tets) {
    for (const auto& f : kFace) {
      Triangle tri{t[f[0]], t[f[1]], t[f[2]]};
      std::array<int, 3> key = tri;
      std::sort(key.begin(), key.end());
      auto [it, inserted] = faces.try_emplace(key, tri, 0);
      ++it->second.second;
    }
  }
  std::vector<Triangle> out;
  for (const auto& [key, value] : faces) {
    if (value.second == 1) out.push_back(value.first);
  }
  return out;
}

double total_volume(const TetMesh& mesh) {
  double v = 0.0;
  for (const Tet& t : mesh.tets) v += signed_volume(mesh.X[t[0]], mesh.X[t[1]], mesh.X[t[2]], mesh.X[t[3]]);
  return v;
}

}  // namespace hapticd::hand
