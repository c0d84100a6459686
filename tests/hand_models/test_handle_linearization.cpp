// The handle-space linearized coupling force against a re-simulation of the step
// with the handles prescribed at displaced poses: the error must be O(|dx|^2).
#include <gtest/gtest.h>

#include <Eigen/SparseLU>
#include <cstdio>

#include "hand_models/handle_linearization.hpp"
#include "hand_models/press_scenario.hpp"
#include "hand_models/procedural_hand.hpp"
#include "hand_test_util.hpp"

namespace hapticd::hand {
namespace {

using testing_util::offset_target;
using testing_util::slab_hand;

// The step from `s` (assembled) with every handle prescribed to end at `end`:
// the flesh's implicit step with its contacts held, then the exact coupling wrench.
Eigen::VectorXd resimulated_wrench(const HandModel& model, const HandState& s, CoupledSolver& solver,
                                   const std::vector<HandleState>& end) {
  const double h = model.config().dt_s;
  const double k = model.config().coupling.stiffness_n_m, d = model.config().coupling.damping_ns_m;
  Eigen::VectorXd rhs = s.system.b_t;  // holds the springs' pull at the current handle poses
  for (int j = 0; j < model.num_handles(); ++j) {
    const RigidHandle& H = model.handles()[j];
    for (size_t si = 0; si < H.nodes.size(); ++si) {
      const Eigen::Vector3d rho0 = s.handles[j].q_WH * H.r_B[si], rho = end[j].q_WH * H.r_B[si];
      const Eigen::Vector3d x_B0 = s.handles[j].p_WH + rho0, x_B = end[j].p_WH + rho;
      const Eigen::Vector3d v_B = end[j].v_WH + end[j].w_WH.cross(rho);
      rhs.segment<3>(3 * H.nodes[si]) += h * (k * (x_B - x_B0) + d * v_B);
    }
  }
  Eigen::MatrixXd v_t;
  EXPECT_TRUE(solver.solve_tool(s.system, rhs, v_t));
  return coupling_wrench(model, s.x + h * v_t, v_t, end);
}

// Presses, drags and twists `model`'s handles for 20 steps (so springs, flesh and any floor
// contacts are loaded), then checks its model against re-simulation.
void expect_quadratic_error(const HandModel& model) {
  const bool floor = model.config().floor.enabled;
  const int handles = model.num_handles();
  HandState s = make_rest_state(model);
  auto solver = make_solver(SolverKind::schur_cholmod);
  for (int k = 0; k < 20; ++k) {
    for (int j = 0; j < handles; ++j)
      set_target(s, j, offset_target(model, j, Eigen::Vector3d(0.001 * k, 0.0005 * j * k, -0.0004 * k), 0.02 * k));
    ASSERT_EQ(step(model, s, *solver), StepStatus::ok);
  }
  if (floor) {
    ASSERT_GT(s.floor_contacts, 0);
  }
  assemble(model, s);
  Eigen::VectorXd v_h, v_t;
  SolveReport report;
  ASSERT_TRUE(solver->solve(s.system, v_h, v_t, report));  // factor the system linearized
  HandleLinearization lin;
  ASSERT_TRUE(linearize_handles(model, s, *solver, lin));
  const int m = model.num_handles();
  // A displacement of every handle: translation, rotation and velocity change together.
  Eigen::VectorXd dir(12 * m);
  for (int i = 0; i < 12 * m; ++i) dir[i] = std::sin(1.7 * i + 0.3);
  auto displaced = [&](double eps) {
    std::vector<HandleState> end = s.handles;
    for (int j = 0; j < m; ++j) {
      end[j].p_WH += eps * 0.01 * dir.segment<3>(12 * j);
      end[j].q_WH = rotate_by(end[j].q_WH, eps * 0.2 * dir.segment<3>(12 * j + 3));
      end[j].v_WH += eps * 0.1 * dir.segment<3>(12 * j + 6);
      end[j].w_WH += eps * 2.0 * dir.segment<3>(12 * j + 9);
    }
    return end;
  };
  const Eigen::VectorXd at_zero = resimulated_wrench(model, s, *solver, s.handles);
  EXPECT_LT((lin.F0 - at_zero).norm(), 1e-9 * (1 + at_zero.norm()));  // exact at the linearization point
  double previous = 0;
  for (double eps : {0.5, 0.25, 0.125}) {
    const std::vector<HandleState> end = displaced(eps);
    const Eigen::VectorXd exact = resimulated_wrench(model, s, *solver, end);
    const double err = (lin.evaluate(end) - exact).norm();
    std::printf("handles %d floor %d eps %.3f: error %.3e, change %.3e\n", m, floor, eps, err, (exact - at_zero).norm());
    const double change = (exact - at_zero).norm();
    EXPECT_LT(err, 0.1 * change) << "eps " << eps;  // the linear term dominates
    if (previous > 0) {
      EXPECT_NEAR(previous / err, 4.0, 0.8) << "eps " << eps;  // O(|dx|^2)
    }
    previous = err;
  }
}

void expect_quadratic_error(int handles, bool floor) {
  HandConfig c;
  c.floor.enabled = floor;
  c.floor.height_m = 0.002;
  c.floor.friction = 0.3;
  expect_quadratic_error(slab_hand(handles, c));
}

TEST(HandleLinearization, MatchesResimulationToSecondOrderWithoutContacts) { expect_quadratic_error(1, false); }
TEST(HandleLinearization, MatchesResimulationToSecondOrderWithFloorContacts) { expect_quadratic_error(1, true); }
TEST(HandleLinearization, CouplesSeveralHandlesThroughTheFleshToSecondOrder) { expect_quadratic_error(2, true); }

// The glove hand: 1.7k tets with separate fingers and soft joints, 16 handles (96 handle DoF),
// its fingertips and palm pressed on a floor.
TEST(HandleLinearization, SixteenHandleGloveHandOnAFloorToSecondOrder) {
  ProceduralHandOptions shape;
  shape.separate_fingers = true;
  const ProceduralHand hand = make_procedural_hand(shape);
  HandConfig c;
  c.handles = procedural_handles(hand, 16);
  c.element_stiffness = procedural_joint_stiffness(hand, 16, kGloveJointStiffness);
  c.material.density_kg_m3 = embedding_density(hand, c.material.density_kg_m3);
  double lowest = 1e300;
  for (const Eigen::Vector3d& X : hand.mesh.X) lowest = std::min(lowest, X.z());
  c.floor.enabled = true;
  c.floor.height_m = lowest + 0.002;
  c.floor.friction = 0.3;
  expect_quadratic_error(HandModel(hand.mesh, c));
}

// Constraint contacts: the slab pressed and dragged on a floor of constraint
// contacts (with friction, some sticking, some sliding). The reference solves
// the step again with the handles prescribed and the held rows as bilateral
// constraints, by a sparse LU of the saddle-point system [A_t J^T; J 0]. The
// drag does not twist: the model's Jacobians are those of the step's start pose,
// so a turning handle would add a first-order error of one step's rotation.
TEST(HandleLinearization, HoldsConstraintContactsToSecondOrder) {
  HandConfig c;
  const HandModel model = slab_hand(1, c);
  HandState s = make_rest_state(model);
  auto solver = make_solver(SolverKind::schur_cholmod);
  const double floor_z = 0.003, h = c.dt_s;
  auto floor_contacts = [&] {
    s.contacts.clear();
    for (int i = 0; i < model.num_nodes(); ++i) {
      const double depth = floor_z - s.x[3 * i + 2];
      if (depth < -0.002) continue;  // speculative within 2 mm
      PointContact pc;
      const auto [tet, local] = model.node_tet(i);
      pc.tet = tet;
      pc.bary = Eigen::Vector4d::Unit(local);
      pc.depth_m = depth;
      pc.friction = 0.4;
      pc.constraint = true;
      s.contacts.push_back(pc);
    }
  };
  HandleLinearization lin;
  std::vector<HandleState> before;
  Eigen::VectorXd x_before;
  for (int k = 0; k < 20; ++k) {
    set_target(s, 0, offset_target(model, 0, Eigen::Vector3d(0.0015 * k, 0, -0.0006 * k)));
    floor_contacts();
    before = s.handles;
    x_before = s.x;
    ASSERT_EQ(step(model, s, *solver, &lin), StepStatus::ok);
  }
  ASSERT_GT(s.held.rows(), 3) << "the slab rests on held contacts";
  const int nh = s.system.handle_dofs(), nt = s.system.tool_dofs(), nc = s.held.rows();
  ASSERT_EQ(nh, 6);
  // Saddle-point matrix of the last step's system, handles prescribed.
  const Eigen::SparseMatrix<double> J_t = s.held.J.rightCols(nt);
  std::vector<Eigen::Triplet<double>> entries;
  for (int col = 0; col < nt; ++col)
    for (Eigen::SparseMatrix<double>::InnerIterator it(s.system.A_t, col); it; ++it)
      entries.emplace_back(static_cast<int>(it.row()), col, it.value());
  for (int col = 0; col < nt; ++col)
    for (Eigen::SparseMatrix<double>::InnerIterator it(J_t, col); it; ++it) {
      entries.emplace_back(nt + static_cast<int>(it.row()), col, it.value());
      entries.emplace_back(col, nt + static_cast<int>(it.row()), it.value());
    }
  Eigen::SparseMatrix<double> KKT(nt + nc, nt + nc);
  KKT.setFromTriplets(entries.begin(), entries.end());
  Eigen::SparseLU<Eigen::SparseMatrix<double>> lu(KKT);
  ASSERT_EQ(lu.info(), Eigen::Success);
  const double k_c = c.coupling.stiffness_n_m, d_c = c.coupling.damping_ns_m;
  auto exact = [&](const std::vector<HandleState>& end) -> Eigen::VectorXd {
    Eigen::VectorXd rhs = Eigen::VectorXd::Zero(nt + nc);
    rhs.head(nt) = s.system.b_t + s.held.impulse.tail(nt);
    const RigidHandle& H = model.handles()[0];
    for (size_t si = 0; si < H.nodes.size(); ++si) {
      const Eigen::Vector3d x_B0 = before[0].p_WH + before[0].q_WH * H.r_B[si];
      const Eigen::Vector3d rho = end[0].q_WH * H.r_B[si];
      const Eigen::Vector3d x_B = end[0].p_WH + rho, v_B = end[0].v_WH + end[0].w_WH.cross(rho);
      rhs.segment<3>(3 * H.nodes[si]) += h * (k_c * (x_B - x_B0) + d_c * v_B);
    }
    rhs.tail(nc) = s.held.u;
    const Eigen::VectorXd v_t = lu.solve(rhs).head(nt);
    return coupling_wrench(model, x_before + h * v_t, v_t, end);
  };
  const Eigen::VectorXd at_zero = exact(s.handles);
  EXPECT_LT((lin.F0 - at_zero).norm(), 1e-6 * (1 + at_zero.norm()));  // PGS tolerance 1e-8 on the impulses
  Eigen::VectorXd dir(12);
  for (int i = 0; i < 12; ++i) dir[i] = std::sin(1.3 * i + 0.7);
  double previous = 0;
  for (double eps : {0.5, 0.25, 0.125}) {
    std::vector<HandleState> end = s.handles;
    end[0].p_WH += eps * 0.004 * dir.head<3>();
    end[0].q_WH = rotate_by(end[0].q_WH, eps * 0.1 * dir.segment<3>(3));
    end[0].v_WH += eps * 0.1 * dir.segment<3>(6);
    end[0].w_WH += eps * 1.0 * dir.segment<3>(9);
    const Eigen::VectorXd reference = exact(end);
    const double err = (lin.evaluate(end) - reference).norm(), change = (reference - at_zero).norm();
    std::printf("held contacts %d, eps %.3f: error %.3e, change %.3e\n", nc, eps, err, change);
    EXPECT_LT(err, 0.1 * change) << "eps " << eps;
    if (previous > 0) {
      EXPECT_NEAR(previous / err, 4.0, 0.8) << "eps " << eps;  // O(|dx|^2)
    }
    previous = err;
  }
  // Held contacts stiffen the model: pushing the handle down costs more than in free space.
  HandleLinearization free_lin;
  assemble(model, s);
  Eigen::VectorXd v_h, v_t;
  SolveReport report;
  ASSERT_TRUE(solver->solve(s.system, v_h, v_t, report));
  ASSERT_TRUE(linearize_handles(model, s, *solver, free_lin));
  EXPECT_GT(-lin.K(2, 2), 1.5 * -free_lin.K(2, 2));
}

TEST(HandleLinearization, EqualsTheSchurComplementOfTheCouplingOverOneStep) {
  // Moving every handle at v for one step: d F / d v_h = h K + D = -S_c / h, with
  // S_c = A_h^c - A_ht A_t^-1 A_th and A_h^c the coupling part of A_h.
  HandConfig c;
  c.drive = DriveParams{0, 0, 0, 0};
  const HandModel model = slab_hand(2, c);
  HandState s = make_rest_state(model);
  s.handles[0].w_WH = Eigen::Vector3d(1, -2, 0.5);
  s.handles[1].p_WH.z() += 0.003;
  auto solver = make_solver(SolverKind::schur_cholmod);
  assemble(model, s);
  Eigen::VectorXd v_h, v_t;
  SolveReport report;
  ASSERT_TRUE(solver->solve(s.system, v_h, v_t, report));
  HandleLinearization lin;
  ASSERT_TRUE(linearize_handles(model, s, *solver, lin));
  const double h = c.dt_s;
  Eigen::MatrixXd A_hc = s.system.A_h;
  for (int j = 0; j < 2; ++j) {
    const Eigen::Matrix3d R = s.handles[j].q_WH.toRotationMatrix();
    A_hc.block<3, 3>(6 * j, 6 * j) -= model.handles()[j].mass_kg * Eigen::Matrix3d::Identity();
    A_hc.block<3, 3>(6 * j + 3, 6 * j + 3) -= R * model.handles()[j].inertia_B * R.transpose();
  }
  Eigen::MatrixXd Y;
  ASSERT_TRUE(solver->solve_tool(s.system, Eigen::MatrixXd(s.system.A_th), Y));
  const Eigen::MatrixXd S_c = A_hc - s.system.A_ht * Y;
  const Eigen::MatrixXd expected = -S_c / h;
  EXPECT_LT((h * lin.K + lin.D - expected).norm(), 1e-9 * expected.norm());
  // The flesh couples the two handles: off-diagonal blocks are not zero.
  const double coupled = lin.K.topRightCorner(6, 6).norm(), own = lin.K.topLeftCorner(6, 6).norm();
  EXPECT_GT(coupled, 1e-3 * own);
}

}  // namespace
}  // namespace hapticd::hand

namespace hapticd::hand {
namespace {

// The Schur solver hands the linearization its own A_t^-1 [b_t, A_th] and only
// the spin part of the coupling Jacobian is solved anew; the result is the
// full solve's (the monolithic solver keeps no factorization, so it takes the
// full path): two spinning handles pressed on a penalty floor.
TEST(HandleLinearization, ReusingTheSchurSolvesGivesTheFullSolvesModel) {
  HandConfig c;
  c.floor.enabled = true;
  c.floor.height_m = 0.003;
  const HandModel model = slab_hand(2, c);
  HandState s = make_rest_state(model);
  auto cholmod = make_solver(SolverKind::schur_cholmod);
  for (int k = 0; k < 10; ++k) {
    for (int j = 0; j < 2; ++j) {
      HandleTarget t = offset_target(model, j, Eigen::Vector3d(0.001 * k, 0, -0.0008 * k));
      t.q_W = Eigen::Quaterniond(Eigen::AngleAxisd(0.05 * k * (j ? -1 : 1), Eigen::Vector3d(0.3, 0.2, 1).normalized()));
      set_target(s, j, t);
    }
    ASSERT_EQ(step(model, s, *cholmod, nullptr), StepStatus::ok);
  }
  ASSERT_GT(s.handles[0].w_WH.norm(), 0.1) << "the handles spin";
  HandleLinearization reused, full;
  assemble(model, s);
  Eigen::VectorXd v_h, v_t;
  SolveReport report;
  ASSERT_TRUE(cholmod->solve(s.system, v_h, v_t, report));
  ASSERT_NE(cholmod->tool_solution(s.system), nullptr);
  ASSERT_TRUE(linearize_handles(model, s, *cholmod, reused));
  auto monolithic = make_solver(SolverKind::monolithic);
  ASSERT_EQ(monolithic->tool_solution(s.system), nullptr);
  ASSERT_TRUE(linearize_handles(model, s, *monolithic, full));
  EXPECT_LT((reused.K - full.K).norm(), 1e-8 * full.K.norm());
  EXPECT_LT((reused.D - full.D).norm(), 1e-8 * full.D.norm());
  EXPECT_LT((reused.F0 - full.F0).norm(), 1e-8 * (1 + full.F0.norm()));
}

}  // namespace
}  // namespace hapticd::hand
