#include "hand_models/procedural_handles.hpp"

#include <algorithm>
#include <cmath>
#include <numbers>
#include <stdexcept>

namespace hapticd::hand {
namespace {

// Phalanx indices of handles 1 .. m - 1.
std::vector<int> handle_phalanges(int m) {
  if (m < 1 || m > 16) throw std::invalid_argument("handles: must be in [1, 16], got " + std::to_string(m));
  std::vector<int> order;
  if (m == 6) {
    for (int f = 0; f < 5; ++f) order.push_back(3 * f + 2);
  } else {
    for (int i = 0; i < m - 1; ++i) order.push_back(i);
  }
  return order;
}

}  // namespace

std::vector<HandFrame> procedural_handle_frames(const ProceduralHand& hand, int m) {
  std::vector<HandFrame> frames{hand.palm};
  for (int i : handle_phalanges(m)) frames.push_back(hand.phalanges[i]);
  return frames;
}

std::vector<int> procedural_skin_handles(const ProceduralHand& hand, int m) {
  const std::vector<int> phalanges = handle_phalanges(m);
  std::vector<int> handle_of_phalanx(15, 0);
  for (size_t j = 0; j < phalanges.size(); ++j) {
    if (m == 6) {
      for (int k = 0; k < 3; ++k) handle_of_phalanx[phalanges[j] - 2 + k] = static_cast<int>(j) + 1;
    } else {
      handle_of_phalanx[phalanges[j]] = static_cast<int>(j) + 1;
    }
  }
  std::vector<int> out(hand.skin_vertices.size(), 0);
  for (size_t v = 0; v < hand.skin_vertices.size(); ++v) {
    const Eigen::Vector3d& X = hand.skin_vertices[v];
    double best = 1e300;
    for (int f = 0; f < 5; ++f) {
      for (int k = 0; k < 3; ++k) {
        const Eigen::Vector3d a = hand.joints[f][k], ab = hand.joints[f][k + 1] - a;
        const double t = ab.dot(X - a) / ab.squaredNorm();
        const double d = (X - (a + std::clamp(t, 0.0, 1.0) * ab)).norm();
        if (d >= best) continue;
        best = d;
        out[v] = k == 0 && t < 0 ? 0 : handle_of_phalanx[3 * f + k];
      }
    }
  }
  return out;
}

namespace {

// Where a finger node of a separate-fingers hand sits on its finger's bones:
// the handle of its phalanx (m = 16 numbering: 1 + 3 finger + phalanx; 0 for
// the palm) and whether it lies within a joint's band, +-kJointBand flesh
// radii (at most 0.4 of either bone) along the bisector of the joint's bones.
struct BoneSide {
  int handle = 0;
  bool in_joint = false;
};

BoneSide bone_side(const ProceduralHand& hand, int i) {
  const int f = hand.node_part[i];
  if (f == kHandPalmPart) return {};
  const Eigen::Vector3d& X = hand.mesh.X[i];
  const auto& J = hand.joints[f];
  // The nearest bone k of the node's finger and where along it the node is.
  int k = 0;
  double t = 0, best = 1e300;
  for (int b = 0; b < 3; ++b) {
    const Eigen::Vector3d ab = J[b + 1] - J[b];
    const double tb = ab.dot(X - J[b]) / ab.squaredNorm();
    const double d = (X - (J[b] + std::clamp(tb, 0.0, 1.0) * ab)).norm();
    if (d < best) best = d, k = b, t = tb;
  }
  // The nearer joint along that bone (0: the base joint, whose proximal side is the palm).
  const int j = t <= 0.5 ? k : k + 1;
  if (j == 3) return {1 + 3 * f + 2, false};  // the fingertip
  const Eigen::Vector3d u_in = j == 0 ? Eigen::Vector3d(J[1] - J[0]) : Eigen::Vector3d(J[j] - J[j - 1]);
  const Eigen::Vector3d u = (u_in.normalized() + (J[j + 1] - J[j]).normalized()).normalized();
  double band = std::min(kJointBand * finger_geometry()[f].radius[j], 0.4 * (J[j + 1] - J[j]).norm());
  if (j > 0) band = std::min(band, 0.4 * (J[j] - J[j - 1]).norm());
  const double s = (X - J[j]).dot(u);
  const int distal = 1 + 3 * f + j;
  return {s >= 0 ? distal : (j == 0 ? 0 : distal - 1), std::abs(s) < band};
}

}  // namespace

std::vector<double> procedural_joint_stiffness(const ProceduralHand& hand, int m, double scale) {
  if (m != 1 + kHandPhalanges || hand.node_part.empty()) return {};
  std::vector<BoneSide> side(hand.mesh.num_nodes());
  for (int i = 0; i < hand.mesh.num_nodes(); ++i) side[i] = bone_side(hand, i);
  std::vector<double> k(hand.mesh.tets.size(), 1.0);
  for (size_t e = 0; e < k.size(); ++e) {
    const Tet& t = hand.mesh.tets[e];
    bool joint = false;
    for (int a = 0; a < 4; ++a) joint = joint || side[t[a]].in_joint || side[t[a]].handle != side[t[0]].handle;
    if (joint) k[e] = scale;
  }
  return k;
}

std::vector<HandleTarget> posture_targets(const ProceduralHand& hand, const HandModel& model,
                                          const HandJointAngles& angles, const Eigen::Vector3d& p_W,
                                          const Eigen::Quaterniond& q_W, bool left) {
  const int m = model.num_handles();
  const std::vector<int> phalanges = handle_phalanges(m);
  const std::vector<HandFrame> rest = procedural_handle_frames(hand, m);
  const SkeletonPose pose = skeleton_pose(angles, left);
  std::vector<HandleTarget> targets(m);
  for (int j = 0; j < m; ++j) {
    const FrameToHandle o = frame_to_handle(rest[j].p, rest[j].R, model.handles()[j]);
    Eigen::Vector3d p_frame = p_W;
    Eigen::Quaterniond q_frame = q_W;
    if (j > 0) {
      const int i = phalanges[j - 1];
      p_frame = p_W + q_W * pose.centre[i];
      q_frame = q_W * Eigen::Quaterniond(pose.R[i]);
    }
    targets[j].p_W = p_frame + q_frame * o.p_F;
    targets[j].q_W = (q_frame * o.q_F).normalized();
  }
  return targets;
}

namespace {

// Separate fingers: copies of a grid node sit at one place, so a sphere takes
// the neighbouring fingers' copies too. Each handle takes the nodes of its own
// part (the palm's, or its finger's) inside its sphere, a node two handles
// reach going to the nearer seed; a handle left without one takes its part's
// node nearest its seed.
void take_own_part_nodes(const ProceduralHand& hand, int m, std::vector<HandleSpec>& specs) {
  const std::vector<int> phalanges = handle_phalanges(m);
  const int n = hand.mesh.num_nodes();
  std::vector<int> owner(n, -1);
  std::vector<double> best(n, 1e300);
  auto part_of = [&](int j) { return j == 0 ? kHandPalmPart : phalanges[j - 1] / 3; };
  for (int j = 0; j < m; ++j) {
    for (int i = 0; i < n; ++i) {
      const double d = (hand.mesh.X[i] - specs[j].seed).norm();
      if (hand.node_part[i] != part_of(j) || d > specs[j].radius_m || d >= best[i]) continue;
      best[i] = d;
      owner[i] = j;
    }
  }
  for (int i = 0; i < n; ++i)
    if (owner[i] >= 0) specs[owner[i]].nodes.push_back(i);
  for (int j = 0; j < m; ++j) {
    if (!specs[j].nodes.empty()) continue;
    int nearest = -1;
    for (int i = 0; i < n; ++i)
      if (hand.node_part[i] == part_of(j) &&
          (nearest < 0 || (hand.mesh.X[i] - specs[j].seed).norm() < (hand.mesh.X[nearest] - specs[j].seed).norm()))
        nearest = i;
    if (nearest >= 0) specs[j].nodes.push_back(nearest);
  }
}

}  // namespace

std::vector<HandleSpec> procedural_handles(const ProceduralHand& hand, int m) {
  // The palm handle grabs the palm's core (seed 004: 79 nodes at 350 tets); every
  // handle reaches at least the nearest grid nodes whatever the resolution.
  const double reach = 1.2 * hand.spacing;
  std::vector<HandleSpec> specs{{hand.palm.name, hand.palm.p, std::max({hand.palm.radius, 0.03, reach}), {}}};
  for (int i : handle_phalanges(m))
    specs.push_back({hand.phalanges[i].name, hand.phalanges[i].p, std::max(hand.phalanges[i].radius, reach), {}});
  if (!hand.node_part.empty()) take_own_part_nodes(hand, m, specs);
  return specs;
}

}  // namespace hapticd::hand
