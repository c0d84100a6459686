#include "hand_models/shape_probes.hpp"

#include <cmath>

namespace hapticd::hand {

std::vector<Eigen::Vector3d> capsule_probes(double lo, double hi, double r) {
  std::vector<Eigen::Vector3d> out;
  for (int a = 0; a < 3; ++a) {
    const double y = lo + 0.5 * a * (hi - lo);
    for (int k = 0; k < 8; ++k) {
      const double phi = k * M_PI / 4;
      out.emplace_back(r * std::cos(phi), y, r * std::sin(phi));
    }
  }
  out.emplace_back(0, lo - r, 0);
  out.emplace_back(0, hi + r, 0);
  return out;
}

std::vector<Eigen::Vector3d> box_probes(const Eigen::Vector3d& half, int grid) {
  std::vector<Eigen::Vector3d> out;
  for (int axis = 0; axis < 3; ++axis)
    for (int sign = -1; sign <= 1; sign += 2)
      for (int i = 0; i < grid; ++i)
        for (int j = 0; j < grid; ++j) {
          const double a = -1.0 + 2.0 * i / (grid - 1), b = -1.0 + 2.0 * j / (grid - 1);
          Eigen::Vector3d p;
          p[axis] = sign * half[axis];
          p[(axis + 1) % 3] = 0.8 * a * half[(axis + 1) % 3];
          p[(axis + 2) % 3] = 0.8 * b * half[(axis + 2) % 3];
          out.push_back(p);
        }
  return out;
}

}  // namespace hapticd::hand
