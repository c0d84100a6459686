// Glove grasps in the world: a right hand with 16 handles (palm + 15 phalanges,
// 1.7k tets, separate fingers) driven like a glove (every handle's target set
// each step from posture_targets, with the velocity from the last target; the
// visual loop's stiff drive) picks up rigid objects standing on a static table:
// descend open, close, lift 5 cm, hold 5 s, open. Measured: the object's lift,
// its slip in the palm frame while held, how soon it falls once the hand opens,
// and the per-finger contact forces on it, with penalty and constraint contact.
//
// The postures and object placements come from a kinematic search (skin points
// carried rigidly by their handles; the distal phalanges' skin lands within
// 2-4 mm of the FEM hand's):
// each fingertip's skin enters its face of the object by a few mm in the closed
// posture, and no skin point comes within a few mm of any other face, at the
// end or on the way there from the open hand, so closing squeezes the object
// instead of shoving it across the table. The thumb abducts toward +x+y, so the
// thumb-finger opposition of this skeleton is diagonal: the objects stand
// turned -30 degrees about z.
//
// The tests run the hand with gravity (with the 1e6 N/m drive its own weight
// moves the handles by micrometres); WeightlessHandStillCarriesTheCubesWeight
// checks the server's weightless hand. Constraint contact runs with its
// reserve rows (the default); the snapshot shows the promoted reserves' forces.
#include <gtest/gtest.h>

#include <Eigen/Geometry>
#include <algorithm>
#include <array>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <numbers>
#include <string>
#include <vector>

#include "hand_models/fem_hand.hpp"
#include "hand_models/press_scenario.hpp"
#include "hand_models/procedural_hand.hpp"
#include "hand_models/skeleton/hand_skeleton.hpp"
#include "server/world/scene_loader.hpp"
#include "server/world/world.hpp"
#include "world_test_util.hpp"

namespace hapticd::world {
namespace {

constexpr double kDeg = std::numbers::pi / 180.0;
constexpr double kMm = 0.001;
constexpr double kG = 9.81;

hand::HandJointAngles degrees(const std::array<std::array<double, 4>, hand::kHandFingers>& d) {
  hand::HandJointAngles a;
  for (int f = 0; f < hand::kHandFingers; ++f)
    for (int k = 0; k < 4; ++k) a.finger[f][k] = d[f][k] * kDeg;
  return a;
}

// A grasp: the closed posture, and where the object stands in the hand frame
// (palm centre, fingers +y, palmar side -z) when the hand closes on it.
struct GraspSpec {
  double size_m = 0.05, mass_kg = 0.1;
  Eigen::Vector3d object_H = Eigen::Vector3d::Zero();  // object centre in the hand frame, m
  double yaw = 0;                                      // the object's turn about z, rad
  hand::HandJointAngles closed;
};

// Tripod grasp of the 5 cm box: thumb on the near face (-y of the box), index
// and middle fingertips on the far face; ring and little stay open above the
// box. The distal pads enter the box by 4 mm (thumb), 2.5 mm (index) and 3.5 mm
// (middle); the box top is 1.1 cm under the palm's skin.
GraspSpec box_grasp() {
  GraspSpec g;
  g.size_m = 0.05;
  g.mass_kg = 0.1;
  g.object_H = {-0.040, 0.050, -0.052};
  g.yaw = -30 * kDeg;
  g.closed = degrees({{{-30, 30, 20, 60}, {-4, 5, 70, 65}, {0, 15, 95, 40}, {8, 0, 6, 6}, {16, 0, 6, 6}}});
  return g;
}

// Pinch of the 2.5 cm cube between the thumb and index fingertips, each pad 3 mm
// into its face; the other fingers stay open. Compare the simulated glove's
// pinch, fingertips touching (clients/sim/glove_trajectory.hpp: thumb -14 31 10
// -8, index -5 50 55 30): here the index bends less, its tip a cube away.
GraspSpec cube_pinch() {
  GraspSpec g;
  g.size_m = 0.025;
  g.mass_kg = 0.02;
  g.object_H = {-0.035, 0.060, -0.055};
  g.yaw = -30 * kDeg;
  g.closed = degrees({{{-15, 30, 5, 15}, {1, 30, 45, 55}, {0, 0, 6, 6}, {8, 0, 6, 6}, {16, 0, 6, 6}}});
  return g;
}

// A static table (top at z = 0), the object standing on it at the origin, the
// hand 4 cm above its grasping pose, in the rest posture.
SceneDesc grasp_scene(const GraspSpec& g, const Eigen::Vector3d& palm_W, HandModelKind model = HandModelKind::fem) {
  SceneDesc scene;
  ObjectDesc table = testing_util::static_table({0.6, 0.6, 0.1}, 0.0);
  table.material.friction = 0.5;
  scene.objects.push_back(table);
  ObjectDesc object;
  object.name = "object";
  object.shape.type = ShapeType::box;
  object.shape.size = Eigen::Vector3d::Constant(g.size_m);
  object.mass_kg = g.mass_kg;
  object.pose.p_W = {0, 0, 0.5 * g.size_m};
  object.pose.q_W = Eigen::Quaterniond(Eigen::AngleAxisd(g.yaw, Eigen::Vector3d::UnitZ()));
  object.material.friction = 0.8;
  scene.objects.push_back(object);
  HandDesc hand;
  hand.name = "right";
  hand.model = model;
  hand.resolution_tets = 1700;
  hand.handles = HandleSet::phalanges;
  hand.material.friction = 0.9;  // skin on the object: sqrt(0.9 * 0.8) = 0.85
  hand.pose.p_W = palm_W;
  scene.hands.push_back(hand);
  return scene;
}

WorldOptions glove_options(ContactModel contact) {
  WorldOptions o;
  o.drive = hand::DriveParams{1e6, 1e3, 1e3, 10};  // the visual loop's almost kinematic drive
  o.contact = contact;
  o.hand_gravity = true;  // see the file comment: false makes the held object weightless
  o.linearize = false;    // no handle-space model needed here (it costs ~50 % more per step)
  return o;
}

// The force of the hand on the object, summed per finger (0-4 thumb..little) and
// for the palm (5), N; with the normal forces' sum. f_W is the force on the
// hand, so the object gets -f_W.
struct HandForces {
  std::array<Eigen::Vector3d, 6> on_object;
  std::array<int, 6> contacts{};
  double normal_sum = 0;
};

HandForces hand_forces(const World& w, int object) {
  HandForces out;
  for (Eigen::Vector3d& f : out.on_object) f.setZero();
  for (const ContactRecord& c : w.snapshot().contacts) {
    if (c.hand != 0 || c.object != object) continue;
    const int j = w.hand(0).skin_handle(c.point);
    const int part = j == 0 ? 5 : (j - 1) / 3;  // handle j >= 1 is phalanx j - 1, finger-major
    out.on_object[part] -= c.f_W;
    ++out.contacts[part];
    out.normal_sum += std::max(0.0, c.f_W.dot(c.n_W));
  }
  return out;
}

// Sets every handle target of `hand` for `angles` with the hand frame at (p, q), each with the
// velocity of getting there from its last target in one step.
void set_posture(const World& w, hand::FemHand& hand, const hand::HandJointAngles& angles, const Eigen::Vector3d& p,
                 const Eigen::Quaterniond& q, bool left) {
  std::vector<hand::HandleTarget> t = posture_targets(hand.shape, *hand.model, angles, p, q, left);
  for (int j = 0; j < hand.model->num_handles(); ++j) {
    t[j].v_W = (t[j].p_W - hand.state.targets[j].p_W) / w.dt();
    t[j].w_W = hand::rotation_difference(t[j].q_W, hand.state.targets[j].q_W) / w.dt();
    set_target(hand.state, j, t[j]);
  }
}

struct GraspRun {
  double lift_m = 0;        // the object's rise from the table to the end of the lift (the palm rises 5 cm)
  double slip_m = 0;        // change of the object's position in the palm frame over the 5 s hold
  double slip_z_m = 0;      // its vertical part (palm frame z is world z)
  double turn_rad = 0;      // the object's rotation in the palm frame over the hold
  double release_s = -1;    // from the start of opening until the object is 5 mm lower; -1: never
  double landed_z_m = 0;    // the object's centre 0.75 s after opening starts
  double normal_sum_n = 0;  // the hand's normal forces on the object, summed, averaged over the hold
  std::array<Eigen::Vector3d, 6> force_n;  // per finger (and palm) on the object, averaged over the hold
  std::array<int, 6> contacts{};           // per finger, at the end of the hold
  std::array<double, 5> into_object{};     // cosine between a finger's force and its distal handle -> object centre
  double step_ms = 0, step_ms_max = 0;
  long resets = 0;
};

// Picks up the object: 0.3 s open above it, descend 4 cm in 0.5 s, close in 0.5 s,
// 0.25 s settling, lift 5 cm in 1 s, hold 5 s, open in 0.25 s, 0.5 s more.
// Moves are half-cosine ramps; each step's targets carry the velocity from the last.
// Any hand model: its handles' targets are the glove's frames (skeleton_pose's segments on the palm)
// carrying each handle where it sits in its frame (Hand::handle_info), as a device link does.
GraspRun run_grasp(const GraspSpec& g, const WorldOptions& options, const SceneDesc& scene) {
  const Eigen::Vector3d grip = Eigen::Vector3d(0, 0, 0.5 * g.size_m) - g.object_H;  // palm when grasping
  const Eigen::Vector3d above = grip + Eigen::Vector3d(0, 0, 0.04);
  World w(scene, options);
  hand::Hand& hand = w.hand(0);
  std::vector<hand::HandleTarget> last(static_cast<std::size_t>(hand.num_handles()));
  for (int j = 0; j < hand.num_handles(); ++j)
    last[j].p_W = hand.handles()[j].p_WH, last[j].q_W = hand.handles()[j].q_WH;
  const int object = w.rigid()->find("object");
  const hand::HandJointAngles open = hand::rest_joint_angles();
  hand::HandJointAngles angles = open;
  Eigen::Vector3d palm = above;
  GraspRun run;
  long steps = 0;
  auto object_p = [&] { return w.snapshot().bodies[object].p_WO; };
  auto step_to = [&](const hand::HandJointAngles& a, const Eigen::Vector3d& p) {
    const hand::SkeletonPose pose = hand::skeleton_pose(a);
    for (int j = 0; j < hand.num_handles(); ++j) {
      const hand::FrameToHandle in = hand.handle_info(j, hand.num_handles()).in_frame;
      const Eigen::Vector3d p_frame = j == 0 ? p : Eigen::Vector3d(p + pose.centre[j - 1]);
      const Eigen::Quaterniond q_frame = j == 0 ? Eigen::Quaterniond::Identity() : Eigen::Quaterniond(pose.R[j - 1]);
      hand::HandleTarget t;
      t.p_W = p_frame + q_frame * in.p_F;
      t.q_W = (q_frame * in.q_F).normalized();
      t.v_W = (t.p_W - last[j].p_W) / w.dt();
      t.w_W = hand::rotation_difference(t.q_W, last[j].q_W) / w.dt();
      hand.set_target(j, t);
      last[j] = t;
    }
    w.step();
    angles = a;
    palm = p;
    ++steps;
    run.step_ms += w.snapshot().timings.total_ms;
    run.step_ms_max = std::max(run.step_ms_max, w.snapshot().timings.total_ms);
  };
  auto move = [&](const hand::HandJointAngles& to, const Eigen::Vector3d& palm_to, double seconds, auto each) {
    const hand::HandJointAngles a0 = angles;
    const Eigen::Vector3d p0 = palm;
    const int n = static_cast<int>(std::lround(seconds / w.dt()));
    for (int k = 1; k <= n; ++k) {
      const double s = 0.5 * (1.0 - std::cos(std::numbers::pi * k / n));
      step_to(hand::HandJointAngles::from_vector((1 - s) * a0.vector() + s * to.vector()), p0 + s * (palm_to - p0));
      each();
    }
  };
  auto nothing = [] {};
  move(open, above, 0.3, nothing);
  move(open, grip, 0.5, nothing);
  move(g.closed, grip, 0.5, nothing);
  move(g.closed, grip, 0.25, nothing);
  const double z0 = object_p().z();
  move(g.closed, grip + Eigen::Vector3d(0, 0, 0.05), 1.0, nothing);
  run.lift_m = object_p().z() - z0;
  auto in_palm = [&] {
    const hand::HandleState& p = w.snapshot().handles[0][0];
    return Eigen::Vector3d(p.q_WH.conjugate() * (object_p() - p.p_WH));
  };
  auto turned_in_palm = [&] { return w.snapshot().handles[0][0].q_WH.conjugate() * w.snapshot().bodies[object].q_WO; };
  const Eigen::Vector3d held0 = in_palm();
  const Eigen::Quaterniond turned0 = turned_in_palm();
  int samples = 0;
  for (Eigen::Vector3d& f : run.force_n) f.setZero();
  std::array<Eigen::Vector3d, 5> to_object;
  for (Eigen::Vector3d& d : to_object) d.setZero();
  move(g.closed, palm, 5.0, [&] {
    const HandForces F = hand_forces(w, object);
    for (int f = 0; f < 6; ++f) run.force_n[f] += F.on_object[f];
    for (int f = 0; f < 5; ++f)
      to_object[f] += (object_p() - w.snapshot().handles[0][3 * f + 3].p_WH).normalized();  // distal handle
    run.normal_sum_n += F.normal_sum;
    ++samples;
  });
  const Eigen::Vector3d held1 = in_palm();
  run.slip_m = (held1 - held0).norm();
  run.slip_z_m = held1.z() - held0.z();
  run.turn_rad = Eigen::AngleAxisd(turned_in_palm() * turned0.conjugate()).angle();
  for (Eigen::Vector3d& f : run.force_n) f /= samples;
  run.normal_sum_n /= samples;
  for (int f = 0; f < 5; ++f)
    run.into_object[f] = run.force_n[f].norm() > 0 ? run.force_n[f].normalized().dot(to_object[f].normalized()) : 0;
  run.contacts = hand_forces(w, object).contacts;
  const double opened_at = w.snapshot().t_s, z_held = object_p().z();
  auto watch = [&] {
    if (run.release_s < 0 && z_held - object_p().z() > 5 * kMm) run.release_s = w.snapshot().t_s - opened_at;
  };
  move(open, palm, 0.25, watch);
  move(open, palm, 0.5, watch);
  run.landed_z_m = object_p().z();
  run.step_ms /= static_cast<double>(steps);
  run.resets = w.snapshot().resets;
  return run;
}

GraspRun run_grasp(const GraspSpec& g, const WorldOptions& options) {
  const Eigen::Vector3d above = Eigen::Vector3d(0, 0, 0.5 * g.size_m + 0.04) - g.object_H;
  return run_grasp(g, options, grasp_scene(g, above));
}

Eigen::Vector3d total_force(const GraspRun& r) {
  Eigen::Vector3d s = Eigen::Vector3d::Zero();
  for (const Eigen::Vector3d& f : r.force_n) s += f;
  return s;
}

void print_run(const char* what, const GraspRun& r) {
  std::printf(
      "[glove grasp] %s: lift %.1f mm, slip over the 5 s hold %.2f mm (vertical %.2f), turn %.1f deg, "
      "released after %.3f s, object at z = %.1f mm 0.75 s after opening; normal forces %.2f N; %.1f ms/step "
      "(max %.1f), %ld resets\n",
      what, r.lift_m / kMm, r.slip_m / kMm, r.slip_z_m / kMm, r.turn_rad / kDeg, r.release_s, r.landed_z_m / kMm,
      r.normal_sum_n, r.step_ms, r.step_ms_max, r.resets);
  for (int f = 0; f < 6; ++f) {
    if (r.force_n[f].norm() == 0 && r.contacts[f] == 0) continue;
    std::printf("[glove grasp]   %-6s %2d contacts, force on the object (%.3f, %.3f, %.3f) N",
                f < 5 ? hand::finger_name(f) : "palm", r.contacts[f], r.force_n[f].x(), r.force_n[f].y(),
                r.force_n[f].z());
    if (f < 5) std::printf(", cosine to the object centre %.2f", r.into_object[f]);
    std::printf("\n");
  }
  const Eigen::Vector3d total = total_force(r);
  std::printf("[glove grasp]   total (%.3f, %.3f, %.3f) N\n", total.x(), total.y(), total.z());
}

// A rigid hand driven by the same glove frames: seed 002's spring hand (ODE capsules on hinges, pulled
// by springs toward the tracked hand) or seed 001's contact-point hand (its capsules on the frames);
// the pair's friction coefficient mu on the box and on the hand.
GraspRun run_rigid_grasp(const GraspSpec& g, double mu, HandModelKind model) {
  const Eigen::Vector3d above = Eigen::Vector3d(0, 0, 0.5 * g.size_m + 0.04) - g.object_H;
  SceneDesc scene = grasp_scene(g, above, model);
  scene.objects[1].material.friction = mu;
  scene.hands[0].material.friction = mu;
  WorldOptions o;
  o.linearize = false;
  return run_grasp(g, o, scene);
}

// ---------------------------------------------------------------------------------------------
// The 100 g box.

// Constraint contacts hold the box with static friction: it rises with the hand
// (49 mm of the palm's 50), stays within 0.6 mm and 1.7 degrees of its place in
// the palm frame over 5 s (0.0-0.6 mm for the box placed 2 mm off either way
// along x and y), and falls as soon as the fingers let go (5 mm lower 0.083 s
// after opening starts, on the table before 0.75 s). The snapshot's forces on
// the held box (promoted reserve rows included) carry its weight.
TEST(WorldGloveGrasp, ConstraintContactsLiftA100gBoxHoldItFiveSecondsAndDropItOnOpening) {
  const GraspSpec g = box_grasp();
  const GraspRun r = run_grasp(g, glove_options(ContactModel::constraint));
  print_run("box, constraint contact", r);
  EXPECT_EQ(r.resets, 0);
  EXPECT_GT(r.lift_m, 0.045);
  EXPECT_LT(r.lift_m, 0.051);
  EXPECT_LT(r.slip_m, 2 * kMm);
  EXPECT_LT(r.turn_rad, 3 * kDeg);
  // Thumb, index and middle all hold it.
  for (int f = 0; f < 3; ++f) EXPECT_GT(r.contacts[f], 0) << hand::finger_name(f);
  EXPECT_GT(r.release_s, 0.0);
  EXPECT_LT(r.release_s, 0.3);
  EXPECT_NEAR(r.landed_z_m, 0.5 * g.size_m, 1 * kMm);  // back on the table (a cube lands on a face)
  const Eigen::Vector3d total = total_force(r);
  EXPECT_NEAR(total.z(), g.mass_kg * kG, 0.1 * g.mass_kg * kG);
  EXPECT_LT(total.head<2>().norm(), 0.1 * g.mass_kg * kG);
}

// Penalty friction is viscous below PointContact::kStickSpeed_m_s (1 cm/s): a
// held weight W slides at the speed where that viscous force carries it,
// u = W v_stick / (mu sum N), the normal forces N summed. Here 28 N of normal
// force and mu = 0.85 let the 0.98 N box creep down at 0.45 mm/s (0.41 predicted):
// 2.0-3.0 mm over the 5 s hold for the box placed 2 mm off either way, over the
// 2 mm the issue allows. Lifting works as with constraint contact; the box falls
// 5 mm 0.13-0.15 s after opening starts.
TEST(WorldGloveGrasp, PenaltyContactsLiftAndDropTheBoxButItCreepsDownAtTheRegularizedFrictionSpeed) {
  const GraspSpec g = box_grasp();
  const GraspRun r = run_grasp(g, glove_options(ContactModel::penalty));
  print_run("box, penalty contact", r);
  EXPECT_EQ(r.resets, 0);
  EXPECT_GT(r.lift_m, 0.045);
  EXPECT_LT(r.lift_m, 0.051);
  for (int f = 0; f < 3; ++f) EXPECT_GT(r.contacts[f], 0) << hand::finger_name(f);
  EXPECT_GT(r.release_s, 0.0);
  EXPECT_LT(r.release_s, 0.3);
  EXPECT_NEAR(r.landed_z_m, 0.5 * g.size_m, 1 * kMm);
  // The hand's forces carry the box's weight (penalty ContactRecords hold every force).
  EXPECT_NEAR(total_force(r).z(), g.mass_kg * kG, 0.1 * g.mass_kg * kG);
  // The creep: downward, at the regularized friction's speed within 40 %.
  const double mu = std::sqrt(0.9 * 0.8);
  const double predicted = g.mass_kg * kG * hand::PointContact::kStickSpeed_m_s / (mu * r.normal_sum_n);
  const double measured = -r.slip_z_m / 5.0;
  std::printf("[glove grasp] penalty creep %.3f mm/s, W v_stick / (mu sum N) = %.3f mm/s\n", measured / kMm,
              predicted / kMm);
  EXPECT_GT(measured, 0.6 * predicted);
  EXPECT_LT(measured, 1.4 * predicted);
}

// ---------------------------------------------------------------------------------------------
// The 20 g cube in a pinch.

void expect_pinch_forces(const GraspSpec& g, const GraspRun& r) {
  // Thumb and index each push the cube toward its centre (within 45 degrees)...
  for (int f = 0; f < 2; ++f) {
    EXPECT_GT(r.contacts[f], 0) << hand::finger_name(f);
    EXPECT_GT(r.into_object[f], std::cos(45 * kDeg)) << hand::finger_name(f);
  }
  // ...and nothing else touches it.
  for (int f = 2; f < 6; ++f) EXPECT_EQ(r.force_n[f].norm(), 0.0) << f;
  // Held still, the hand's forces balance the weight: vertically within 10 %,
  // the squeeze cancelling horizontally.
  const Eigen::Vector3d total = total_force(r);
  EXPECT_NEAR(total.z(), g.mass_kg * kG, 0.1 * g.mass_kg * kG);
  EXPECT_LT(total.head<2>().norm(), 0.1 * g.mass_kg * kG);
}

// Thumb and index squeeze the cube with ~11 N each (3 mm of flesh), their sum carries its
// 0.196 N weight to 0.1 %, and it stays put (0.0-0.4 mm and at most 1.4 degrees
// over the hold for the cube placed 2 mm off either way along x and y); it
// falls 5 mm 0.067 s after opening starts.
// Issue 18's bar for a rigid hand: the tripod grasp of the 100 g box holds it 5 s with under 2 mm of
// slip at mu = 0.8, the fingers carrying its weight, and it falls once they open; at mu = 0.05 the box
// slips out and stays on the table.
void expect_rigid_hand_holds_the_box(HandModelKind model, const char* name) {
  const GraspRun held = run_rigid_grasp(box_grasp(), 0.8, model);
  print_run((std::string("box, ") + name + ", mu 0.8").c_str(), held);
  EXPECT_GT(held.lift_m, 40 * kMm);
  EXPECT_LT(held.slip_m, 2 * kMm);
  EXPECT_NEAR(total_force(held).z(), 0.1 * kG, 0.05 * 0.1 * kG) << "the hand carries the box's weight";
  EXPECT_GT(held.release_s, 0.0);
  EXPECT_LT(held.release_s, 0.25) << "it falls once the fingers open";
  EXPECT_EQ(held.resets, 0);
  const GraspRun slipped = run_rigid_grasp(box_grasp(), 0.05, model);
  print_run((std::string("box, ") + name + ", mu 0.05").c_str(), slipped);
  EXPECT_LT(slipped.lift_m, 5 * kMm);
  EXPECT_EQ(slipped.resets, 0);
}

// Measured: lifted 42.7 of the palm's 50 mm, 0.16 mm of slip, the fingers' forces carrying its weight
// to 0.1 %.
TEST(WorldGloveGrasp, TheSpringHandHoldsTheBoxAtMu08AndLetsItSlipAtMu005) {
  expect_rigid_hand_holds_the_box(HandModelKind::spring, "spring hand");
}

// The fingers' capsules on the glove's frames, their contact points squeezing the box. Measured:
// lifted 46.5 of the palm's 50 mm, 0.02 mm of slip, the thumb, index and middle carrying its weight to
// 0.1 %.
TEST(WorldGloveGrasp, TheContactPointHandHoldsTheBoxAtMu08AndLetsItSlipAtMu005) {
  expect_rigid_hand_holds_the_box(HandModelKind::contact_point, "contact-point hand");
}

TEST(WorldGlovePinch, ConstraintContactsHoldA20gCubeAndTheFingerForcesBalanceItsWeight) {
  const GraspSpec g = cube_pinch();
  const GraspRun r = run_grasp(g, glove_options(ContactModel::constraint));
  print_run("cube pinch, constraint contact", r);
  EXPECT_EQ(r.resets, 0);
  EXPECT_GT(r.lift_m, 0.045);
  EXPECT_LT(r.slip_m, 2 * kMm);
  EXPECT_LT(r.turn_rad, 3 * kDeg);
  expect_pinch_forces(g, r);
  EXPECT_GT(r.release_s, 0.0);
  EXPECT_LT(r.release_s, 0.3);
  EXPECT_NEAR(r.landed_z_m, 0.5 * g.size_m, 1 * kMm);
}

// Penalty contact carries the cube too, forces balanced the same way, but two
// fingertip pads hold the torque of its weight about the pinch axis only
// through the creeping viscous friction: it turns 52 degrees in the pinch over
// the hold and its centre moves 5.4 mm (34-59 degrees and 2.3-8.9 mm for the
// cube placed 2 mm off either way).
TEST(WorldGlovePinch, PenaltyContactsLiftTheCubeWithBalancedFingerForcesButItTurnsInThePinch) {
  const GraspSpec g = cube_pinch();
  const GraspRun r = run_grasp(g, glove_options(ContactModel::penalty));
  print_run("cube pinch, penalty contact", r);
  EXPECT_EQ(r.resets, 0);
  EXPECT_GT(r.lift_m, 0.04);
  expect_pinch_forces(g, r);
  EXPECT_GT(r.turn_rad, 20 * kDeg);
  EXPECT_LT(r.slip_m, 15 * kMm);
  EXPECT_GT(r.release_s, 0.0);
  EXPECT_LT(r.release_s, 0.3);
}

// ---------------------------------------------------------------------------------------------
// The same pinch as the server runs it. Disabled: both fail until the library
// changes described in the file comment are made; enable them with those.

// hand_gravity = false (as hapticd runs hands): the cube keeps the world's
// gravity in the hand's implicit step (ContactBody::gravity_W), so the fingers
// carry its 0.196 N weight. They summed to 0.000 N when the body took the
// hand's zero gravity.
TEST(WorldGlovePinch, WeightlessHandStillCarriesTheCubesWeight) {
  const GraspSpec g = cube_pinch();
  WorldOptions o = glove_options(ContactModel::constraint);
  o.hand_gravity = false;
  const GraspRun r = run_grasp(g, o);
  print_run("cube pinch, weightless hand", r);
  expect_pinch_forces(g, r);
}

// ---------------------------------------------------------------------------------------------
// The handover of scenes/two_hands.json.

// How far the palmar skin of a palm-up hand stands above its hand frame's origin under a
// w x w square centred on it and turned `yaw` about the vertical, m: the highest skin point
// there, where a box set on the palm rests (the palmar surface's height bisected from the
// hand's signed distance on a 2 mm grid; a palm-up left hand, turned half a turn about y,
// is the right hand's shape over the same world offsets).
double palm_height_under(double w, double yaw) {
  double highest = 0;
  const Eigen::Matrix2d R = Eigen::Rotation2Dd(yaw).toRotationMatrix();
  for (double u = -w / 2; u <= w / 2; u += 0.002) {
    for (double v = -w / 2; v <= w / 2; v += 0.002) {
      const Eigen::Vector2d xy = R * Eigen::Vector2d(u, v);
      double inside = 0, outside = -0.04;  // the palm centre is inside, 4 cm below it is not
      for (int i = 0; i < 40; ++i) {
        const double z = 0.5 * (inside + outside);
        (hand::procedural_hand_sdf(Eigen::Vector3d(xy.x(), xy.y(), z)) < 0 ? inside : outside) = z;
      }
      highest = std::max(highest, -inside);
    }
  }
  return highest;
}

// The right glove hand picks the 100 g box up from the table (the tripod of
// box_grasp) and lifts it 8 cm; the left hand, palm up, comes under it; the right
// sets the box down on the left palm (4 mm lower than where it would just touch)
// and opens and withdraws; the left carries the box 8 cm away and 2 cm up and
// holds it. Constraint contact, as the scene says. The box must stay on the left
// palm (within 3 mm of its place in the left palm frame from the moment the
// right hand has let go to the end) and touch neither the right hand nor the
// table at the end. Hand-hand contact is on (two hands); whether the hands touch
// on the way is printed.
TEST(WorldGloveHandover, RightHandSetsTheBoxOnTheLeftPalmAndTheLeftCarriesItAway) {
  SceneDesc scene = load_scene(std::string(HAPTICD_SCENES_DIR) + "/two_hands.json");
  WorldOptions options = glove_options(scene.contact);
  World w(scene, options);
  hand::FemHand& right = hand::as_fem(w.hand(0));
  hand::FemHand& left = hand::as_fem(w.hand(1));
  ASSERT_EQ(w.hand_name(0), "right_hand");
  const int box = w.rigid()->find("box");
  const int table = w.rigid()->find("table");
  const GraspSpec g = box_grasp();
  const Eigen::Quaterniond q_right = scene.hands[0].pose.q_W, q_left = scene.hands[1].pose.q_W;
  struct Driven {
    hand::FemHand* hand;
    Eigen::Quaterniond q;
    bool left;
    hand::HandJointAngles angles = hand::rest_joint_angles();
    Eigen::Vector3d palm;
  };
  Driven R{&right, q_right, false, hand::rest_joint_angles(), scene.hands[0].pose.p_W};
  Driven L{&left, q_left, true, hand::rest_joint_angles(), scene.hands[1].pose.p_W};
  long steps = 0, hand_hand_steps = 0;
  auto box_p = [&] { return w.snapshot().bodies[box].p_WO; };
  auto touches = [&](int hand, int object) {
    for (const ContactRecord& c : w.snapshot().contacts)
      if (c.hand == hand && c.object == object && c.other_hand < 0 && c.f_W.norm() > 1e-6) return true;
    return false;
  };
  // Both hands move together: each eased from where it is to (angles, palm) in `seconds`.
  auto move = [&](Driven& a, const hand::HandJointAngles& a_to, const Eigen::Vector3d& a_palm, Driven& b,
                  const hand::HandJointAngles& b_to, const Eigen::Vector3d& b_palm, double seconds, auto each) {
    const hand::HandJointAngles a0 = a.angles, b0 = b.angles;
    const Eigen::Vector3d pa0 = a.palm, pb0 = b.palm;
    const int n = static_cast<int>(std::lround(seconds / w.dt()));
    for (int k = 1; k <= n; ++k) {
      const double s = 0.5 * (1.0 - std::cos(std::numbers::pi * k / n));
      a.angles = hand::HandJointAngles::from_vector((1 - s) * a0.vector() + s * a_to.vector());
      b.angles = hand::HandJointAngles::from_vector((1 - s) * b0.vector() + s * b_to.vector());
      a.palm = pa0 + s * (a_palm - pa0);
      b.palm = pb0 + s * (b_palm - pb0);
      for (Driven* d : {&a, &b}) set_posture(w, *d->hand, d->angles, d->palm, d->q, d->left);
      w.step();
      ++steps;
      for (const ContactRecord& c : w.snapshot().contacts)
        if (c.other_hand >= 0) {
          ++hand_hand_steps;
          break;
        }
      each();
    }
  };
  auto nothing = [] {};
  const hand::HandJointAngles open = hand::rest_joint_angles();
  // The right hand's pick-up, as in run_grasp, then 8 cm up.
  const Eigen::Vector3d grip = w.snapshot().bodies[box].p_WO - g.object_H;
  move(R, open, grip, L, open, L.palm, 0.5, nothing);
  move(R, g.closed, grip, L, open, L.palm, 0.5, nothing);
  move(R, g.closed, grip, L, open, L.palm, 0.25, nothing);
  const Eigen::Vector3d lifted = grip + Eigen::Vector3d(0, 0, 0.08);
  move(R, g.closed, lifted, L, open, L.palm, 1.0, nothing);
  ASSERT_GT(box_p().z(), scene.objects[box].pose.p_W.z() + 0.07) << "the right hand did not lift the box";
  // The left palm under the box, 2 mm below touching it: first across below it, then up.
  const Eigen::Vector3d c = box_p();
  const Eigen::Vector3d box_x = w.snapshot().bodies[box].q_WO * Eigen::Vector3d::UnitX();
  const double yaw = std::atan2(box_x.y(), box_x.x());  // about -30 degrees
  const double under = c.z() - 0.5 * g.size_m - palm_height_under(g.size_m, yaw) - 0.002;
  move(L, open, Eigen::Vector3d(c.x(), c.y(), under - 0.02), R, g.closed, lifted, 1.0, nothing);
  move(L, open, Eigen::Vector3d(c.x(), c.y(), under), R, g.closed, lifted, 0.5, nothing);
  // The right hand sets the box down 4 mm (2 mm into the left palm's flesh), opens and withdraws.
  const Eigen::Vector3d set_down = lifted - Eigen::Vector3d(0, 0, 0.004);
  move(R, g.closed, set_down, L, open, L.palm, 0.4, nothing);
  move(R, g.closed, set_down, L, open, L.palm, 0.3, nothing);
  move(R, open, set_down, L, open, L.palm, 0.5, nothing);
  move(R, open, set_down + Eigen::Vector3d(0.05, 0, 0.06), L, open, L.palm, 0.5, nothing);
  const bool right_touches_after_release = touches(0, box);
  auto in_left_palm = [&] {
    const hand::HandleState& p = w.snapshot().handles[1][0];
    return Eigen::Vector3d(p.q_WH.conjugate() * (box_p() - p.p_WH));
  };
  const Eigen::Vector3d held0 = in_left_palm();
  double drift = 0;
  // The left hand carries it 8 cm away (-x) and 2 cm up in 1 s and holds it 1 s.
  const Eigen::Vector3d away = L.palm + Eigen::Vector3d(-0.08, 0, 0.02);
  auto watch = [&] { drift = std::max(drift, (in_left_palm() - held0).norm()); };
  move(L, open, away, R, open, R.palm, 1.0, watch);
  move(L, open, away, R, open, R.palm, 1.0, watch);
  const Eigen::Vector3d on_palm = in_left_palm();
  std::printf(
      "[handover] box at (%.1f, %.1f, %.1f) mm in the left palm frame after the right let go; largest "
      "drift while carried %.2f mm; right hand touching the box after letting go: %s; steps with "
      "hand-hand contact %ld of %ld; resets %ld\n",
      held0.x() / kMm, held0.y() / kMm, held0.z() / kMm, drift / kMm, right_touches_after_release ? "yes" : "no",
      hand_hand_steps, steps, w.snapshot().resets);
  EXPECT_EQ(w.snapshot().resets, 0);
  EXPECT_FALSE(right_touches_after_release);
  EXPECT_FALSE(touches(0, box));
  EXPECT_FALSE(touches(1, table));
  EXPECT_TRUE(touches(1, box));
  EXPECT_LT(drift, 3 * kMm);
  // On the palm (palmar side is -z of the left hand frame), within its outline.
  EXPECT_LT(on_palm.z(), -0.01);
  EXPECT_LT(on_palm.head<2>().norm(), 0.03);
  EXPECT_GT(box_p().z(), scene.objects[table].pose.p_W.z() + 0.05);
}

// ---------------------------------------------------------------------------------------------
// Hard cases of a glove: a finger driven deep into a table, tracking glitches.

// The 16-handle hand palm down with its palm centre 3.5 cm over a static table (top at z = 0).
World glove_over_table(ContactModel contact) {
  GraspSpec nothing_held = box_grasp();
  SceneDesc scene = grasp_scene(nothing_held, Eigen::Vector3d(0, 0, 0.035));
  scene.objects.pop_back();  // the table alone
  return World(scene, glove_options(contact));
}

// Every handle's distance from its target, largest, m.
double largest_target_error(const hand::FemHand& hand, int first = 0, int last = 16) {
  double e = 0;
  for (int j = first; j < last; ++j) e = std::max(e, (hand.state.handles[j].p_WH - hand.state.targets[j].p_W).norm());
  return e;
}

bool inverted_elements(const hand::FemHand& hand) {
  for (int e = 0; e < hand.model->fem().num_tets(); ++e)
    if (!(hand.model->fem().deformation_gradient(e, hand.state.x).determinant() > 0)) return true;
  return false;
}

class WorldGloveHardCases : public testing::TestWithParam<ContactModel> {};

// The index finger's three targets 5 cm under the table top, ramped in 0.1 s and held 1 s (the
// tracked finger went through the table), then back. The index handles follow their almost
// kinematic drive into the table (in the server the proxy stops them, its coupling feeling the
// flesh); the flesh's coupling springs stretch and the table holds the skin: its deepest point
// stays within a few millimetres (constraint) or a couple of centimetres (penalty springs against
// the stretched coupling). The other fingers keep following their targets, the finger comes back,
// nothing resets or stays inverted.
TEST_P(WorldGloveHardCases, IndexDrivenFiveCentimetresIntoTheTable) {
  World w = glove_over_table(GetParam());
  hand::FemHand& hand = hand::as_fem(w.hand(0));
  const Eigen::Vector3d palm(0, 0, 0.035);
  const std::vector<hand::HandleTarget> rest =
      posture_targets(hand.shape, *hand.model, hand::rest_joint_angles(), palm, Eigen::Quaterniond::Identity(), false);
  for (int k = 0; k < 20; ++k)
    set_posture(w, hand, hand::rest_joint_angles(), palm, Eigen::Quaterniond::Identity(), false), w.step();
  const int index_first = 1 + 3 * 1, index_last = index_first + 3;  // handles of the index phalanges
  double deepest = 0, others = 0;
  const int ramp = 6, held = 60;
  for (int k = 1; k <= ramp + held; ++k) {
    const double s = std::min(1.0, static_cast<double>(k) / ramp);
    for (int j = 0; j < 16; ++j) {
      hand::HandleTarget t = rest[j];
      if (j >= index_first && j < index_last) t.p_W.z() -= s * (rest[j].p_W.z() + 0.05);  // 5 cm under the top
      set_target(hand.state, j, t);
    }
    w.step();
    ASSERT_TRUE(hand.state.x.allFinite());
    deepest = std::max(deepest, w.snapshot().max_penetration_m);
    if (k > ramp + 15)
      others =
          std::max({others, largest_target_error(hand, 0, index_first), largest_target_error(hand, index_last, 16)});
  }
  const double index_held = largest_target_error(hand, index_first, index_last);
  for (int k = 0; k < 30; ++k) {
    for (int j = 0; j < 16; ++j) set_target(hand.state, j, rest[j]);
    w.step();
  }
  std::printf(
      "[glove hard] %s: index targets 5 cm under the table: deepest skin point %.2f mm, index handles %.1f mm "
      "from their targets, the other handles within %.3f mm; 0.5 s after release within %.3f mm; resets %ld\n",
      GetParam() == ContactModel::constraint ? "constraint" : "penalty", deepest / kMm, index_held / kMm, others / kMm,
      largest_target_error(hand) / kMm, w.snapshot().resets);
  EXPECT_EQ(w.snapshot().resets, 0);
  EXPECT_LT(deepest, GetParam() == ContactModel::constraint ? 3 * kMm : 20 * kMm);
  EXPECT_LT(others, 2 * kMm);
  EXPECT_LT(largest_target_error(hand), 2 * kMm);
  EXPECT_FALSE(inverted_elements(hand));
}

// Tracking glitches: every phalanx target jumps 3-10 cm in a random direction for one step, then
// for a third of a second every step; each time the tracking comes back the hand is back on its
// targets within 0.5 s, finite, with no element left inverted, without needing a reset (the
// safety response: the hand placed back on the palm's target, at rest).
TEST_P(WorldGloveHardCases, EveryFingerTeleportedByTrackingGlitches) {
  World w = glove_over_table(GetParam());
  hand::FemHand& hand = hand::as_fem(w.hand(0));
  const Eigen::Vector3d palm(0, 0, 0.06);
  const std::vector<hand::HandleTarget> rest =
      posture_targets(hand.shape, *hand.model, hand::rest_joint_angles(), palm, Eigen::Quaterniond::Identity(), false);
  for (int k = 0; k < 30; ++k)
    set_posture(w, hand, hand::rest_joint_angles(), palm, Eigen::Quaterniond::Identity(), false), w.step();
  std::srand(7);
  auto jump = []() -> Eigen::Vector3d {  // a value, not an expression of the local d
    const Eigen::Vector3d d = Eigen::Vector3d::Random().normalized();
    return (0.03 + 0.07 * (0.5 + 0.5 * Eigen::Vector2d::Random().x())) * d;
  };
  double worst_back = 0;
  for (int glitch_steps : {1, 20}) {
    for (int k = 0; k < glitch_steps; ++k) {
      for (int j = 1; j < 16; ++j) {
        hand::HandleTarget t = rest[j];
        t.p_W += jump();
        set_target(hand.state, j, t);
      }
      w.step();
      ASSERT_TRUE(hand.state.x.allFinite());
    }
    for (int k = 0; k < 30; ++k) {
      for (int j = 0; j < 16; ++j) set_target(hand.state, j, rest[j]);
      w.step();
      ASSERT_TRUE(hand.state.x.allFinite());
    }
    worst_back = std::max(worst_back, largest_target_error(hand));
    EXPECT_FALSE(inverted_elements(hand)) << glitch_steps << " glitch steps";
  }
  std::printf(
      "[glove hard] %s: tracking glitches of 3-10 cm on every phalanx: back within %.3f mm 0.5 s later; "
      "resets %ld\n",
      GetParam() == ContactModel::constraint ? "constraint" : "penalty", worst_back / kMm, w.snapshot().resets);
  EXPECT_LT(worst_back, 2 * kMm);
  EXPECT_EQ(w.snapshot().resets, 0);
}

INSTANTIATE_TEST_SUITE_P(Contact, WorldGloveHardCases, testing::Values(ContactModel::penalty, ContactModel::constraint),
                         [](const testing::TestParamInfo<ContactModel>& i) {
                           return i.param == ContactModel::penalty ? "Penalty" : "Constraint";
                         });

}  // namespace
}  // namespace hapticd::world
