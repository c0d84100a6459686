#pragma once
// Scene pieces and geometry shared by the world tests.
#include <Eigen/Geometry>
#include <algorithm>

#include "hand_models/hand_model.hpp"
#include "server/world/scene.hpp"

namespace hapticd::testing_util {

// A 350-tet right hand whose palm centre is 3 cm above z = 0.
inline void add_test_hand(world::SceneDesc& scene) {
  world::HandDesc hand;
  hand.name = "right";
  hand.resolution_tets = 350;
  hand.pose.p_W = {0, 0, 0.03};
  scene.hands.push_back(hand);
}

// A 5 cm rigid box on z = 0, in front of the test hand's fingertips.
inline void add_push_box(world::SceneDesc& scene, double mass_kg, double friction = 0.5) {
  world::ObjectDesc box;
  box.name = "box";
  box.shape.type = world::ShapeType::box;
  box.shape.size = {0.05, 0.05, 0.05};
  box.mass_kg = mass_kg;
  box.pose.p_W = {0.0, 0.16, 0.025};
  box.material.friction = friction;
  scene.objects.push_back(box);
}

// The handle target of step k of a push along +y at 10 cm/s from `start`.
inline hand::HandleTarget push_along_y(const hand::HandleState& start, int k, double dt) {
  hand::HandleTarget t;
  t.p_W = start.p_WH + Eigen::Vector3d(0, 0.1 * (k + 1) * dt, 0);
  t.q_W = start.q_WH;
  t.v_W = Eigen::Vector3d(0, 0.1, 0);
  return t;
}

// The point of segment ab nearest p.
inline Eigen::Vector3d segment_closest(const Eigen::Vector3d& p, const Eigen::Vector3d& a, const Eigen::Vector3d& b) {
  const Eigen::Vector3d ab = b - a;
  return a + std::clamp((p - a).dot(ab) / ab.squaredNorm(), 0.0, 1.0) * ab;
}

// The point of triangle abc nearest p: p projected on its plane where that lies inside it, else the
// nearest point of its edges.
inline Eigen::Vector3d triangle_closest(const Eigen::Vector3d& p, const Eigen::Vector3d& a, const Eigen::Vector3d& b,
                                        const Eigen::Vector3d& c) {
  const Eigen::Vector3d n = (b - a).cross(c - a);
  const Eigen::Vector3d q = p - n.dot(p - a) / n.squaredNorm() * n;
  if (n.dot((b - a).cross(q - a)) >= 0 && n.dot((c - b).cross(q - b)) >= 0 && n.dot((a - c).cross(q - c)) >= 0)
    return q;
  Eigen::Vector3d best = segment_closest(p, a, b);
  for (const Eigen::Vector3d& e : {segment_closest(p, b, c), segment_closest(p, c, a)})
    if ((p - e).squaredNorm() < (p - best).squaredNorm()) best = e;
  return best;
}

}  // namespace hapticd::testing_util
