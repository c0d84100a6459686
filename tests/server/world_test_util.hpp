#pragma once
// Scene pieces and geometry shared by the world tests.
#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <vector>

#include "hand_models/embedded_surface.hpp"
#include "hand_models/hand_model.hpp"
#include "server/world/scene.hpp"

namespace hapticd::testing_util {

// A static box called "table" of `size`, its top at z = top_z, centred on the z axis.
inline world::ObjectDesc static_table(const Eigen::Vector3d& size, double top_z) {
  world::ObjectDesc table;
  table.name = "table";
  table.kind = world::BodyKind::static_body;
  table.shape.type = world::ShapeType::box;
  table.shape.size = size;
  table.pose.p_W = {0, 0, top_z - 0.5 * size.z()};
  return table;
}

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

// Probe k of `probes` around a surface (clearance tests): from 30 cm out from `centre` along a fixed
// spread of directions, inward in 4 mm steps to the first point within k's share of [near_m, far_m]
// of the triangles (every one tried). Its distance to them and its nearest point on them.
struct SurfaceProbe {
  Eigen::Vector3d p = Eigen::Vector3d::Zero(), nearest = Eigen::Vector3d::Zero();
  double distance = 0;
};
inline SurfaceProbe probe_surface(int k, const Eigen::Vector3d& centre, double near_m, double far_m,
                                  const std::vector<Eigen::Vector3d>& vertices,
                                  const std::vector<hand::Triangle>& triangles) {
  const Eigen::Vector3d dir = Eigen::Vector3d(std::sin(1.3 * k), std::cos(2.1 * k), std::sin(0.7 * k + 1)).normalized();
  const double want = near_m + (far_m - near_m) * (0.5 + 0.5 * std::sin(3.7 * k));
  SurfaceProbe out;
  for (double along = 0.3; along > 0; along -= 0.004) {
    out.p = centre + along * dir;
    out.distance = 1e9;
    for (const hand::Triangle& tri : triangles) {
      const Eigen::Vector3d q = triangle_closest(out.p, vertices[tri[0]], vertices[tri[1]], vertices[tri[2]]);
      if ((out.p - q).norm() < out.distance) out.distance = (out.p - q).norm(), out.nearest = q;
    }
    if (out.distance <= want) break;
  }
  return out;
}

}  // namespace hapticd::testing_util
