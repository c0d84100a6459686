// Penalty point contacts (the world's cheap contact baseline): equivalence with
// the floor, force balance at rest, Coulomb friction when sliding, bad input.
#include <gtest/gtest.h>

#include <limits>

#include "hand_test_util.hpp"

namespace hapticd {
namespace {

using testing_util::offset_target;
using testing_util::slab_hand;

// Floor-like contacts for every node below z = height, built from outside.
std::vector<PointContact> floor_as_contacts(const HandModel& model, const HandState& s, double height, double k,
                                            double d, double mu) {
  std::vector<PointContact> out;
  for (int i = 0; i < model.num_nodes(); ++i) {
    const double depth = height - s.x[3 * i + 2];
    if (depth <= 0) continue;
    PointContact c;
    const auto [tet, local] = model.node_tet(i);
    c.tet = tet;
    c.bary = Eigen::Vector4d::Unit(local);
    c.depth_m = depth;
    c.stiffness_n_m = k;
    c.damping_ns_m = d;
    c.friction = mu;
    out.push_back(c);
  }
  return out;
}

TEST(PointContact, ContactsFromOutsideReproduceTheFloorExactly) {
  HandConfig with_floor;
  with_floor.floor.enabled = true;
  with_floor.floor.height_m = 0.003;
  with_floor.floor.friction = 0.5;
  const HandModel floor_model = slab_hand(1, with_floor);
  const HandModel plain_model = slab_hand(1);
  HandState a = make_rest_state(floor_model), b = make_rest_state(plain_model);
  auto sa = make_solver(SolverKind::schur_cholmod), sb = make_solver(SolverKind::schur_cholmod);
  for (int k = 0; k < 40; ++k) {
    const HandleTarget t = offset_target(floor_model, 0, Eigen::Vector3d(0.002 * k, 0, -0.0002 * k));
    set_target(a, 0, t);
    set_target(b, 0, t);
    b.contacts = floor_as_contacts(plain_model, b, 0.003, with_floor.floor.stiffness_n_m,
                                   with_floor.floor.damping_ns_m, 0.5);
    ASSERT_EQ(step(floor_model, a, *sa), StepStatus::ok);
    ASSERT_EQ(step(plain_model, b, *sb), StepStatus::ok);
  }
  EXPECT_GT(a.floor_contacts, 10);
  EXPECT_LT((a.x - b.x).cwiseAbs().maxCoeff(), 1e-12);
}

TEST(PointContact, RestingOnTheFloorTheContactForcesCarryTheWeight) {
  HandConfig c;
  c.drive = DriveParams{0, 0, 0, 0};  // nothing holds the hand up but the floor
  c.floor.enabled = true;
  c.floor.height_m = 0.0;
  c.floor.stiffness_n_m = 5000;
  c.floor.damping_ns_m = 5;
  const HandModel model = slab_hand(1, c);
  HandState s = make_rest_state(model);
  auto solver = make_solver(SolverKind::schur_cholmod);
  for (int k = 0; k < 240; ++k) ASSERT_EQ(step(model, s, *solver), StepStatus::ok);
  Eigen::Vector3d total = Eigen::Vector3d::Zero();
  double depth_sum = 0;
  for (const PointContact& pc : s.active_contacts) {
    total += pc.f_W;
    depth_sum += pc.depth_m;
  }
  const double weight = 9.81 * (model.fem().lumped_mass().sum() + model.handles()[0].mass_kg);
  EXPECT_NEAR(total.z(), weight, 0.01 * weight);
  EXPECT_LT(std::abs(total.x()) + std::abs(total.y()), 1e-6 * weight);
  // At rest the springs alone carry the weight: sum of k depth = weight.
  EXPECT_NEAR(c.floor.stiffness_n_m * depth_sum, weight, 0.01 * weight);
}

TEST(PointContact, SlidingFrictionIsMuTimesTheNormalForce) {
  HandConfig c;
  c.floor.enabled = true;
  c.floor.height_m = 0.0;
  c.floor.stiffness_n_m = 5000;
  c.floor.friction = 0.4;
  c.drive.stiffness_n_m = 0;  // the handle is dragged by its velocity target only
  c.drive.rot_stiffness_nm_rad = 100;
  const HandModel model = slab_hand(1, c);
  HandState s = make_rest_state(model);
  auto solver = make_solver(SolverKind::schur_cholmod);
  HandleTarget t = offset_target(model, 0, Eigen::Vector3d::Zero());
  t.v_W = Eigen::Vector3d(0.2, 0, 0);  // 20 cm/s, well above the 1 cm/s stick speed
  for (int k = 0; k < 120; ++k) {
    set_target(s, 0, t);
    ASSERT_EQ(step(model, s, *solver), StepStatus::ok);
  }
  Eigen::Vector3d total = Eigen::Vector3d::Zero();
  for (const PointContact& pc : s.active_contacts) total += pc.f_W;
  ASSERT_GT(total.z(), 0.1);
  EXPECT_NEAR(-total.x() / total.z(), 0.4, 0.02 * 0.4);  // opposes the slide, mu N
}

TEST(PointContact, MalformedContactsAreDroppedNotAssembled) {
  const HandModel model = slab_hand(1);
  HandState s = make_rest_state(model);
  auto solver = make_solver(SolverKind::schur_cholmod);
  PointContact bad;
  bad.depth_m = std::numeric_limits<double>::quiet_NaN();
  PointContact out_of_range;
  out_of_range.tet = model.fem().num_tets();
  PointContact not_unit;
  not_unit.n_W = Eigen::Vector3d(0, 0, 2);
  s.contacts = {bad, out_of_range, not_unit};
  EXPECT_EQ(step(model, s, *solver), StepStatus::ok);
  EXPECT_TRUE(s.active_contacts.empty());
  EXPECT_TRUE(s.x.allFinite());
  for (const PointContact& c : s.contacts) EXPECT_EQ(c.f_W, Eigen::Vector3d::Zero());
}

}  // namespace
}  // namespace hapticd
