#pragma once
// Scene pieces shared by the world tests.
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

}  // namespace hapticd::testing_util
