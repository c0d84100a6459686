// A free deformable object: the hand's FEM body with zero handles
// (HandConfig::free_body). Every solver must handle m = 0 (eq. 7 reduces to
// A_t v_t = b_t, plus any implicit contact bodies), free fall must be exact,
// external forces must enter as impulses, and a divergence must reset the body
// where it was instead of at a handle target it does not have.
#include <gtest/gtest.h>

#include <cmath>
#include <limits>

#include "hand_models/box_mesh.hpp"
#include "hand_models/coupled_solver.hpp"
#include "hand_models/hand_model.hpp"

namespace hapticd::hand {
namespace {

constexpr SolverKind kAllSolvers[] = {SolverKind::monolithic, SolverKind::schur_cg, SolverKind::schur_cholmod,
                                      SolverKind::schur_lagged};

// A 4 cm cube of soft material, 3 x 3 x 3 cells (162 tets), bottom face on z = 0.
HandModel free_cube(HandConfig config = {}) {
  config.free_body = true;
  config.handles.clear();
  return HandModel(make_box_mesh({0.04, 0.04, 0.04}, {3, 3, 3}, Eigen::Vector3d(-0.02, -0.02, 0)), config);
}

double total_mass(const HandModel& model) { return model.fem().lumped_mass().sum(); }

TEST(FreeBody, ValidationAsksForHandlesExactlyWhenTheBodyIsAHand) {
  HandConfig config;
  config.free_body = true;
  EXPECT_NO_THROW(validate(config));
  config.handles.push_back({"palm", Eigen::Vector3d::Zero(), 0.01, {}});
  try {
    validate(config);
    FAIL() << "a free body with a handle was accepted";
  } catch (const std::invalid_argument& e) {
    EXPECT_STREQ(e.what(), "handles: a free body has no handles");
  }
  config = HandConfig{};
  try {
    validate(config);
    FAIL() << "a hand without handles was accepted";
  } catch (const std::invalid_argument& e) {
    EXPECT_STREQ(e.what(), "handles: a hand needs at least one handle");
  }
}

TEST(FreeBody, RestStateHasNoHandleDofs) {
  const HandModel model = free_cube();
  const HandState state = make_rest_state(model);
  EXPECT_EQ(model.num_handles(), 0);
  EXPECT_TRUE(state.handles.empty());
  EXPECT_EQ(state.system.A_th.cols(), 0);
  EXPECT_EQ(state.f_ext.size(), 3 * model.num_nodes());
  EXPECT_EQ(state.f_ext.norm(), 0.0);
}

// Without mass damping nothing resists a uniform translation: every solver
// reproduces v = g t exactly and the cube does not deform.
TEST(FreeBody, FreeFallIsExactWithEverySolver) {
  HandConfig config;
  config.material.rayleigh_alpha_per_s = 0;  // mass damping would also damp the fall (a drag g / alpha)
  const HandModel model = free_cube(config);
  for (SolverKind kind : kAllSolvers) {
    HandState state = make_rest_state(model);
    auto solver = make_solver(kind);
    const int steps = 30;
    for (int k = 0; k < steps; ++k) ASSERT_EQ(step(model, state, *solver), StepStatus::ok) << to_string(kind);
    const double t = steps * config.dt_s;
    const Eigen::Vector3d expected_p = total_mass(model) * t * config.gravity_m_s2;
    // 1e-9 relative: CG's per-solve tolerance 1e-10 over 30 steps (the direct solvers reach rounding).
    EXPECT_LT((linear_momentum(model, state) - expected_p).norm(), 1e-9 * expected_p.norm()) << to_string(kind);
    // Implicit Euler displacement of a uniformly accelerated body: g h^2 k (k + 1) / 2.
    const Eigen::Vector3d drop = config.gravity_m_s2 * config.dt_s * config.dt_s * steps * (steps + 1) / 2;
    double worst = 0;
    for (int i = 0; i < model.num_nodes(); ++i)
      worst = std::max(worst, (state.x.segment<3>(3 * i) - model.mesh().X[i] - drop).norm());
    EXPECT_LT(worst, 1e-9 * drop.norm()) << to_string(kind);
  }
}

TEST(FreeBody, ExternalForcesAddTheirImpulseExactly) {
  HandConfig config;
  config.material.rayleigh_alpha_per_s = 0;
  config.gravity_m_s2.setZero();
  const HandModel model = free_cube(config);
  HandState state = make_rest_state(model);
  auto solver = make_solver(SolverKind::schur_cholmod);
  // 1 N along x on one corner node: the total impulse is 1 N x h per step, whatever the body does with it.
  state.f_ext[0] = 1.0;
  for (int k = 0; k < 10; ++k) ASSERT_EQ(step(model, state, *solver), StepStatus::ok);
  const Eigen::Vector3d p = linear_momentum(model, state);
  EXPECT_NEAR(p.x(), 10 * config.dt_s, 1e-12);
  EXPECT_NEAR(p.y(), 0, 1e-12);
  EXPECT_NEAR(p.z(), 0, 1e-12);
  // A non-finite external force is dropped, not assembled.
  state.f_ext[1] = std::numeric_limits<double>::quiet_NaN();
  ASSERT_EQ(step(model, state, *solver), StepStatus::ok);
  EXPECT_TRUE(state.x.allFinite());
  EXPECT_EQ(state.resets, 0);
}

// The cube lands on a penalty floor while a rigid body, solved implicitly with
// it, is pressed onto its top by constraint contacts: every solver follows the
// monolithic reference step for step.
TEST(FreeBody, EverySolverFollowsTheMonolithicReferenceWithContactsAndABody) {
  HandConfig config;
  config.floor.enabled = true;
  config.floor.height_m = 0.002;  // the bottom nodes start 2 mm inside
  config.floor.stiffness_n_m = 500;
  config.floor.friction = 0.5;
  const HandModel model = free_cube(config);
  auto run = [&](SolverKind kind) {
    HandState state = make_rest_state(model);
    auto solver = make_solver(kind);
    for (int k = 0; k < 20; ++k) {
      ContactBody body;
      body.gravity_W = config.gravity_m_s2;  // as weightless as the cube
      body.mass_kg = 0.05;
      body.inertia_W = 1e-5 * Eigen::Matrix3d::Identity();
      body.p_com_W = Eigen::Vector3d(0, 0, 0.05);
      body.v_W = Eigen::Vector3d(0.01, 0, -0.1);
      state.bodies = {body};
      state.contacts.clear();
      for (int i = 0; i < model.num_nodes(); ++i) {
        if (model.mesh().X[i].z() < 0.04 - 1e-9 || std::abs(model.mesh().X[i].x()) > 0.015) continue;
        PointContact c;
        const auto [tet, local] = model.node_tet(i);
        c.tet = tet;
        c.bary = Eigen::Vector4d::Unit(local);
        c.n_W = -Eigen::Vector3d::UnitZ();  // out of the body, down into the cube
        c.depth_m = 0.04 + 0.0005 - state.x[3 * i + 2];
        c.friction = 0.3;
        c.body = 0;
        c.constraint = true;
        state.contacts.push_back(c);
      }
      if (step(model, state, *solver) != StepStatus::ok) ADD_FAILURE() << to_string(kind) << " step " << k;
    }
    return state;
  };
  const HandState reference = run(SolverKind::monolithic);
  EXPECT_GT(reference.floor_contacts, 0);
  EXPECT_GT(reference.held.rows(), 0);  // the body's contacts pushed
  for (SolverKind kind : {SolverKind::schur_cg, SolverKind::schur_cholmod, SolverKind::schur_lagged}) {
    const HandState s = run(kind);
    // 1e-7 relative: Gauss-Seidel stops at 1e-8 on each step's contact problem, CG at 1e-10.
    EXPECT_LT((s.x - reference.x).norm(), 1e-7 * reference.x.norm()) << to_string(kind);
    EXPECT_LT((s.v - reference.v).norm(), 1e-7 * reference.v.norm() + 1e-9) << to_string(kind);
    EXPECT_EQ(s.resets, 0) << to_string(kind);
  }
}

TEST(FreeBody, ANonFiniteStateResetsTheBodyWhereItWasAtRest) {
  const HandModel model = free_cube();
  HandState state = make_rest_state(model);
  auto solver = make_solver(SolverKind::schur_cholmod);
  // Moved and turned rigidly, then a NaN velocity: the reset keeps the pose and stops the body.
  const Eigen::Matrix3d R = Eigen::AngleAxisd(0.7, Eigen::Vector3d(1, 2, 3).normalized()).toRotationMatrix();
  const Eigen::Vector3d p(0.3, -0.2, 0.5);
  for (int i = 0; i < model.num_nodes(); ++i) state.x.segment<3>(3 * i) = p + R * model.mesh().X[i];
  const Eigen::VectorXd placed = state.x;
  state.v[4] = std::numeric_limits<double>::quiet_NaN();
  EXPECT_NE(step(model, state, *solver), StepStatus::ok);
  EXPECT_EQ(state.resets, 1);
  EXPECT_EQ(state.v.norm(), 0.0);
  // 1e-12 m: the rigid fit of an undeformed shape is exact to rounding.
  EXPECT_LT((state.x - placed).cwiseAbs().maxCoeff(), 1e-12);
  EXPECT_EQ(step(model, state, *solver), StepStatus::ok);  // and it steps on
}

}  // namespace
}  // namespace hapticd::hand
