// Two hands in one world: a right hand and a left hand (its mirror image),
// palm to palm, touch each other's flesh (hand-hand contact, World::step):
// pressed together by their drives they stop at each other's skin and each
// drive holds what the other hand pushes; let go after a push, they pass its
// momentum on (exactly with constraint contacts, within a few percent with
// penalty contacts); in both contact models.
// A single hand builds nothing for it. The shipped two-hand scene steps.
#include <gtest/gtest.h>

#include <Eigen/Geometry>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <numbers>

#include "hand_models/fem_hand.hpp"
#include "hand_models/procedural_hand.hpp"
#include "server/world/scene_loader.hpp"
#include "server/world/world.hpp"
#include "world_test_util.hpp"

namespace hapticd::world {
namespace {

constexpr int kTets = 700;
// A device-like stiff drive (N/m, N s/m, N m/rad, N m s/rad), as the server's proxies.
constexpr hand::DriveParams kStiffDrive{1e6, 1e3, 1e3, 10};

// How far below its hand frame's origin (the palm centre) a right hand's
// palmar skin (-z) meets that of another right hand turned half a turn about
// x (palm up, fingers the other way, over the same centre), m: the palms are
// not flat, so their pads meet where h(x, y) + h(-x, -y) is lowest, h the
// height of the palmar surface (the hand's signed distance's zero, bisected)
// over a 2 mm grid over the palm.
double palms_meet_depth() {
  auto height = [](double x, double y) {
    double inside = 0, outside = -0.04;  // the palm centre is inside, 4 cm below it is not
    for (int i = 0; i < 40; ++i) {
      const double z = 0.5 * (inside + outside);
      (hand::procedural_hand_sdf(Eigen::Vector3d(x, y, z)) < 0 ? inside : outside) = z;
    }
    return inside;
  };
  double lowest = 0;
  for (double x = -0.03; x <= 0.03; x += 0.002)
    for (double y = -0.035; y <= 0.035; y += 0.002) lowest = std::min(lowest, height(x, y) + height(-x, -y));
  return -lowest / 2;
}

// The right hand palm down above the plane z = 0, the left hand below it,
// turned palm up by half a turn about x (its fingers along -y): palm over
// palm, each hand the other's point reflection through the origin, the thumbs
// clear of each other. Their palms' skins are gap_m apart. The left hand may
// be moved along the plane and turned about z (then no symmetry balances the
// two hands' forces). No gravity.
SceneDesc palm_to_palm(double gap_m, double rayleigh_alpha_per_s = 1.0,
                       const Eigen::Vector3d& left_shift = Eigen::Vector3d::Zero(), double left_turn_rad = 0) {
  SceneDesc scene;
  scene.gravity_m_s2.setZero();
  static const double reach = palms_meet_depth();
  const double z = gap_m / 2 + reach;  // each palm centre's distance from the plane
  HandDesc right;
  right.name = "right";
  right.resolution_tets = kTets;
  right.pose.p_W = {0, 0, z};
  right.material.rayleigh_alpha_per_s = rayleigh_alpha_per_s;
  HandDesc left = right;
  left.name = "left";
  left.side = HandSide::left;
  left.pose.p_W = Eigen::Vector3d(0, 0, -z) + left_shift;
  left.pose.q_W = Eigen::AngleAxisd(left_turn_rad, Eigen::Vector3d::UnitZ()) *
                  Eigen::AngleAxisd(std::numbers::pi, Eigen::Vector3d::UnitX());
  scene.hands = {right, left};
  return scene;
}

Eigen::Vector3d total(const Eigen::VectorXd& f) {
  Eigen::Vector3d sum = Eigen::Vector3d::Zero();
  for (int i = 0; i < f.size() / 3; ++i) sum += f.segment<3>(3 * i);
  return sum;
}

// The drive's force on handle 0 (the palm), N.
Eigen::Vector3d drive_force(const hand::FemHand& hand) {
  const hand::DriveParams& d = hand.model->config().drive;
  const hand::HandleState& h = hand.state.handles[0];
  const hand::HandleTarget& t = hand.state.targets[0];
  return -d.stiffness_n_m * (h.p_WH - t.p_W) - d.damping_ns_m * (h.v_WH - t.v_W);
}

// The deepest skin point of hand `skin` inside hand `flesh`, m: every skin
// point (not only those the contacts kept), through a query of the flesh's
// own (a world without hand-hand contact has none).
double deepest_skin_point(const hand::FemHand& skin, const hand::FemHand& flesh) {
  DeformedMeshQuery query(flesh.model->mesh(), hand::SurfaceMesh{flesh.shape.skin_vertices, flesh.shape.skin_triangles},
                          0.003, 6);
  query.update(flesh.state.x);
  double deepest = 0;
  for (size_t v = 0; v < skin.shape.skin_tet.size(); ++v) {
    const hand::Tet& t = skin.model->mesh().tets[skin.shape.skin_tet[v]];
    Eigen::Vector3d p = Eigen::Vector3d::Zero();
    for (int k = 0; k < 4; ++k) p += skin.shape.skin_bary[v][k] * skin.state.x.segment<3>(3 * t[k]);
    MeshPenetration pen;
    if (query.penetration(p, 0, pen)) deepest = std::max(deepest, pen.depth_m);
  }
  return deepest;
}

class TwoHands : public testing::TestWithParam<ContactModel> {
 protected:
  WorldOptions options(const hand::DriveParams& drive = kStiffDrive) const {
    WorldOptions o;
    o.contact = GetParam();
    o.hand_gravity = false;
    o.drive = drive;
    return o;
  }
};

// Pressing, from palms 2 cm apart: each palm target moves 11.5 mm toward the
// other hand at 3 cm/s, then holds: the targets overlap by 3 mm, which the
// flesh and the contacts take up. Also: the mean step time and the deepest
// hand-hand contact recorded.
struct PressResult {
  double step_ms = 0, collide_ms = 0, max_depth_m = 0;  // mean step and collision times
  int touching_steps = 0;
};
PressResult press(World& world, int steps) {
  PressResult r;
  const hand::HandleTarget start[2] = {hand::as_fem(world.hand(0)).state.targets[0],
                                       hand::as_fem(world.hand(1)).state.targets[0]};
  constexpr double kTravel = 0.0115, kSpeed = 0.03;  // m, m/s (each hand)
  double time_ms = 0;
  for (int k = 0; k < steps; ++k) {
    const double t = (k + 1) * world.dt();
    for (int h = 0; h < 2; ++h) {
      hand::HandleTarget target = start[h];
      const double sign = h == 0 ? -1 : 1;  // the right hand comes down, the left hand up
      target.p_W.z() += sign * std::min(kTravel, kSpeed * t);
      target.v_W.z() = kSpeed * t < kTravel ? sign * kSpeed : 0;
      set_target(hand::as_fem(world.hand(h)).state, 0, target);
    }
    const auto t0 = std::chrono::steady_clock::now();
    world.step();
    time_ms += std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
    r.collide_ms += world.snapshot().timings.collide_ms / steps;
    bool touching = false;
    for (const ContactRecord& c : world.snapshot().contacts)
      if (c.other_hand >= 0) {
        touching = true;
        r.max_depth_m = std::max(r.max_depth_m, c.depth_m);
      }
    r.touching_steps += touching;
  }
  r.step_ms = time_ms / steps;
  return r;
}

TEST_P(TwoHands, PressedPalmToPalmTheyStopAtEachOtherWithEqualAndOppositeForces) {
  World world(palm_to_palm(0.02), options());
  ASSERT_EQ(world.num_hands(), 2);
  hand::FemHand& right = hand::as_fem(world.hand(0));
  hand::FemHand& left = hand::as_fem(world.hand(1));
  ASSERT_NE(world.hand_query(0), nullptr);
  ASSERT_NE(world.hand_query(1), nullptr);
  const PressResult r = press(world, 240);  // 4 s: 0.4 s moving, then holding
  const WorldSnapshot& s = world.snapshot();
  ASSERT_TRUE(right.state.x.allFinite() && left.state.x.allFinite());
  EXPECT_EQ(s.resets, 0);
  EXPECT_GT(r.touching_steps, 200);

  // Both ways: the right hand's skin in the left hand's flesh and the left's
  // in the right's, each recorded for both hands (at a skin point, or in the flesh: point -1).
  int right_in_left = 0, left_in_right = 0;
  Eigen::Vector3d recorded[2] = {Eigen::Vector3d::Zero(), Eigen::Vector3d::Zero()};
  for (const ContactRecord& c : s.contacts) {
    if (c.other_hand < 0) continue;
    EXPECT_EQ(c.object, -1);
    EXPECT_EQ(c.other_deformable, -1);
    ASSERT_EQ(c.hand + c.other_hand, 1);
    right_in_left += c.hand == 0 && c.point >= 0;
    left_in_right += c.hand == 1 && c.point >= 0;
    recorded[c.hand] += c.f_W;
  }
  EXPECT_GT(right_in_left, 0);
  EXPECT_GT(left_in_right, 0);

  // Equal and opposite: what each hand's step took from the other.
  const Eigen::Vector3d on_right = total(world.hand_contact_forces(0)), on_left = total(world.hand_contact_forces(1));
  // The drives at rest hold what the other hand pushes (no gravity, no other contact).
  const Eigen::Vector3d drive_right = drive_force(right), drive_left = drive_force(left);
  const double force = on_right.norm();
  const double drift = std::max(right.state.v.cwiseAbs().maxCoeff(), left.state.v.cwiseAbs().maxCoeff());  // m/s
  std::printf(
      "%s: contact force on right (%.3f, %.3f, %.3f) N, on left (%.3f, %.3f, %.3f) N, balance error %.2e N; "
      "drives %.3f / %.3f N (error %.2e / %.2e N); skin points in contact %d + %d; deepest skin point %.3f mm "
      "(recorded %.3f mm); node speed %.1e m/s; step %.2f ms\n",
      std::string(to_string(GetParam())).c_str(), on_right.x(), on_right.y(), on_right.z(), on_left.x(), on_left.y(),
      on_left.z(), (on_right + on_left).norm(), drive_right.z(), drive_left.z(), (drive_right + on_right).norm(),
      (drive_left + on_left).norm(), right_in_left, left_in_right,
      1e3 * std::max(deepest_skin_point(right, left), deepest_skin_point(left, right)), 1e3 * r.max_depth_m, drift,
      r.step_ms);
  EXPECT_GT(on_right.z(), 1.5);           // pushed up, N: the targets overlap by 3 mm
  EXPECT_GT(on_right.z(), 0.95 * force);  // palm to palm: along z, but for the pads' slopes
  // The records hold every force the steps applied.
  EXPECT_LT((recorded[0] - on_right).norm(), 1e-9 * force);
  EXPECT_LT((recorded[1] - on_left).norm(), 1e-9 * force);
  if (GetParam() == ContactModel::constraint) {
    EXPECT_LT((on_right + on_left).norm(), 1e-9 * force);  // the impulses themselves, handed over
  } else {
    // Each hand's own penalty contacts, equal at rest (the same depths, against the same midpoints).
    EXPECT_LT((on_right + on_left).norm(), 1e-3 * force);
  }
  EXPECT_LT((drive_right + on_right).norm(), 0.01 * force);
  EXPECT_LT((drive_left + on_left).norm(), 0.01 * force);
  EXPECT_LT(drift, 1e-3);  // at rest
  // Neither passes into the other: no skin point deeper than 2 mm in the other hand.
  EXPECT_LT(deepest_skin_point(right, left), 2e-3);
  EXPECT_LT(deepest_skin_point(left, right), 2e-3);
  EXPECT_LT(r.max_depth_m, 2e-3);
}

// The right hand, let go (no drive), flies at 0.3 m/s into the resting left
// hand 1 cm away, which is moved 1.5 cm along x and 2 cm along y and turned by
// 20 degrees: nothing but the contacts' pairing balances the two hands'
// forces. Without mass-proportional damping nothing else changes the hands'
// momentum: the contacts only move it from one hand to the other.
TEST_P(TwoHands, LetGoAfterAPushTheyConserveMomentum) {
  World world(palm_to_palm(0.01, 0.0, {0.015, 0.02, 0}, 0.35), options(hand::DriveParams{0, 0, 0, 0}));
  hand::FemHand& right = hand::as_fem(world.hand(0));
  hand::FemHand& left = hand::as_fem(world.hand(1));
  const Eigen::Vector3d v0(0, 0, -0.3);
  for (int i = 0; i < right.model->num_nodes(); ++i) right.state.v.segment<3>(3 * i) = v0;
  right.state.handles[0].v_WH = v0;
  const Eigen::Vector3d P0 = linear_momentum(*right.model, right.state) + linear_momentum(*left.model, left.state);
  double worst = 0, deepest = 0;
  int touching_steps = 0;
  for (int k = 0; k < 60; ++k) {  // 1 s
    world.step();
    ASSERT_TRUE(right.state.x.allFinite() && left.state.x.allFinite()) << "step " << k;
    const Eigen::Vector3d P = linear_momentum(*right.model, right.state) + linear_momentum(*left.model, left.state);
    worst = std::max(worst, (P - P0).norm());
    bool touching = false;
    for (const ContactRecord& c : world.snapshot().contacts)
      if (c.other_hand >= 0) touching = true, deepest = std::max(deepest, c.depth_m);
    touching_steps += touching;
  }
  const Eigen::Vector3d P_right = linear_momentum(*right.model, right.state);
  const Eigen::Vector3d P_left = linear_momentum(*left.model, left.state);
  std::printf(
      "%s: momentum %.4f kg m/s, error up to %.2e kg m/s (%.1e); right %.4f, left %.4f kg m/s; touching %d "
      "steps, deepest %.2f mm\n",
      std::string(to_string(GetParam())).c_str(), P0.norm(), worst, worst / P0.norm(), P_right.z(), P_left.z(),
      touching_steps, 1e3 * deepest);
  EXPECT_EQ(world.snapshot().resets, 0);
  EXPECT_GT(touching_steps, 0);
  EXPECT_LT(P_left.z(), 0.3 * P0.z());  // the push passed: a good part of it is the left hand's now
  if (GetParam() == ContactModel::constraint) {
    EXPECT_LT(worst, 1e-9 * P0.norm());  // the impulses themselves, handed over
  } else {
    // Each hand's own penalty contacts, against the pair's midpoint as it
    // moved at the start of the step: the forces differ by what that motion
    // changed over the step (the two points' inertias differ).
    EXPECT_LT(worst, 0.05 * P0.norm());
  }
  EXPECT_LT(deepest, 5e-3);
}

INSTANTIATE_TEST_SUITE_P(Contact, TwoHands, testing::Values(ContactModel::penalty, ContactModel::constraint),
                         [](const testing::TestParamInfo<ContactModel>& i) { return std::string(to_string(i.param)); });

// Model only what a scene needs: one hand builds no hand-hand query (nor
// does a scene whose hand-hand contact is off), and two hands without it pass
// through each other. The cost of hand-hand contact: the pressing run's step
// time with and without it.
TEST(TwoHandsCost, OneHandBuildsNoHandHandQueryAndWithoutItHandsPassThrough) {
  SceneDesc one;
  testing_util::add_test_hand(one);
  const World single(one);
  EXPECT_EQ(single.hand_query(0), nullptr);
  EXPECT_EQ(single.hand_contact_forces(0).size(), 0);

  WorldOptions with = WorldOptions{};
  with.hand_gravity = false;
  with.drive = kStiffDrive;
  WorldOptions without = with;
  without.hand_hand_contacts = false;
  World off(palm_to_palm(0.02), without);
  EXPECT_EQ(off.hand_query(0), nullptr);
  EXPECT_EQ(off.hand_query(1), nullptr);
  const PressResult r_off = press(off, 150);
  EXPECT_EQ(r_off.touching_steps, 0);
  EXPECT_EQ(off.snapshot().resets, 0);
  World on(palm_to_palm(0.02), with);
  const PressResult r_on = press(on, 150);
  const double deepest_off = deepest_skin_point(hand::as_fem(off.hand(0)), hand::as_fem(off.hand(1)));
  const double deepest_on = deepest_skin_point(hand::as_fem(on.hand(0)), hand::as_fem(on.hand(1)));
  std::printf(
      "step %.2f ms with hand-hand contact, %.2f ms without (+%.0f %%), of which collision %.2f / %.2f ms; "
      "deepest skin point %.2f mm with it, %.2f mm without\n",
      r_on.step_ms, r_off.step_ms, 100 * (r_on.step_ms / r_off.step_ms - 1), r_on.collide_ms, r_off.collide_ms,
      1e3 * deepest_on, 1e3 * deepest_off);
  // The palms' targets overlap by 3 mm: without contact the skins sink into each other, with it they touch.
  EXPECT_GT(deepest_off, 1e-3);
  EXPECT_LT(deepest_on, 0.5e-3);
  EXPECT_GT(r_on.touching_steps, 100);
}

// scenes/two_hands.json: a right glove hand palm down over a 100 g box on a
// table, a left one palm up beside it (to take the box over: the handover is
// in test_world_glove.cpp), each driven by its own glove.
TEST(TwoHandsScene, LoadsAndSteps) {
  const SceneDesc scene = load_scene(std::string(HAPTICD_SCENES_DIR) + "/two_hands.json");
  ASSERT_EQ(scene.hands.size(), 2u);
  ASSERT_EQ(scene.devices.size(), 2u);
  const HandDesc* right = scene.find_hand("right_hand");
  const HandDesc* left = scene.find_hand("left_hand");
  ASSERT_NE(right, nullptr);
  ASSERT_NE(left, nullptr);
  EXPECT_EQ(right->side, HandSide::right);
  EXPECT_EQ(left->side, HandSide::left);
  for (const HandDesc* h : {right, left}) {
    EXPECT_EQ(h->handles, HandleSet::phalanges) << h->name;
    const DeviceDesc* glove = scene.device_for_hand(h->name);
    ASSERT_NE(glove, nullptr) << h->name;
    EXPECT_EQ(glove->kind, DeviceKind::glove) << h->name;
    // The glove's workspace sits at the hand: its rest pose is the hand's.
    EXPECT_EQ(glove->workspace.offset_W, h->pose.p_W) << h->name;
    EXPECT_LT(glove->workspace.R_WD.angularDistance(h->pose.q_W), 1e-9) << h->name;
  }
  EXPECT_NE(scene.device_for_hand("right_hand"), scene.device_for_hand("left_hand"));
  const ObjectDesc* box = scene.find_object("box");
  ASSERT_NE(box, nullptr);
  EXPECT_EQ(box->mass_kg, 0.1);
  // The right palm (-z of its hand frame) faces down onto the box below it, the left palm faces up.
  EXPECT_LT((right->pose.q_W * Eigen::Vector3d(0, 0, -1)).z(), -0.99);
  EXPECT_GT(right->pose.p_W.z(), box->pose.p_W.z() + 0.05);
  EXPECT_GT((left->pose.q_W * Eigen::Vector3d(0, 0, -1)).z(), 0.99);

  for (const bool scene_contact : {false, true}) {  // the server's penalty contacts, the scene's constraint ones
    WorldOptions options;
    options.hand_gravity = false;
    if (scene_contact) options.contact.reset();
    World world(scene, options);
    ASSERT_EQ(world.num_hands(), 2);
    EXPECT_NE(world.hand_query(0), nullptr);
    // Nothing touches the hands where they start.
    for (const ContactRecord& c : world.snapshot().contacts) EXPECT_LT(c.hand, 0);
    for (int k = 0; k < 30; ++k) world.step();
    const WorldSnapshot& s = world.snapshot();
    EXPECT_EQ(s.resets, 0);
    for (int h = 0; h < 2; ++h) EXPECT_TRUE(hand::as_fem(world.hand(h)).state.x.allFinite());
    for (const RigidBodyState& b : s.bodies) EXPECT_TRUE(b.p_WO.allFinite());
    // The box rests on the table.
    const RigidBodyState b = world.rigid()->state(world.rigid()->find("box"));
    EXPECT_NEAR(b.p_WO.z(), box->pose.p_W.z(), 2e-3);
    EXPECT_LT(b.v_WO.norm(), 0.01);
  }
}

}  // namespace
}  // namespace hapticd::world
