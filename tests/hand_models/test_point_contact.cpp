// Penalty point contacts (the world's cheap contact baseline): equivalence with
// the floor, force balance at rest, Coulomb friction when sliding, bad input.
#include <gtest/gtest.h>

#include <limits>

#include "hand_test_util.hpp"

namespace hapticd::hand {
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

// Contacts of every node within `margin` of a wall x = x_wall of contact body 0
// (normal -x, out of the body), for slabs pushed along +x.
std::vector<PointContact> wall_contacts(const HandModel& model, const HandState& s, double x_wall, double margin) {
  std::vector<PointContact> out;
  for (int i = 0; i < model.num_nodes(); ++i) {
    const double depth = s.x[3 * i] - x_wall;
    if (depth <= -margin) continue;
    PointContact pc;
    const auto [tet, local] = model.node_tet(i);
    pc.tet = tet;
    pc.bary = Eigen::Vector4d::Unit(local);
    pc.n_W = -Eigen::Vector3d::UnitX();
    pc.depth_m = depth;
    pc.body = 0;
    out.push_back(pc);
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

// A free hand (no gravity, drive or mass damping) thrown against a free body: the
// body is solved implicitly with the hand, so their total momentum is conserved.
TEST(PointContact, ImplicitBodyContactConservesMomentumAtAnyMassRatio) {
  HandConfig c;
  c.gravity_m_s2.setZero();
  c.drive = DriveParams{0, 0, 0, 0};
  c.material.rayleigh_alpha_per_s = 0;
  const HandModel model = slab_hand(1, c);
  const double hand_mass = model.fem().lumped_mass().sum() + model.handles()[0].mass_kg;
  for (double body_mass : {1e-3 * hand_mass, hand_mass, 1e3 * hand_mass}) {
    HandState s = make_rest_state(model);
    for (int i = 0; i < model.num_nodes(); ++i) s.v[3 * i] = 0.5;  // the slab moves along +x
    s.handles[0].v_WH = Eigen::Vector3d(0.5, 0, 0);
    ContactBody body;
    body.gravity_W.setZero();  // no gravity anywhere: momentum is conserved
    body.mass_kg = body_mass;
    body.inertia_W = body_mass * 1e-4 * Eigen::Matrix3d::Identity();
    body.p_com_W = Eigen::Vector3d(0.06, 0, 0.01);
    auto solver = make_solver(SolverKind::schur_cholmod);
    Eigen::Vector3d p0 = linear_momentum(model, s) + body_mass * body.v_W;
    for (int k = 0; k < 30; ++k) {
      // The slab's +x face presses into a wall of the body at x = 0.04 (normal -x out of the body).
      s.bodies = {body};
      s.contacts = wall_contacts(model, s, 0.04 + (body.p_com_W.x() - 0.06), 0.0);
      for (PointContact& pc : s.contacts) pc.stiffness_n_m = 5000, pc.damping_ns_m = 5, pc.friction = 0.5;
      ASSERT_EQ(step(model, s, *solver), StepStatus::ok);
      body.v_W += s.bodies[0].dv_W;
      body.w_W += s.bodies[0].dw_W;
      body.p_com_W += c.dt_s * body.v_W;
    }
    const Eigen::Vector3d p1 = linear_momentum(model, s) + body_mass * body.v_W;
    EXPECT_LT((p1 - p0).norm(), 1e-9 * p0.norm()) << "body/hand mass " << body_mass / hand_mass;
    EXPECT_GT(body.v_W.x(), 0.0) << "the body was pushed";
    EXPECT_TRUE(s.x.allFinite());
  }
}

TEST(ConstraintContact, SlabRestsOnTheFloorWithoutPenetrationAndCarriesItsWeight) {
  HandConfig c;
  c.drive = DriveParams{0, 0, 0, 0};
  const HandModel model = slab_hand(1, c);
  HandState s = make_rest_state(model);
  for (int i = 0; i < model.num_nodes(); ++i) s.x[3 * i + 2] += 0.002;  // dropped from 2 mm
  auto solver = make_solver(SolverKind::schur_cholmod);
  double max_depth_late = 0;
  for (int k = 0; k < 180; ++k) {
    s.contacts = floor_as_contacts(model, s, 0.0, 0, 0, 0.5);
    for (PointContact& pc : s.contacts) pc.constraint = true;
    // Nodes within 1 mm above the floor are contacts too (a speculative margin):
    // the constraint keeps them from crossing it during the step.
    for (int i = 0; i < model.num_nodes(); ++i) {
      const double gap = s.x[3 * i + 2];
      if (gap <= 0 || gap > 1e-3) continue;
      PointContact pc;
      const auto [tet, local] = model.node_tet(i);
      pc.tet = tet;
      pc.bary = Eigen::Vector4d::Unit(local);
      pc.depth_m = -gap;
      pc.friction = 0.5;
      pc.constraint = true;
      s.contacts.push_back(pc);
    }
    ASSERT_EQ(step(model, s, *solver), StepStatus::ok) << "step " << k;
    if (k >= 120)
      for (int i = 0; i < model.num_nodes(); ++i) max_depth_late = std::max(max_depth_late, -s.x[3 * i + 2]);
  }
  EXPECT_LT(max_depth_late, 0.05e-3);  // m: far below a penalty contact's sag
  Eigen::Vector3d total = Eigen::Vector3d::Zero();
  for (const PointContact& pc : s.contacts) total += pc.f_W;
  const double weight = 9.81 * (model.fem().lumped_mass().sum() + model.handles()[0].mass_kg);
  EXPECT_NEAR(total.z(), weight, 0.02 * weight);
  EXPECT_LT(s.v.cwiseAbs().maxCoeff(), 1e-3);  // at rest
}

TEST(ConstraintContact, PushingAnImplicitBodyConservesMomentum) {
  HandConfig c;
  c.gravity_m_s2.setZero();
  c.drive = DriveParams{0, 0, 0, 0};
  c.material.rayleigh_alpha_per_s = 0;
  const HandModel model = slab_hand(1, c);
  HandState s = make_rest_state(model);
  for (int i = 0; i < model.num_nodes(); ++i) s.v[3 * i] = 0.5;
  s.handles[0].v_WH = Eigen::Vector3d(0.5, 0, 0);
  ContactBody body;
  body.gravity_W.setZero();  // no gravity anywhere: momentum is conserved
  body.mass_kg = 0.05;
  body.inertia_W = 0.05 * 1e-4 * Eigen::Matrix3d::Identity();
  body.p_com_W = Eigen::Vector3d(0.06, 0, 0.01);
  auto solver = make_solver(SolverKind::schur_cholmod);
  const Eigen::Vector3d p0 = linear_momentum(model, s) + body.mass_kg * body.v_W;
  for (int k = 0; k < 30; ++k) {
    s.bodies = {body};
    s.contacts = wall_contacts(model, s, body.p_com_W.x() - 0.02, 1e-3);  // 1 mm speculative margin
    for (PointContact& pc : s.contacts) pc.friction = 0.3, pc.constraint = true;
    ASSERT_EQ(step(model, s, *solver), StepStatus::ok);
    body.v_W += s.bodies[0].dv_W;
    body.w_W += s.bodies[0].dw_W;
    body.p_com_W += c.dt_s * body.v_W;
  }
  const Eigen::Vector3d p1 = linear_momentum(model, s) + body.mass_kg * body.v_W;
  EXPECT_LT((p1 - p0).norm(), 1e-6 * p0.norm());  // PGS tolerance 1e-8 on the impulses
  EXPECT_GT(body.v_W.x(), 0.1);                     // pushed along
}

}  // namespace
}  // namespace hapticd::hand
