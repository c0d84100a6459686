// Deformable objects in the world: a soft cube dropped on a floor comes to rest
// on it, the hand pushes a soft bunny across a floor (it deforms, gains no
// energy it was not given, passes every reaction on), in both contact models.
#include <gtest/gtest.h>

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <memory>
#include <string>
#include <vector>

#include "hand_models/fem_hand.hpp"
#include "server/world/scene_loader.hpp"
#include "server/world/world.hpp"
#include "world_test_util.hpp"

namespace hapticd::world {
namespace {

class DeformableWorld : public testing::TestWithParam<ContactModel> {
 protected:
  WorldOptions options() const {
    WorldOptions o;
    o.contact = GetParam();
    return o;
  }
};

ObjectDesc static_floor() {
  ObjectDesc floor;
  floor.name = "floor";
  floor.kind = BodyKind::static_body;
  floor.shape.type = ShapeType::plane;
  floor.material.friction = 0.5;
  return floor;
}

// A deformable FEM box called "cube" of the given size, centred at p_W.
ObjectDesc soft_cube(const Eigen::Vector3d& size, const Eigen::Vector3d& p_W) {
  ObjectDesc cube;
  cube.name = "cube";
  cube.kind = BodyKind::deformable;
  cube.shape.type = ShapeType::box;
  cube.shape.size = size;
  cube.pose.p_W = p_W;
  return cube;
}

Eigen::Vector3d centroid(const DeformableObject& o) {
  Eigen::Vector3d c = Eigen::Vector3d::Zero();
  for (int i = 0; i < o.model->num_nodes(); ++i) c += o.state.x.segment<3>(3 * i);
  return c / o.model->num_nodes();
}

double lowest_surface_z(const WorldSnapshot& s, int d) {
  double z = 1e300;
  for (const Eigen::Vector3d& p : s.deformables[d].surface_W) z = std::min(z, p.z());
  return z;
}

// Largest distance of a node from the best rigid placement of the rest shape: what the body
// deformed, without its motion (its fit is tested against known motions below).
double max_deformation(const DeformableObject& o) { return detail::rigid_fit(o).deviation_m; }

TEST_P(DeformableWorld, SoftCubeDroppedOnTheFloorComesToRestOnItWithoutDrift) {
  SceneDesc scene;
  scene.objects.push_back(static_floor());
  ObjectDesc cube = soft_cube({0.04, 0.04, 0.04}, {0, 0, 0.04});     // falls 2 cm
  cube.pose.q_W = Eigen::AngleAxisd(0.1, Eigen::Vector3d::UnitX());  // lands on an edge first
  scene.objects.push_back(cube);
  World world(scene, options());
  ASSERT_EQ(world.num_deformables(), 1);
  ASSERT_EQ(world.num_hands(), 0);
  ASSERT_FALSE(world.rigid()->has_dynamics());  // no rigid body: no ODE dynamics world
  const DeformableObject& o = world.deformable(0);
  EXPECT_EQ(o.model->num_handles(), 0);
  EXPECT_EQ(o.query, nullptr);  // no hand to touch it: no hand-contact query
  EXPECT_NEAR(o.model->fem().lumped_mass().sum(), 1000 * 0.04 * 0.04 * 0.04, 1e-12);  // default density
  double max_penetration_late = 0, max_speed_late = 0;
  Eigen::Vector3d c_at_2s = Eigen::Vector3d::Zero();
  for (int k = 0; k < 240; ++k) {  // 4 s
    world.step();
    ASSERT_TRUE(o.state.x.allFinite()) << "step " << k;
    if (k == 120) c_at_2s = centroid(o);
    if (k >= 90) {
      max_penetration_late = std::max(max_penetration_late, world.snapshot().max_penetration_m);
      max_penetration_late = std::max(max_penetration_late, -lowest_surface_z(world.snapshot(), 0));
    }
    if (k >= 180) max_speed_late = std::max(max_speed_late, o.state.v.cwiseAbs().maxCoeff());
  }
  const WorldSnapshot& s = world.snapshot();
  EXPECT_EQ(s.resets, 0);
  int floor_contacts = 0;
  for (const ContactRecord& c : s.contacts) floor_contacts += c.deformable == 0 && c.object == 0 && c.hand < 0;
  EXPECT_GE(floor_contacts, 4);  // it stands on its face
  std::printf("penetration %.3f mm, lowest surface point %.3f mm, drift %.4f mm, speed %.2e m/s\n",
              1e3 * max_penetration_late, 1e3 * lowest_surface_z(s, 0), 1e3 * (centroid(o) - c_at_2s).norm(),
              max_speed_late);
  EXPECT_LT(max_penetration_late, 1e-3);
  EXPECT_LT(lowest_surface_z(s, 0), 1e-3);            // and not hovering either
  EXPECT_LT((centroid(o) - c_at_2s).norm(), 0.1e-3);  // no drift over the last 2 s
  EXPECT_LT(max_speed_late, 1e-3);                    // m/s: at rest, no jitter
  // It sags under its own weight a little and stands where it fell.
  EXPECT_NEAR(centroid(o).z(), 0.02, 2e-3);
  EXPECT_LT(centroid(o).head<2>().norm(), 5e-3);
}

// Deformable vs rigid: the cube's surface points against a dynamic ODE box,
// solved implicitly in the cube's step (a ContactBody with its supports), the
// box's velocity change handed back to ODE.
TEST_P(DeformableWorld, RigidBoxDroppedOnASoftCubeRestsOnIt) {
  SceneDesc scene;
  scene.objects.push_back(static_floor());
  ObjectDesc cube = soft_cube({0.06, 0.06, 0.04}, {0, 0, 0.02});
  cube.material.youngs_modulus_pa = 100e3;
  scene.objects.push_back(cube);
  ObjectDesc box;
  box.name = "box";
  box.kind = BodyKind::rigid;
  box.shape.type = ShapeType::box;
  box.shape.size = {0.03, 0.03, 0.03};
  box.mass_kg = 0.1;
  box.pose.p_W = {0.005, -0.003, 0.04 + 0.015 + 0.01};  // 1 cm above the cube
  scene.objects.push_back(box);
  World world(scene, options());
  ASSERT_TRUE(world.rigid()->has_dynamics());
  const int b = world.rigid()->find("box");
  double max_penetration_late = 0;
  for (int k = 0; k < 180; ++k) {  // 3 s
    world.step();
    ASSERT_TRUE(world.deformable(0).state.x.allFinite()) << "step " << k;
    if (k >= 120) max_penetration_late = std::max(max_penetration_late, world.snapshot().max_penetration_m);
  }
  const RigidBodyState s = world.rigid()->state(b);
  double top = -1e300;  // the cube's top under the box
  for (const Eigen::Vector3d& p : world.snapshot().deformables[0].surface_W)
    if (std::abs(p.x() - s.p_WO.x()) < 0.01 && std::abs(p.y() - s.p_WO.y()) < 0.01) top = std::max(top, p.z());
  std::printf("box at z %.4f m, cube top under it %.4f m, v %.2e m/s, penetration %.3f mm\n", s.p_WO.z(), top,
              s.v_WO.norm(), 1e3 * max_penetration_late);
  EXPECT_EQ(world.snapshot().resets, 0);
  EXPECT_NEAR(s.p_WO.z() - 0.015, top, 1.5e-3);  // resting on the cube's top, within 1.5 mm
  EXPECT_LT(top, 0.04);                          // which it presses in
  EXPECT_LT(s.v_WO.norm(), 5e-3);
  EXPECT_LT(max_penetration_late, 1.5e-3);
}

// The test hand (palm 3 cm above the floor, fingers along +y) 1.5 cm behind a
// soft bunny standing on the floor, a static wall 10 cm ahead of the bunny; the
// hand pushes 15 cm along +y: the bunny across the floor, then into the wall.
constexpr double kWallGap = 0.10;
constexpr double kBunnyFrontY = 0.19 + 0.0469;  // the bunny is 9.37 cm deep along y

SceneDesc bunny_push_scene() {
  SceneDesc scene;
  scene.objects.push_back(static_floor());
  ObjectDesc wall;
  wall.name = "wall";
  wall.kind = BodyKind::static_body;
  wall.shape.type = ShapeType::box;
  wall.shape.size = {0.3, 0.02, 0.2};
  wall.pose.p_W = {0, kBunnyFrontY + kWallGap + 0.01, 0.1};
  scene.objects.push_back(wall);
  ObjectDesc bunny;
  bunny.name = "bunny";
  bunny.kind = BodyKind::deformable;
  bunny.shape.type = ShapeType::tet_mesh;
  const std::string assets = std::string(HAPTICD_SCENES_DIR) + "/assets/";
  bunny.shape.file = assets + "bunny_271.node";
  bunny.shape.surface_file = assets + "bunny.obj";
  bunny.shape.embedding_file = assets + "bunny_271.embed";
  bunny.pose.p_W = {0, 0.19, 0.0005};  // its back 1.5 cm ahead of the fingertips, just above the floor
  bunny.mass_kg = 0.2;
  bunny.material.youngs_modulus_pa = 10e3;  // soft silicone
  bunny.material.poisson_ratio = 0.45;
  bunny.material.friction = 0.8;
  scene.objects.push_back(bunny);
  testing_util::add_test_hand(scene);
  return scene;
}

TEST_P(DeformableWorld, PushingASoftBunnyDeformsItAndCreatesNoEnergy) {
  World world(bunny_push_scene(), options());
  hand::FemHand& hand = hand::as_fem(world.hand(0));
  const DeformableObject& bunny = world.deformable(0);
  ASSERT_NE(bunny.query, nullptr);
  EXPECT_EQ(bunny.body.surface.triangles.size(), 3674u);
  // Settle on the floor first (0.5 s), hand held where it is.
  for (int k = 0; k < 30; ++k) world.step();
  const Eigen::Vector3d c0 = centroid(bunny);
  const double settled_deformation = max_deformation(bunny);  // its own weight
  const double E0 = total_energy(*bunny.model, bunny.state);
  const hand::HandleState start = hand.state.handles[0];
  double work = 0, worst_excess = -1e300, max_deform = 0, max_reaction_error = 0;
  int touching_steps = 0;
  double max_bunny_penetration = 0, max_front = -1e300;
  for (int k = 0; k < 120; ++k) {  // 2 s: 1.5 s pushing at 10 cm/s, then holding
    set_target(hand.state, 0, testing_util::push_along_y(start, std::min(k, 89), world.dt()));
    world.step();
    const WorldSnapshot& s = world.snapshot();
    ASSERT_TRUE(bunny.state.x.allFinite() && hand.state.x.allFinite()) << "step " << k;
    // Every hand contact on the bunny comes back to it, reversed, as nodal forces.
    Eigen::Vector3d on_hand = Eigen::Vector3d::Zero();
    bool touching = false;
    for (const ContactRecord& c : s.contacts)
      if (c.hand == 0 && c.other_deformable == 0) on_hand += c.f_W, touching = true;
    touching_steps += touching;
    Eigen::Vector3d applied = Eigen::Vector3d::Zero();
    for (int i = 0; i < bunny.model->num_nodes(); ++i) applied += bunny.f_hands_W.segment<3>(3 * i);
    if (GetParam() == ContactModel::constraint) {
      // Constraint contacts: exactly the impulses the hand got, reversed (1e-12 N: summation order).
      max_reaction_error = std::max(max_reaction_error, (on_hand + applied).norm());
    }
    // Work of the hands' forces over the step: f . (x_end - x_start) = f . v_end h (implicit Euler).
    work += world.dt() * bunny.f_hands_W.dot(bunny.state.v);
    for (const ContactRecord& c : s.contacts)
      if (c.deformable == 0) max_bunny_penetration = std::max(max_bunny_penetration, c.depth_m);
    double front = -1e300;
    for (const Eigen::Vector3d& p : s.deformables[0].surface_W) front = std::max(front, p.y());
    max_front = std::max(max_front, front);
    const double E = total_energy(*bunny.model, bunny.state);
    worst_excess = std::max(worst_excess, E - E0 - work);
    max_deform = std::max(max_deform, max_deformation(bunny));
  }
  const Eigen::Vector3d moved = centroid(bunny) - c0;
  std::printf(
      "bunny moved (%.4f, %.4f, %.4f) m, front %.1f mm from the wall, deformed up to %.2f mm (%.2f mm "
      "settled), penetration %.2f mm; work %.4f J, energy excess %.2e J, touching %d steps, reaction error "
      "%.1e N\n",
      moved.x(), moved.y(), moved.z(), 1e3 * (kBunnyFrontY + kWallGap - max_front), 1e3 * max_deform,
      1e3 * settled_deformation, 1e3 * max_bunny_penetration, work, worst_excess, touching_steps, max_reaction_error);
  EXPECT_EQ(world.snapshot().resets, 0);
  EXPECT_GT(touching_steps, 30);
  EXPECT_GT(moved.y(), 0.03);                            // pushed along
  EXPECT_LT(max_front, kBunnyFrontY + kWallGap + 2e-3);  // the wall stops it
  EXPECT_LT(std::abs(moved.z()), 0.01);                  // still on the floor
  EXPECT_LT(max_bunny_penetration, 2e-3);                // into the floor and the wall
  EXPECT_GT(max_deform, settled_deformation + 2e-3);     // the push deformed it, not only its weight
  EXPECT_GT(work, 0.0);
  // Implicit Euler and Rayleigh damping only take energy out. 1e-5 of the work:
  // the work is summed from the recorded end-of-step contact forces, whose
  // regularized friction and push-only normal differ slightly from the
  // linearized forces the penalty step solved with.
  EXPECT_LT(worst_excess, 1e-5 * work);
  EXPECT_LT(max_reaction_error, 1e-12);
}

// The scene's soft bunny (0.2 kg of silicone, 271 tets) on the 4 cm table, alone, stepped as a
// loaded visual loop steps it: at 15 Hz (and, with constraint contact, 10 Hz) it comes to rest where
// 60 Hz steps put it. Gravity alone carries a point 4.4 cm in a 67 ms step: the points that reached
// the table fell through its top, or into it past the middle and out its bottom: measured before
// the reach of a deformable object's points grew with the step, the centroid ended 41 mm (15 Hz)
// and 100 mm (10 Hz) from its 60 Hz rest with constraint contact, 34 mm with penalty at 15 Hz.
// Penalty contact at 10 Hz is not asked: 4.9 cm of fall per step pass the whole table.
TEST_P(DeformableWorld, SoftBunnyStepsAtSlowVisualRatesComeToRestOnTheTableAsAt60Hz) {
  SceneDesc scene = load_scene(std::string(HAPTICD_SCENES_DIR) + "/deformable_bunny.json");
  scene.hands.clear();
  scene.devices.clear();
  const auto rest = [&](double dt_s, double& deepest) {
    scene.dt_s = dt_s;
    World world(scene, options());
    deepest = 0;
    for (int k = 0; k < std::lround(2.0 / dt_s); ++k) {
      world.step();
      if (k * dt_s > 0.5) deepest = std::max(deepest, world.snapshot().max_penetration_m);
    }
    return centroid(world.deformable(0));
  };
  double deepest_60 = 0;
  const Eigen::Vector3d reference = rest(1.0 / 60, deepest_60);
  for (const double rate : {15.0, 10.0}) {
    if (rate < 15 && GetParam() == ContactModel::penalty) continue;
    double deepest = 0;
    const Eigen::Vector3d c = rest(1.0 / rate, deepest);
    std::printf(
        "%s at %.0f Hz: centroid %.2f mm from its 60 Hz rest, deepest point %.2f mm after 0.5 s (60 Hz: %.2f mm)\n",
        std::string(to_string(GetParam())).c_str(), rate, 1e3 * (c - reference).norm(), 1e3 * deepest,
        1e3 * deepest_60);
    EXPECT_LT((c - reference).norm(), 1e-3) << rate << " Hz";
    EXPECT_LT(deepest, 1e-3) << rate << " Hz";
  }
}

// A soft cube dropped 25 cm onto a 4 cm table, in steps of 17, 100, 150 and 200 ms from the first
// (the world built for 60 Hz: its first collision looked ahead as far as a 17 ms step carries a
// point), constraint contact: no surface point goes more than 1 mm into the table, and the cube ends
// on it. Measured before a free body's reach counted backward Euler's whole gravity step (g h^2, not
// half of it) uncapped, and a much longer step collided again: 9.4 mm into the table at 100 ms, through
// it at 150 and 200 ms. With penalty contact (no speculative rows, by design) it still goes through
// at 150 ms.
TEST(DeformableWorldSlowSteps, ASoftCubeDroppedOntoATableStaysOnItAtStepsOfUpTo200Ms) {
  for (const double dt : {1.0 / 60, 0.1, 0.15, 0.2}) {
    SceneDesc scene;
    const double top = 0.75;
    scene.objects.push_back(testing_util::static_table({1.0, 1.0, 0.04}, top));
    ObjectDesc cube = soft_cube({0.04, 0.04, 0.04}, {0, 0, top + 0.02 + 0.25});
    cube.material.youngs_modulus_pa = 2e5;
    scene.objects.push_back(cube);
    WorldOptions options;
    options.contact = ContactModel::constraint;
    World world(scene, options);
    double lowest = 1e9, end = 1e9;
    for (int k = 0; k < static_cast<int>(std::lround(2.0 / dt)); ++k) {
      world.step(dt);
      end = lowest_surface_z(world.snapshot(), 0);
      lowest = std::min(lowest, end);
    }
    std::printf("%.0f ms steps: deepest %.2f mm into the table, ends %.2f mm from its top, resets %ld\n", 1e3 * dt,
                1e3 * (top - lowest), 1e3 * (end - top), static_cast<long>(world.snapshot().resets));
    EXPECT_GT(lowest, top - 1e-3) << dt;
    EXPECT_NEAR(end, top, 1e-3) << dt;
    EXPECT_EQ(world.snapshot().resets, 0) << dt;
  }
}

// What a hand's skin point far from a deformable object is measured against (detail::rigid_fit,
// detail::far_clearance). The bunny's nodes carried by a known rotation and translation give them back
// to 1e-9 with no deviation. With a 1.5 cm dent pressed into its top as well, its clearance from 1 to
// 8 cm out is never more than the distance to the deformed surface (its triangles between the deformed
// surface points, every one tried; a point of one is a convex combination of points each within the
// deviation of its rigid image), short of it by at most the coarse grid's two errors (0.87 of a 1.5 cm
// cell each) and twice the deviation, and answered wherever that leaves a positive bound.
TEST(DeformableObjectClearance, TheRigidFitCarriesTheRestSurfacesClearanceToTheDeformedOneAsALowerBound) {
  const SceneDesc scene = load_scene(std::string(HAPTICD_SCENES_DIR) + "/deformable_bunny.json");
  const ObjectDesc* desc = nullptr;
  for (const ObjectDesc& d : scene.objects)
    if (d.name == "bunny") desc = &d;
  ASSERT_NE(desc, nullptr);
  const std::unique_ptr<DeformableObject> o = make_deformable_object(*desc, DeformableBuild{});
  const std::vector<Eigen::Vector3d>& X = o->body.mesh.X;
  const Eigen::Matrix3d R0 = Eigen::AngleAxisd(0.4, Eigen::Vector3d(1, 2, 3).normalized()).toRotationMatrix();
  const Eigen::Vector3d t0(0.05, -0.02, 0.1);
  for (size_t i = 0; i < X.size(); ++i) o->state.x.segment<3>(3 * i) = R0 * X[i] + t0;
  const DeformableObject::RigidFit rigid = detail::rigid_fit(*o);
  EXPECT_LT((rigid.R - R0).norm(), 1e-9);
  EXPECT_LT((rigid.t - t0).norm(), 1e-9);
  EXPECT_LT(rigid.deviation_m, 1e-9);

  size_t top = 0;
  for (size_t i = 0; i < X.size(); ++i)
    if (X[i].z() > X[top].z()) top = i;
  for (size_t i = 0; i < X.size(); ++i)
    o->state.x.segment<3>(3 * i) -= 0.015 * std::exp(-(X[i] - X[top]).squaredNorm() / (0.02 * 0.02)) * R0.col(2);
  o->fit = detail::rigid_fit(*o);
  const double deviation = o->fit.deviation_m;
  EXPECT_GT(deviation, 0.005) << "the dent is part of the fit's deviation";
  const int n_surface = static_cast<int>(o->body.surface_tet.size());
  std::vector<Eigen::Vector3d> surface(static_cast<size_t>(n_surface));
  Eigen::Vector3d centre = Eigen::Vector3d::Zero();
  for (int v = 0; v < n_surface; ++v) surface[v] = detail::surface_point(*o, v), centre += surface[v] / n_surface;
  const double far_error = 2 * 0.8660254 * 0.015;
  int answered = 0, owed = 0;
  double worst_short = 0, worst_over = -1;
  std::vector<double> cosines;
  for (int k = 0; k < 200; ++k) {
    const testing_util::SurfaceProbe probe =
        testing_util::probe_surface(k, centre, 0.01, 0.08, surface, o->body.surface.triangles);
    const Eigen::Vector3d& p = probe.p;
    const double exact = probe.distance;
    const bool owed_answer = exact > far_error + 2 * deviation;
    owed += owed_answer;
    double gap;
    Eigen::Vector3d n;
    if (!detail::far_clearance(*o, p, gap, n)) {
      EXPECT_FALSE(owed_answer) << "no bound " << 1e3 * exact << " mm out";
      continue;
    }
    ++answered;
    // The fine grid's own interpolation error (0.5 mm, MeshSdf's test) where it answers.
    EXPECT_LE(gap, exact + 0.5e-3) << "at " << 1e3 * exact << " mm";
    worst_over = std::max(worst_over, gap - exact);
    worst_short = std::max(worst_short, exact - gap);
    cosines.push_back(n.dot((p - probe.nearest).normalized()));
  }
  ASSERT_FALSE(cosines.empty());
  std::sort(cosines.begin(), cosines.end());
  std::printf(
      "dented bunny (deviation %.1f mm): %d of 200 points 1-8 cm out bounded (%d owed one), short by at most "
      "%.1f mm, over by at most %.2f mm; normal from the nearest surface point at a cosine of at least %.2f, "
      "of %.3f for 95 %% of them\n",
      1e3 * deviation, answered, owed, 1e3 * worst_short, 1e3 * worst_over, cosines.front(),
      cosines[cosines.size() / 20]);
  EXPECT_GE(owed, 50) << "too few points far enough out to test the bound's reach";
  EXPECT_LE(worst_short, far_error + 2 * deviation);
  EXPECT_GT(cosines[cosines.size() / 20], 0.9);
}

INSTANTIATE_TEST_SUITE_P(Contact, DeformableWorld, testing::Values(ContactModel::penalty, ContactModel::constraint),
                         [](const testing::TestParamInfo<ContactModel>& i) { return std::string(to_string(i.param)); });

}  // namespace
}  // namespace hapticd::world
