// The glove grasps the bench compares the hand models on (server/offline/touch.hpp: the box's tripod,
// the ball's power grasp, the plate's pinch), checked on the skeleton's own geometry, apart from any
// hand model: the commanded hand (hand_skeleton.hpp's phalanges as capsules, placed by the scene and
// the glove's motion) starts clear of the object and the table, and once closed at the object it
// presses into the object with the fingers the grasp names, and only them, by less than the thinnest
// phalanx's diameter (into it, not through it). The closed command may reach into the table (the
// ball's fingertips under its equator do, as a user's would; the simulated hand stops on it): printed,
// not bounded. Distances by sampling each phalanx's axis (0.2 mm apart) against the shapes' exact
// signed distances.
#include <gtest/gtest.h>

#include <algorithm>
#include <array>
#include <cstdio>
#include <string>

#include "hand_models/skeleton/hand_skeleton.hpp"
#include "server/offline/touch.hpp"
#include "server/world/scene_loader.hpp"

namespace hapticd::offline {
namespace {

using Eigen::Vector3d;

const world::ObjectDesc& object(const world::SceneDesc& s, const std::string& name) {
  for (const world::ObjectDesc& o : s.objects)
    if (o.name == name) return o;
  throw std::invalid_argument(name);
}

// Signed distance from p to a box or sphere object, m (negative inside).
double signed_distance(const world::ObjectDesc& o, const Vector3d& p_W) {
  const Vector3d p = o.pose.q_W.conjugate() * (p_W - o.pose.p_W);
  if (o.shape.type == world::ShapeType::sphere) return p.norm() - o.shape.radius;
  const Vector3d q = p.cwiseAbs() - 0.5 * o.shape.size;
  return q.cwiseMax(0.0).norm() + std::min(q.maxCoeff(), 0.0);
}

// The commanded hand at time t: per finger, the least signed distance of its three phalanges (their
// capsules, radius interpolated along the bone) to `o`, m.
std::array<double, hand::kHandFingers> finger_distances(const sim::GloveTrajectory& motion, double t,
                                                        const Eigen::Quaterniond& q_WH, const world::ObjectDesc& o) {
  const hand::SkeletonPose s = hand::skeleton_pose(hand::HandJointAngles::from_vector(motion.angles(t)));
  const sim::Vec3d p = motion.palm_position(t);
  const Vector3d palm_W(p.x, p.y, p.z);
  std::array<double, hand::kHandFingers> d;
  for (int f = 0; f < hand::kHandFingers; ++f) {
    d[f] = 1e9;
    const hand::FingerGeometry& g = hand::finger_geometry()[f];
    for (int k = 0; k < 3; ++k)
      for (int i = 0; i <= 200; ++i) {
        const double u = i / 200.0;
        const Vector3d x = palm_W + q_WH * ((1 - u) * s.joints[f][k] + u * s.joints[f][k + 1]);
        d[f] = std::min(d[f], signed_distance(o, x) - ((1 - u) * g.radius[k] + u * g.radius[k + 1]));
      }
  }
  return d;
}

// The thinnest phalanx's diameter, m (the fingertips of index, ring and little: 15.6 mm).
double thinnest_phalanx() {
  double r = 1;
  for (const hand::FingerGeometry& g : hand::finger_geometry())
    r = std::min(r, *std::min_element(g.radius.begin(), g.radius.end()));
  return 2 * r;
}

struct PlanCase {
  GraspKind kind;
  std::array<bool, hand::kHandFingers> presses;  // thumb .. little: presses into the object when closed
};

class GraspPlans : public ::testing::TestWithParam<PlanCase> {};

TEST_P(GraspPlans, StartClearAndCloseIntoTheirObjectWithTheirFingersOnly) {
  const PlanCase c = GetParam();
  const world::SceneDesc s =
      grasp_scene(world::load_scene(std::string(HAPTICD_SCENES_DIR) + "/glove_grasp.json"), c.kind);
  const world::HandDesc& h = s.hands[0];
  const sim::GloveTrajectory motion = grasp_release_trajectory(h.pose.p_W, h.pose.q_W, c.kind);
  const world::ObjectDesc& held = object(s, grasp_object(c.kind));
  const world::ObjectDesc& table = object(s, "table");
  // Resting on the table, not in it.
  EXPECT_NEAR(signed_distance(table, held.pose.p_W - Vector3d(0, 0,
                                                              held.shape.type == world::ShapeType::sphere
                                                                  ? held.shape.radius
                                                                  : 0.5 * held.shape.size.z())),
              0.0, 1e-9);
  const auto open = finger_distances(motion, 0.0, h.pose.q_W, held);
  const auto open_table = finger_distances(motion, 0.0, h.pose.q_W, table);
  const double t = GraspSchedule::kGrippedAt;
  const auto closed = finger_distances(motion, t, h.pose.q_W, held);
  const auto closed_table = finger_distances(motion, t, h.pose.q_W, table);
  for (int f = 0; f < hand::kHandFingers; ++f) {
    std::printf("%s %s: open %+.1f mm (table %+.1f), closed %+.1f mm (table %+.1f)\n", grasp_name(c.kind),
                hand::finger_name(f), 1e3 * open[f], 1e3 * open_table[f], 1e3 * closed[f], 1e3 * closed_table[f]);
    EXPECT_GT(open[f], 0.005) << hand::finger_name(f) << " starts in the object";
    EXPECT_GT(open_table[f], 0.005) << hand::finger_name(f) << " starts in the table";
    if (c.presses[f]) {
      EXPECT_LT(closed[f], 0.0) << hand::finger_name(f) << " does not reach the object";
      EXPECT_GT(closed[f], -thinnest_phalanx()) << hand::finger_name(f) << " closes through the object";
    } else {
      EXPECT_GT(closed[f], 0.0) << hand::finger_name(f) << " touches the object";
    }
  }
}

const auto kPlans = ::testing::Values(PlanCase{GraspKind::tripod_box, {true, true, true, false, false}},
                                      PlanCase{GraspKind::power_ball, {true, true, true, true, true}},
                                      PlanCase{GraspKind::pinch_plate, {true, true, false, false, false}});

std::string plan_name(const ::testing::TestParamInfo<PlanCase>& info) { return grasp_name(info.param.kind); }

INSTANTIATE_TEST_SUITE_P(Touch, GraspPlans, kPlans, plan_name);

}  // namespace
}  // namespace hapticd::offline
