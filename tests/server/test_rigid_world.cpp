// The ODE rigid world against closed forms: Coulomb friction on an incline,
// free fall, a hinge limit.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <numbers>
#include <stdexcept>
#include <string>

#include "hand_models/embedded_surface.hpp"
#include "server/world/rigid_world.hpp"
#include "server/world/scene_loader.hpp"
#include "world_test_util.hpp"

namespace hapticd::world {
namespace {

// A static slab tilted by theta about x, a 10 cm box resting on it, both with friction mu.
SceneDesc incline_scene(double theta, double mu) {
  SceneDesc scene;
  scene.dt_s = 1.0 / 240.0;
  MaterialDesc m;
  m.friction = mu;
  const Eigen::Quaterniond tilt(Eigen::AngleAxisd(theta, Eigen::Vector3d::UnitX()));
  ObjectDesc slope;
  slope.name = "slope";
  slope.kind = BodyKind::static_body;
  slope.shape.type = ShapeType::box;
  slope.shape.size = {1.0, 4.0, 0.1};
  slope.pose.q_W = tilt;
  slope.material = m;
  ObjectDesc box;
  box.name = "box";
  box.kind = BodyKind::rigid;
  box.shape.type = ShapeType::box;
  box.shape.size = {0.1, 0.1, 0.1};
  box.mass_kg = 0.5;
  box.pose.q_W = tilt;
  box.pose.p_W = tilt * Eigen::Vector3d(0, 0, 0.05 + 0.05);  // resting on the slope's top face
  box.material = m;
  scene.objects = {slope, box};
  return scene;
}

// Distance travelled down the slope after `seconds`, m.
double slide_after(RigidWorld& world, double theta, double seconds, double dt) {
  const int box = world.find("box");
  const Eigen::Vector3d p0 = world.state(box).p_WO;
  for (int k = 0; k < static_cast<int>(std::lround(seconds / dt)); ++k) world.step(dt);
  const Eigen::Vector3d down_slope = Eigen::AngleAxisd(theta, Eigen::Vector3d::UnitX()) * -Eigen::Vector3d::UnitY();
  return (world.state(box).p_WO - p0).dot(down_slope);
}

TEST(RigidWorld, BoxOnInclineSticksWhenTanThetaIsBelowMu) {
  const double mu = 0.6, theta = std::atan(0.8 * mu);
  const SceneDesc scene = incline_scene(theta, mu);
  RigidWorld world(scene);
  const double slide = slide_after(world, theta, 2.0, scene.dt_s);
  std::printf("sticking box moved %.2e m; contacts %d\n", slide, world.contacts_last_step());
  EXPECT_LT(std::abs(slide), 1e-3);  // m: it stays put
  EXPECT_GT(world.contacts_last_step(), 0);
}

TEST(RigidWorld, BoxOnInclineSlidesWithCoulombAcceleration) {
  const double g = 9.81;
  for (double mu : {0.2, 0.5}) {
    const double theta = std::atan(mu) + 0.25;
    const SceneDesc scene = incline_scene(theta, mu);
    RigidWorld world(scene);
    const int box = world.find("box");
    // Let the contact settle, then measure the acceleration over one second.
    slide_after(world, theta, 0.1, scene.dt_s);
    const double v0 = world.state(box).v_WO.norm();
    slide_after(world, theta, 1.0, scene.dt_s);
    const double a = world.state(box).v_WO.norm() - v0;
    const double expected = g * (std::sin(theta) - mu * std::cos(theta));
    std::printf("mu %.2f theta %.3f: a = %.4f m/s^2, expected %.4f\n", mu, theta, a, expected);
    EXPECT_NEAR(a, expected, 0.02 * expected) << "mu " << mu;
  }
}

// A box's supports are its corners on the static geometry, gaps within the margin included: exact
// depths and positions from the box's pose, whether ODE finds a contact or not.
TEST(RigidWorld, SupportsOfABoxAreItsCornersOnTheStaticGeometryGapsWithinTheMarginIncluded) {
  RigidWorld world(incline_scene(0, 0.5));
  const int box = world.find("box");
  std::vector<RigidWorld::BodyContact> found;
  RigidBodyState pose = world.state(box);
  pose.p_WO.z() -= 1e-4;  // pressed 0.1 mm into the slab (top face at z = 0.05)
  world.set_state(box, pose);
  world.supports_of(box, found, 0.002);
  ASSERT_EQ(found.size(), 4u) << "the four bottom corners";
  for (const RigidWorld::BodyContact& c : found) {
    EXPECT_NEAR(c.depth_m, 1e-4, 1e-9);
    EXPECT_NEAR(std::abs(c.p_W.x()), 0.05, 1e-9);
    EXPECT_NEAR(std::abs(c.p_W.y()), 0.05, 1e-9);
    EXPECT_NEAR(c.n_W.z(), 1.0, 1e-9) << "out of the slab, into the box";
    EXPECT_EQ(c.other, world.find("slope"));
  }
  for (double lift : {0.001, 0.003}) {
    RigidBodyState lifted = pose;
    lifted.p_WO += Eigen::Vector3d(0.01, 0, lift);  // also slid 1 cm along the slab
    world.set_state(box, lifted);
    world.contacts_of(box, found);
    EXPECT_TRUE(found.empty()) << "ODE finds the lifted box";
    world.supports_of(box, found, 0.002);
    if (lift > 0.002) {
      EXPECT_TRUE(found.empty());  // beyond the margin
      continue;
    }
    ASSERT_EQ(found.size(), 4u);
    for (const RigidWorld::BodyContact& c : found) {
      EXPECT_NEAR(c.depth_m, 1e-4 - lift, 1e-9);  // a gap of the lift less the old depth
      EXPECT_NEAR(c.p_W.z(), 0.05 + lift - 1e-4, 1e-9);
    }
  }
  // Tilted by 1 degree about y, the box stands on one edge; the far edge's corners, 1.7 mm up, are
  // supports too (ODE reports only the touching edge): a step that tips the box about the near edge
  // must not carry the far one into the slab.
  RigidBodyState tilted = pose;
  const double tilt = std::numbers::pi / 180;
  tilted.q_WO = Eigen::Quaterniond(Eigen::AngleAxisd(tilt, Eigen::Vector3d::UnitY()));
  tilted.p_WO.z() = 0.05 + 0.05 * std::cos(tilt) + 0.05 * std::sin(tilt) - 1e-4;  // the +x edge 0.1 mm in
  world.set_state(box, tilted);
  world.supports_of(box, found, 0.002);
  ASSERT_EQ(found.size(), 4u);
  int near = 0, far = 0;
  for (const RigidWorld::BodyContact& c : found) {
    if (c.p_W.x() > 0) {
      ++near;
      EXPECT_NEAR(c.depth_m, 1e-4, 1e-9);
    } else {
      ++far;
      EXPECT_NEAR(c.depth_m, 1e-4 - 0.1 * std::sin(tilt), 1e-9);
    }
  }
  EXPECT_EQ(near, 2);
  EXPECT_EQ(far, 2);
}

// The scenes' bunny on the table, tipped 1 degree onto one foot: ODE's contacts are under that foot
// only, the supports span both feet (the other ~1 mm up, within the margin), spread over the base
// rather than 8 points within 1 cm under one foot as ODE's trimesh collider listed them: a hand's
// step then tipped the bunny about that foot, rocking it by 10 degrees at 15 Hz.
TEST(RigidWorld, ABunnyTippedOntoOneFootIsSupportedUnderBoth) {
  SceneDesc scene = load_scene(std::string(HAPTICD_SCENES_DIR) + "/stylus_bunny.json");
  RigidWorld world(scene);
  const int bunny = world.find("bunny");
  for (int k = 0; k < 120; ++k) world.step(1.0 / 60);  // settle
  std::vector<RigidWorld::BodyContact> found;
  const auto extent_x = [&] {
    double lo = 1e9, hi = -1e9;
    for (const RigidWorld::BodyContact& c : found) lo = std::min(lo, c.p_W.x()), hi = std::max(hi, c.p_W.x());
    return found.empty() ? 0.0 : hi - lo;
  };
  RigidBodyState tipped = world.state(bunny);
  tipped.q_WO = Eigen::Quaterniond(Eigen::AngleAxisd(std::numbers::pi / 180, Eigen::Vector3d::UnitY())) * tipped.q_WO;
  world.set_state(bunny, tipped);
  // Down (or up) until its lowest vertex is 0.1 mm into the table top (z = 0.75).
  std::vector<Eigen::Vector3d> vertices;
  ASSERT_TRUE(world.support_points(bunny, vertices));
  double lowest = 1e9;
  for (const Eigen::Vector3d& v : vertices) lowest = std::min(lowest, v.z());
  tipped.p_WO.z() += 0.75 - 1e-4 - lowest;
  world.set_state(bunny, tipped);
  world.contacts_of(bunny, found);
  const double ode_extent = extent_x();
  world.supports_of(bunny, found, 0.002);
  const double support_extent = extent_x();
  std::printf("bunny tipped 1 degree: ODE's contacts span %.1f mm in x, the supports %.1f mm (%zu)\n", 1e3 * ode_extent,
              1e3 * support_extent, found.size());
  EXPECT_LT(ode_extent, 0.03) << "ODE's contacts were expected under one foot only";
  EXPECT_GT(support_extent, 0.05);
  EXPECT_EQ(found.size(), 16u);  // as many as supports_of keeps: the base has more vertices within the margin
  for (const RigidWorld::BodyContact& c : found) {
    EXPECT_GT(c.depth_m, -0.002);
    EXPECT_LE(c.depth_m, 1e-4 + 1e-9);
  }
}

// A body of another shape has ODE's contacts; when ODE finds none (a lifted body), supports_of keeps
// the last ones (moved with the body, depth reduced by the lift) within the margin, for a few steps.
TEST(RigidWorld, SupportsOfASphereRememberTheLastContactsWithinTheMargin) {
  SceneDesc scene = incline_scene(0, 0.5);
  scene.objects[1].shape.type = ShapeType::sphere;
  scene.objects[1].shape.radius = 0.05;
  RigidWorld world(scene);
  const int ball = world.find("box");
  std::vector<RigidWorld::BodyContact> found;
  RigidBodyState pose = world.state(ball);
  pose.p_WO.z() -= 1e-4;
  world.set_state(ball, pose);
  world.supports_of(ball, found, 0.002);
  ASSERT_EQ(found.size(), 1u);
  EXPECT_NEAR(found[0].depth_m, 1e-4, 1e-6);
  RigidBodyState lifted = pose;
  lifted.p_WO += Eigen::Vector3d(0.01, 0, 0.001);
  world.set_state(ball, lifted);
  world.contacts_of(ball, found);
  EXPECT_TRUE(found.empty()) << "ODE finds the lifted ball";
  world.supports_of(ball, found, 0.002);
  ASSERT_EQ(found.size(), 1u);
  EXPECT_NEAR(found[0].depth_m, 1e-4 - 0.001, 1e-6);
  EXPECT_NEAR(found[0].p_W.z(), 0.05 + 0.001 - 1e-4, 1e-3);
  // Forgotten a few steps of the world later.
  for (long k = 0; k <= RigidWorld::kSupportMemorySteps; ++k) {
    world.set_state(ball, lifted);
    world.step(1e-6);
  }
  world.set_state(ball, lifted);
  world.supports_of(ball, found, 0.002);
  EXPECT_TRUE(found.empty());
}

TEST(RigidWorld, FreeFallFollowsGravityAndMassComesFromDensity) {
  SceneDesc scene;
  ObjectDesc ball;
  ball.name = "ball";
  ball.shape.type = ShapeType::sphere;
  ball.shape.radius = 0.05;
  ball.material.density_kg_m3 = 1000;
  ball.pose.p_W = {0, 0, 1};
  scene.objects = {ball};
  RigidWorld world(scene);
  EXPECT_NEAR(world.mass_kg(0), 1000 * 4.0 / 3.0 * M_PI * std::pow(0.05, 3), 1e-12);
  for (int k = 0; k < 60; ++k) world.step(scene.dt_s);
  // Semi-implicit Euler: v = g t exactly, z = 1 - g dt^2 n (n + 1) / 2.
  EXPECT_NEAR(world.state(0).v_WO.z(), -9.81, 1e-9);
  EXPECT_NEAR(world.state(0).p_WO.z(), 1 - 9.81 * scene.dt_s * scene.dt_s * 60 * 61 / 2, 1e-9);
}

TEST(RigidWorld, HingeLimitStopsAFallingLid) {
  SceneDesc scene;
  ObjectDesc lid;
  lid.name = "lid";
  lid.shape.type = ShapeType::box;
  lid.shape.size = {0.2, 0.2, 0.01};
  lid.mass_kg = 0.3;
  lid.pose.p_W = {0.1, 0, 0};
  JointDesc hinge;
  hinge.name = "hinge";
  hinge.body_a = "lid";
  hinge.body_b = "world";
  hinge.anchor_W = {0, 0, 0};
  hinge.axis_W = {0, 1, 0};
  hinge.limited = true;
  hinge.lo = -0.5;
  hinge.hi = 0.5;
  scene.objects = {lid};
  scene.joints = {hinge};
  RigidWorld world(scene);
  for (int k = 0; k < 240; ++k) world.step(scene.dt_s);
  // Gravity swings the lid down about +y until the 0.5 rad stop.
  const Eigen::Vector3d x_axis = world.state(0).q_WO * Eigen::Vector3d::UnitX();
  const double angle = std::atan2(-x_axis.z(), x_axis.x());
  EXPECT_NEAR(angle, 0.5, 0.02);
  EXPECT_NEAR(world.state(0).p_WO.norm(), 0.1, 1e-3);  // its centre stays on the hinge circle
}

// A 10 cm box resting on a floor plane.
SceneDesc box_on_floor() {
  SceneDesc scene;
  ObjectDesc floor;
  floor.name = "floor";
  floor.kind = BodyKind::static_body;
  floor.shape.type = ShapeType::plane;
  ObjectDesc box;
  box.name = "box";
  box.shape.type = ShapeType::box;
  box.shape.size = {0.1, 0.1, 0.1};
  box.mass_kg = 0.5;
  box.pose.p_W = {0, 0, 0.05};
  scene.objects = {floor, box};
  return scene;
}

bool finite(const RigidBodyState& s) {
  return s.p_WO.allFinite() && s.q_WO.coeffs().allFinite() && s.v_WO.allFinite() && s.w_W.allFinite();
}

TEST(RigidWorld, ABodySetToANonFiniteOrAbsurdVelocityIsResetAtRestAndCounted) {
  const SceneDesc scene = box_on_floor();
  RigidWorld world(scene);
  const int box = world.find("box");
  for (int k = 0; k < 30; ++k) world.step(scene.dt_s);
  const RigidBodyState settled = world.state(box);
  EXPECT_EQ(world.resets(), 0);
  // Each: non-finite linear, absurd linear (2x the bound), absurd angular (2x), non-finite angular.
  const Eigen::Vector3d v_bad[] = {{NAN, 0, 0}, {0, 100, 0}, {0, 0, 0}, {0, 0, 0}};
  const Eigen::Vector3d w_bad[] = {{0, 0, 0}, {0, 0, 0}, {2000, 0, 0}, {0, INFINITY, 0}};
  for (int i = 0; i < 4; ++i) {
    RigidBodyState s = world.state(box);
    s.v_WO = v_bad[i];
    s.w_W = w_bad[i];
    world.set_state(box, s);
    world.step(scene.dt_s);
    const RigidBodyState after = world.state(box);
    EXPECT_EQ(world.resets(), i + 1);
    ASSERT_TRUE(finite(after)) << i;
    // Back where it rested, at rest (one step of gravity and contact since: well under 1 mm, 0.2 m/s).
    EXPECT_LT((after.p_WO - settled.p_WO).norm(), 1e-3) << i;
    EXPECT_LT(after.v_WO.norm(), 0.2) << i;
    EXPECT_LT(after.w_W.norm(), 1.0) << i;
  }
}

TEST(RigidWorld, ABodyTheStepCarriesBeyondItsBoundsGoesBackToItsStartOfStepPose) {
  // Absurd gravity: one 1/60 s step takes the ball to 1667 m/s, 33 times the speed bound.
  SceneDesc scene;
  scene.gravity_m_s2 = {0, 0, -1e5};
  ObjectDesc ball;
  ball.name = "ball";
  ball.shape.type = ShapeType::sphere;
  ball.shape.radius = 0.05;
  ball.mass_kg = 0.1;
  ball.pose.p_W = {0, 0, 1};
  scene.objects = {ball};
  RigidWorld world(scene);
  for (int k = 0; k < 10; ++k) {
    world.step(scene.dt_s);
    ASSERT_TRUE(finite(world.state(0)));
    EXPECT_EQ(world.state(0).p_WO, Eigen::Vector3d(0, 0, 1)) << k;
    EXPECT_EQ(world.state(0).v_WO, Eigen::Vector3d::Zero()) << k;
  }
  EXPECT_EQ(world.resets(), 10);
}

TEST(RigidWorld, FastButBoundedBodiesAreNotReset) {
  // 40 m/s and 800 rad/s, under the bounds (50 m/s, 1000 rad/s): free flight goes on.
  SceneDesc scene;
  ObjectDesc ball;
  ball.name = "ball";
  ball.shape.type = ShapeType::sphere;
  ball.shape.radius = 0.05;
  ball.mass_kg = 0.1;
  ball.linear_velocity = {40, 0, 0};
  ball.angular_velocity = {0, 800, 0};
  scene.objects = {ball};
  RigidWorld world(scene);
  for (int k = 0; k < 30; ++k) world.step(scene.dt_s);
  EXPECT_EQ(world.resets(), 0);
  EXPECT_NEAR(world.state(0).p_WO.x(), 40 * 30 * scene.dt_s, 1e-9);
}

// The bunny's clearance from 1 to 9.5 cm out (far_clearance: the fine grid within its 1.65 cm, a
// 1.5 cm grid beyond) against the distance to its triangles, every one of them tried: never more than
// the distance (a clearance plane must not let a skin point through), short of it by at most the
// coarse grid's two errors (its interpolant's and the one taken off, 0.87 cell each), and its
// normal out of the surface, along the direction from the nearest surface point for most points.
// Within the fine grid's reach it is that grid's distance, which contacts use too.
TEST(RigidWorld, AMeshsFarClearanceIsALowerBoundOfItsDistanceWithinTheCoarseGridsError) {
  SceneDesc scene = load_scene(std::string(HAPTICD_SCENES_DIR) + "/stylus_bunny.json");
  RigidWorld world(scene);
  const int bunny = world.find("bunny");
  std::vector<Eigen::Vector3d> vertices;
  ASSERT_TRUE(world.support_points(bunny, vertices));
  const hand::SurfaceMesh mesh = hand::load_obj(std::string(HAPTICD_SCENES_DIR) + "/assets/bunny.obj");
  ASSERT_EQ(vertices.size(), mesh.vertices.size());
  Eigen::Vector3d centre = Eigen::Vector3d::Zero();
  for (const Eigen::Vector3d& v : vertices) centre += v / static_cast<double>(vertices.size());
  int answered = 0, far = 0;
  double worst_short = 0, worst_over = -1;
  std::vector<double> cosines;
  for (int k = 0; k < 300; ++k) {
    // From 30 cm out toward the centre until the point is 1 to 9.5 cm from the surface.
    const testing_util::SurfaceProbe probe =
        testing_util::probe_surface(k, centre, 0.01, 0.095, vertices, mesh.triangles);
    const Eigen::Vector3d& p = probe.p;
    const double exact = probe.distance;
    double gap;
    Eigen::Vector3d n;
    if (!world.far_clearance(bunny, p, gap, n)) continue;
    ++answered;
    far += exact > 0.0165;
    // The fine grid's own interpolation error (0.5 mm, MeshSdf's test) where it answers.
    EXPECT_LE(gap, exact + (exact < 0.0165 ? 0.5e-3 : 1e-9)) << "at " << 1e3 * exact << " mm";
    worst_over = std::max(worst_over, gap - exact);
    worst_short = std::max(worst_short, exact - gap);
    cosines.push_back(n.dot((p - probe.nearest).normalized()));
  }
  std::sort(cosines.begin(), cosines.end());
  const double cosine_5 = cosines[cosines.size() / 20];
  std::printf(
      "bunny's clearance at %d points 1-9.5 cm out (%d beyond the fine grid): short by at most %.1f mm, "
      "over by at most %.2f mm; normal from the nearest surface point at a cosine of at least %.2f, of "
      "%.3f for 95 %% of them\n",
      answered, far, 1e3 * worst_short, 1e3 * worst_over, cosines.front(), cosine_5);
  EXPECT_GE(answered, 270) << "points up to 9.5 cm out were expected to be answered";
  EXPECT_GE(far, 150);
  EXPECT_LE(worst_short, 2 * 0.8660254 * 0.015);
  // Out of the surface everywhere (a plane facing the wrong way would let a point through); near a
  // medial axis, between two parts of the bunny, the coarse gradient turns toward the other part.
  EXPECT_GT(cosines.front(), 0.0);
  EXPECT_GT(cosine_5, 0.95);
}

}  // namespace
}  // namespace hapticd::world

namespace hapticd::world {
namespace {

// The scenes' rigid mesh bunny (0.2 kg) on the 4 cm table, stepped alone as a loaded visual loop
// steps the world: at 15 and 10 Hz it rests where 60 Hz steps put it. Measured before RigidWorld
// split a long step into substeps of at most 1/30 s: at 15 Hz it fell through the table to the
// floor (origin 75 to 85 cm below its 60 Hz rest), at 10 Hz it hopped on the table (2.0 cm below to 2.4 cm above).
TEST(RigidWorldSlowSteps, MeshBunnyRestsOnTheTableAtSlowVisualRatesAsAt60Hz) {
  SceneDesc scene = load_scene(std::string(HAPTICD_SCENES_DIR) + "/stylus_bunny.json");
  scene.hands.clear();
  scene.devices.clear();
  const auto height_range = [&](double dt_s, double& low, double& high) {
    RigidWorld world(scene);
    const int bunny = world.find("bunny");
    ASSERT_GE(bunny, 0);
    low = 1e300, high = -1e300;
    for (int k = 0; k < std::lround(3.0 / dt_s); ++k) {
      world.step(dt_s);
      if (k * dt_s < 1.0) continue;  // settled
      low = std::min(low, world.state(bunny).p_WO.z());
      high = std::max(high, world.state(bunny).p_WO.z());
    }
  };
  double rest_low = 0, rest_high = 0;
  height_range(1.0 / 60, rest_low, rest_high);
  for (const double rate : {15.0, 10.0}) {
    double low = 0, high = 0;
    height_range(1.0 / rate, low, high);
    std::printf("mesh bunny at %.0f Hz: origin height %.2f to %.2f mm from its 60 Hz rest\n", rate,
                1e3 * (low - rest_low), 1e3 * (high - rest_low));
    EXPECT_LT(std::abs(low - rest_low), 1e-4) << rate << " Hz";
    EXPECT_LT(std::abs(high - rest_high), 1e-4) << rate << " Hz";
  }
}

// ODE's own reports (ensure_ode_for_this_thread): a message, such as the warning its LCP solver
// raises when it meets a degenerate pivot and recovers, is counted and printed nowhere; a fatal error
// or a debug trap throws instead of aborting the server, with ODE's number and text.
TEST(RigidWorld, OdesMessagesAreCountedSilentlyAndItsErrorsThrowInsteadOfAborting) {
  ensure_ode_for_this_thread();
  const long before = ode_messages();
  ::testing::internal::CaptureStderr();
  dMessage(3, "LCP internal error, s <= 0 (s=%.4e)", 0.0);
  EXPECT_EQ(::testing::internal::GetCapturedStderr(), "");
  EXPECT_EQ(ode_messages(), before + 1);
  for (const bool debug : {false, true}) {
    try {
      if (debug) {
        dDebug(2, "trap %d", 7);
      } else {
        dError(1, "bad argument %s", "x");
      }
      ADD_FAILURE() << "no throw";
    } catch (const std::runtime_error& e) {
      EXPECT_EQ(std::string(e.what()), debug ? "ODE error 2: trap 7" : "ODE error 1: bad argument x");
    }
  }
}
}  // namespace
}  // namespace hapticd::world
