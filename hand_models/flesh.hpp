#pragma once
// A body of flesh as the world's collision sees it: a tet mesh stepped by the implicit co-rotational
// FEM step (hand_model.hpp) whose contacts are points embedded in its tets (PointContact's tet and
// barycentric weights), and the points of it that collide (a hand's skin or a deformable object's
// surface vertices), each embedded in a tet. The world finds a flesh's contacts and writes them,
// with the rigid bodies they touch and those bodies' supports, into its state before it steps.
// The deformable FEM hand (seed 004) is such a body behind the Hand interface (Hand::flesh), and so
// is every deformable object. Non-owning: the body that holds the model and state outlives it.
#include <Eigen/Core>
#include <vector>

#include "hand_models/hand_model.hpp"
#include "hand_models/tet_mesh.hpp"

namespace hapticd::hand {

struct Flesh {
  const HandModel* model = nullptr;
  HandState* state = nullptr;
  // The colliding points: per point, the tet it lies in and its weights in the tet's node order.
  const std::vector<int>* point_tet = nullptr;
  const std::vector<Eigen::Vector4d>* point_bary = nullptr;
  // The closed surface through those points at rest (vertex i is point i), outward: how deep a point
  // of another body is inside this flesh is measured against it (hand-hand contact, a rigid mesh's
  // vertices in a hand's flesh).
  const std::vector<Eigen::Vector3d>* rest_surface_vertices = nullptr;
  const std::vector<Triangle>* surface_triangles = nullptr;
  double friction = 0.5;  // Coulomb coefficient of the flesh's surface (combined with the other side's)

  // Point i where the flesh is now (nodal positions x) or how fast it moves (nodal velocities v).
  Eigen::Vector3d point(int i, const Eigen::VectorXd& x_or_v) const {
    const auto k = static_cast<std::size_t>(i);
    return embedded_value(model->mesh().tets[static_cast<std::size_t>((*point_tet)[k])], (*point_bary)[k], x_or_v);
  }
  int num_points() const { return static_cast<int>(point_tet->size()); }
};

}  // namespace hapticd::hand
