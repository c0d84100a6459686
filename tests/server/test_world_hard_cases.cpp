// World hard cases, with penalty and with constraint contact: a handle driven
// 10 cm into a box in one step, a 2 mm plate, a 3 m/s impact, 1:1000 mass
// ratios. Nothing may go non-finite, reset or fly off; penetration recovers
// once the push stops.
#include <gtest/gtest.h>

#include <algorithm>

#include "hand_models/fem_hand.hpp"
#include "server/world/world.hpp"
#include "world_test_util.hpp"

namespace hapticd::world {
namespace {

// A static slab (top face at z = 0) under a 350-tet hand resting 3 cm above it,
// plus optionally a rigid box to push.
SceneDesc slab_scene(double slab_thickness, double box_mass_kg) {
  SceneDesc scene;
  ObjectDesc slab;
  slab.name = "slab";
  slab.kind = BodyKind::static_body;
  slab.shape.type = ShapeType::box;
  slab.shape.size = {1.0, 1.0, slab_thickness};
  slab.pose.p_W = {0, 0, -0.5 * slab_thickness};
  scene.objects.push_back(slab);
  if (box_mass_kg > 0) testing_util::add_push_box(scene, box_mass_kg);
  testing_util::add_test_hand(scene);
  return scene;
}

hand::HandleTarget target_at(const hand::HandleState& start, const Eigen::Vector3d& offset,
                             const Eigen::Vector3d& v = {0, 0, 0}) {
  hand::HandleTarget t;
  t.p_W = start.p_WH + offset;
  t.q_W = start.q_WH;
  t.v_W = v;
  return t;
}

class WorldHardCases : public testing::TestWithParam<ContactModel> {
 protected:
  WorldOptions options() const {
    WorldOptions o;
    o.contact = GetParam();
    return o;
  }
};

bool finite(const World& w) {
  const hand::FemHand& h = hand::as_fem(w.hand(0));
  bool ok = h.state.x.allFinite() && h.state.v.allFinite();
  for (const RigidBodyState& b : w.snapshot().bodies) ok = ok && b.p_WO.allFinite() && b.v_WO.allFinite();
  return ok;
}

// The lowest skin point of a hand, m.
double lowest_skin_z(const hand::Hand& hand) {
  double lowest = 1e9;
  for (int v = 0; v < hand.num_skin_points(); ++v) lowest = std::min(lowest, hand.skin_point(v).z());
  return lowest;
}

// Presses the test hand's handle 5.5 cm down from its start (2.5 cm past the
// top of a slab under it: ~75 N of drive), ramped over 0.5 s, for 2 s.
void press_into_slab(World& world) {
  hand::FemHand& hand = hand::as_fem(world.hand(0));
  const hand::HandleState start = hand.state.handles[0];
  for (int k = 0; k < 120; ++k) {
    set_target(hand.state, 0, target_at(start, {0, 0, -0.055 * std::min(1.0, k / 30.0)}));
    world.step();
    ASSERT_TRUE(finite(world)) << "step " << k;
  }
}

// The hand at rest on the slab after a press (hand 0, one handle): the load the slab must carry (the
// drive's pull toward the target plus the weight of the flesh and the handle, N, along -z), what the
// contacts carry, their depths and the hand's largest speed.
struct SettledPress {
  double load_n = 0, contact_fz_n = 0, depth_sum_m = 0, max_depth_m = 0, v_max_m_s = 0, mass_kg = 0;
  int points = 0;  // contacts with a positive depth
};
SettledPress settled_press(const World& world, const WorldOptions& o) {
  const hand::FemHand& hand = hand::as_fem(world.hand(0));
  SettledPress r;
  r.mass_kg = hand.model->fem().lumped_mass().sum();
  for (const hand::RigidHandle& h : hand.model->handles()) r.mass_kg += h.mass_kg;
  r.load_n = o.drive.stiffness_n_m * (hand.state.handles[0].p_WH - hand.state.targets[0].p_W).z() + r.mass_kg * 9.81;
  for (const ContactRecord& c : world.snapshot().contacts) {
    if (c.hand != 0) continue;
    r.contact_fz_n += c.f_W.z();
    if (c.depth_m <= 0) continue;
    ++r.points;
    r.depth_sum_m += c.depth_m;
  }
  r.max_depth_m = world.snapshot().max_penetration_m;
  r.v_max_m_s = hand.state.v.cwiseAbs().maxCoeff();
  return r;
}

TEST_P(WorldHardCases, HandleDriven10cmIntoAStaticBoxInOneStepRecoversWithinHalfASecond) {
  World world(slab_scene(0.1, 0), options());
  hand::FemHand& hand = hand::as_fem(world.hand(0));
  const hand::HandleState start = hand.state.handles[0];
  for (int k = 0; k < 30; ++k) {  // 0.5 s with the target 10 cm inside the slab
    set_target(hand.state, 0, target_at(start, {0, 0, -0.1}));
    world.step();
    ASSERT_TRUE(finite(world)) << "step " << k;
  }
  EXPECT_GT(world.snapshot().contacts.size(), 10u);
  for (int k = 0; k < 30; ++k) {  // released: back to the start pose, 3 cm above
    set_target(hand.state, 0, target_at(start, {0, 0, 0}));
    world.step();
    ASSERT_TRUE(finite(world));
  }
  EXPECT_LT(world.snapshot().max_penetration_m, 1e-4);  // recovered within 0.5 s
  EXPECT_EQ(world.snapshot().resets, 0);
}

TEST_P(WorldHardCases, HandPressedOnATwoMillimetrePlateDoesNotTunnelThrough) {
  World world(slab_scene(0.002, 0), options());
  press_into_slab(world);
  EXPECT_GT(lowest_skin_z(world.hand(0)), -0.002);  // no skin point has come out under the plate
  EXPECT_EQ(world.snapshot().resets, 0);
}

// Constraint contacts keep one row per 4 cm cell here: without the cells'
// other points in reserve the skin between rows sinks 1.5 mm into the slab
// under 75 N; with them no point goes deeper than the reserve threshold.
TEST(WorldConstraintContacts, ReservePointsHoldTheSkinBetweenSparseRows) {
  double lowest[2];
  for (bool reserves : {false, true}) {
    WorldOptions o;
    o.contact = ContactModel::constraint;
    o.contact_cluster_m = 0.04;
    o.contact_reserves = reserves;
    World world(slab_scene(0.1, 0), o);
    press_into_slab(world);
    lowest[reserves] = lowest_skin_z(world.hand(0));
    EXPECT_EQ(world.snapshot().resets, 0);
  }
  EXPECT_LT(lowest[0], -1e-3);
  EXPECT_GT(lowest[1], -hand::kReserveDepth_m);
}

TEST_P(WorldHardCases, HandAt3MetresPerSecondIntoABoxStaysFiniteAndSettles) {
  World world(slab_scene(0.1, 0), options());
  hand::FemHand& hand = hand::as_fem(world.hand(0));
  const hand::HandleState start = hand.state.handles[0];
  // The target dives at 3 m/s from 3 cm above the slab to 2 cm inside it in 1/60 s steps, then holds there.
  for (int k = 0; k < 60; ++k) {
    const double dz = std::max(-0.05, -3.0 * (k + 1) * world.dt());
    set_target(hand.state, 0, target_at(start, {0, 0, dz}, {0, 0, dz > -0.05 ? -3.0 : 0.0}));
    world.step();
    ASSERT_TRUE(finite(world)) << "step " << k;
    ASSERT_LT(hand.state.v.cwiseAbs().maxCoeff(), 10.0) << "step " << k;  // m/s: no blow-up
  }
  EXPECT_EQ(world.snapshot().resets, 0);
  // Held pressed: at rest again, the skin no deeper than the drive's force over the contact stiffness allows.
  EXPECT_LT(hand.state.v.cwiseAbs().maxCoeff(), 0.05);
  const WorldOptions o = options();
  const SettledPress p = settled_press(world, o);
  // The reference: the same target reached slowly (5 cm/s over 1 s), then held 1 s.
  World slow(slab_scene(0.1, 0), o);
  for (int k = 0; k < 120; ++k) {
    const double dz = -0.05 * std::min(1.0, (k + 1) / 60.0);
    slow.hand(0).set_target(0, target_at(start, {0, 0, dz}, {0, 0, k < 59 ? -0.05 : 0.0}));
    slow.step();
  }
  const SettledPress ref = settled_press(slow, o);
  std::printf("[3 m/s] load %.3f N (drive + %.3f kg), contacts carry %.3f N; %d points in contact, mean depth %.4g mm "
              "(load / k n: %.4g), deepest %.4g mm (slow press %.4g mm); speed %.2g m/s\n",
              p.load_n, p.mass_kg, p.contact_fz_n, p.points, 1e3 * p.depth_sum_m / std::max(p.points, 1),
              1e3 * p.load_n / (o.contact_stiffness_n_m * std::max(p.points, 1)), 1e3 * p.max_depth_m,
              1e3 * ref.max_depth_m, p.v_max_m_s);
  // At rest the contacts carry the load, up to the forces of the residual motion: each contact's and
  // the drive's damping on the largest speed, and the momentum it could lose in a step.
  const double rest_n = (p.points * o.contact_damping_ns_m + o.drive.damping_ns_m) * p.v_max_m_s +
                        p.mass_kg * p.v_max_m_s / world.dt();
  EXPECT_NEAR(p.contact_fz_n, p.load_n, rest_n);
  if (GetParam() == ContactModel::penalty) {
    // Penalty springs: the mean depth is the load over the contact stiffness of the points in contact.
    EXPECT_NEAR(p.depth_sum_m / p.points, p.load_n / (o.contact_stiffness_n_m * p.points),
                rest_n / (o.contact_stiffness_n_m * p.points));
    // Settled: no point deeper than the same press reached slowly leaves it, up to the depth that
    // the residual motion's damping accounts for at one point (c v / k).
    EXPECT_LE(p.max_depth_m, ref.max_depth_m + o.contact_damping_ns_m * p.v_max_m_s / o.contact_stiffness_n_m);
  } else {
    // Constraint rows are pushed out by kContactDepthRecovery of their depth each step, and a reserve
    // point joins the rows before a step carries it deeper than kReserveDepth_m: settled, nothing deeper.
    EXPECT_LE(p.max_depth_m, hand::kReserveDepth_m);
  }
}

TEST_P(WorldHardCases, PushingObjectsAThousandTimesLighterAndHeavierThanTheHand) {
  const double hand_mass = 0.3;  // kg, about the procedural hand's
  for (double ratio : {1e-3, 1e3}) {
    World world(slab_scene(0.1, ratio * hand_mass), options());
    hand::FemHand& hand = hand::as_fem(world.hand(0));
    RigidWorld& rigid = *world.rigid();
    const int box = rigid.find("box");
    const Eigen::Vector3d box0 = rigid.state(box).p_WO;
    const hand::HandleState start = hand.state.handles[0];
    double max_box_speed = 0;
    for (int k = 0; k < 90; ++k) {  // the hand moves 15 cm along +y at 10 cm/s into the box
      set_target(hand.state, 0, testing_util::push_along_y(start, k, world.dt()));
      world.step();
      ASSERT_TRUE(finite(world)) << "ratio " << ratio << " step " << k;
      max_box_speed = std::max(max_box_speed, rigid.state(box).v_WO.norm());
    }
    const Eigen::Vector3d moved = rigid.state(box).p_WO - box0;
    EXPECT_EQ(world.snapshot().resets, 0) << "ratio " << ratio;
    if (ratio < 1) {
      EXPECT_GT(moved.y(), 0.03) << "the light box is pushed along";
      EXPECT_LT(max_box_speed, 1.0) << "and not launched (the hand moves at 0.1 m/s)";
    } else {
      EXPECT_LT(moved.norm(), 0.005) << "the 300 kg box barely moves";
    }
  }
}

TEST_P(WorldHardCases, ADivergedBodyUnderTheHandIsResetCountedAndNeverReachesTheSnapshotOrTheModel) {
  World world(slab_scene(0.1, 0.3), options());
  hand::FemHand& hand = hand::as_fem(world.hand(0));
  RigidWorld& rigid = *world.rigid();
  const int box = rigid.find("box");
  const hand::HandleState start = hand.state.handles[0];
  const auto model_finite = [&world] {
    const hand::HandleLinearization& m = world.snapshot().linear_models[0];
    return m.K.allFinite() && m.D.allFinite() && m.F0.allFinite();
  };
  for (int k = 0; k < 90; ++k) {  // the hand pushes the box along +y from step ~40 on
    // Mid-push: a NaN velocity, then 200 m/s (4x the bound), set on the box between two steps.
    if (k == 50 || k == 70) {
      const auto& contacts = world.snapshot().contacts;
      ASSERT_TRUE(std::any_of(contacts.begin(), contacts.end(),
                              [&](const ContactRecord& c) { return c.hand == 0 && c.object == box; }))
          << "the hand touches the box at step " << k;
      RigidBodyState b = rigid.state(box);
      b.v_WO = k == 50 ? Eigen::Vector3d(NAN, 0, 0) : Eigen::Vector3d(0, 200, 0);
      rigid.set_state(box, b);
    }
    set_target(hand.state, 0, testing_util::push_along_y(start, k, world.dt()));
    world.step();
    ASSERT_TRUE(finite(world)) << "step " << k;
    ASSERT_TRUE(model_finite()) << "step " << k;
    for (const ContactRecord& c : world.snapshot().contacts) ASSERT_TRUE(c.f_W.allFinite()) << "step " << k;
    EXPECT_EQ(world.snapshot().body_resets, k < 50 ? 0 : k < 70 ? 1 : 2) << "step " << k;
  }
  EXPECT_EQ(world.snapshot().resets, 0);  // the hand itself never diverged
  EXPECT_LT(rigid.state(box).v_WO.norm(), 1.0);
}

INSTANTIATE_TEST_SUITE_P(Contact, WorldHardCases, testing::Values(ContactModel::penalty, ContactModel::constraint),
                         [](const testing::TestParamInfo<ContactModel>& i) {
                           return i.param == ContactModel::penalty ? "penalty" : "constraint";
                         });

}  // namespace
}  // namespace hapticd::world
