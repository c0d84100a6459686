#pragma once
// Small hand-like bodies for the coupled-step tests.
#include <cmath>

#include "hand_models/box_mesh.hpp"
#include "hand_models/coupled_solver.hpp"
#include "hand_models/hand_model.hpp"

namespace hapticd::testing_util {

// An 8 x 8 x 2 cm slab of flesh with `handles` handles on a grid over its top.
inline hand::HandModel slab_hand(int handles, hand::HandConfig config = {}, std::array<int, 3> cells = {8, 8, 2}) {
  const double L = 0.08, T = 0.02;
  hand::TetMesh mesh = hand::make_box_mesh({L, L, T}, cells, Eigen::Vector3d(-L / 2, -L / 2, 0));
  config.handles.clear();
  const int side = static_cast<int>(std::ceil(std::sqrt(static_cast<double>(handles))));
  for (int j = 0; j < handles; ++j) {
    const double px = -L / 2 + L * (j % side + 0.5) / side, py = -L / 2 + L * (j / side + 0.5) / side;
    config.handles.push_back({"h" + std::to_string(j), Eigen::Vector3d(px, py, T), std::min(0.5 * L / side, 0.015), {}});
  }
  return hand::HandModel(std::move(mesh), config);
}

// Target of handle j moved by `offset` from its rest pose and rotated by `angle` about z.
inline hand::HandleTarget offset_target(const hand::HandModel& model, int j, const Eigen::Vector3d& offset,
                                        double angle = 0.0) {
  hand::HandleTarget t;
  t.p_W = model.handles()[j].p_WH_rest + offset;
  t.q_W = Eigen::Quaterniond(Eigen::AngleAxisd(angle, Eigen::Vector3d::UnitZ()));
  return t;
}

// Largest relative difference of two solutions of the same system.
inline double relative_difference(const Eigen::VectorXd& a_h, const Eigen::VectorXd& a_t, const Eigen::VectorXd& b_h,
                                  const Eigen::VectorXd& b_t) {
  const double diff = std::sqrt((a_h - b_h).squaredNorm() + (a_t - b_t).squaredNorm());
  return diff / std::sqrt(b_h.squaredNorm() + b_t.squaredNorm());
}

// Smallest determinant of the deformation gradient over all elements.
inline double min_det_F(const hand::HandModel& model, const hand::HandState& s) {
  double m = 1e300;
  for (int e = 0; e < model.fem().num_tets(); ++e) m = std::min(m, model.fem().deformation_gradient(e, s.x).determinant());
  return m;
}

}  // namespace hapticd::testing_util
