// The contact-point hand of seed 001 in the world (scene "model": "contact_point"): its contact
// points' Coulomb states against the force they carry, a box pushed on a floor against Newton and
// Coulomb, a held object spun by one finger (seed 001 Fig. 1), its handle-space model against its own
// force law at moved handles, and the hard cases.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <numbers>

#include "hand_models/contact_point/contact_point_hand.hpp"
#include "server/world/scene_loader.hpp"
#include "server/world/world.hpp"

namespace hapticd::world {
namespace {

using hand::contact_point::ContactPointHand;
using hand::contact_point::ContactState;

constexpr double kG = 9.81;
const double kGamma = hand::contact_point::ContactPointParams{}.gamma_n_m;  // per contact, N/m
constexpr int kThumbDistal = 1 + 2, kIndexDistal = 1 + 3 + 2;

// A floor plane at z = 0 (its friction `floor_mu`) and a contact-point hand driven by a glove's 16
// frames (each shape where its frame puts it), parked 1 m up.
SceneDesc glove_scene(double floor_mu = 0.5, Eigen::Vector3d gravity = {0, 0, -kG}) {
  SceneDesc scene;
  scene.dt_s = 1.0 / 60.0;
  scene.gravity_m_s2 = gravity;
  ObjectDesc floor;
  floor.name = "floor";
  floor.kind = BodyKind::static_body;
  floor.shape.type = ShapeType::plane;
  floor.shape.normal = {0, 0, 1};
  floor.material.friction = floor_mu;
  scene.objects.push_back(floor);
  HandDesc hand;
  hand.name = "hand";
  hand.model = HandModelKind::contact_point;
  hand.handles = HandleSet::phalanges;
  hand.material.friction = 0.6;
  hand.material.friction_static = 0.8;
  hand.pose.p_W = {0, 0, 1};
  scene.hands.push_back(hand);
  return scene;
}

ObjectDesc box(const char* name, const Eigen::Vector3d& size, double mass, const Eigen::Vector3d& p, double mu) {
  ObjectDesc b;
  b.name = name;
  b.shape.type = ShapeType::box;
  b.shape.size = size;
  b.mass_kg = mass;
  b.pose.p_W = p;
  b.material.friction = mu;
  return b;
}

// The glove scene with a static 20 x 20 x 2 cm block on the floor (its top at z = 2 cm, mu 1).
SceneDesc block_scene() {
  SceneDesc scene = glove_scene();
  scene.objects.push_back(box("block", {0.2, 0.2, 0.02}, 1.0, {0, 0, 0.01}, 1.0));
  scene.objects.back().kind = BodyKind::static_body;
  return scene;
}

// Every frame parked far above the scene but those given.
struct Frames {
  std::vector<hand::HandleTarget> t = std::vector<hand::HandleTarget>(16);
  Frames() {
    for (int j = 0; j < 16; ++j) t[j].p_W = {0.3 * j, 0, 1.0};
  }
};

void drive(World& w, const Frames& f) {
  for (int j = 0; j < w.hand(0).num_handles(); ++j) ASSERT_TRUE(w.hand(0).set_target(j, f.t[j]));
}

const ContactPointHand& hand_of(const World& w) { return dynamic_cast<const ContactPointHand&>(w.hand(0)); }

// The radius of a phalanx's capsule: half the distance from the axis to the far side.
double capsule_radius(const ContactPointHand& h, int shape) {
  return h.project_to_surface(shape, Eigen::Vector3d(1, 0, 0)).x();
}

// Issue 18: the palm pressed 2 mm into the top of a box that cannot move (a 1 kg box on a floor of
// friction 2) and dragged along it 2 um per step: its contact's samples stay stuck while the
// tangential force is below mu_st times the normal force and all slide at the step where it passes
// it; the force then is the kinetic mu_dyn times the normal.
TEST(WorldContactPointHand, APalmDraggedOnABoxSlipsWhereTheTangentialForcePassesMuTimesTheNormal) {
  SceneDesc scene = glove_scene(2.0);
  scene.objects.push_back(box("box", {0.2, 0.2, 0.02}, 1.0, {0, 0, 0.01}, 1.0));
  World w(scene);
  const ContactPointHand& hand = hand_of(w);
  Frames f;
  const double depth = 0.002, z = 0.02 + hand::kPalmHalfThickness_m - depth;
  f.t[0].p_W = {0, 0, z + 0.001};  // first within the threshold: the contact is made
  drive(w, f);
  w.step();
  f.t[0].p_W = {0, 0, z};
  drive(w, f);
  for (int k = 0; k < 10; ++k) w.step();
  const ContactPointHand::Contact& c = hand.contact(0);
  ASSERT_EQ(c.object, w.rigid()->find("box"));
  ASSERT_EQ(c.count, 8);
  const double mu_st = std::sqrt(0.8 * 1.0), mu_dyn = std::sqrt(0.6 * 1.0);
  EXPECT_NEAR(c.mu_static, mu_st, 1e-12);
  EXPECT_NEAR(c.f_W.z(), kGamma * depth, 0.02 * kGamma * depth) << "gamma times the depth, up";
  double ratio_stuck = 0, ratio_switch = -1, ratio_after = -1;
  for (int k = 1; k <= 1500 && ratio_after < 0; ++k) {
    f.t[0].p_W.x() = 2e-6 * k;
    drive(w, f);
    w.step();
    const Eigen::Vector3d F = c.f_W;
    const double ratio = F.head<2>().norm() / F.z();
    int sliding = 0;
    for (int i = 0; i < c.count; ++i) sliding += c.samples[i].state == ContactState::sliding;
    if (sliding == 0 && ratio_switch < 0) ratio_stuck = ratio;
    if (sliding > 0 && ratio_switch < 0) {
      EXPECT_EQ(sliding, c.count) << "a flat palm on a flat box: every sample at once";
      ratio_switch = ratio;
      continue;
    }
    if (ratio_switch >= 0) ratio_after = ratio;
  }
  std::printf("tangential / normal force: last stuck %.4f, mu_st %.4f; sliding %.4f, mu_dyn %.4f\n", ratio_stuck, mu_st,
              ratio_switch, mu_dyn);
  EXPECT_LE(ratio_stuck, mu_st);
  EXPECT_GT(ratio_stuck, 0.98 * mu_st) << "it stuck until the force reached the cone";
  EXPECT_NEAR(ratio_switch, mu_dyn, 0.01 * mu_dyn) << "the kinetic force when it slides";
  EXPECT_GE(ratio_after, 0) << "it went on after the switch";
  EXPECT_EQ(w.snapshot().resets, 0);
}

// Issue 18: the index's distal phalanx (upright) pushes a 200 g box across a floor (mu 0.3) with a
// growing force: in every step where the box slides, its acceleration is (F_x - mu (m g - F_z)) / m
// for the force F the hand gave it in that step (F_z, ~0.14 N here, the finger's friction on the
// face as the box tips forward a little, unloads the floor).
TEST(WorldContactPointHand, ABoxPushedAcrossTheFloorAcceleratesAsNewtonAndCoulombSay) {
  SceneDesc scene = glove_scene(0.3);
  const double m = 0.2, mu = 0.3, half = 0.02;
  scene.objects.push_back(box("box", {0.04, 0.04, 0.04}, m, {0, 0, half}, 0.3));
  World w(scene);
  const int b = w.rigid()->find("box");
  const ContactPointHand& hand = hand_of(w);
  const double r = capsule_radius(hand, kIndexDistal);
  Frames f;
  // The capsule upright (the segment's y along world z), its side 1 mm from the box's -x face.
  f.t[kIndexDistal].q_W = Eigen::Quaterniond::FromTwoVectors(Eigen::Vector3d::UnitY(), Eigen::Vector3d::UnitZ());
  const double x0 = -half - r - 0.001;
  double x = x0, v = 0;
  const double a_hand = 1.5;  // m/s^2, from rest
  f.t[kIndexDistal].p_W = {x, 0, half};
  drive(w, f);
  w.step();
  int checked = 0;
  double worst = 0;
  for (int k = 0; k < 40; ++k) {
    v += a_hand * w.dt();
    x += v * w.dt();
    f.t[kIndexDistal].p_W.x() = x;
    f.t[kIndexDistal].v_W.x() = v;
    drive(w, f);
    const double v0 = w.snapshot().bodies[b].v_WO.x();
    w.step();
    const double v1 = w.snapshot().bodies[b].v_WO.x();
    const double F = hand.applied_wrench(b).x();
    const double a = (v1 - v0) / w.dt(), expected = (F - mu * (m * kG - hand.applied_wrench(b).z())) / m;
    if (v0 < 0.01 || expected < 0.1) continue;  // sliding, pushed past its kinetic friction
    worst = std::max(worst, std::abs(a - expected) / expected);
    ++checked;
  }
  std::printf("%d sliding steps checked, worst relative acceleration error %.4f, box at x %.1f mm\n", checked, worst,
              1e3 * w.snapshot().bodies[b].p_WO.x());
  EXPECT_GE(checked, 10);
  EXPECT_LT(worst, 0.01);
  EXPECT_EQ(w.snapshot().body_resets, 0);
}

// Seed 001 Fig. 1: a weightless 50 g box held between the thumb's and the index's distal phalanges
// (each 1.5 mm into its face) turns when the index alone slides 2 cm along its face, and does not
// when both move together.
TEST(WorldContactPointHand, AnObjectHeldBetweenTwoFingersSpinsWhenOneMovesAlongIt) {
  for (const bool both : {false, true}) {
    SceneDesc scene = glove_scene(0.5, Eigen::Vector3d::Zero());
    const double half = 0.02;
    scene.objects.push_back(box("box", {0.04, 0.04, 0.04}, 0.05, {0, 0, 0.3}, 1.0));
    World w(scene);
    const int b = w.rigid()->find("box");
    const ContactPointHand& hand = hand_of(w);
    Frames f;
    const double x_index = half + capsule_radius(hand, kIndexDistal) - 0.0015;
    const double x_thumb = -(half + capsule_radius(hand, kThumbDistal) - 0.0015);
    for (int k = 0; k <= 24; ++k) {  // 0.4 s, 5 cm/s
      const double up = 0.05 * k * w.dt();
      f.t[kIndexDistal].p_W = {x_index, 0, 0.3 + up};
      f.t[kThumbDistal].p_W = {x_thumb, 0, 0.3 + (both ? up : 0.0)};
      drive(w, f);
      w.step();
    }
    const RigidBodyState s = w.snapshot().bodies[b];
    const Eigen::AngleAxisd turn(s.q_WO);
    const double about_y = turn.angle() * turn.axis().y();
    std::printf("%s: box turned %.3f rad about y (axis %.2f %.2f %.2f), centre up %.1f mm\n",
                both ? "both fingers up" : "index up", about_y, turn.axis().x(), turn.axis().y(), turn.axis().z(),
                1e3 * (s.p_WO.z() - 0.3));
    if (both) {
      EXPECT_LT(std::abs(turn.angle()), 0.05);
      EXPECT_GT(s.p_WO.z() - 0.3, 0.015) << "carried up";
    } else {
      EXPECT_LT(about_y, -0.2) << "the +x face dragged up turns it about -y";
      EXPECT_GT(std::abs(turn.axis().y()), 0.95);
    }
    EXPECT_EQ(w.snapshot().body_resets, 0);
  }
}

// The handle-space model is this hand's force law at the moved handle: a palm 3 mm into a static
// box, moved deeper, sideways within the cone and lifted off, feels from the model what the hand's
// own contacts give at that pose (exactly: the same law); a finger 5 mm above the floor with no
// contact yet engages through its speculative row when moved 8 mm down, and the world's contact
// made there agrees within 20 %.
TEST(WorldContactPointHand, ItsModelIsItsContactLawAtTheMovedHandleAndEngagesANearSurface) {
  World w(block_scene());
  ContactPointHand& hand = dynamic_cast<ContactPointHand&>(w.hand(0));
  Frames f;
  const double z = 0.02 + hand::kPalmHalfThickness_m - 0.003;
  f.t[0].p_W = {0, 0, z + 0.0035};
  drive(w, f);
  w.step();
  f.t[0].p_W = {0, 0, z};
  drive(w, f);
  w.step();
  hand::HandleLinearization model;
  ASSERT_TRUE(hand.linearize_next_step(model, hand::ContactLinearization::unilateral));
  ASSERT_GE(model.contacts.count(), 8);
  for (const Eigen::Vector3d& dx : {Eigen::Vector3d(0, 0, -0.002), Eigen::Vector3d(0.0005, 0.0003, 0),
                                    Eigen::Vector3d(0, 0, 0.002), Eigen::Vector3d(0, 0, 0.01)}) {
    std::vector<hand::HandleState> moved = hand.handles();
    moved[0].p_WH += dx;
    const Eigen::VectorXd predicted = model.evaluate(moved);
    hand::HandleTarget t = f.t[0];
    t.p_W += dx;
    hand.set_target(0, t);
    const Eigen::VectorXd actual = hand.coupling_wrench();
    hand.set_target(0, f.t[0]);
    EXPECT_LT((predicted - actual).norm(), 1e-6 * std::max(1.0, actual.norm()))
        << "dx " << dx.transpose() << ": model " << predicted.head<3>().transpose() << ", law "
        << actual.head<3>().transpose();
    if (dx.z() > 0.003) {
      EXPECT_EQ(actual.norm(), 0.0) << "lifted off: no pull";
    }
  }
  // The index 5 mm above the block, no contact: its speculative row engages 3 mm deep.
  f.t[0].p_W = {0, 0, 0.5};
  const double r = capsule_radius(hand, kIndexDistal);
  f.t[kIndexDistal].p_W = {0, 0, 0.02 + r + 0.005};
  drive(w, f);
  w.step();
  ASSERT_EQ(hand.contact(kIndexDistal).object, -1);
  ASSERT_TRUE(hand.linearize_next_step(model, hand::ContactLinearization::unilateral));
  std::vector<hand::HandleState> moved = hand.handles();
  moved[kIndexDistal].p_WH.z() -= 0.008;
  const double predicted = model.evaluate(moved)[6 * kIndexDistal + 2];
  EXPECT_NEAR(predicted, kGamma * 0.003, 1e-6) << "the contact's gamma at the 3 mm the move goes in";
  f.t[kIndexDistal].p_W.z() -= 0.008;
  drive(w, f);
  w.step();
  w.step();
  const double actual = hand.coupling_wrench()[6 * kIndexDistal + 2];
  std::printf("speculative row %.3f N, the world's contact %.3f N\n", predicted, actual);
  EXPECT_NEAR(predicted, actual, 0.2 * actual);
}

// The model is the law where the tick asks it: at the step's end, the frames carried along by their
// devices' velocities for a step (the tick extrapolates its proxies there), and without the samples the law
// leaves out. A fingertip 1 mm into the top of a block, 2 mm in from its edge, then moved 8 mm past
// the edge at the same height: its samples' tangent plane (the top) says 1 mm inside, the block's
// surface 3-9 mm beside it, so the law exerts nothing, and neither may the model (with the tangent
// planes as rows it pushed ~1 N up, and on the bunny a stale plane held a lifting stylus 0.6 N down).
TEST(WorldContactPointHand, ItsModelIsTheLawAtTheStepEndAndLeavesOutWhatTheLawLeavesOut) {
  World w(block_scene());
  ContactPointHand& hand = dynamic_cast<ContactPointHand&>(w.hand(0));
  const double h = 1.0 / 60.0;
  hand.set_step_length(h);
  const double r = capsule_radius(hand, kIndexDistal);
  Frames f;
  f.t[0].p_W = {0, 0, 0.5};
  f.t[kIndexDistal].p_W = {0.1 - 0.002, 0, 0.02 + r - 0.001};
  drive(w, f);
  w.step();
  ASSERT_EQ(hand.contact(kIndexDistal).object, 1);
  // Its proxy pushed along at 10 cm/s by the rows: the anchor stays (the proxy's motion is the
  // rendering's own).
  hand::HandleTarget moving = f.t[kIndexDistal];
  moving.v_W = {0.1, 0, 0};
  ASSERT_TRUE(hand.set_target(kIndexDistal, moving));
  hand::HandleLinearization model;
  ASSERT_TRUE(hand.linearize_next_step(model, hand::ContactLinearization::unilateral));
  EXPECT_LT((model.x0[kIndexDistal].p_WH - moving.p_W).norm(), 1e-12);
  // The device moving up and along the block at 3 and 6 cm/s: the model's anchor is a step ahead.
  const Eigen::Vector3d v(0.03, 0, 0.06);
  moving.v_device_W = v;
  ASSERT_TRUE(hand.set_target(kIndexDistal, moving));
  ASSERT_TRUE(hand.linearize_next_step(model, hand::ContactLinearization::unilateral));
  EXPECT_LT((model.x0[kIndexDistal].p_WH - (moving.p_W + h * v)).norm(), 1e-12);
  ASSERT_GE(model.contacts.count(), 1);
  const auto model_is_the_law = [&](const Eigen::Vector3d& dx) {
    std::vector<hand::HandleState> moved = model.x0;
    moved[kIndexDistal].p_WH += dx;
    const Eigen::VectorXd predicted = model.evaluate(moved);
    hand::HandleTarget at = f.t[kIndexDistal];
    at.p_W = moved[kIndexDistal].p_WH;
    ASSERT_TRUE(hand.set_target(kIndexDistal, at));
    const Eigen::VectorXd actual = hand.coupling_wrench();
    EXPECT_GT(actual.norm(), 0.1) << "dx " << dx.transpose() << ": pressed in, the law pushes";
    EXPECT_LT((predicted - actual).norm(), 1e-6 * std::max(1.0, actual.norm()))
        << "dx " << dx.transpose() << ": model " << predicted.segment<3>(6 * kIndexDistal).transpose() << ", law "
        << actual.segment<3>(6 * kIndexDistal).transpose();
  };
  for (const Eigen::Vector3d& dx : {Eigen::Vector3d(0, 0, -0.002), Eigen::Vector3d(-0.0003, 0.0002, -0.0015)})
    model_is_the_law(dx);
  // Dragged 2 mm along the block, 1 mm in, the samples slide: the model's cone is then the kinetic
  // one, as the law's force (a static cone said 0.89 N along the block where the law says 0.77 N).
  f.t[kIndexDistal].p_W.y() -= 0.002;
  drive(w, f);
  w.step();
  ASSERT_EQ(hand.contact(kIndexDistal).samples[0].state, ContactState::sliding);
  ASSERT_TRUE(hand.linearize_next_step(model, hand::ContactLinearization::unilateral));
  model_is_the_law({0, -0.0005, -0.0002});
  // Past the edge at the same height: the contact is kept (within its release distance), the law
  // and the model exert nothing.
  f.t[kIndexDistal].p_W.x() += 0.008;
  drive(w, f);
  w.step();
  ASSERT_EQ(hand.contact(kIndexDistal).object, 1) << "the contact should outlive the move";
  const Eigen::VectorXd law = hand.coupling_wrench();
  ASSERT_TRUE(hand.linearize_next_step(model, hand::ContactLinearization::unilateral));
  const Eigen::VectorXd at_anchor = model.evaluate(model.x0);
  std::printf("past the edge: law %.4f N, model %.4f N\n", law.segment<3>(6 * kIndexDistal).norm(),
              at_anchor.segment<3>(6 * kIndexDistal).norm());
  EXPECT_EQ(law.norm(), 0.0);
  EXPECT_LT(at_anchor.norm(), 1e-9);
  // Its rows are the block's side now: the finger moved back 6 mm toward it meets the side ~1-3 mm in.
  std::vector<hand::HandleState> back = model.x0;
  back[kIndexDistal].p_WH.x() -= 0.006;
  EXPECT_GT(model.evaluate(back)[6 * kIndexDistal], 0.1) << "the side pushes the finger back out (+x)";
}

// A finger sliding along a curved surface within the step the model looks ahead: the index's distal
// 1 mm into the lower half of a fixed 3 cm sphere, 40 degrees below its equator, its device carrying it
// up along the sphere to 15 degrees below (the frame's target there, as the tick's anchor puts it).
// Its samples' contact points were made 25 degrees back, where the tangent plane faces down more: by
// that plane the finger is 3.7 mm in (R - (R - 1 mm) cos 25 degrees). The world's next ODE step
// slides each such sample first (section 3.5) and pushes with the slid point; the model at its anchor
// must be that force, not the stale plane's (on the bunny, a stylus lifting a finger along its flank
// was pulled down 1.1 N by those).
TEST(WorldContactPointHand, ItsModelSlidesTheSamplesAsTheWorldsNextStepDoes) {
  SceneDesc scene = glove_scene();
  const Eigen::Vector3d centre(0, 0, 0.1);
  const double R = 0.03;
  ObjectDesc sphere = box("sphere", Eigen::Vector3d::Zero(), 1.0, centre, 0.5);
  sphere.kind = BodyKind::static_body;
  sphere.shape.type = ShapeType::sphere;
  sphere.shape.radius = R;
  scene.objects.push_back(sphere);
  World w(scene);
  ContactPointHand& hand = dynamic_cast<ContactPointHand&>(w.hand(0));
  const double h = w.dt(), r = capsule_radius(hand, kIndexDistal);
  // The capsule's axis is along y: its side touches the sphere in the xz plane, at angle phi below the
  // equator, 1 mm deep.
  const auto outward = [](double phi_deg) {
    const double phi = phi_deg * std::numbers::pi / 180;
    return Eigen::Vector3d(std::cos(phi), 0, -std::sin(phi));
  };
  const auto finger_at = [&](double phi_deg) { return Eigen::Vector3d(centre + (R + r - 0.001) * outward(phi_deg)); };
  Frames f;
  f.t[kIndexDistal].p_W = finger_at(40);
  drive(w, f);
  w.step();
  w.step();
  const ContactPointHand::Contact& contact = hand.contact(kIndexDistal);
  ASSERT_EQ(contact.object, w.rigid()->find("sphere"));
  ASSERT_GT(contact.f_W.norm(), 0.3) << "pressed 1 mm: pushed out";
  // The device carries the frame to 15 degrees within the step.
  hand::HandleTarget moving = f.t[kIndexDistal];
  moving.v_device_W = (finger_at(15) - finger_at(40)) / h;
  ASSERT_TRUE(hand.set_target(kIndexDistal, moving));
  hand::HandleLinearization model;
  ASSERT_TRUE(hand.linearize_next_step(model, hand::ContactLinearization::unilateral));
  ASSERT_LT((model.x0[kIndexDistal].p_WH - finger_at(15)).norm(), 1e-12);
  const Eigen::Vector3d predicted = model.evaluate(model.x0).segment<3>(6 * kIndexDistal);
  // The stale planes' force there: each sample's spring from its contact point as it stands.
  Eigen::Vector3d stale = Eigen::Vector3d::Zero();
  {
    Eigen::Isometry3d T = hand.shape_pose(kIndexDistal);
    T.translation() = finger_at(15);
    for (int k = 0; k < contact.count; ++k) {
      const ContactPointHand::Sample& s = contact.samples[k];
      stale += hand::contact_point::contact_force(kGamma / contact.count, contact.mu_static, contact.mu_dynamic,
                                                  s.C_O + centre, s.n_O, T * s.p_S)
                   .total();
    }
  }
  // The world's next step with the frame there.
  f.t[kIndexDistal].p_W = finger_at(15);
  drive(w, f);
  w.step();
  const Eigen::Vector3d world = contact.f_W;
  std::printf(
      "at 15 degrees: the world pushes (%.3f, %.3f, %.3f) N, the model (%.3f, %.3f, %.3f) N, the stale "
      "planes (%.3f, %.3f, %.3f) N\n",
      world.x(), world.y(), world.z(), predicted.x(), predicted.y(), predicted.z(), stale.x(), stale.y(), stale.z());
  EXPECT_LT((predicted - world).norm(), 1e-6 * std::max(1.0, world.norm()));
  EXPECT_GT(world.norm(), 0.1) << "1 mm in: pushed out";
  EXPECT_GT((stale - world).norm(), 0.5 * world.norm()) << "the case should tell the stale planes from the slid ones";
}

// A 6-frame glove (palm and distal phalanges): each distal shape sits on its frame, the proximal and
// middle phalanges where the posture the frames give puts them (flexions shared 3 : 3 : 2 come back
// exactly), on the palm's frame; a 1 cm block 2 mm into the index's distal pushes that frame alone, one
// 2 mm into its proximal phalanx the palm's alone.
TEST(WorldContactPointHand, ASixFrameGlovesFramesPlaceItsFingersAndEachContactPushesItsFrame) {
  hand::HandJointAngles a = hand::rest_joint_angles();
  for (int f = 0; f < hand::kHandFingers; ++f) a.finger[f] = {a.finger[f][0], 0.3, 0.3, 0.2};
  const hand::SkeletonPose pose = hand::skeleton_pose(a);
  const Eigen::Vector3d palm(0, 0, 0.3);
  auto hold_posture = [&](ContactPointHand& hand) {  // the glove's 6 frames in the posture
    for (int j = 0; j < 6; ++j) {
      hand::HandleTarget t;
      t.p_W = j == 0 ? palm : Eigen::Vector3d(palm + pose.centre[3 * (j - 1) + 2]);
      if (j > 0) t.q_W = Eigen::Quaterniond(pose.R[3 * (j - 1) + 2]);
      ASSERT_TRUE(hand.set_target(j, t));
    }
  };
  for (const int pressed : {kIndexDistal, 1 + 3}) {  // the index's distal, then its proximal phalanx
    // Where the pressed shape reaches lowest, from a hand built in the posture.
    Eigen::Vector3d lowest(0, 0, 1);
    {
      SceneDesc probe = glove_scene();
      probe.hands[0].handles = HandleSet::fingertips;
      World w(probe);
      ContactPointHand& hand = dynamic_cast<ContactPointHand&>(w.hand(0));
      ASSERT_EQ(hand.num_handles(), 6);
      hold_posture(hand);
      for (int i = 0; i < hand::kHandPhalanges; ++i) {
        const Eigen::Isometry3d T = hand.shape_pose(1 + i);
        EXPECT_LT((T.translation() - (palm + pose.centre[i])).norm(), 1e-9) << i;
        EXPECT_LT((T.linear() - pose.R[i]).norm(), 1e-9) << i;
        EXPECT_EQ(hand.shape_handle(1 + i), i % 3 == 2 ? 1 + i / 3 : 0) << i;
      }
      for (int k = 0; k < 4000; ++k) {
        const Eigen::Vector3d q =
            hand.shape_pose(pressed) * hand.project_to_surface(pressed, Eigen::Vector3d::Random() * 0.05);
        if (q.z() < lowest.z()) lowest = q;
      }
    }
    SceneDesc scene = glove_scene();
    scene.hands[0].handles = HandleSet::fingertips;
    scene.objects.push_back(box("block", {0.01, 0.01, 0.01}, 1.0, lowest + Eigen::Vector3d(0, 0, 0.002 - 0.005), 1.0));
    scene.objects.back().kind = BodyKind::static_body;
    World w(scene);
    ContactPointHand& hand = dynamic_cast<ContactPointHand&>(w.hand(0));
    hold_posture(hand);
    w.step();
    w.step();
    const Eigen::VectorXd F = hand.coupling_wrench();
    const int frame = hand.shape_handle(pressed);
    // The world records the contact on that frame's part of the hand (its flag for the device).
    int recorded = 0;
    for (const ContactRecord& c : w.snapshot().contacts) {
      EXPECT_EQ(hand.skin_handle(c.point), frame);
      ++recorded;
    }
    EXPECT_GT(recorded, 0);
    std::printf("shape %d 2 mm into the block: frame %d feels %.3f N up, all the others %.3g N\n", pressed, frame,
                F[6 * frame + 2], (F.norm() - F.segment<6>(6 * frame).norm()));
    EXPECT_GT(F[6 * frame + 2], 0.5 * kGamma * 0.002) << "pushed up";
    for (int j = 0; j < 6; ++j) {
      if (j != frame) {
        EXPECT_EQ(F.segment<6>(6 * j).norm(), 0.0) << j;
      }
    }
  }
}

// Hard cases: a NaN target is refused; a palm teleported 10 cm into a box on the floor and a 3 m/s
// impact end without anything non-finite; boxes 1000 times lighter and heavier than the 0.65 kg of a
// hand (0.65 g and 650 kg) pressed 2 cm stay on the floor, and nothing resets.
TEST(WorldContactPointHand, HardCasesEndWithoutNaNAndWithoutResets) {
  for (const double mass : {0.65e-3, 0.2, 650.0}) {
    SceneDesc scene = glove_scene();
    scene.objects.push_back(box("box", {0.2, 0.2, 0.02}, mass, {0, 0, 0.01}, 0.5));
    World w(scene);
    const int b = w.rigid()->find("box");
    Frames f;
    hand::HandleTarget bad = f.t[0];
    bad.p_W.x() = NAN;
    EXPECT_FALSE(w.hand(0).set_target(0, bad));
    const double top = 0.02 + hand::kPalmHalfThickness_m;
    double lowest = 1, highest = 0;
    auto step = [&](double palm_z, double vz) {
      f.t[0].p_W = {0, 0, palm_z};
      f.t[0].v_W = {0, 0, vz};
      drive(w, f);
      w.step();
      const double zb = w.snapshot().bodies[b].p_WO.z();
      lowest = std::min(lowest, zb), highest = std::max(highest, zb);
      ASSERT_TRUE(w.hand(0).coupling_wrench().allFinite());
      ASSERT_TRUE(w.snapshot().bodies[b].p_WO.allFinite());
    };
    for (int k = 0; k < 30; ++k) step(top + 0.001 - 0.02 * std::min(1.0, k / 20.0), 0);  // a 2 cm press
    EXPECT_GT(w.hand(0).coupling_wrench().z(), 0.9 * kGamma * 0.019) << mass << " kg: the handle feels the press";
    for (int k = 0; k < 30; ++k) step(top + 0.05, 0);  // off
    for (int k = 0; k < 30; ++k) step(top - 0.1, 0);   // a 10 cm teleport in
    for (int k = 0; k < 30; ++k) step(top + 0.05, 0);
    for (int k = 0; k < 30; ++k) step(std::max(top + 0.05 - 3.0 * k * w.dt(), top - 0.02), -3.0);  // 3 m/s
    std::printf("%.4g kg box: between z %.2f and %.2f mm, %ld body resets\n", mass, 1e3 * lowest, 1e3 * highest,
                w.snapshot().body_resets);
    EXPECT_NEAR(lowest, 0.01, 0.002) << mass << " kg: on the floor";
    EXPECT_NEAR(highest, 0.01, 0.002) << mass << " kg";
    EXPECT_EQ(w.snapshot().resets, 0);
    EXPECT_EQ(w.snapshot().body_resets, 0);
  }
}

// The shipped scenes load and step: the stylus's (the bunny on the table, the palm lowered 5 cm onto
// it, touching) and the glove's (the hand open above the table, touching nothing).
TEST(WorldContactPointHand, TheSceneFilesLoadAndStep) {
  World stylus(load_scene(std::string(HAPTICD_SCENES_DIR) + "/contact_point_bunny.json"));
  EXPECT_EQ(stylus.hand(0).model_name(), "contact_point");
  const hand::HandleState start = stylus.hand(0).handles()[0];
  bool touched = false;
  for (int k = 0; k < 60; ++k) {
    hand::HandleTarget t;
    t.p_W = start.p_WH - Eigen::Vector3d(0, 0, 0.05 * std::min(1.0, k / 30.0));
    t.q_W = start.q_WH;
    stylus.hand(0).set_target(0, t);
    stylus.step();
    for (const ContactRecord& c : stylus.snapshot().contacts) touched = touched || c.hand == 0;
  }
  EXPECT_TRUE(touched);
  EXPECT_EQ(stylus.snapshot().resets, 0);
  EXPECT_EQ(stylus.snapshot().body_resets, 0);
  EXPECT_TRUE(stylus.hand(0).coupling_wrench().allFinite());
  World glove(load_scene(std::string(HAPTICD_SCENES_DIR) + "/contact_point_grasp.json"));
  EXPECT_EQ(glove.hand(0).num_handles(), 16);
  for (int k = 0; k < 30; ++k) glove.step();
  EXPECT_EQ(glove.snapshot().resets, 0);
  EXPECT_EQ(glove.snapshot().body_resets, 0);
  EXPECT_TRUE(glove.snapshot().contacts.empty() ||
              std::none_of(glove.snapshot().contacts.begin(), glove.snapshot().contacts.end(),
                           [](const ContactRecord& c) { return c.hand == 0; }));
}

}  // namespace
}  // namespace hapticd::world
