#pragma once
// Probe points spread over a hand shape's surface, in the shape's frame: where a rigid hand looks for
// the objects near it (seed 001's contact-point hand starts its contacts at them; the spring hand's
// stylus model takes its rows at them).
#include <Eigen/Core>
#include <vector>

namespace hapticd::hand {

// A capsule with its axis along y from lo to hi and radius r: three stations by eight around, and the
// two poles.
std::vector<Eigen::Vector3d> capsule_probes(double lo, double hi, double r);

// A box of half extents `half`: each face on a grid x grid grid over 80 % of it (grid >= 2).
std::vector<Eigen::Vector3d> box_probes(const Eigen::Vector3d& half, int grid = 3);

}  // namespace hapticd::hand
