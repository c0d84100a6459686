// The coupled implicit step (seed 004 eq. 7): Schur + CG and Schur + CHOLMOD
// against the monolithic reference, conservation and convergence in dt.
#include <gtest/gtest.h>

#include "hand_models/press_scenario.hpp"
#include "hand_test_util.hpp"

namespace hapticd::hand {
namespace {

using testing_util::offset_target;
using testing_util::relative_difference;
using testing_util::slab_hand;

class SolverAgreement : public ::testing::TestWithParam<int> {};

TEST_P(SolverAgreement, SchurCgAndSchurCholmodEqualTheMonolithicSolve) {
  const int m = GetParam();
  HandConfig config;
  config.floor.enabled = true;
  config.floor.height_m = -0.002;
  const HandModel model = slab_hand(m, config);
  ASSERT_EQ(model.num_handles(), m);
  HandState state = make_rest_state(model);
  auto mono = make_solver(SolverKind::monolithic);
  SolverOptions cg_options;
  cg_options.cg_tolerance = 1e-10;
  auto cg = make_solver(SolverKind::schur_cg, cg_options);
  auto chol = make_solver(SolverKind::schur_cholmod);
  auto lagged = make_solver(SolverKind::schur_lagged);
  double worst_cg = 0, worst_chol = 0, worst_lagged = 0;
  long lagged_iterations = 0;
  for (int k = 0; k < 12; ++k) {
    // Press down, push sideways and twist, differently per handle, so handles strain the flesh between them.
    for (int j = 0; j < m; ++j)
      set_target(state, j, offset_target(model, j, Eigen::Vector3d(0.002 * j / m, -0.001 * k, -0.0008 * k), 0.02 * k));
    assemble(model, state);
    Eigen::VectorXd v_h_ref, v_t_ref, v_h, v_t;
    SolveReport report;
    ASSERT_TRUE(mono->solve(state.system, v_h_ref, v_t_ref, report));
    ASSERT_TRUE(cg->solve(state.system, v_h, v_t, report));
    worst_cg = std::max(worst_cg, relative_difference(v_h, v_t, v_h_ref, v_t_ref));
    ASSERT_TRUE(chol->solve(state.system, v_h, v_t, report));
    worst_chol = std::max(worst_chol, relative_difference(v_h, v_t, v_h_ref, v_t_ref));
    SolveReport lagged_report;
    ASSERT_TRUE(lagged->solve(state.system, v_h, v_t, lagged_report));
    worst_lagged = std::max(worst_lagged, relative_difference(v_h, v_t, v_h_ref, v_t_ref));
    lagged_iterations += lagged_report.iterations;
    EXPECT_LT(relative_residual(state.system, v_h_ref, v_t_ref), 1e-12);
    ASSERT_EQ(step(model, state, *mono), StepStatus::ok);
  }
  EXPECT_GT(state.floor_contacts, 0);
  EXPECT_LT(worst_cg, 1e-8);
  EXPECT_LT(worst_chol, 1e-8);
  EXPECT_LT(worst_lagged, 1e-8);
  EXPECT_GT(lagged_iterations, 0);  // it did reuse an old factorization, not refactor every step
}

INSTANTIATE_TEST_SUITE_P(Handles, SolverAgreement, ::testing::Values(1, 2, 16));

TEST(CoupledStep, AllSolversAgreeOnTheProceduralHandPressedIntoTheFloor) {
  for (int handles : {1, 6}) {
    PressScenarioOptions options;
    options.target_tets = 350;
    options.handles = handles;
    options.press_time_s = 0.2;
    PressScenario scene = make_press_scenario(options);
    auto mono = make_solver(SolverKind::monolithic);
    std::vector<std::unique_ptr<CoupledSolver>> fast;
    for (SolverKind k : {SolverKind::schur_cg, SolverKind::schur_cholmod, SolverKind::schur_lagged})
      fast.push_back(make_solver(k));
    double worst = 0;
    for (int k = 0; k < 30; ++k) {
      scene.drive((k + 1) * scene.model->config().dt_s);
      ASSERT_EQ(step(*scene.model, scene.state, *mono), StepStatus::ok);
      for (auto& solver : fast) {
        Eigen::VectorXd v_h, v_t;
        SolveReport r;
        ASSERT_TRUE(solver->solve(scene.state.system, v_h, v_t, r)) << to_string(solver->kind());
        worst = std::max(worst, relative_difference(v_h, v_t, scene.state.v_h_next, scene.state.v_t_next));
      }
    }
    EXPECT_GE(scene.state.floor_contacts, 8) << "the hand is pressed into the floor";  // 350 tets: 142 nodes
    EXPECT_LT(worst, 1e-8) << handles << " handles";
  }
}

HandConfig free_floating() {
  HandConfig c;
  c.gravity_m_s2.setZero();
  c.drive = DriveParams{0, 0, 0, 0};
  c.material.rayleigh_alpha_per_s = 0;  // mass-proportional damping acts like drag on rigid motion
  return c;
}

TEST(CoupledStep, FreeFloatingHandAndHandlesConserveLinearMomentum) {
  const HandModel model = slab_hand(2, free_floating());
  for (SolverKind kind :
       {SolverKind::schur_cholmod, SolverKind::schur_lagged, SolverKind::schur_cg, SolverKind::monolithic}) {
    HandState state = make_rest_state(model);
    std::srand(11);
    state.v = 0.2 * Eigen::VectorXd::Random(state.v.size());
    state.handles[0].v_WH = Eigen::Vector3d(0.3, -0.1, 0.2);
    state.handles[1].w_WH = Eigen::Vector3d(0, 4.0, 6.0);
    const Eigen::Vector3d p0 = linear_momentum(model, state);
    auto solver = make_solver(kind);
    double worst = 0;
    for (int k = 0; k < 100; ++k) {
      ASSERT_EQ(step(model, state, *solver), StepStatus::ok);
      worst = std::max(worst, (linear_momentum(model, state) - p0).norm());
    }
    // Internal forces cancel exactly in eq. 7; what is left is the solver's own error.
    // (tolerances: rounding of ~1e4x larger internal forces over 100 steps; the
    // iterative solvers' residuals per step: CG 1e-10 per solve, GMRES 1e-12).
    const double tol = kind == SolverKind::schur_cg ? 1e-6 : kind == SolverKind::schur_lagged ? 1e-8 : 1e-10;
    EXPECT_LT(worst, tol * p0.norm()) << to_string(kind);
  }
}

TEST(CoupledStep, FreeFloatingHandLosesEnergyMonotonicallyToDamping) {
  const HandModel model = slab_hand(1, free_floating());
  HandState state = make_rest_state(model);
  std::srand(5);
  state.v = 0.3 * Eigen::VectorXd::Random(state.v.size());
  auto solver = make_solver(SolverKind::schur_cholmod);
  double previous = total_energy(model, state);
  for (int k = 0; k < 200; ++k) {
    ASSERT_EQ(step(model, state, *solver), StepStatus::ok);
    const double e = total_energy(model, state);
    EXPECT_LE(e, previous * (1 + 1e-9)) << "step " << k;
    previous = e;
  }
}

// Trajectory of a pressed, twisted slab over 0.2 s at a given step; returns node positions.
Eigen::VectorXd pressed_slab_positions(double dt) {
  HandConfig c;
  c.dt_s = dt;
  const HandModel model = slab_hand(1, c, {4, 4, 1});
  HandState state = make_rest_state(model);
  auto solver = make_solver(SolverKind::schur_cholmod);
  const int steps = static_cast<int>(std::lround(0.2 / dt));
  for (int k = 0; k < steps; ++k) {
    const double t = (k + 1) * dt;
    set_target(state, 0, offset_target(model, 0, Eigen::Vector3d(0.01 * t, 0, -0.02 * t), 2.0 * t));
    step(model, state, *solver);
  }
  return state.x;
}

TEST(CoupledStep, ImplicitEulerConvergesAtFirstOrderInTheTimeStep) {
  const Eigen::VectorXd reference = pressed_slab_positions(0.2 / 10240);
  const double e1 = (pressed_slab_positions(0.2 / 160) - reference).norm();
  const double e2 = (pressed_slab_positions(0.2 / 320) - reference).norm();
  const double e3 = (pressed_slab_positions(0.2 / 640) - reference).norm();
  std::printf("position error at dt/1, dt/2, dt/4: %.3e %.3e %.3e\n", e1, e2, e3);
  // First order: each halving of dt halves the error (ratio 2; the reference's own error shifts it a little).
  EXPECT_NEAR(e1 / e2, 2.0, 0.3);
  EXPECT_NEAR(e2 / e3, 2.0, 0.3);
}

}  // namespace
}  // namespace hapticd::hand
