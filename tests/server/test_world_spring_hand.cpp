// The spring hand of seed 002 in the world (scene "model": "spring"): its ODE bodies stepped with
// the objects, its contacts recorded, the palm spring's reaction as the handle's force and model,
// and the hard cases (teleports, a fast impact, NaN and absurd targets).
#include <gtest/gtest.h>

#include <cmath>

#include "hand_models/spring/spring_hand.hpp"
#include "server/haptic/device_link.hpp"
#include "server/world/scene_loader.hpp"
#include "server/world/world.hpp"

namespace hapticd::world {
namespace {

// A floor plane at z = 0 and a right spring hand driven by its palm, palm centre 5 cm up.
SceneDesc floor_scene() {
  SceneDesc scene;
  scene.dt_s = 1.0 / 60.0;
  scene.gravity_m_s2 = {0, 0, -9.81};
  ObjectDesc floor;
  floor.name = "floor";
  floor.kind = BodyKind::static_body;
  floor.shape.type = ShapeType::plane;
  floor.shape.normal = {0, 0, 1};
  scene.objects.push_back(floor);
  HandDesc hand;
  hand.name = "spring";
  hand.model = HandModelKind::spring;
  hand.pose.p_W = {0, 0, 0.05};
  scene.hands.push_back(hand);
  return scene;
}

hand::HandleTarget palm_at(const Eigen::Vector3d& p, const Eigen::Vector3d& v = Eigen::Vector3d::Zero()) {
  hand::HandleTarget t;
  t.p_W = p;
  t.v_W = v;
  return t;
}

const hand::spring::SpringHand& spring_of(const World& w) {
  return dynamic_cast<const hand::spring::SpringHand&>(w.hand(0));
}

TEST(WorldSpringHand, APalmPressedIntoTheFloorRestsOnItAndTheHandleFeelsTheContactsThroughItsSpring) {
  World w(floor_scene());
  EXPECT_EQ(w.hand(0).model_name(), "spring");
  EXPECT_EQ(w.hand(0).flesh(), nullptr);
  const double rest_z = 0.0125;           // the palm box's half thickness: its centre resting on the floor
  const double target_z = rest_z - 0.02;  // the tracked palm 2 cm below that
  for (int k = 0; k < 90; ++k) {          // down over 0.5 s, then held 1 s
    const double t = (k + 1) * w.dt();
    w.hand(0).set_target(0, palm_at({0, 0, 0.05 + std::min(t / 0.5, 1.0) * (target_z - 0.05)}));
    w.step();
  }
  const WorldSnapshot& s = w.snapshot();
  EXPECT_EQ(s.resets, 0);
  EXPECT_LT(s.max_penetration_m, 0.002);
  const hand::spring::SpringHand& hand = spring_of(w);
  EXPECT_NEAR(hand.rig().palm_position().z(), rest_z, 0.002);
  // The springs' reaction on the handle (the palm's, 2 cm stretched: ~40 N, and the fingertips')
  // balances, at rest, what ODE's contacts hold up less the hand's weight.
  const Eigen::VectorXd F = w.hand(0).coupling_wrench();
  EXPECT_GT(F.z(), 2000.0 * 0.018);
  double contact_z = 0;
  int records = 0;
  for (const ContactRecord& c : s.contacts) {
    if (c.hand != 0) continue;
    ++records;
    contact_z += c.f_W.z();
    EXPECT_GT(c.n_W.z(), 0.99) << "the floor's normal, toward the hand";
  }
  EXPECT_GT(records, 0);
  const double weight = 9.81 * hand.rig().total_mass_kg();
  EXPECT_NEAR(F.z(), contact_z - weight, 0.02 * F.z()) << "contacts " << contact_z << " N, weight " << weight << " N";
  std::printf("handle force %.2f N, contacts %.2f N (%d), hand weight %.2f N\n", F.z(), contact_z, records, weight);
}

// The model of the coming step (what the haptic loop renders until the next) against the world
// stepped with the handle held where the model is asked: the springs' reaction on it averaged over
// the world's ODE steps (the impulse it took, over the step). The baseline is the reaction with the
// spring hand held where it was (the model before it took the hand's motion over the step).
struct Prediction {
  double model_error_n = 0, held_error_n = 0, actual_z_n = 0;
};

Prediction predict_step(World& w, const Eigen::Vector3d& dx) {
  hand::HandleLinearization model;
  EXPECT_TRUE(w.hand(0).linearize_next_step(model, hand::ContactLinearization::unilateral));
  const hand::HandleState x0 = w.hand(0).handles()[0];
  EXPECT_TRUE(w.hand(0).set_target(0, palm_at(x0.p_WH + dx, dx / w.dt())));
  const Eigen::VectorXd held = w.hand(0).coupling_wrench(), predicted = model.evaluate(w.hand(0).handles());
  w.step();
  const Eigen::VectorXd actual = spring_of(w).rig().mean_reaction_since_reading();
  return {(predicted - actual).head<3>().norm(), (held - actual).head<3>().norm(), actual.z()};
}

TEST(WorldSpringHand, AGlovesModelIsTheSpringsReactionLinearizedInItsFrames) {
  SceneDesc scene = floor_scene();
  scene.hands[0].handles = HandleSet::phalanges;
  scene.hands[0].pose.p_W = {0, 0, 0.15};  // in free space
  World w(scene);
  for (int k = 0; k < 10; ++k) w.step();
  hand::HandleLinearization model;
  ASSERT_TRUE(w.hand(0).linearize_next_step(model, hand::ContactLinearization::unilateral));
  ASSERT_EQ(model.F0.size(), 6 * 16);
  const hand::HandleState x0 = w.hand(0).handles()[0];
  // Moved and moving: the springs are linear in the handle's position and velocity, so is the model.
  hand::HandleTarget t;
  t.p_W = x0.p_WH + Eigen::Vector3d(0.004, -0.006, 0.008);
  t.q_W = x0.q_WH;
  t.v_W = {0.2, 0, -0.1};
  t.w_W = {0, 0.5, 0.2};
  ASSERT_TRUE(w.hand(0).set_target(0, t));
  EXPECT_LT((w.hand(0).coupling_wrench() - model.evaluate(w.hand(0).handles())).norm(), 1e-6);
  // Turned: the fingertips' tracked ends swing with the handle, so the model is exact to first
  // order only: half the turn, a quarter of the error.
  auto turned_error = [&](double angle) {
    t.p_W = x0.p_WH;
    t.q_W = Eigen::Quaterniond(Eigen::AngleAxisd(angle, Eigen::Vector3d(1, 2, 3).normalized())) * x0.q_WH;
    t.v_W.setZero();
    t.w_W.setZero();
    EXPECT_TRUE(w.hand(0).set_target(0, t));
    return (w.hand(0).coupling_wrench() - model.evaluate(w.hand(0).handles())).norm();
  };
  const double e1 = turned_error(0.02), e2 = turned_error(0.01);
  EXPECT_NEAR(e1 / e2, 4.0, 0.2) << e1 << " " << e2;
  EXPECT_GT((w.hand(0).coupling_wrench() - model.F0).norm(), 100 * e2) << "the turn changes the reaction";
}

// The lowest point of the spring hand's shapes (its palm box and phalanx capsules), from ODE's geoms.
double lowest_point_z(const hand::spring::SpringHand& hand) {
  double lowest = INFINITY;
  for (int g = 0; g < hand.num_geoms(); ++g) {
    const dReal* p = dGeomGetPosition(hand.geom(g));
    const dReal* R = dGeomGetRotation(hand.geom(g));
    if (g == 0) {
      dVector3 l;
      dGeomBoxGetLengths(hand.geom(g), l);
      lowest = std::min(lowest, p[2] - 0.5 * (std::abs(R[8]) * l[0] + std::abs(R[9]) * l[1] + std::abs(R[10]) * l[2]));
    } else {
      dReal r, length;
      dGeomCapsuleGetParams(hand.geom(g), &r, &length);
      lowest = std::min(lowest, p[2] - 0.5 * length * std::abs(R[10]) - r);  // the axis is the geom's z
    }
  }
  return lowest;
}

// The world stepped `steps` times with the palm's handle held at p.
void settle_palm_at(World& w, const Eigen::Vector3d& p, int steps) {
  for (int k = 0; k < steps; ++k) {
    ASSERT_TRUE(w.hand(0).set_target(0, palm_at(p)));
    w.step();
  }
}

// `model` evaluated with the palm's handle at p (the hand's handles are set there, not stepped).
Eigen::VectorXd model_at_palm(World& w, const hand::HandleLinearization& model, const Eigen::Vector3d& p) {
  EXPECT_TRUE(w.hand(0).set_target(0, palm_at(p)));
  return model.evaluate(w.hand(0).handles());
}

// A stylus's model: the springs pressing a massless copy of the hand, held at the handle, against
// the objects (seed 002 section 4.6.2: no force in free motion). References: the world's own law, the
// springs' reaction once the spring hand has come to rest on the floor, and the hand's geometry.
TEST(WorldSpringHand, AStylussModelPressesAMasslessCopyOfTheHandAgainstTheObjects) {
  WorldOptions options;
  options.hand_gravity = false;  // the springs carry nothing but what the floor pushes
  World w(floor_scene(), options);
  const hand::spring::SpringHand& hand = spring_of(w);
  auto settle_at = [&](const Eigen::Vector3d& p) { settle_palm_at(w, p, 90); };
  auto model_at = [&](const hand::HandleLinearization& model, const Eigen::Vector3d& p) {
    return model_at_palm(w, model, p);
  };
  // Hovering with the hand's lowest point 6 mm above the floor, within the probes' reach.
  settle_at({0, 0, 0.05});
  settle_at({0, 0, 0.05 - lowest_point_z(hand) + 0.006});
  const double gap = lowest_point_z(hand);
  ASSERT_NEAR(gap, 0.006, 0.5e-3);
  const Eigen::Vector3d x0 = w.hand(0).handles()[0].p_WH;
  hand::HandleLinearization hover;
  ASSERT_TRUE(w.hand(0).linearize_next_step(hover, hand::ContactLinearization::unilateral));
  EXPECT_EQ(model_at(hover, x0).norm(), 0.0) << "free motion";
  EXPECT_EQ(model_at(hover, x0 + Eigen::Vector3d(0.01, 0.01, 0.02)).norm(), 0.0);
  EXPECT_EQ(model_at(hover, x0 - Eigen::Vector3d(0, 0, gap - 0.001)).norm(), 0.0) << "1 mm short of the floor";
  // 3 mm past the gap: what the world's spring hand takes once it rests on the floor there.
  const Eigen::Vector3d pressed = x0 - Eigen::Vector3d(0, 0, gap + 0.003);
  const double predicted = model_at(hover, pressed).z();
  settle_at(pressed);
  const double law = w.hand(0).coupling_wrench().z();
  std::printf("3 mm past a %.2f mm gap: model %.3f N, the world at rest %.3f N\n", 1e3 * gap, predicted, law);
  EXPECT_GT(law, 0.1);
  EXPECT_NEAR(predicted, law, 0.15 * law);
  // At rest on the floor the model is the law (its rows are ODE's contacts; measured 3 % apart: the
  // fingertip's spring stiffens both the hand the palm's springs hold and the finger's joints)...
  hand::HandleLinearization resting;
  ASSERT_TRUE(w.hand(0).linearize_next_step(resting, hand::ContactLinearization::unilateral));
  const Eigen::VectorXd at_rest = model_at(resting, pressed), reaction = w.hand(0).coupling_wrench();
  std::printf("at rest: model %.3f N, the world %.3f N\n", at_rest.z(), reaction.z());
  EXPECT_LT((at_rest - reaction).norm(), 0.05 * reaction.norm())
      << at_rest.transpose() << " / " << reaction.transpose();
  // ...and lifting lets go, where the springs holding the hand down would pull the handle to it.
  const Eigen::Vector3d lifted = pressed + Eigen::Vector3d(0, 0, 0.01);
  EXPECT_LT(model_at(resting, lifted).norm(), 1e-9);
  EXPECT_LT(w.hand(0).coupling_wrench().z(), -10.0);
}

// The same over a peak: a static 4 cm box standing on a corner, its top corner 2 mm under the palm
// and off its centre, between the palm's probe points. A flat palm meets a peak along the palm's own
// normal (ODE's box contacts take it so); the object's normal at a probe point beside the peak is the
// direction from the corner, ~65 degrees from it, and a model that held the palm apart along those
// let the massless hand slide down the corner's flank: measured before the palm's points took their
// face's normal, the model 3 mm past the gap gave 3.38 N up and 1.81 N sideways where the world at
// rest gives 6.29 N up and 0.09 N sideways (after: 6.01 N up, 0.11 N sideways). Reference: the
// world's spring hand at rest there.
TEST(WorldSpringHand, AStylussModelHoldsAFlatPalmOnAPeakAlongThePalmsNormal) {
  SceneDesc scene = floor_scene();
  scene.objects.clear();
  const double palm_bottom = 0.05 - 0.0125, gap = 0.002, half_diagonal = 0.02 * std::sqrt(3.0);
  ObjectDesc peak;
  peak.name = "peak";
  peak.kind = BodyKind::static_body;
  peak.shape.type = ShapeType::box;
  peak.shape.size = {0.04, 0.04, 0.04};
  // The box's diagonal (1, 1, 1) turned onto +z.
  peak.pose.q_W = Eigen::Quaterniond::FromTwoVectors(Eigen::Vector3d(1, 1, 1), Eigen::Vector3d::UnitZ());
  const Eigen::Vector2d off(0.0041, 0.0027);  // from the palm's centre: 4-5 mm from the nearest probe points
  peak.pose.p_W = {off.x(), off.y(), palm_bottom - gap - half_diagonal};
  scene.objects.push_back(peak);
  WorldOptions options;
  options.hand_gravity = false;
  World w(scene, options);
  const hand::spring::SpringHand& hand = spring_of(w);
  auto settle_at = [&](const Eigen::Vector3d& p) { settle_palm_at(w, p, 120); };
  auto model_at = [&](const hand::HandleLinearization& model, const Eigen::Vector3d& p) {
    return model_at_palm(w, model, p);
  };
  settle_at({0, 0, 0.05});
  const dReal* palm = dGeomGetPosition(hand.geom(0));
  ASSERT_NEAR(palm[2] - 0.0125, palm_bottom, 0.5e-3);
  ASSERT_LT(Eigen::Vector2d(palm[0], palm[1]).norm(), 0.5e-3);
  ASSERT_LT(w.hand(0).coupling_wrench().norm(), 1e-9) << "hovering";
  const Eigen::Vector3d x0 = w.hand(0).handles()[0].p_WH;
  hand::HandleLinearization hover;
  ASSERT_TRUE(w.hand(0).linearize_next_step(hover, hand::ContactLinearization::unilateral));
  ASSERT_GT(hover.contacts.count(), 0) << "the peak is within the probes' reach";
  EXPECT_EQ(model_at(hover, x0 - Eigen::Vector3d(0, 0, gap - 0.001)).norm(), 0.0) << "1 mm short of the peak";
  const Eigen::Vector3d pressed = x0 - Eigen::Vector3d(0, 0, gap + 0.003);
  const Eigen::VectorXd predicted = model_at(hover, pressed);
  settle_at(pressed);
  const Eigen::VectorXd law = w.hand(0).coupling_wrench();
  std::printf("3 mm past the peak: model force %.3f %.3f %.3f N, the world at rest %.3f %.3f %.3f N\n", predicted[0],
              predicted[1], predicted[2], law[0], law[1], law[2]);
  ASSERT_GT(law.z(), 1.0);
  EXPECT_LT(law.head<2>().norm(), 0.05 * law.z()) << "the world's palm rests on the peak";
  EXPECT_LT((predicted.head<3>() - law.head<3>()).norm(), 0.15 * law.z());
}

TEST(WorldSpringHand, ItsBodyStepModelPredictsTheStepsForceInFreeSpacePressingAndLifting) {
  WorldOptions options;
  options.spring_body_step_model = true;
  World w(floor_scene(), options);
  // Free space: a 1 cm jump of the handle. The spring palm follows within the step.
  for (int k = 0; k < 30; ++k) w.step();
  const Prediction jump = predict_step(w, {0.01, 0, 0});
  std::printf("free jump: model error %.3f N, held hand %.3f N\n", jump.model_error_n, jump.held_error_n);
  EXPECT_LT(jump.model_error_n, 0.05 * jump.held_error_n);  // measured 0.87 against 33.2 N
  // Pressing: the palm 2 cm into the floor (its contacts are the model's rows), then 2 mm deeper.
  for (int k = 0; k < 60; ++k) {
    w.hand(0).set_target(0, palm_at({0.01, 0, 0.05 + std::min((k + 1) / 30.0, 1.0) * (-0.0075 - 0.05)}));
    w.step();
  }
  const Prediction deeper = predict_step(w, {0, 0, -0.002});
  std::printf("press 2 mm deeper: model error %.3f N, held hand %.3f N (force %.2f N)\n", deeper.model_error_n,
              deeper.held_error_n, deeper.actual_z_n);
  EXPECT_LT(deeper.model_error_n, 0.1);  // measured 0.02 N of 57 N
  // Lifting 3 cm in one step: the rows release, nothing pulls toward the floor.
  const Prediction lift = predict_step(w, {0, 0, 0.03});
  std::printf("lift 3 cm: model error %.3f N, held hand %.3f N (force %.2f N)\n", lift.model_error_n, lift.held_error_n,
              lift.actual_z_n);
  EXPECT_LT(lift.model_error_n, 0.05 * lift.held_error_n);  // measured 0.84 against 69.9 N
}

TEST(WorldSpringHand, HardCasesEndWithoutNaNAndWithACountedResetWhereOneIsNeeded) {
  World w(floor_scene());
  const hand::spring::SpringHand& hand = spring_of(w);
  // A NaN target is refused and the last one kept.
  EXPECT_FALSE(w.hand(0).set_target(0, palm_at({NAN, 0, 0.05})));
  EXPECT_TRUE(w.hand(0).handles()[0].p_WH.allFinite());
  // A 10 cm teleport: followed, no reset.
  w.hand(0).set_target(0, palm_at({0.1, 0, 0.05}));
  for (int k = 0; k < 60; ++k) w.step();
  EXPECT_EQ(w.snapshot().resets, 0);
  EXPECT_NEAR((hand.rig().palm_position() - Eigen::Vector3d(0.1, 0, 0.05)).norm(), 0.0, 0.005);
  // A 3 m/s impact on the floor: the palm stays on it (no tunnelling).
  double lowest = 1;
  for (int k = 0; k < 60; ++k) {
    const double z = std::max(0.05 - 3.0 * (k + 1) * w.dt(), -0.05);
    w.hand(0).set_target(0, palm_at({0.1, 0, z}, {0, 0, z > -0.05 ? -3.0 : 0.0}));
    w.step();
    lowest = std::min(lowest, hand.rig().palm_position().z());
  }
  EXPECT_GT(lowest, 0.0125 - 0.005);
  EXPECT_EQ(w.snapshot().resets, 0);
  // A 100 m teleport: the palm spring flings the hand past any sane speed; it is placed on the
  // target at rest, and the reset counted.
  w.hand(0).set_target(0, palm_at({100, 0, 0.05}));
  w.step();
  EXPECT_EQ(w.snapshot().resets, 1);
  EXPECT_LT((hand.rig().palm_position() - Eigen::Vector3d(100, 0, 0.05)).norm(), 1e-9);
  for (int k = 0; k < 10; ++k) w.step();
  EXPECT_EQ(w.snapshot().resets, 1);
  EXPECT_TRUE(w.hand(0).coupling_wrench().allFinite());
}

// A glove's 16 frames: the palm and each phalanx's segment frame on it (skeleton_pose).
std::vector<hand::HandleTarget> glove_frames(const hand::HandJointAngles& a, const Eigen::Vector3d& palm) {
  const hand::SkeletonPose pose = hand::skeleton_pose(a);
  std::vector<hand::HandleTarget> t(16);
  t[0].p_W = palm;
  for (int i = 0; i < hand::kHandPhalanges; ++i) {
    t[i + 1].p_W = palm + pose.centre[i];
    t[i + 1].q_W = Eigen::Quaterniond(pose.R[i]);
  }
  return t;
}

// A 1:1000 mass ratio either way: the 0.65 kg hand presses a 0.65 g box and a 650 kg box on the
// floor (2 cm of the tracked palm into each), and holds 1 s: no reset, nothing non-finite, the box
// under the palm and on the floor.
TEST(WorldSpringHand, ItPressesBoxesAThousandTimesLighterAndHeavierThanItself) {
  for (const double mass : {0.65e-3, 650.0}) {
    SceneDesc scene = floor_scene();
    ObjectDesc box;
    box.name = "box";
    box.shape.type = ShapeType::box;
    box.shape.size = {0.06, 0.06, 0.02};
    box.mass_kg = mass;
    box.pose.p_W = {0, 0, 0.01};
    scene.objects.push_back(box);
    World w(scene);
    const int b = w.rigid()->find("box");
    const double target_z = 0.02 + 0.0125 - 0.02;  // the palm's centre 2 cm below resting on the box
    double highest = 0, lowest = 1;
    for (int k = 0; k < 90; ++k) {
      const double t = (k + 1) * w.dt();
      w.hand(0).set_target(0, palm_at({0, 0, 0.05 + std::min(t / 0.5, 1.0) * (target_z - 0.05)}));
      w.step();
      const double z = w.snapshot().bodies[b].p_WO.z();
      highest = std::max(highest, z), lowest = std::min(lowest, z);
      ASSERT_TRUE(w.hand(0).coupling_wrench().allFinite()) << mass << " kg, step " << k;
    }
    EXPECT_EQ(w.snapshot().resets, 0) << mass;
    EXPECT_EQ(w.snapshot().body_resets, 0) << mass;
    EXPECT_NEAR(lowest, 0.01, 0.002) << mass << " kg: the box stays on the floor";
    EXPECT_NEAR(highest, 0.01, 0.002) << mass << " kg";
    EXPECT_GT(w.hand(0).coupling_wrench().z(), 30.0) << mass << " kg: the handle feels the press";
    std::printf("%.4g kg box: palm at z %.4f, handle force %.2f N\n", mass, spring_of(w).rig().palm_position().z(),
                w.hand(0).coupling_wrench().z());
  }
}

TEST(WorldSpringHand, AGlovesFramesBendItsFingersAndEachFrameFeelsItsSprings) {
  SceneDesc scene = floor_scene();
  scene.hands[0].handles = HandleSet::phalanges;
  scene.hands[0].pose.p_W = {0, 0, 0.15};  // in free space
  WorldOptions options;
  options.hand_gravity = false;
  World w(scene, options);
  ASSERT_EQ(w.hand(0).num_handles(), 16);
  for (int j = 0; j < 16; ++j) EXPECT_EQ(w.hand(0).handle_info(j, 16).in_frame.p_F.norm(), 0.0) << "the frame itself";
  hand::HandJointAngles fist = hand::rest_joint_angles();
  for (int f = 1; f < hand::kHandFingers; ++f) fist.finger[f][1] = fist.finger[f][2] = fist.finger[f][3] = 1.2;
  const std::vector<hand::HandleTarget> frames = glove_frames(fist, {0, 0, 0.15});
  for (int k = 0; k < 90; ++k) {
    for (int j = 0; j < 16; ++j) ASSERT_TRUE(w.hand(0).set_target(j, frames[j]));
    w.step();
  }
  const hand::spring::SpringHand& hand = spring_of(w);
  EXPECT_LT((hand.rig().joint_angles().vector() - fist.vector()).cwiseAbs().maxCoeff(), 2e-3);
  EXPECT_EQ(w.snapshot().resets, 0);
  // Settled in free space: nothing left to feel.
  EXPECT_LT(w.hand(0).coupling_wrench().cwiseAbs().maxCoeff(), 0.01);
  // The index's tracked middle phalanx turned 0.1 rad further about its hinge: the tracked PIP
  // flexes 0.1 more and the DIP 0.1 less. The PIP spring pulls the middle frame back (-k 0.1) and the
  // proximal one on (+k 0.1); the DIP spring pulls the middle frame back too (-k 0.1) and the distal
  // one on (+k 0.1). The model says so to first order.
  hand::HandleLinearization model;
  ASSERT_TRUE(w.hand(0).linearize_next_step(model, hand::ContactLinearization::unilateral));
  std::vector<hand::HandleTarget> bent = frames;
  const int middle = 1 + 3 * 1 + 1;
  const Eigen::Vector3d axis = hand.rig().joint_axis_W(4 * 1 + 2);
  bent[middle].q_W = Eigen::Quaterniond(Eigen::AngleAxisd(0.1, axis)) * frames[middle].q_W;
  bent[middle].p_W += Eigen::Vector3d(0.001, 0, 0);
  for (int j = 0; j < 16; ++j) ASSERT_TRUE(w.hand(0).set_target(j, bent[j]));
  const Eigen::VectorXd F = w.hand(0).coupling_wrench();
  const double k = hand.rig().params().joint.k;
  EXPECT_NEAR(F.segment<3>(6 * middle + 3).dot(axis), -2 * k * 0.1, 0.02 * k * 0.1);
  EXPECT_NEAR(F.segment<3>(6 * (middle - 1) + 3).dot(axis), k * 0.1, 0.02 * k * 0.1);
  EXPECT_NEAR(F.segment<3>(6 * (middle + 1) + 3).dot(axis), k * 0.1, 0.02 * k * 0.1);
  const Eigen::VectorXd predicted = model.evaluate(w.hand(0).handles());
  EXPECT_LT((predicted - F).norm(), 0.05 * F.norm());
}

// Section 4.5 through the world: a glove-driven hand in free space gives every finger zero (4.6.2),
// whatever its springs pull; its index bent into the floor gives the index a force resisting the
// flexion, and the fingers above the floor none.
// A 6-frame glove (palm and distal phalanges) bends the fingers to the posture its frames give
// (flexions shared 3:3:2 come back), and each joint spring's reaction reaches the distal frame by its
// share: with the index flexed 0.1 rad further in all (shared 3:3:2), its distal frame's torque about
// the flexion axis is what a 16-frame glove's proximal, middle and distal frames feel, weighted by how
// far each turns for a turn of the distal (3/8, 6/8, 1), at the same spring hand.
TEST(WorldSpringHand, ASixFrameGlovesDistalFramesBendItsFingersAndFeelTheirJointsShares) {
  hand::HandJointAngles posture = hand::rest_joint_angles();
  for (int f = 0; f < hand::kHandFingers; ++f)
    posture.finger[f] = {posture.finger[f][0], 3.0 / 8 * 1.2, 3.0 / 8 * 1.2, 2.0 / 8 * 1.2};
  hand::HandJointAngles further = posture;
  further.finger[1][1] += 3.0 / 8 * 0.1, further.finger[1][2] += 3.0 / 8 * 0.1, further.finger[1][3] += 2.0 / 8 * 0.1;
  Eigen::VectorXd wrench[2];
  Eigen::Vector3d axis;
  for (const int frames : {6, 16}) {
    SceneDesc scene = floor_scene();
    scene.hands[0].handles = frames == 6 ? HandleSet::fingertips : HandleSet::phalanges;
    scene.hands[0].pose.p_W = {0, 0, 0.15};
    WorldOptions options;
    options.hand_gravity = false;
    World w(scene, options);
    ASSERT_EQ(w.hand(0).num_handles(), frames);
    auto drive = [&](const hand::HandJointAngles& a) {
      const std::vector<hand::HandleTarget> all = glove_frames(a, {0, 0, 0.15});
      for (int j = 0; j < frames; ++j)
        ASSERT_TRUE(w.hand(0).set_target(j, all[j == 0 ? 0 : frames == 6 ? 3 * (j - 1) + 3 : j]));
    };
    for (int k = 0; k < 90; ++k) {
      drive(posture);
      w.step();
    }
    const hand::spring::SpringHand& hand = spring_of(w);
    EXPECT_LT((hand.rig().joint_angles().vector() - posture.vector()).cwiseAbs().maxCoeff(), 2e-3) << frames;
    EXPECT_EQ(w.snapshot().resets, 0);
    drive(further);
    wrench[frames == 16] = w.hand(0).coupling_wrench();
    axis = hand.rig().joint_axis_W(4 * 1 + 3);  // the index's flexion axes are parallel
  }
  const int distal6 = 1 + 1, proximal16 = 1 + 3 * 1;
  const double six = axis.dot(wrench[0].segment<3>(6 * distal6 + 3));
  const double sixteen = 3.0 / 8 * axis.dot(wrench[1].segment<3>(6 * proximal16 + 3)) +
                         6.0 / 8 * axis.dot(wrench[1].segment<3>(6 * (proximal16 + 1) + 3)) +
                         axis.dot(wrench[1].segment<3>(6 * (proximal16 + 2) + 3));
  std::printf("index distal frame about its flexion axis: 6 frames %.5f N m, 16 frames weighted %.5f N m\n", six,
              sixteen);
  EXPECT_LT(six, -0.01) << "the springs pull the flexed finger back";
  EXPECT_NEAR(six, sixteen, 1e-3 * std::abs(sixteen));
}

TEST(WorldSpringHand, TheGloveForceIsZeroForAFingerTouchingNothingAndResistsTheFloorsBlock) {
  SceneDesc scene = floor_scene();
  scene.hands[0].handles = HandleSet::phalanges;
  WorldOptions options;
  options.hand_gravity = false;
  // Fingers straight, the palm 15 cm up (free space), then 4.5 cm up: the straight fingers clear
  // the floor; the index bent 0.5, 0.3, 0.2 rad would put its distal capsule 9 mm into it.
  hand::HandJointAngles straight;
  for (int f = 0; f < hand::kHandFingers; ++f) straight.finger[f] = {hand::rest_joint_angles().finger[f][0], 0, 0, 0};
  Eigen::Vector3d palm(0, 0, 0.15);
  scene.hands[0].pose.p_W = palm;
  World w(scene, options);
  const auto drive = [&](const hand::HandJointAngles& a, int steps) {
    const std::vector<hand::HandleTarget> frames = glove_frames(a, palm);
    for (int k = 0; k < steps; ++k) {
      for (int j = 0; j < 16; ++j) ASSERT_TRUE(w.hand(0).set_target(j, frames[j]));
      w.step();
    }
  };
  const hand::spring::SpringHand& hand = spring_of(w);
  // Free space, the tracked index flexing: its springs pull, yet no finger touches anything.
  hand::HandJointAngles bent = straight;
  bent.finger[1] = {straight.finger[1][0], 0.5, 0.4, 0.3};
  drive(straight, 30);
  drive(bent, 3);
  EXPECT_GT(std::abs(hand.rig().joint_torque(4 * 1 + 1)), 0.01) << "the index's springs pull";
  for (int f = 0; f < hand::kHandFingers; ++f) EXPECT_EQ(hand.glove_feedback(f), 0.0) << f;
  // The spring index comes down onto the floor and stops there, less flexed than the tracked one.
  bent.finger[1] = {straight.finger[1][0], 0.5, 0.3, 0.2};
  palm.z() = 0.045;
  drive(bent, 60);
  EXPECT_GT(hand.glove_feedback(1), 0.05) << "the index is stopped by the floor: the glove resists its flexion";
  for (int f : {2, 3, 4}) EXPECT_EQ(hand.glove_feedback(f), 0.0) << f;
  std::printf("index glove force %.3f N, base joint torque %.4f N m\n", hand.glove_feedback(1),
              hand.rig().joint_torque(4 * 1 + 1));
  // The server's cable output with the paper's coefficients, on the wrenches the tracked frames get
  // (the springs' reaction): the same formula, taken on the tracked hand's joints and fingertip
  // rather than the spring hand's, and on the fingertip spring's whole force rather than its part
  // without the palm's pose. Measured 6 % apart (1.341 against 1.261 N).
  haptic::DeviceLink link;
  link.handles = 16;
  link.output = haptic::ForceOutput::finger_lines;
  link.limits.max_force_n = 100.0;
  link.feedback_a = {1.0, 1.0, 1.0, 1.0};
  const Eigen::VectorXd reaction = w.hand(0).coupling_wrench();
  haptic::HapticPose frames_W[16];
  haptic::ReplyWrench wrench[16];
  for (int j = 0; j < 16; ++j) {
    frames_W[j].p_W = w.hand(0).handles()[j].p_WH;
    frames_W[j].q_W = w.hand(0).handles()[j].q_WH;
    wrench[j].f_D = reaction.segment<3>(6 * j);
    wrench[j].tau_D = reaction.segment<3>(6 * j + 3);
  }
  haptic::project_onto_finger_lines(link, frames_W, wrench);
  const Eigen::Vector3d n = frames_W[6].q_W * link.actuator_line_F;  // the index's distal frame's dorsal axis
  const double cable = wrench[6].f_D.dot(n);
  std::printf("the server's index cable %.3f N, the rig's formula %.3f N\n", cable, hand.glove_feedback(1, n));
  EXPECT_NEAR(cable, hand.glove_feedback(1, n), 0.1 * hand.glove_feedback(1, n));
}

TEST(WorldSpringHand, TheSceneFileLoadsAndStepsWithTheBunny) {
  World w(load_scene(std::string(HAPTICD_SCENES_DIR) + "/spring_bunny.json"));
  for (int k = 0; k < 30; ++k) w.step();
  EXPECT_EQ(w.snapshot().resets, 0);
  EXPECT_EQ(w.snapshot().body_resets, 0);
  EXPECT_TRUE(w.hand(0).coupling_wrench().allFinite());
}

}  // namespace
}  // namespace hapticd::world
