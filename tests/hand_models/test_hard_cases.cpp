// Numerical stability on hard cases: stiff coupling at a large step, teleports,
// fast spin, inverted and flattened elements, near-incompressible flesh, long
// runs and NaN input. Failure must reset, never propagate.
#include <gtest/gtest.h>

#include <limits>

#include "hand_test_util.hpp"

namespace hapticd::hand {
namespace {

using testing_util::min_det_F;
using testing_util::offset_target;
using testing_util::slab_hand;

bool state_finite(const HandState& s) {
  bool ok = s.x.allFinite() && s.v.allFinite();
  for (const HandleState& h : s.handles) ok = ok && h.p_WH.allFinite() && h.q_WH.coeffs().allFinite();
  return ok;
}

class HardCasesPerSolver : public ::testing::TestWithParam<SolverKind> {};

TEST_P(HardCasesPerSolver, CouplingStiffness1e6AtDt30HzStaysStableAndTracksTheTarget) {
  HandConfig c;
  c.coupling.stiffness_n_m = 1e6;
  c.coupling.damping_ns_m = 10;
  c.dt_s = 1.0 / 30.0;
  c.floor.enabled = true;
  c.floor.height_m = -0.005;
  const HandModel model = slab_hand(1, c);
  HandState s = make_rest_state(model);
  auto solver = make_solver(GetParam());
  double max_energy = 0;
  for (int k = 0; k < 150; ++k) {
    const double t = k * c.dt_s;
    set_target(s, 0, offset_target(model, 0, Eigen::Vector3d(0.02 * std::sin(t), 0, -0.01 * std::min(t, 1.0)), 0.3 * t));
    ASSERT_EQ(step(model, s, *solver), StepStatus::ok) << "step " << k;
    max_energy = std::max(max_energy, total_energy(model, s) - total_energy(model, make_rest_state(model)));
  }
  EXPECT_TRUE(state_finite(s));
  EXPECT_EQ(s.resets, 0);
  // Handle within 5 mm of its target (drive spring vs the floor and the flesh's weight).
  EXPECT_LT((s.handles[0].p_WH - s.targets[0].p_W).norm(), 0.005);
  EXPECT_LT(max_energy, 1.0);  // J; the flesh holds millijoules when pressed
}

TEST_P(HardCasesPerSolver, HandleTeleported10cmInOneStepRecoversWithoutGainingEnergy) {
  HandConfig c;
  c.gravity_m_s2.setZero();
  const HandModel model = slab_hand(1, c);
  HandState s = make_rest_state(model);
  auto solver = make_solver(GetParam());
  for (int k = 0; k < 10; ++k) step(model, s, *solver);
  // Tracking glitch: handle and its target jump 10 cm; the flesh stays behind.
  s.handles[0].p_WH += Eigen::Vector3d(0.1, 0, 0);
  s.targets[0].p_W += Eigen::Vector3d(0.1, 0, 0);
  double energy = total_energy(model, s);
  const double e_teleport = energy;
  for (int k = 0; k < 120; ++k) {
    ASSERT_EQ(step(model, s, *solver), StepStatus::ok) << "step " << k;
    const double e = total_energy(model, s);
    EXPECT_LE(e, energy * (1 + 1e-6) + 1e-12 * e_teleport) << "energy grew at step " << k;  // rounding floor
    energy = e;
  }
  EXPECT_LT(energy, 1e-3 * e_teleport);  // two seconds later the hand has caught up and settled
  double centroid_x = 0;
  for (int i = 0; i < model.num_nodes(); ++i) centroid_x += s.x[3 * i] / model.num_nodes();
  EXPECT_NEAR(centroid_x, 0.1, 0.005);
  EXPECT_GT(min_det_F(model, s), 0.5);
}

TEST_P(HardCasesPerSolver, HandleSpunAt10RadPerSecondFollowsWithBoundedEnergy) {
  HandConfig c;
  c.gravity_m_s2.setZero();
  const HandModel model = slab_hand(1, c);
  HandState s = make_rest_state(model);
  auto solver = make_solver(GetParam());
  const double w = 10.0;
  double max_energy = 0;
  for (int k = 0; k < 240; ++k) {
    HandleTarget t = offset_target(model, 0, Eigen::Vector3d::Zero(), w * (k + 1) * c.dt_s);
    t.q_W = Eigen::AngleAxisd(w * (k + 1) * c.dt_s, Eigen::Vector3d(1, 1, 1).normalized()) * Eigen::Quaterniond::Identity();
    t.w_W = w * Eigen::Vector3d(1, 1, 1).normalized();
    set_target(s, 0, t);
    ASSERT_EQ(step(model, s, *solver), StepStatus::ok) << "step " << k;
    if (k > 60) max_energy = std::max(max_energy, total_energy(model, s));
  }
  EXPECT_TRUE(state_finite(s));
  // Rotational kinetic energy of the slab at 10 rad/s, ~ 1/2 I w^2 with I ~ m L^2 / 6 -> a few mJ.
  const double mass = model.fem().lumped_mass().sum();
  const double spin_energy = 0.5 * mass * 0.08 * 0.08 / 6 * w * w;
  EXPECT_LT(max_energy, 5 * spin_energy);
  EXPECT_GT(max_energy, 0.2 * spin_energy);  // it does spin
  EXPECT_LT(rotation_difference(s.handles[0].q_WH, s.targets[0].q_W).norm(), 0.3);
  EXPECT_GT(min_det_F(model, s), 0.3);
}

INSTANTIATE_TEST_SUITE_P(FastSolvers, HardCasesPerSolver,
                         ::testing::Values(SolverKind::schur_cholmod, SolverKind::schur_lagged),
                         [](const auto& p) { return std::string(to_string(p.param)); });

TEST(HardCases, InvertedAndFlattenedElementsRecoverTheirVolume) {
  HandConfig c;
  c.gravity_m_s2.setZero();
  const HandModel model = slab_hand(1, c);
  for (double squash : {0.0, -0.5}) {  // flattened to a plane; inverted through it
    HandState s = make_rest_state(model);
    for (int i = 0; i < model.num_nodes(); ++i)
      if (s.x[3 * i] < 0) s.x[3 * i + 2] *= squash;  // half the slab, away from the handle region
    ASSERT_LE(min_det_F(model, s), 1e-12);
    auto solver = make_solver(SolverKind::schur_cholmod);
    for (int k = 0; k < 120; ++k) ASSERT_EQ(step(model, s, *solver), StepStatus::ok) << "squash " << squash;
    EXPECT_GT(min_det_F(model, s), 0.7) << "squash " << squash;
    EXPECT_NEAR(total_volume(TetMesh{[&] {
                                       std::vector<Eigen::Vector3d> X(model.num_nodes());
                                       for (int i = 0; i < model.num_nodes(); ++i) X[i] = s.x.segment<3>(3 * i);
                                       return X;
                                     }(),
                                     model.mesh().tets, {}}),
                0.08 * 0.08 * 0.02, 0.02 * 0.08 * 0.08 * 0.02)
        << "squash " << squash;
  }
}

TEST(HardCases, NearlyIncompressibleFleshSolvesExactlyAndStaysStable) {
  HandConfig c;
  c.material.poisson_ratio = 0.49;
  c.floor.enabled = true;
  c.floor.height_m = -0.002;
  const HandModel model = slab_hand(2, c);
  HandState s = make_rest_state(model);
  auto mono = make_solver(SolverKind::monolithic);
  auto chol = make_solver(SolverKind::schur_cholmod);
  auto cg = make_solver(SolverKind::schur_cg);
  for (int k = 0; k < 30; ++k) {
    for (int j = 0; j < 2; ++j) set_target(s, j, offset_target(model, j, Eigen::Vector3d(0, 0, -0.0005 * k)));
    assemble(model, s);
    Eigen::VectorXd v_h_ref, v_t_ref, v_h, v_t;
    SolveReport r;
    ASSERT_TRUE(mono->solve(s.system, v_h_ref, v_t_ref, r));
    ASSERT_TRUE(chol->solve(s.system, v_h, v_t, r));
    EXPECT_LT(testing_util::relative_difference(v_h, v_t, v_h_ref, v_t_ref), 1e-8);
    ASSERT_TRUE(cg->solve(s.system, v_h, v_t, r));
    EXPECT_LT(testing_util::relative_difference(v_h, v_t, v_h_ref, v_t_ref), 1e-8);
    ASSERT_EQ(step(model, s, *chol), StepStatus::ok);
  }
  // Pressed 1.5 cm into the floor over 0.5 s: volume changes by < 5 % (nu = 0.49 resists it).
  std::vector<Eigen::Vector3d> X(model.num_nodes());
  for (int i = 0; i < model.num_nodes(); ++i) X[i] = s.x.segment<3>(3 * i);
  EXPECT_NEAR(total_volume(TetMesh{X, model.mesh().tets, {}}) / total_volume(model.mesh()), 1.0, 0.05);
  EXPECT_GT(s.floor_contacts, 0);
}

TEST(HardCases, TenThousandStepsPressingAndStrokingKeepEnergyBoundedAndFinite) {
  HandConfig c;
  c.floor.enabled = true;
  c.floor.height_m = -0.004;
  const HandModel model = slab_hand(1, c, {6, 6, 2});
  HandState s = make_rest_state(model);
  auto solver = make_solver(SolverKind::schur_cholmod);
  double first_max = 0, last_max = 0;
  for (int k = 0; k < 10000; ++k) {
    const double t = k * c.dt_s;
    set_target(s, 0, offset_target(model, 0, Eigen::Vector3d(0.02 * std::sin(t), 0.02 * std::cos(0.7 * t), -0.006 * (1 + std::sin(2 * t))), 0.5 * std::sin(t)));
    ASSERT_EQ(step(model, s, *solver), StepStatus::ok) << "step " << k;
    const double e = total_energy(model, s);
    ASSERT_TRUE(std::isfinite(e));
    if (k < 1000) first_max = std::max(first_max, e);
    if (k >= 9000) last_max = std::max(last_max, e);
  }
  // A periodic drive: the energy envelope at the end is no larger than at the start.
  EXPECT_LT(last_max, 1.2 * first_max);
  EXPECT_GT(min_det_F(model, s), 0.3);
}

TEST(HardCases, NanTargetIsRefusedAndNanStateResetsInsteadOfPropagating) {
  const HandModel model = slab_hand(1);
  HandState s = make_rest_state(model);
  auto solver = make_solver(SolverKind::schur_cholmod);
  HandleTarget bad = offset_target(model, 0, Eigen::Vector3d(0, 0, -0.01));
  bad.p_W.x() = std::numeric_limits<double>::quiet_NaN();
  const Eigen::Vector3d before = s.targets[0].p_W;
  EXPECT_FALSE(set_target(s, 0, bad));
  EXPECT_EQ(s.targets[0].p_W, before);
  bad = offset_target(model, 0, Eigen::Vector3d(0, 0, -0.01));
  bad.q_W.coeffs() << 0, 0, 0, 0;
  EXPECT_FALSE(set_target(s, 0, bad));
  // A NaN that got into the state (e.g. from a corrupted world) resets the hand at its target.
  s.x[7] = std::numeric_limits<double>::quiet_NaN();
  EXPECT_NE(step(model, s, *solver), StepStatus::ok);
  EXPECT_EQ(s.resets, 1);
  EXPECT_TRUE(state_finite(s));
  EXPECT_EQ(step(model, s, *solver), StepStatus::ok);
  EXPECT_TRUE(state_finite(s));
  // An absurd velocity (beyond max_speed_m_s) is a divergence too.
  s.v[4] = 1e6;
  EXPECT_EQ(step(model, s, *solver), StepStatus::reset_diverged);
  EXPECT_EQ(s.resets, 2);
  EXPECT_LT(s.v.cwiseAbs().maxCoeff(), 1e-12);
}

}  // namespace
}  // namespace hapticd::hand
