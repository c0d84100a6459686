#include <gtest/gtest.h>
#include <unistd.h>

#include <array>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <limits>
#include <nlohmann/json.hpp>
#include <string>
#include <tuple>
#include <vector>

#include "protocol/codec.hpp"
#include "protocol/limits.hpp"
#include "server/haptic/device_link.hpp"
#include "server/world/scene_loader.hpp"
#include "server/world/world.hpp"

namespace hapticd::world {
namespace {

namespace fs = std::filesystem;
using json = nlohmann::json;

const fs::path kScenes = HAPTICD_SCENES_DIR;

// Exact comparisons: the loader copies defaults and file values without arithmetic.
void expect_vec(const Eigen::Vector3d& v, double x, double y, double z) {
  EXPECT_EQ(v, Eigen::Vector3d(x, y, z)) << v.transpose();
}
void expect_identity(const Eigen::Quaterniond& q) {
  EXPECT_EQ(q.coeffs(), Eigen::Quaterniond::Identity().coeffs()) << q.coeffs().transpose();
}
void expect_default_material(const MaterialDesc& m, double density_kg_m3) {
  EXPECT_EQ(m.name, "");
  EXPECT_EQ(m.youngs_modulus_pa, 50e3);
  EXPECT_EQ(m.poisson_ratio, 0.45);
  EXPECT_EQ(m.density_kg_m3, density_kg_m3);
  EXPECT_EQ(m.friction, 0.5);
  EXPECT_EQ(m.friction_static, -1.0);
  EXPECT_EQ(m.static_friction(), 0.5);
  EXPECT_EQ(m.restitution, 0.0);
  EXPECT_EQ(m.rayleigh_alpha_per_s, 1.0);
  EXPECT_EQ(m.rayleigh_beta_s, 0.005);
}

class SceneLoaderTest : public ::testing::Test {
 protected:
  // Small stand-in assets: the loader checks files exist, not what they hold.
  static void SetUpTestSuite() {
    dir_ = fs::path(::testing::TempDir()) / ("hapticd_scene_loader_" + std::to_string(getpid()));
    fs::create_directories(dir_ / "assets");
    for (const char* name : {"assets/tiny.obj", "assets/tiny.node", "assets/tiny.ele", "assets/tiny.embed",
                             "assets/lonely.node", "assets/tiny.msh"})
      std::ofstream(dir_ / name) << "# test stand-in\n";
    fs::create_directories(dir_ / "assets/folder.obj");
  }
  static void TearDownTestSuite() {
    std::error_code ec;
    fs::remove_all(dir_, ec);
  }

  static SceneDesc parse(const std::string& text) { return parse_scene_text(text, dir_.string(), "test.json"); }
  static SceneDesc parse(const json& doc) { return parse(doc.dump()); }

  // The error names key_path exactly and its message reads "test.json: <key_path>: <problem...>".
  static ::testing::AssertionResult fails_at(const std::string& text, const std::string& key_path,
                                             const std::string& problem) {
    try {
      parse(text);
    } catch (const SceneError& e) {
      const std::string expected = "test.json: " + (key_path.empty() ? "" : key_path + ": ") + problem;
      if (e.key_path() == key_path && std::string(e.what()).find(expected) != std::string::npos)
        return ::testing::AssertionSuccess();
      return ::testing::AssertionFailure() << "message: " << e.what() << "\nexpected it to contain: " << expected;
    }
    return ::testing::AssertionFailure() << "parsed without error";
  }
  static ::testing::AssertionResult fails_at(const json& doc, const std::string& key_path, const std::string& problem) {
    return fails_at(doc.dump(), key_path, problem);
  }

  // A valid scene with one of everything; each bad-input test breaks one thing.
  static json valid() {
    return json::parse(R"({
      "version": 1,
      "materials": {"wood": {"friction": 0.4, "density_kg_m3": 700}},
      "objects": [
        {"name": "floor", "kind": "static", "shape": {"type": "plane", "normal": [0, 0, 1], "offset": 0}},
        {"name": "box", "kind": "rigid", "shape": {"type": "box", "size": [0.04, 0.04, 0.04]}, "material": "wood"},
        {"name": "lid", "kind": "rigid", "shape": {"type": "box", "size": [0.1, 0.1, 0.01]}, "mass_kg": 0.1}
      ],
      "joints": [{"name": "hinge", "type": "hinge", "body_a": "lid", "body_b": "box",
                  "anchor": [0, 0, 0], "axis": [1, 0, 0]}],
      "hands": [{"name": "hand"}],
      "devices": [{"name": "stylus", "kind": "stylus", "hand": "hand"}]
    })");
  }

  static fs::path dir_;
};

fs::path SceneLoaderTest::dir_;

TEST_F(SceneLoaderTest, ValidFixtureParses) {
  const SceneDesc scene = parse(valid());
  EXPECT_EQ(scene.objects.size(), 3u);
  EXPECT_EQ(scene.joints.size(), 1u);
  EXPECT_EQ(scene.hands.size(), 1u);
  EXPECT_EQ(scene.devices.size(), 1u);
}

TEST_F(SceneLoaderTest, MinimalSceneHasEveryDefault) {
  const SceneDesc scene = parse(std::string(R"({"version": 1})"));
  EXPECT_EQ(scene.name, "test");  // the file name's stem
  EXPECT_EQ(scene.path, "test.json");
  expect_vec(scene.gravity_m_s2, 0, 0, -9.81);
  EXPECT_EQ(scene.visual_rate_hz, 60.0);
  EXPECT_EQ(scene.dt_s, 1.0 / 60.0);
  EXPECT_EQ(scene.contact, ContactModel::constraint);
  EXPECT_TRUE(scene.materials.empty());
  EXPECT_TRUE(scene.objects.empty());
  EXPECT_TRUE(scene.joints.empty());
  EXPECT_TRUE(scene.hands.empty());
  EXPECT_TRUE(scene.devices.empty());
  EXPECT_FALSE(scene.needs_rigid_world());
  EXPECT_FALSE(scene.needs_deformable_objects());
}

TEST_F(SceneLoaderTest, MinimalEntitiesHaveEveryDefault) {
  const SceneDesc scene = parse(std::string(R"({
    "version": 1,
    "visual_rate_hz": 30,
    "materials": {"plain": {}},
    "objects": [
      {"name": "cube", "kind": "rigid", "shape": {"type": "box", "size": [0.1, 0.2, 0.3]}},
      {"name": "ground", "kind": "static", "shape": {"type": "plane", "normal": [0, 0, 2], "offset": 0}},
      {"name": "rock", "kind": "static", "shape": {"type": "mesh", "file": "assets/tiny.obj"}},
      {"name": "jelly", "kind": "deformable", "shape": {"type": "tet_mesh", "file": "assets/tiny.node"}}
    ],
    "joints": [{"name": "weld", "type": "fixed", "body_a": "cube", "body_b": "world"}],
    "hands": [{"name": "hand"}],
    "devices": [{"name": "pen", "kind": "stylus", "hand": "hand"}]
  })"));
  EXPECT_EQ(scene.dt_s, 1.0 / 30.0);  // follows visual_rate_hz when absent
  ASSERT_EQ(scene.materials.size(), 1u);
  EXPECT_EQ(scene.materials[0].name, "plain");
  MaterialDesc unnamed = scene.materials[0];
  unnamed.name.clear();
  expect_default_material(unnamed, 1000.0);

  ASSERT_EQ(scene.objects.size(), 4u);
  const ObjectDesc& cube = scene.objects[0];
  EXPECT_EQ(cube.name, "cube");
  EXPECT_EQ(cube.kind, BodyKind::rigid);
  EXPECT_EQ(cube.shape.type, ShapeType::box);
  expect_vec(cube.shape.size, 0.1, 0.2, 0.3);
  EXPECT_EQ(cube.shape.scale, 1.0);
  EXPECT_EQ(cube.shape.file, "");
  EXPECT_EQ(cube.shape.embedding_file, "");
  expect_vec(cube.pose.p_W, 0, 0, 0);
  expect_identity(cube.pose.q_W);
  EXPECT_EQ(cube.mass_kg, -1.0);
  expect_default_material(cube.material, 1000.0);
  expect_vec(cube.linear_velocity, 0, 0, 0);
  expect_vec(cube.angular_velocity, 0, 0, 0);

  const ObjectDesc& ground = scene.objects[1];
  EXPECT_EQ(ground.kind, BodyKind::static_body);
  expect_vec(ground.shape.normal, 0, 0, 1);  // normalised
  EXPECT_EQ(ground.shape.offset, 0.0);
  EXPECT_EQ(ground.mass_kg, -1.0);

  const ObjectDesc& rock = scene.objects[2];
  EXPECT_EQ(rock.shape.file, (dir_ / "assets/tiny.obj").lexically_normal().string());
  EXPECT_TRUE(fs::path(rock.shape.file).is_absolute());
  EXPECT_EQ(rock.shape.scale, 1.0);
  const ObjectDesc& jelly = scene.objects[3];
  EXPECT_EQ(jelly.shape.file, (dir_ / "assets/tiny.node").lexically_normal().string());
  EXPECT_EQ(jelly.shape.embedding_file, "");

  ASSERT_EQ(scene.joints.size(), 1u);
  const JointDesc& weld = scene.joints[0];
  EXPECT_EQ(weld.type, JointType::fixed);
  EXPECT_EQ(weld.body_a, "cube");
  EXPECT_EQ(weld.body_b, "world");
  expect_vec(weld.anchor_W, 0, 0, 0);
  expect_vec(weld.axis_W, 0, 0, 1);
  EXPECT_FALSE(weld.limited);
  EXPECT_EQ(weld.lo, 0.0);
  EXPECT_EQ(weld.hi, 0.0);

  ASSERT_EQ(scene.hands.size(), 1u);
  const HandDesc& hand = scene.hands[0];
  EXPECT_EQ(hand.model, HandModelKind::fem);
  EXPECT_EQ(hand.side, HandSide::right);
  EXPECT_EQ(hand.resolution_tets, 1700);
  EXPECT_EQ(hand.handles, HandleSet::palm);
  expect_default_material(hand.material, 1070.0);
  expect_vec(hand.pose.p_W, 0, 0, 0);
  expect_identity(hand.pose.q_W);
  EXPECT_EQ(hand.coupling_stiffness_n_m, 2000.0);
  EXPECT_EQ(hand.coupling_damping_ns_m, 2.0);

  ASSERT_EQ(scene.devices.size(), 1u);
  const DeviceDesc& pen = scene.devices[0];
  EXPECT_EQ(pen.kind, DeviceKind::stylus);
  EXPECT_EQ(pen.hand, "hand");
  EXPECT_EQ(pen.workspace.scale, 1.0);
  expect_vec(pen.workspace.offset_W, 0, 0, 0);
  expect_identity(pen.workspace.R_WD);
  EXPECT_EQ(pen.max_force_n, 8.0);
  EXPECT_EQ(pen.max_torque_nm, 0.5);
  EXPECT_EQ(pen.max_force_rate_n_s, 1000.0);
  EXPECT_EQ(pen.stiffness_n_m, 1000.0);
  EXPECT_EQ(scene.device_for_hand("hand"), &pen);
  EXPECT_EQ(scene.find_object("rock"), &rock);
  EXPECT_EQ(scene.find_object("nothing"), nullptr);
}

TEST_F(SceneLoaderTest, ExplicitValuesAreReadAndNormalised) {
  const SceneDesc scene = parse(std::string(R"({
    "version": 1, "name": "explicit", "gravity": [0, -9.8, 0], "visual_rate_hz": 50, "dt_s": 0.005,
    "contact": "penalty",
    "materials": {"rubber": {"youngs_modulus_pa": 1e6, "poisson_ratio": 0.49, "density_kg_m3": 1200,
                             "friction": 0.9, "friction_static": 1.1, "restitution": 0.6,
                             "rayleigh_alpha_per_s": 0, "rayleigh_beta_s": 0.01}},
    "objects": [
      {"name": "ball", "kind": "rigid", "shape": {"type": "sphere", "radius": 0.02}, "density_kg_m3": 500,
       "material": {"friction": 0.2}, "linear_velocity": [1, 2, 3], "angular_velocity": [0, 0, 10],
       "pose": {"position": [0.1, 0.2, 0.3], "orientation": {"w": 0, "x": 0, "y": 0, "z": 2}}},
      {"name": "pill", "kind": "rigid", "shape": {"type": "capsule", "radius": 0.01, "length": 0.05}, "mass_kg": 0.3,
       "material": "rubber"},
      {"name": "can", "kind": "static", "shape": {"type": "cylinder", "radius": 0.03, "length": 0.1}},
      {"name": "jelly", "kind": "deformable", "shape": {"type": "tet_mesh", "file": "assets/../assets/tiny.node",
       "scale": 0.5, "surface": "assets/tiny.obj", "embedding": "assets/tiny.embed"}},
      {"name": "gel", "kind": "deformable", "shape": {"type": "tet_mesh", "file": "assets/tiny.msh"}},
      {"name": "slab", "kind": "deformable", "shape": {"type": "box", "size": [0.1, 0.1, 0.02]}}
    ],
    "joints": [
      {"name": "pivot", "type": "hinge", "body_a": "ball", "body_b": "pill", "anchor": [1, 2, 3], "axis": [0, 3, 4],
       "limits": [-0.5, 0.5]},
      {"name": "rail", "type": "slider", "body_a": "pill", "body_b": "can", "axis": [1, 0, 0], "limits": [0, 0.2]},
      {"name": "socket", "type": "ball", "body_a": "ball", "body_b": "world", "anchor": [0, 0, 1]}
    ],
    "hands": [{"name": "lefty", "model": "soft_pad", "side": "left", "resolution_tets": 5000, "handles": "phalanges",
               "material": {"youngs_modulus_pa": 80000}, "pose": {"position": [0, 0, 1]},
               "coupling_stiffness_n_m": 3000, "coupling_damping_ns_m": 0}],
    "devices": [{"name": "glove", "kind": "glove", "hand": "lefty",
                 "workspace": {"scale": 2, "offset": [0, 0, 0.5], "orientation": {"w": 1, "x": 1, "y": 0, "z": 0}},
                 "max_force_n": 3, "max_torque_nm": 0.1, "max_force_rate_n_s": 200, "stiffness_n_m": 500,
                 "force_output": "finger_lines", "actuator_line": [0, -3, 4], "feedback_a": [1, 0.5, 0.25, 2]}]
  })"));
  EXPECT_EQ(scene.name, "explicit");
  expect_vec(scene.gravity_m_s2, 0, -9.8, 0);
  EXPECT_EQ(scene.visual_rate_hz, 50.0);
  EXPECT_EQ(scene.dt_s, 0.005);
  EXPECT_EQ(scene.contact, ContactModel::penalty);

  const ObjectDesc& ball = *scene.find_object("ball");
  EXPECT_EQ(ball.shape.radius, 0.02);
  EXPECT_EQ(ball.material.density_kg_m3, 500.0);  // the object's density wins over the material's
  EXPECT_EQ(ball.material.friction, 0.2);
  EXPECT_EQ(ball.material.youngs_modulus_pa, 50e3);  // inline materials start from the defaults
  expect_vec(ball.linear_velocity, 1, 2, 3);
  expect_vec(ball.angular_velocity, 0, 0, 10);
  expect_vec(ball.pose.p_W, 0.1, 0.2, 0.3);
  EXPECT_EQ(ball.pose.q_W.coeffs(), Eigen::Vector4d(0, 0, 1, 0));  // (x, y, z, w): normalised

  const ObjectDesc& pill = *scene.find_object("pill");
  EXPECT_EQ(pill.mass_kg, 0.3);
  EXPECT_EQ(pill.material.name, "rubber");
  EXPECT_EQ(pill.material.static_friction(), 1.1);
  EXPECT_EQ(pill.material.restitution, 0.6);
  EXPECT_EQ(pill.shape.length, 0.05);
  EXPECT_EQ(scene.find_object("can")->shape.type, ShapeType::cylinder);

  const ObjectDesc& jelly = *scene.find_object("jelly");
  EXPECT_EQ(jelly.shape.file, (dir_ / "assets/tiny.node").lexically_normal().string());
  EXPECT_EQ(jelly.shape.surface_file, (dir_ / "assets/tiny.obj").lexically_normal().string());
  EXPECT_EQ(jelly.shape.embedding_file, (dir_ / "assets/tiny.embed").lexically_normal().string());
  EXPECT_EQ(jelly.shape.scale, 0.5);
  EXPECT_EQ(scene.find_object("slab")->kind, BodyKind::deformable);
  EXPECT_TRUE(scene.needs_deformable_objects());

  const JointDesc& pivot = scene.joints[0];
  expect_vec(pivot.anchor_W, 1, 2, 3);
  EXPECT_NEAR((pivot.axis_W - Eigen::Vector3d(0, 0.6, 0.8)).norm(), 0, 4 * std::numeric_limits<double>::epsilon());
  EXPECT_TRUE(pivot.limited);
  EXPECT_EQ(pivot.lo, -0.5);
  EXPECT_EQ(pivot.hi, 0.5);
  EXPECT_EQ(scene.joints[1].type, JointType::slider);
  EXPECT_EQ(scene.joints[2].type, JointType::ball);
  EXPECT_EQ(scene.joints[2].body_b, "world");

  const HandDesc& lefty = scene.hands[0];
  EXPECT_EQ(lefty.model, HandModelKind::soft_pad);
  EXPECT_EQ(lefty.side, HandSide::left);
  EXPECT_EQ(lefty.resolution_tets, 5000);
  EXPECT_EQ(lefty.handles, HandleSet::phalanges);
  EXPECT_EQ(lefty.material.youngs_modulus_pa, 80000.0);
  EXPECT_EQ(lefty.material.density_kg_m3, 1070.0);  // an inline hand material starts from the hand's defaults
  EXPECT_EQ(lefty.coupling_stiffness_n_m, 3000.0);
  EXPECT_EQ(lefty.coupling_damping_ns_m, 0.0);

  const DeviceDesc& glove = scene.devices[0];
  EXPECT_EQ(glove.kind, DeviceKind::glove);
  EXPECT_EQ(glove.workspace.scale, 2.0);
  expect_vec(glove.workspace.offset_W, 0, 0, 0.5);
  EXPECT_NEAR(glove.workspace.R_WD.norm(), 1.0, 4 * std::numeric_limits<double>::epsilon());
  EXPECT_NEAR(glove.workspace.R_WD.w(), std::sqrt(0.5), 4 * std::numeric_limits<double>::epsilon());
  EXPECT_EQ(glove.max_force_n, 3.0);
  EXPECT_EQ(glove.max_torque_nm, 0.1);
  EXPECT_EQ(glove.max_force_rate_n_s, 200.0);
  EXPECT_EQ(glove.stiffness_n_m, 500.0);
  EXPECT_EQ(glove.force_output, GloveForceOutput::finger_lines);
  expect_vec(glove.actuator_line_F, 0, -0.6, 0.8);  // normalised
  EXPECT_EQ(glove.feedback_a, (std::array<double, 4>{1, 0.5, 0.25, 2}));
}

// ---------------------------------------------------------------------------
// The shipped scenes

void expect_stylus_drives_right_fem_hand(const SceneDesc& scene) {
  ASSERT_EQ(scene.hands.size(), 1u);
  ASSERT_EQ(scene.devices.size(), 1u);
  const HandDesc& hand = scene.hands[0];
  EXPECT_EQ(hand.model, HandModelKind::fem);
  EXPECT_EQ(hand.side, HandSide::right);
  EXPECT_EQ(hand.resolution_tets, 1700);
  EXPECT_EQ(hand.handles, HandleSet::palm);
  EXPECT_EQ(scene.devices[0].kind, DeviceKind::stylus);
  EXPECT_EQ(scene.device_for_hand(hand.name), &scene.devices[0]);
  ASSERT_NE(scene.find_object("floor"), nullptr);
  EXPECT_EQ(scene.find_object("floor")->shape.type, ShapeType::plane);
  ASSERT_NE(scene.find_object("table"), nullptr);
  EXPECT_EQ(scene.find_object("table")->kind, BodyKind::static_body);
}

TEST(ShippedScenes, StylusBunnyLoads) {
  const SceneDesc scene = load_scene((kScenes / "stylus_bunny.json").string());
  expect_stylus_drives_right_fem_hand(scene);
  const ObjectDesc* bunny = scene.find_object("bunny");
  ASSERT_NE(bunny, nullptr);
  EXPECT_EQ(bunny->kind, BodyKind::rigid);
  EXPECT_EQ(bunny->shape.type, ShapeType::mesh);
  EXPECT_EQ(bunny->mass_kg, 0.2);
  EXPECT_EQ(fs::path(bunny->shape.file), (kScenes / "assets/bunny.obj").lexically_normal());
  EXPECT_TRUE(scene.needs_rigid_world());
  EXPECT_FALSE(scene.needs_deformable_objects());
}

// The glove scenes: each hand with phalanx handles, driven by its own 16-frame glove.
TEST(ShippedScenes, GloveScenesGiveEachPhalanxHandItsOwnGlove) {
  for (const char* name : {"glove_grasp.json", "two_hands.json"}) {
    const SceneDesc scene = load_scene((kScenes / name).string());
    ASSERT_FALSE(scene.hands.empty()) << name;
    EXPECT_EQ(scene.devices.size(), scene.hands.size()) << name;
    for (const HandDesc& hand : scene.hands) {
      EXPECT_EQ(hand.handles, HandleSet::phalanges) << name;
      const DeviceDesc* glove = scene.device_for_hand(hand.name);
      ASSERT_NE(glove, nullptr) << name << " " << hand.name;
      EXPECT_EQ(glove->kind, DeviceKind::glove);
      // The glove's tracker space puts the hand frame where the scene places the hand.
      EXPECT_LT((glove->workspace.offset_W - hand.pose.p_W).norm(), 1e-12) << name << " " << hand.name;
    }
    const ObjectDesc* box = scene.find_object("box");
    ASSERT_NE(box, nullptr) << name;
    EXPECT_EQ(box->mass_kg, 0.1);
  }
  const SceneDesc two = load_scene((kScenes / "two_hands.json").string());
  ASSERT_EQ(two.hands.size(), 2u);
  EXPECT_NE(two.hands[0].side, two.hands[1].side);
}

TEST(ShippedScenes, DeformableBunnyLoads) {
  const SceneDesc scene = load_scene((kScenes / "deformable_bunny.json").string());
  expect_stylus_drives_right_fem_hand(scene);
  const ObjectDesc* bunny = scene.find_object("bunny");
  ASSERT_NE(bunny, nullptr);
  EXPECT_EQ(bunny->kind, BodyKind::deformable);
  EXPECT_EQ(bunny->shape.type, ShapeType::tet_mesh);
  EXPECT_EQ(fs::path(bunny->shape.file), (kScenes / "assets/bunny_271.node").lexically_normal());
  EXPECT_EQ(fs::path(bunny->shape.surface_file), (kScenes / "assets/bunny.obj").lexically_normal());
  EXPECT_EQ(fs::path(bunny->shape.embedding_file), (kScenes / "assets/bunny_271.embed").lexically_normal());
  EXPECT_TRUE(scene.needs_deformable_objects());
  EXPECT_TRUE(scene.needs_rigid_world());  // the blocks
}

TEST(ShippedScenes, BlocksHasTwentySmallBlocksOnTheTable) {
  const SceneDesc scene = load_scene((kScenes / "blocks.json").string());
  expect_stylus_drives_right_fem_hand(scene);
  const ObjectDesc& table = *scene.find_object("table");
  const double table_top = table.pose.p_W.z() + table.shape.size.z() / 2;
  int blocks = 0;
  for (const ObjectDesc& o : scene.objects) {
    if (o.kind != BodyKind::rigid) continue;
    ++blocks;
    EXPECT_EQ(o.shape.type, ShapeType::box) << o.name;
    EXPECT_GE(o.shape.size.minCoeff(), 0.03) << o.name;
    EXPECT_LE(o.shape.size.maxCoeff(), 0.04) << o.name;
    // Resting on the table: upright boxes (rotated about z only) whose bottom is its top.
    EXPECT_NEAR(o.pose.p_W.z() - o.shape.size.z() / 2, table_top, 1e-9) << o.name;
    EXPECT_NEAR(std::abs((o.pose.q_W * Eigen::Vector3d::UnitZ()).z()), 1.0, 1e-9) << o.name;
  }
  EXPECT_EQ(blocks, 20);
  EXPECT_TRUE(scene.needs_rigid_world());
  EXPECT_FALSE(scene.needs_deformable_objects());
}

// ---------------------------------------------------------------------------
// Model only what a scene needs

TEST_F(SceneLoaderTest, NeedsFollowTheObjectKinds) {
  json doc = json::parse(R"({"version": 1, "objects": [
    {"name": "floor", "kind": "static", "shape": {"type": "plane", "normal": [0, 0, 1], "offset": 0}}],
    "hands": [{"name": "hand"}]})");
  SceneDesc scene = parse(doc);
  EXPECT_FALSE(scene.needs_rigid_world());  // static geometry and a hand need no rigid solver
  EXPECT_FALSE(scene.needs_deformable_objects());

  json with_rigid = doc;
  with_rigid["objects"].push_back(json::parse(R"({"name": "cube", "kind": "rigid",
                                                  "shape": {"type": "box", "size": [0.04, 0.04, 0.04]}})"));
  scene = parse(with_rigid);
  EXPECT_TRUE(scene.needs_rigid_world());
  EXPECT_FALSE(scene.needs_deformable_objects());

  json with_deformable = doc;
  with_deformable["objects"].push_back(json::parse(R"({"name": "jelly", "kind": "deformable",
                                                       "shape": {"type": "box", "size": [0.04, 0.04, 0.04]}})"));
  scene = parse(with_deformable);
  EXPECT_FALSE(scene.needs_rigid_world());
  EXPECT_TRUE(scene.needs_deformable_objects());
}

// ---------------------------------------------------------------------------
// Bad input: one class per test, each naming the exact key path.

TEST_F(SceneLoaderTest, RejectsUnknownKey) {
  json doc = valid();
  doc["objects"][0]["colour"] = "red";
  EXPECT_TRUE(fails_at(doc, "objects[0].colour", "unknown key"));
  doc = valid();
  doc["frobnicate"] = true;
  EXPECT_TRUE(fails_at(doc, "frobnicate", "unknown key"));
  doc = valid();
  doc["devices"][0]["workspace"] = {{"scael", 2}};
  EXPECT_TRUE(fails_at(doc, "devices[0].workspace.scael", "unknown key"));
  doc = valid();
  doc["objects"][1]["shape"]["radius"] = 0.1;  // a sphere's key on a box
  EXPECT_TRUE(fails_at(doc, "objects[1].shape.radius", "unknown key for a box"));
}

TEST_F(SceneLoaderTest, RejectsWrongType) {
  json doc = valid();
  doc["hands"][0]["resolution_tets"] = "1700";
  EXPECT_TRUE(fails_at(doc, "hands[0].resolution_tets", "expected an integer, got string"));
  doc["hands"][0]["resolution_tets"] = 1700.5;
  EXPECT_TRUE(fails_at(doc, "hands[0].resolution_tets", "expected an integer, got number 1700.5"));
  doc["hands"][0]["resolution_tets"] = 1.7e3;  // integral: accepted
  EXPECT_EQ(parse(doc).hands[0].resolution_tets, 1700);
  EXPECT_TRUE(fails_at(std::string(R"({"version": 1, "hands": [{"name": "h", "resolution_tets": 1e23}]})"),
                       "hands[0].resolution_tets", "must be in [100, 20000], got 1e+23"));
  EXPECT_TRUE(fails_at(std::string(R"({"version": 9.3e18})"), "version", "must be in"));
  doc = valid();
  doc["gravity"] = {0, "down", -9.81};
  EXPECT_TRUE(fails_at(doc, "gravity[1]", "expected a number, got string"));
  doc["gravity"] = {0, -9.81};
  EXPECT_TRUE(fails_at(doc, "gravity", "expected 3 numbers, got 2"));
  doc = valid();
  doc["objects"] = json::object();
  EXPECT_TRUE(fails_at(doc, "objects", "expected an array, got object"));
  doc = valid();
  doc["objects"][1]["material"] = 3;
  EXPECT_TRUE(fails_at(doc, "objects[1].material", "expected a material name or an inline material object"));
  EXPECT_TRUE(fails_at(std::string("[1, 2]"), "", "expected an object, got array"));
}

TEST_F(SceneLoaderTest, RejectsMissingRequiredKey) {
  json doc = valid();
  doc["objects"][1].erase("shape");
  EXPECT_TRUE(fails_at(doc, "objects[1].shape", "missing required key"));
  doc = valid();
  doc["joints"][0].erase("axis");
  EXPECT_TRUE(fails_at(doc, "joints[0].axis", "missing required key"));
  doc = valid();
  doc["devices"][0].erase("kind");
  EXPECT_TRUE(fails_at(doc, "devices[0].kind", "missing required key"));
  doc = valid();
  doc["objects"][0]["pose"] = {{"orientation", {{"w", 1}, {"x", 0}, {"y", 0}}}};
  EXPECT_TRUE(fails_at(doc, "objects[0].pose.orientation.z", "missing required key"));
}

TEST_F(SceneLoaderTest, RejectsNegativeFriction) {
  json doc = valid();
  doc["materials"]["wood"]["friction"] = -0.2;
  EXPECT_TRUE(fails_at(doc, "materials.wood.friction", "must be in [0, 10], got -0.2"));
  doc = valid();
  doc["objects"][2]["material"] = {{"friction", -1}};
  EXPECT_TRUE(fails_at(doc, "objects[2].material.friction", "must be in [0, 10], got -1"));
  doc = valid();
  doc["materials"]["wood"]["friction_static"] = 0.3;  // below the kinetic 0.4
  EXPECT_TRUE(fails_at(doc, "materials.wood.friction_static", "must be >= friction (0.4), got 0.3"));
}

TEST_F(SceneLoaderTest, RejectsRestitutionAboveOne) {
  json doc = valid();
  doc["materials"]["wood"]["restitution"] = 1.5;
  EXPECT_TRUE(fails_at(doc, "materials.wood.restitution", "must be in [0, 1], got 1.5"));
}

TEST_F(SceneLoaderTest, RejectsNegativeMass) {
  json doc = valid();
  doc["objects"][2]["mass_kg"] = -0.1;
  EXPECT_TRUE(fails_at(doc, "objects[2].mass_kg", "must be in [1e-04, 1000], got -0.1"));
  doc["objects"][2]["mass_kg"] = 0;
  EXPECT_TRUE(fails_at(doc, "objects[2].mass_kg", "must be in [1e-04, 1000], got 0"));
}

TEST_F(SceneLoaderTest, RejectsMassOnStaticObject) {
  json doc = valid();
  doc["objects"][0]["mass_kg"] = 10;
  EXPECT_TRUE(fails_at(doc, "objects[0].mass_kg", "static objects have no mass"));
  doc = valid();
  doc["objects"][0]["linear_velocity"] = {1, 0, 0};
  EXPECT_TRUE(fails_at(doc, "objects[0].linear_velocity", "static objects do not move"));
}

TEST_F(SceneLoaderTest, RejectsBothMassAndDensity) {
  json doc = valid();
  doc["objects"][2]["density_kg_m3"] = 500;
  EXPECT_TRUE(fails_at(doc, "objects[2].density_kg_m3", "conflicts with mass_kg"));
  doc = valid();
  doc["objects"][2]["material"] = {{"density_kg_m3", 500}};
  EXPECT_TRUE(fails_at(doc, "objects[2].material.density_kg_m3", "conflicts with mass_kg"));
  // A named material's density is only a default: mass_kg overrides it without conflict.
  doc = valid();
  doc["objects"][2]["material"] = "wood";
  EXPECT_EQ(parse(doc).objects[2].mass_kg, 0.1);
}

TEST_F(SceneLoaderTest, RejectsUnknownShape) {
  json doc = valid();
  doc["objects"][0]["shape"] = {{"type", "cone"}};
  try {
    parse(doc);
    FAIL() << "parsed";
  } catch (const SceneError& e) {
    EXPECT_STREQ(e.what(),
                 "test.json: objects[0].shape.type: unknown shape 'cone' "
                 "(expected box, sphere, capsule, cylinder, plane, mesh, tet_mesh)");
  }
}

TEST_F(SceneLoaderTest, RejectsShapeNotAllowedForTheKind) {
  json doc = valid();
  doc["objects"][1]["shape"] = {{"type", "plane"}, {"normal", {0, 0, 1}}, {"offset", 0}};
  EXPECT_TRUE(fails_at(doc, "objects[1].shape.type", "a plane can only be static"));
  doc["objects"][1]["shape"] = {{"type", "tet_mesh"}, {"file", "assets/tiny.node"}};
  EXPECT_TRUE(fails_at(doc, "objects[1].shape.type", "tet_mesh is for deformable objects"));
  doc["objects"][1]["kind"] = "deformable";
  doc["objects"][1]["shape"] = {{"type", "sphere"}, {"radius", 0.1}};
  EXPECT_TRUE(fails_at(doc, "objects[1].shape.type", "deformable objects need a tet_mesh or box shape"));
  doc = valid();
  doc["objects"][0]["shape"]["normal"] = {0, 0, 0};
  EXPECT_TRUE(fails_at(doc, "objects[0].shape.normal", "must be a non-zero vector"));
  doc = valid();
  doc["objects"][1]["shape"]["size"] = {0.04, 0, 0.04};
  EXPECT_TRUE(fails_at(doc, "objects[1].shape.size[1]", "must be in [0.001, 100], got 0"));
}

TEST_F(SceneLoaderTest, RejectsZeroNormQuaternion) {
  json doc = valid();
  doc["objects"][1]["pose"] = {{"orientation", {{"w", 0}, {"x", 0}, {"y", 0}, {"z", 0}}}};
  EXPECT_TRUE(fails_at(doc, "objects[1].pose.orientation", "zero quaternion"));
  doc = valid();
  doc["devices"][0]["workspace"] = {{"orientation", {{"w", 0.0}, {"x", 0.0}, {"y", -0.0}, {"z", 0.0}}}};
  EXPECT_TRUE(fails_at(doc, "devices[0].workspace.orientation", "zero quaternion"));
  // Tiny but non-zero components normalise without underflow.
  doc["devices"][0]["workspace"] = {{"orientation", {{"w", 1e-200}, {"x", 0}, {"y", 0}, {"z", 0}}}};
  expect_identity(parse(doc).devices[0].workspace.R_WD);
}

TEST_F(SceneLoaderTest, RejectsNonFiniteNumber) {
  // JSON has no NaN or infinity; an overflowing literal is caught while parsing, with its position.
  const std::string text =
      "{\"version\": 1, \"objects\": [\n"
      "  {\"name\": \"cube\", \"kind\": \"rigid\", \"mass_kg\": 1e400,\n"
      "   \"shape\": {\"type\": \"box\", \"size\": [1, 1, 1]}}]}";
  try {
    parse(text);
    FAIL() << "parsed";
  } catch (const SceneError& e) {
    EXPECT_EQ(e.key_path(), "objects[0].mass_kg");
    EXPECT_EQ(e.line(), 2);
    EXPECT_EQ(e.column(), 52);  // the literal's last byte, as nlohmann counts
    EXPECT_NE(std::string(e.what()).find("test.json:2:52: objects[0].mass_kg: number overflow"), std::string::npos)
        << e.what();
  }
  json doc = valid();
  doc["objects"][2]["mass_kg"] = "NaN";
  EXPECT_TRUE(fails_at(doc, "objects[2].mass_kg", "expected a number, got string"));
  // A document built in code can hold non-finite numbers.
  doc["objects"][2]["mass_kg"] = std::numeric_limits<double>::quiet_NaN();
  try {
    parse_scene(doc, dir_.string(), "code");
    FAIL() << "parsed";
  } catch (const SceneError& e) {
    EXPECT_STREQ(e.what(), "code: objects[2].mass_kg: must be finite, got nan");
  }
}

TEST_F(SceneLoaderTest, RejectsUnknownMaterialName) {
  json doc = valid();
  doc["objects"][1]["material"] = "steel";
  EXPECT_TRUE(fails_at(doc, "objects[1].material", "no material named 'steel' (defined: wood)"));
  doc["hands"][0]["material"] = "skin";
  doc["objects"][1]["material"] = "wood";
  EXPECT_TRUE(fails_at(doc, "hands[0].material", "no material named 'skin'"));
}

TEST_F(SceneLoaderTest, RejectsDuplicateOrBadName) {
  json doc = valid();
  doc["objects"][2]["name"] = "box";
  EXPECT_TRUE(fails_at(doc, "objects[2].name", "duplicate name 'box' (first used at objects[1].name)"));
  doc = valid();
  doc["hands"][0]["name"] = "lid";  // one namespace for objects, joints, hands and devices
  doc["devices"][0]["hand"] = "lid";
  EXPECT_TRUE(fails_at(doc, "hands[0].name", "duplicate name 'lid'"));
  doc = valid();
  doc["objects"][1]["name"] = "";
  EXPECT_TRUE(fails_at(doc, "objects[1].name", "must not be empty"));
  doc["objects"][1]["name"] = "my box";
  EXPECT_TRUE(fails_at(doc, "objects[1].name", "name 'my box' may only contain letters, digits"));
  doc["objects"][1]["name"] = "world";
  EXPECT_TRUE(fails_at(doc, "objects[1].name", "'world' is reserved"));
}

TEST_F(SceneLoaderTest, RejectsDuplicateKey) {
  // nlohmann alone would silently keep the second value.
  EXPECT_TRUE(fails_at(std::string(R"({"version": 1, "objects": [{"name": "a", "name": "b"}]})"), "objects[0].name",
                       "duplicate key"));
}

TEST_F(SceneLoaderTest, RejectsJointToUnknownBody) {
  json doc = valid();
  doc["joints"][0]["body_b"] = "ghost";
  EXPECT_TRUE(fails_at(doc, "joints[0].body_b", "no object named 'ghost'"));
  doc["joints"][0]["body_b"] = "lid";
  EXPECT_TRUE(fails_at(doc, "joints[0].body_b", "joins 'lid' to itself"));
  doc["joints"][0]["body_a"] = "world";
  EXPECT_TRUE(fails_at(doc, "joints[0].body_a", "must be an object"));
  doc = valid();
  doc["joints"][0]["body_a"] = "floor";
  doc["joints"][0]["body_b"] = "world";
  EXPECT_TRUE(fails_at(doc, "joints[0].body_b", "a joint needs at least one rigid body"));
  doc = valid();
  doc["joints"][0]["type"] = "ball";
  EXPECT_TRUE(fails_at(doc, "joints[0].axis", "only hinge and slider joints have an axis"));
  doc = valid();
  doc["joints"][0]["limits"] = {1, -1};
  EXPECT_TRUE(fails_at(doc, "joints[0].limits", "lo must be <= hi, got [1, -1]"));
}

TEST_F(SceneLoaderTest, RejectsDeviceToUnknownHand) {
  json doc = valid();
  doc["devices"][0]["hand"] = "left_hand";
  EXPECT_TRUE(fails_at(doc, "devices[0].hand", "no hand named 'left_hand'"));
}

TEST_F(SceneLoaderTest, RejectsTwoDevicesOnOneHand) {
  json doc = valid();
  doc["devices"].push_back({{"name", "glove"}, {"kind", "glove"}, {"hand", "hand"}});
  EXPECT_TRUE(fails_at(doc, "devices[1].hand", "hand 'hand' is already driven by devices[0]"));
}

TEST_F(SceneLoaderTest, RejectsFingerOutputsWhereThereAreNoFingers) {
  json doc = valid();
  doc["devices"][0]["force_output"] = "finger_lines";
  EXPECT_TRUE(fails_at(doc, "devices[0].force_output", "only a glove has finger outputs"));
  doc["devices"][0]["kind"] = "glove";
  EXPECT_TRUE(fails_at(doc, "devices[0].force_output", "finger_lines needs the hand's handles to be fingertips"));
  doc["hands"][0]["handles"] = "fingertips";
  EXPECT_NO_THROW(parse(doc));
  doc["devices"][0]["force_output"] = "cables";
  EXPECT_TRUE(fails_at(doc, "devices[0].force_output", "unknown force output 'cables'"));
  doc["devices"][0]["force_output"] = "frames";
  doc["devices"][0]["actuator_line"] = {0, 0, 0};
  EXPECT_TRUE(fails_at(doc, "devices[0].actuator_line", "must be a non-zero vector"));
}

// A rigid hand (seeds 002 and 001) collides with rigid and static objects only: with a deformable object
// in the scene it is refused at its model, naming the object; the FEM hand takes it.
TEST_F(SceneLoaderTest, RefusesARigidHandInASceneWithADeformableObject) {
  json doc = valid();
  doc["objects"].push_back(
      json::parse(R"({"name": "cushion", "kind": "deformable", "shape": {"type": "box", "size": [0.1, 0.1, 0.05]}})"));
  EXPECT_NO_THROW(parse(doc.dump()));
  for (const char* model : {"spring", "contact_point"}) {
    doc["hands"][0]["model"] = model;
    EXPECT_TRUE(fails_at(doc, "hands[0].model",
                         std::string("the ") + model +
                             " hand does not touch deformable objects, and 'cushion' is one (use \"fem\", or make "
                             "it rigid)"))
        << model;
  }
}

TEST_F(SceneLoaderTest, TakesSeed002sGloveCoefficientsOnlyWhereTheyApply) {
  json doc = valid();
  doc["devices"][0]["kind"] = "glove";
  doc["hands"][0]["handles"] = "fingertips";
  doc["devices"][0]["feedback_a"] = {0, 0, 0, 1};
  EXPECT_TRUE(fails_at(doc, "devices[0].feedback_a", "feedback_a needs \"force_output\": \"finger_lines\""));
  doc["devices"][0]["force_output"] = "finger_lines";
  EXPECT_EQ(parse(doc).devices[0].feedback_a, (std::array<double, 4>{0, 0, 0, 1}));
  doc["devices"][0]["feedback_a"] = {0, 0, 0.5, 1};
  EXPECT_TRUE(fails_at(doc, "devices[0].feedback_a",
                       "the joint torques' coefficients a1..a3 need a hand with phalanx handles (a 16-frame glove)"));
  doc["hands"][0]["handles"] = "phalanges";
  EXPECT_EQ(parse(doc).devices[0].feedback_a, (std::array<double, 4>{0, 0, 0.5, 1}));
  doc["devices"][0]["feedback_a"] = {0, 0, 0.5};
  EXPECT_TRUE(
      fails_at(doc, "devices[0].feedback_a", "expected an array of 4 numbers (a1, a2, a3, a4), got 3 elements"));
  doc["devices"][0]["feedback_a"] = {0, -1, 0.5, 1};
  EXPECT_TRUE(fails_at(doc, "devices[0].feedback_a[1]", "must be in [0, 10], got -1"));
  doc["devices"][0]["feedback_a"] = "all";
  EXPECT_TRUE(fails_at(doc, "devices[0].feedback_a", "expected an array of 4 numbers (a1, a2, a3, a4), got string"));
}

TEST_F(SceneLoaderTest, RejectsMissingMeshFile) {
  json doc = valid();
  doc["objects"][1]["shape"] = {{"type", "mesh"}, {"file", "assets/missing.obj"}};
  EXPECT_TRUE(fails_at(doc, "objects[1].shape.file", "cannot open '" + (dir_ / "assets/missing.obj").string() + "'"));
  doc["objects"][1]["shape"]["file"] = "assets/folder.obj";
  EXPECT_TRUE(
      fails_at(doc, "objects[1].shape.file", "'" + (dir_ / "assets/folder.obj").string() + "' is not a regular file"));
  doc["objects"][1]["shape"]["file"] = "assets/tiny.stl";
  EXPECT_TRUE(fails_at(doc, "objects[1].shape.file", "expected a .obj file"));
  doc["objects"][1]["kind"] = "deformable";
  doc["objects"][1]["shape"] = {{"type", "tet_mesh"}, {"file", "assets/lonely.node"}};
  EXPECT_TRUE(fails_at(doc, "objects[1].shape.file", "cannot open '" + (dir_ / "assets/lonely.ele").string() + "'"));
  doc["objects"][1]["shape"] = {
      {"type", "tet_mesh"}, {"file", "assets/tiny.node"}, {"surface", "assets/tiny.obj"}, {"embedding", "nope.embed"}};
  EXPECT_TRUE(fails_at(doc, "objects[1].shape.embedding", "cannot open"));
  doc["objects"][1]["shape"]["surface"] = "assets/tiny.node";
  EXPECT_TRUE(fails_at(doc, "objects[1].shape.surface", "expected a .obj file"));
}

TEST_F(SceneLoaderTest, SurfaceAndEmbeddingComeTogether) {
  json doc = valid();
  doc["objects"][1]["kind"] = "deformable";
  doc["objects"][1]["shape"] = {{"type", "tet_mesh"}, {"file", "assets/tiny.node"}, {"embedding", "assets/tiny.embed"}};
  EXPECT_TRUE(fails_at(doc, "objects[1].shape.embedding", "needs \"surface\" (the OBJ surface it embeds)"));
  doc["objects"][1]["shape"] = {{"type", "tet_mesh"}, {"file", "assets/tiny.node"}, {"surface", "assets/tiny.obj"}};
  EXPECT_TRUE(fails_at(doc, "objects[1].shape.surface", "needs \"embedding\""));
  doc["objects"][1]["shape"] = {{"type", "box"}, {"size", {0.1, 0.1, 0.1}}, {"surface", "assets/tiny.obj"}};
  EXPECT_TRUE(fails_at(doc, "objects[1].shape.surface", "unknown key for a box"));
}

TEST_F(SceneLoaderTest, RejectsBadVersion) {
  EXPECT_TRUE(fails_at(std::string(R"({"version": 2, "future_key": 1})"), "version", "unsupported version 2"));
  EXPECT_TRUE(fails_at(std::string(R"({"version": "1"})"), "version", "expected an integer, got string"));
  EXPECT_TRUE(fails_at(std::string(R"({"name": "x"})"), "version", "missing required key"));
}

TEST_F(SceneLoaderTest, ReportsSyntaxErrorLineAndColumn) {
  const std::string text = "{\n  \"version\": 1,\n  \"objects\": [}\n}\n";  // '}' at line 3, column 15
  try {
    parse(text);
    FAIL() << "parsed";
  } catch (const SceneError& e) {
    EXPECT_EQ(e.line(), 3);
    EXPECT_EQ(e.column(), 15);
    EXPECT_NE(std::string(e.what()).find("test.json:3:15: objects[0]: syntax error"), std::string::npos) << e.what();
  }
  // The same position nlohmann reports itself, on a few shapes of broken text.
  for (const std::string broken : {"{\"a\": tru }", "{\n\t\"version\": 1,\n\t\"name\": \"h\u00e9\" x}",
                                   "{\"version\": 1,\n\n  \"objects\": [1, 2,]}"}) {
    int nlohmann_line = 0, nlohmann_column = 0;
    try {
      [[maybe_unused]] const json parsed = json::parse(broken);
    } catch (const json::parse_error& e) {
      const std::string what = e.what();
      ASSERT_EQ(std::sscanf(what.c_str() + what.find("line"), "line %d, column %d", &nlohmann_line, &nlohmann_column),
                2)
          << what;
    }
    try {
      parse(broken);
      ADD_FAILURE() << "parsed " << broken;
    } catch (const SceneError& e) {
      EXPECT_EQ(e.line(), nlohmann_line) << broken << " -> " << e.what();
      EXPECT_EQ(e.column(), nlohmann_column) << broken << " -> " << e.what();
    }
  }
  // Where the offending byte is a newline nlohmann says (next line, column 0); the byte is on this line.
  try {
    parse(std::string("{\"v\": \"unterminated\n}"));
    FAIL() << "parsed";
  } catch (const SceneError& e) {
    EXPECT_EQ(e.line(), 1);
    EXPECT_EQ(e.column(), 20);
  }
  try {
    parse(std::string(""));
    FAIL() << "parsed";
  } catch (const SceneError& e) {
    EXPECT_EQ(e.line(), 1);
    EXPECT_NE(std::string(e.what()).find("unexpected end of input"), std::string::npos) << e.what();
  }
}

// Every range rule, one row each: {path to set, value, expected key path, expected problem}.
TEST_F(SceneLoaderTest, RejectsOutOfRangeValues) {
  struct Row {
    json::json_pointer where;
    json value;
    std::string key_path, problem;
  };
  const std::vector<Row> rows = {
      {json::json_pointer("/materials/wood/poisson_ratio"), 0.5, "materials.wood.poisson_ratio",
       "must be in [-0.9, 0.49], got 0.5"},
      {json::json_pointer("/materials/wood/youngs_modulus_pa"), 0, "materials.wood.youngs_modulus_pa",
       "must be in [100, 1e+09], got 0"},
      {json::json_pointer("/materials/wood/density_kg_m3"), -1, "materials.wood.density_kg_m3",
       "must be in [1, 25000], got -1"},
      {json::json_pointer("/materials/wood/rayleigh_beta_s"), -1, "materials.wood.rayleigh_beta_s",
       "must be in [0, 1], got -1"},
      {json::json_pointer("/visual_rate_hz"), 0, "visual_rate_hz", "must be in [10, 1000], got 0"},
      {json::json_pointer("/visual_rate_hz"), 5, "visual_rate_hz", "must be in [10, 1000], got 5"},
      {json::json_pointer("/dt_s"), 0.2, "dt_s", "must be in [1e-04, 0.1], got 0.2"},
      {json::json_pointer("/dt_s"), 0, "dt_s", "must be in [1e-04, 0.1], got 0"},
      {json::json_pointer("/contact"), "soft", "contact",
       "unknown contact model 'soft' (expected constraint, penalty)"},
      {json::json_pointer("/hands/0/resolution_tets"), 10, "hands[0].resolution_tets", "must be in [100, 20000]"},
      {json::json_pointer("/hands/0/resolution_tets"), 18446744073709551615ull, "hands[0].resolution_tets",
       "must be in [100, 20000], got 18446744073709551615"},
      {json::json_pointer("/hands/0/coupling_stiffness_n_m"), 0, "hands[0].coupling_stiffness_n_m",
       "must be in [1, 1e+06], got 0"},
      {json::json_pointer("/hands/0/model"), "robot", "hands[0].model", "unknown hand model 'robot'"},
      {json::json_pointer("/devices/0/workspace"), {{"scale", 0}}, "devices[0].workspace.scale",
       "must be in [0.01, 100], got 0"},
      {json::json_pointer("/devices/0/max_force_n"), 0, "devices[0].max_force_n", "must be in [0.01, 10000], got 0"},
      {json::json_pointer("/devices/0/max_torque_nm"), -1, "devices[0].max_torque_nm",
       "must be in [0.001, 1000], got -1"},
      {json::json_pointer("/devices/0/max_force_rate_n_s"), 0, "devices[0].max_force_rate_n_s",
       "must be in [1, 1e+07], got 0"},
      {json::json_pointer("/devices/0/stiffness_n_m"), 0, "devices[0].stiffness_n_m", "must be in [1, 1e+05], got 0"},
  };
  for (const Row& row : rows) {
    json doc = valid();
    doc[row.where] = row.value;
    EXPECT_TRUE(fails_at(doc, row.key_path, row.problem)) << row.where.to_string();
  }
}

TEST_F(SceneLoaderTest, RejectsHostileJson) {
  try {
    parse(std::string(20000, '['));
    FAIL() << "parsed";
  } catch (const SceneError& e) {
    EXPECT_NE(std::string(e.what()).find("nested deeper than 64 levels"), std::string::npos) << e.what();
  }
  EXPECT_THROW(parse(std::string("{\"version\": 1} trailing")), SceneError);
  EXPECT_THROW(parse(std::string("{\"version\": 1 /* comment */}")), SceneError);
  EXPECT_THROW(parse(std::string("{\"version\": 1, \"name\": \"\xff\"}")), SceneError);  // invalid UTF-8
}

TEST_F(SceneLoaderTest, LoadSceneReportsUnreadableFiles) {
  try {
    load_scene((dir_ / "no_such_scene.json").string());
    FAIL() << "loaded";
  } catch (const SceneError& e) {
    EXPECT_EQ(std::string(e.what()), (dir_ / "no_such_scene.json").string() + ": cannot open");
  }
  EXPECT_THROW(load_scene(dir_.string()), SceneError);
  // Relative asset paths resolve against the scene file's directory, not the working directory.
  std::ofstream(dir_ / "rock.json") << R"({"version": 1, "objects": [
    {"name": "rock", "kind": "static", "shape": {"type": "mesh", "file": "assets/tiny.obj", "scale": 2}}]})";
  const SceneDesc scene = load_scene((dir_ / "rock.json").string());
  EXPECT_EQ(scene.name, "rock");
  EXPECT_EQ(scene.objects[0].shape.file, (dir_ / "assets/tiny.obj").lexically_normal().string());
  EXPECT_EQ(scene.objects[0].shape.scale, 2.0);
}

// The user-found bug: a device limit beyond what the Welcome's float32 may carry loaded, and then the
// encoder refused every Welcome, so every Hello went unanswered. The bounds are the wire's constants.
TEST_F(SceneLoaderTest, RejectsDeviceLimitsTheWireCannotCarry) {
  const double inf = std::numeric_limits<double>::infinity();
  json doc = valid();
  doc["devices"][0]["max_force_n"] = 2.0 * protocol::kMaxForceN;
  EXPECT_TRUE(fails_at(doc, "devices[0].max_force_n", "must be in [0.01, 10000], got 20000"));
  doc["devices"][0]["max_force_n"] = std::nextafter(static_cast<double>(protocol::kMaxForceN), inf);
  EXPECT_TRUE(fails_at(doc, "devices[0].max_force_n", "must be in [0.01, 10000], got 10000.000000000002"));
  doc["devices"][0]["max_force_n"] = 1e-50;  // 0 as a float32: the Welcome wants > 0
  EXPECT_TRUE(fails_at(doc, "devices[0].max_force_n", "must be in [0.01, 10000], got 1e-50"));
  doc["devices"][0]["max_force_n"] = static_cast<double>(protocol::kMaxForceN);
  EXPECT_EQ(parse(doc).devices[0].max_force_n, protocol::kMaxForceN);

  doc = valid();
  doc["devices"][0]["max_torque_nm"] = 1e30;
  EXPECT_TRUE(fails_at(doc, "devices[0].max_torque_nm", "must be in [0.001, 1000], got 1e+30"));
  doc = valid();
  doc["devices"][0]["max_force_rate_n_s"] = 1e39;  // infinite as a float32
  EXPECT_TRUE(fails_at(doc, "devices[0].max_force_rate_n_s", "must be in [1, 1e+07], got 1e+39"));
}

TEST_F(SceneLoaderTest, RejectsAbsurdMasses) {
  json doc = valid();
  for (const double mass_kg : {1e-300, -0.0, 1e300, 1000.5}) {
    doc["objects"][2]["mass_kg"] = mass_kg;
    EXPECT_TRUE(fails_at(doc, "objects[2].mass_kg", "must be in [1e-04, 1000], got ")) << mass_kg;
  }
  // A mass from the density and the shape's volume is bounded as a given one is.
  doc = valid();
  doc["objects"][1]["shape"]["size"] = {100, 100, 100};
  EXPECT_TRUE(fails_at(doc, "objects[1]",
                       "its mass (density 700 kg/m^3 x volume 1e+06 m^3 = 7e+08 kg) must be in [1e-04, 1000] kg"));
  doc["objects"][1]["shape"]["size"] = {0.001, 0.001, 0.001};
  EXPECT_TRUE(fails_at(doc, "objects[1]", "its mass (density 700 kg/m^3 x volume 1e-09 m^3"));
  doc["objects"][1]["mass_kg"] = 0.001;  // a given mass instead: fine
  doc["objects"][1]["material"] = "wood";
  EXPECT_NO_THROW(parse(doc));
}

TEST_F(SceneLoaderTest, RejectsAbsurdTimeStepsRatesAndGravity) {
  const std::vector<std::tuple<const char*, json, std::string, std::string>> rows = {
      {"/dt_s", 1e-9, "dt_s", "must be in [1e-04, 0.1], got 1e-09"},
      {"/dt_s", 1e9, "dt_s", "must be in [1e-04, 0.1], got 1e+09"},
      {"/visual_rate_hz", 1e9, "visual_rate_hz", "must be in [10, 1000], got 1e+09"},
      {"/gravity", {0, 0, -1e6}, "gravity[2]", "must be in [-100, 100], got -1e+06"},
  };
  for (const auto& [where, value, key_path, problem] : rows) {
    json doc = valid();
    doc[json::json_pointer(where)] = value;
    EXPECT_TRUE(fails_at(doc, key_path, problem)) << where;
  }
}

TEST_F(SceneLoaderTest, RejectsAbsurdResolution) {
  json doc = valid();
  doc["hands"][0]["resolution_tets"] = 1'000'000;  // minutes to build and gigabytes to factor
  EXPECT_TRUE(fails_at(doc, "hands[0].resolution_tets", "must be in [100, 20000], got 1000000"));
  doc["hands"][0]["resolution_tets"] = kMaxHandTets + 1;
  EXPECT_TRUE(fails_at(doc, "hands[0].resolution_tets", "must be in [100, 20000], got 20001"));
  doc["hands"][0]["resolution_tets"] = kMaxHandTets;
  EXPECT_EQ(parse(doc).hands[0].resolution_tets, kMaxHandTets);
}

TEST_F(SceneLoaderTest, RejectsPositionsSpeedsAndLimitsBeyondTheWorldsBounds) {
  json doc = valid();
  doc["objects"][1]["pose"] = {{"position", {0, 0, 1e9}}};
  EXPECT_TRUE(fails_at(doc, "objects[1].pose.position", "length must be <= 1000 m, got 1e+09"));
  doc = valid();
  doc["objects"][1]["linear_velocity"] = {1000, 0, 0};
  EXPECT_TRUE(fails_at(doc, "objects[1].linear_velocity", "length must be <= 50 m/s, got 1000"));
  doc = valid();
  doc["objects"][1]["angular_velocity"] = {0, 0, 1e6};
  EXPECT_TRUE(fails_at(doc, "objects[1].angular_velocity", "length must be <= 1000 rad/s, got 1e+06"));
  doc = valid();
  doc["joints"][0]["limits"] = {-4, 1};  // ODE's hinge stops lie in [-pi, pi]
  EXPECT_TRUE(fails_at(doc, "joints[0].limits[0]", "must be in [-3.141592653589793, 3.141592653589793], got -4"));
  doc = valid();
  doc["devices"][0]["workspace"] = {{"offset", {0, 0, -2000}}};
  EXPECT_TRUE(fails_at(doc, "devices[0].workspace.offset", "length must be <= 1000 m, got 2000"));
  doc = valid();
  doc["objects"][0]["shape"]["offset"] = 1e5;
  EXPECT_TRUE(fails_at(doc, "objects[0].shape.offset", "must be in [-1000, 1000], got 1e+05"));
}

bool world_is_finite(const World& world) {
  const WorldSnapshot& s = world.snapshot();
  for (const auto& hand : s.handles)
    for (const hand::HandleState& h : hand)
      if (!h.p_WH.allFinite() || !h.q_WH.coeffs().allFinite() || !h.v_WH.allFinite() || !h.w_WH.allFinite())
        return false;
  for (const RigidBodyState& b : s.bodies)
    if (!b.p_WO.allFinite() || !b.q_WO.coeffs().allFinite() || !b.v_WO.allFinite() || !b.w_W.allFinite())
      return false;
  for (const DeformableSnapshot& d : s.deformables)
    for (const Eigen::Vector3d& x : d.nodes_W)
      if (!x.allFinite()) return false;
  return true;
}

// The independent check of the bounds: every value at the top of its range (the second hand and its
// stylus at the bottom; the floor at the bottom of its range) loads, builds a World that steps with finite results, and each device's
// link gives a Welcome the protocol's encoder accepts.
TEST_F(SceneLoaderTest, SceneAtTheEdgeOfEveryRangeBuildsStepsAndServes) {
  const std::string assets = (kScenes / "assets").string();
  json doc = json::parse(R"({
    "version": 1,
    "gravity": [100, 100, 100], "visual_rate_hz": 1000, "dt_s": 0.1, "contact": "constraint",
    "materials": {"edge": {"youngs_modulus_pa": 1e9, "poisson_ratio": 0.49, "density_kg_m3": 25000, "friction": 10,
                           "friction_static": 10, "restitution": 1, "rayleigh_alpha_per_s": 1000,
                           "rayleigh_beta_s": 1}},
    "objects": [
      {"name": "floor", "kind": "static", "shape": {"type": "plane", "normal": [0, 0, 1], "offset": -1000}},
      {"name": "wall", "kind": "static", "shape": {"type": "box", "size": [100, 100, 100]},
       "pose": {"position": [1000, 0, 0]}, "material": "edge"},
      {"name": "box", "kind": "rigid", "shape": {"type": "box", "size": [100, 100, 100]}, "mass_kg": 1000,
       "material": "edge", "pose": {"position": [0, 0, -1000]}, "linear_velocity": [50, 0, 0],
       "angular_velocity": [0, 0, 1000]},
      {"name": "ball", "kind": "rigid", "shape": {"type": "sphere", "radius": 100}, "mass_kg": 1000, "material": "edge"},
      {"name": "pill", "kind": "rigid", "shape": {"type": "capsule", "radius": 100, "length": 100}, "mass_kg": 1000},
      {"name": "drum", "kind": "rigid", "shape": {"type": "cylinder", "radius": 100, "length": 100}, "mass_kg": 1000},
      {"name": "jelly", "kind": "deformable", "shape": {"type": "box", "size": [1, 1, 1]}, "mass_kg": 1000,
       "material": "edge", "linear_velocity": [0, 50, 0], "angular_velocity": [1000, 0, 0]}
    ],
    "joints": [
      {"name": "hinge", "type": "hinge", "body_a": "box", "body_b": "world", "anchor": [0, 0, -1000],
       "axis": [0, 0, 1], "limits": [-3.141592653589793, 3.141592653589793]},
      {"name": "slider", "type": "slider", "body_a": "drum", "body_b": "world", "axis": [1, 0, 0],
       "limits": [-1000, 1000]}
    ],
    "hands": [
      {"name": "big", "resolution_tets": 20000, "handles": "phalanges", "material": "edge",
       "coupling_stiffness_n_m": 1e6, "coupling_damping_ns_m": 1000, "pose": {"position": [0, 1000, 0]}},
      {"name": "small", "resolution_tets": 100, "coupling_stiffness_n_m": 1, "coupling_damping_ns_m": 0}
    ],
    "devices": [
      {"name": "glove", "kind": "glove", "hand": "big",
       "workspace": {"scale": 100, "offset": [0, 0, 1000]}, "stiffness_n_m": 1e5},
      {"name": "stylus", "kind": "stylus", "hand": "small", "workspace": {"scale": 0.01}, "max_force_n": 0.01,
       "max_torque_nm": 0.001, "max_force_rate_n_s": 1, "stiffness_n_m": 1}
    ]
  })");
  // The file-given shapes at their largest scale (absolute paths: the shipped assets).
  doc["objects"].push_back({{"name", "statue"}, {"kind", "static"},
                            {"shape", {{"type", "mesh"}, {"file", assets + "/bunny.obj"}, {"scale", 100}}},
                            {"pose", {{"position", {0, -1000, 0}}}}});
  doc["objects"].push_back({{"name", "soft_bunny"}, {"kind", "deformable"}, {"mass_kg", 1000}, {"material", "edge"},
                            {"shape", {{"type", "tet_mesh"}, {"file", assets + "/bunny_271.node"}, {"scale", 100},
                                       {"surface", assets + "/bunny.obj"}, {"embedding", assets + "/bunny_271.embed"}}}});
  // The device limits at the wire's own.
  doc["devices"][0]["max_force_n"] = static_cast<double>(protocol::kMaxForceN);
  doc["devices"][0]["max_torque_nm"] = static_cast<double>(protocol::kMaxTorqueNm);
  doc["devices"][0]["max_force_rate_n_s"] = static_cast<double>(protocol::kMaxForceRateNPerS);

  const SceneDesc scene = parse(doc);
  // The server's contact model (penalty, WorldOptions' default), then the scene's (constraint): bodies
  // inside the 100 m ball make thousands of rows, and a step solves the deepest kMaxStepContacts of them.
  for (const std::optional<ContactModel> contact : {std::optional<ContactModel>(ContactModel::penalty),
                                                    std::optional<ContactModel>()}) {
    WorldOptions options;
    options.contact = contact;
    World world(scene, options);
    ASSERT_TRUE(world_is_finite(world));
    for (int k = 0; k < 3; ++k) {
      world.step();
      ASSERT_TRUE(world_is_finite(world)) << "step " << k + 1;
    }
    protocol::Encoder encoder;
    for (const DeviceDesc& d : scene.devices) {
      const haptic::DeviceLink link = haptic::make_device_link(world, d, 1000.0);
      // As HapticCore's handshake fills it.
      std::uint16_t ids[haptic::kMaxHapticHandles];
      for (int j = 0; j < link.handles; ++j) ids[j] = static_cast<std::uint16_t>(j);
      protocol::Welcome w;
      haptic::fill_welcome(link, 1, 1000, {ids, static_cast<std::size_t>(link.handles)}, w);
      const protocol::EncodeResult r = encoder.encode(w);
      EXPECT_TRUE(r.ok()) << d.name << ": " << protocol::to_string(r.reason);
    }
  }
}

}  // namespace
}  // namespace hapticd::world
