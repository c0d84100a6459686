// The handle-space model with its contacts as unilateral rows (ContactLinearization::unilateral)
// against a re-simulation of the coming step with the handles prescribed at displaced end states: the
// flesh's implicit step (sparse LU of A_t) and its floor contacts solved as a complementarity problem
// of their own (J, W and the free velocities built here from the contacts, not from the model's
// rows). The model must agree to second order where the contacts push, and where the handle lifts
// away it must release them (no pull), as the re-simulation does and the bilateral model does not.
#include <gtest/gtest.h>

#include <Eigen/SparseLU>
#include <cstdio>

#include "hand_models/contact_pgs.hpp"
#include "hand_models/handle_linearization.hpp"
#include "hand_test_util.hpp"

namespace hapticd::hand {
namespace {

using testing_util::offset_target;
using testing_util::slab_hand;

constexpr double kFloorZ = 0.003, kFriction = 0.4;

// Floor contacts at a few of the slab's lowest nodes (at most kMaxLinearizedContacts, so the model
// carries every one), speculative within 2 mm.
void set_floor_contacts(const HandModel& model, HandState& s) {
  s.contacts.clear();
  for (int i = 0; i < model.num_nodes(); i += 7) {
    const double depth = kFloorZ - s.x[3 * i + 2];
    if (depth < -0.002) continue;
    PointContact pc;
    const auto [tet, local] = model.node_tet(i);
    pc.tet = tet;
    pc.bary = Eigen::Vector4d::Unit(local);
    pc.n_W = Eigen::Vector3d::UnitZ();
    pc.depth_m = depth;
    pc.friction = kFriction;
    pc.constraint = true;
    s.contacts.push_back(pc);
    if (static_cast<int>(s.contacts.size()) == kMaxLinearizedContacts) break;
  }
}

struct Resimulation {
  Eigen::VectorXd wrench;  // on the handle
  double normal_impulse = 0;  // sum over the contacts, N s
};

// The coming step from `s` (assembled, contacts as set) with the handle prescribed to end at `end`.
Resimulation resimulate(const HandModel& model, const HandState& s, const std::vector<HandleState>& end) {
  const double h = model.config().dt_s;
  const double k = model.config().coupling.stiffness_n_m, d = model.config().coupling.damping_ns_m;
  const int nt = s.system.tool_dofs();
  Eigen::VectorXd rhs = s.system.b_t;  // holds the springs' pull at the current handle pose
  const RigidHandle& H = model.handles()[0];
  for (size_t si = 0; si < H.nodes.size(); ++si) {
    const Eigen::Vector3d rho0 = s.handles[0].q_WH * H.r_B[si], rho = end[0].q_WH * H.r_B[si];
    const Eigen::Vector3d x_B0 = s.handles[0].p_WH + rho0, x_B = end[0].p_WH + rho;
    rhs.segment<3>(3 * H.nodes[si]) += h * (k * (x_B - x_B0) + d * (end[0].v_WH + end[0].w_WH.cross(rho)));
  }
  Eigen::SparseLU<Eigen::SparseMatrix<double>> lu(s.system.A_t);
  EXPECT_EQ(lu.info(), Eigen::Success);
  // J: per contact node, the rows (n, t1, t2) = (z, x, y) of its velocity.
  const int c = static_cast<int>(s.contacts.size());
  Eigen::MatrixXd Jt = Eigen::MatrixXd::Zero(nt, 3 * c);
  ContactProblem p;
  p.bias.resize(c);
  for (int i = 0; i < c; ++i) {
    const PointContact& pc = s.contacts[i];
    const Tet& t = model.mesh().tets[pc.tet];
    for (int a = 0; a < 4; ++a) {
      Jt(3 * t[a] + 2, 3 * i) += pc.bary[a];
      Jt(3 * t[a] + 0, 3 * i + 1) += pc.bary[a];
      Jt(3 * t[a] + 1, 3 * i + 2) += pc.bary[a];
    }
    p.bias[i] = pc.depth_m > 0 ? kContactDepthRecovery * pc.depth_m / h : pc.depth_m / h;
    p.mu.push_back(pc.friction);
  }
  const Eigen::VectorXd v_free = lu.solve(rhs);
  const Eigen::MatrixXd X = lu.solve(Jt);
  p.W = Jt.transpose() * X;
  p.u_free = Jt.transpose() * v_free;
  PgsOptions options;
  options.max_iterations = 200000;
  options.tolerance = 1e-14;
  const PgsResult r = solve_contacts_pgs(p, options);
  EXPECT_LT(contact_residual(p, r.lambda), 1e-10);
  const Eigen::VectorXd v_t = v_free + X * r.lambda;
  Resimulation out;
  out.wrench = coupling_wrench(model, s.x + h * v_t, v_t, end);
  for (int i = 0; i < c; ++i) out.normal_impulse += r.lambda[3 * i];
  return out;
}

class UnilateralLinearization : public ::testing::Test {
 protected:
  void SetUp() override {
    for (int k = 0; k < 20; ++k) {
      set_target(s, 0, offset_target(model, 0, Eigen::Vector3d(0.0015 * k, 0, -0.0006 * k)));
      set_floor_contacts(model, s);
      ASSERT_EQ(step(model, s, *solver), StepStatus::ok);
    }
    set_floor_contacts(model, s);
    ASSERT_GT(s.contacts.size(), 3u);
    // The bilateral model first (it holds the last step's pushing rows), then the unilateral one.
    HandState copy = s;
    ASSERT_TRUE(linearize_next_step(model, copy, *solver, bilateral, ContactLinearization::held));
    ASSERT_GT(copy.held.rows(), 3);
    ASSERT_TRUE(linearize_next_step(model, s, *solver, lin, ContactLinearization::unilateral));
    ASSERT_EQ(lin.contacts.count(), static_cast<int>(s.contacts.size()));
  }
  // The handle displaced by eps along `dir` (position m, rotation rad, velocity m/s, angular velocity rad/s).
  std::vector<HandleState> displaced(double eps, const Eigen::Matrix<double, 12, 1>& dir) const {
    std::vector<HandleState> end = s.handles;
    end[0].p_WH += eps * dir.head<3>();
    end[0].q_WH = rotate_by(end[0].q_WH, eps * dir.segment<3>(3));
    end[0].v_WH += eps * dir.segment<3>(6);
    end[0].w_WH += eps * dir.segment<3>(9);
    return end;
  }
  HandConfig config;
  HandModel model = slab_hand(1, config);
  HandState s = make_rest_state(model);
  std::unique_ptr<CoupledSolver> solver = make_solver(SolverKind::schur_cholmod);
  HandleLinearization lin, bilateral;
};

TEST_F(UnilateralLinearization, MatchesTheResimulatedContactsToSecondOrderWhileTheyPush) {
  const Resimulation at_zero = resimulate(model, s, s.handles);
  ASSERT_GT(at_zero.normal_impulse, 0) << "the slab presses on the floor";
  EXPECT_LT((lin.evaluate(s.handles) - at_zero.wrench).norm(), 1e-6 * (1 + at_zero.wrench.norm()));
  Eigen::Matrix<double, 12, 1> dir;
  for (int i = 0; i < 12; ++i) dir[i] = std::sin(1.3 * i + 0.7);
  dir.head<3>() *= 0.002, dir.segment<3>(3) *= 0.05, dir.segment<3>(6) *= 0.05, dir.segment<3>(9) *= 0.5;
  double previous = 0;
  for (double eps : {0.2, 0.1, 0.05}) {
    const std::vector<HandleState> end = displaced(eps, dir);
    const Resimulation ref = resimulate(model, s, end);
    const double err = (lin.evaluate(end) - ref.wrench).norm(), change = (ref.wrench - at_zero.wrench).norm();
    std::printf("unilateral, %d contacts, eps %.3f: error %.3e, change %.3e\n", lin.contacts.count(), eps, err, change);
    EXPECT_LT(err, 0.1 * change) << "eps " << eps;
    if (previous > 0) {
      EXPECT_NEAR(previous / err, 4.0, 1.0) << "eps " << eps;  // O(|dx|^2)
    }
    previous = err;
  }
}

TEST_F(UnilateralLinearization, ReleasesEveryContactWhenTheHandleLiftsAwayWhereTheBilateralModelPulls) {
  // The handle 2 cm above its anchor (past the press of 11 mm), moving up at 0.5 m/s: the
  // re-simulated flesh leaves the floor.
  Eigen::Matrix<double, 12, 1> dir = Eigen::Matrix<double, 12, 1>::Zero();
  dir[2] = 0.02, dir[8] = 0.5;
  const std::vector<HandleState> end = displaced(1.0, dir);
  const Resimulation ref = resimulate(model, s, end);
  EXPECT_EQ(ref.normal_impulse, 0) << "the reference releases every contact";
  const Eigen::VectorXd unilateral = lin.evaluate(end), held = bilateral.evaluate(end);
  const double err = (unilateral - ref.wrench).head<3>().norm(), held_err = (held - ref.wrench).head<3>().norm();
  std::printf("lift: reference f_z %.4f N, unilateral %.4f N (error %.2e), bilateral %.4f N (error %.2e)\n",
              ref.wrench[2], unilateral[2], err, held[2], held_err);
  // The flesh's own response is linear in the lift: the model is exact for it but for the coupling's
  // rotation terms (none here).
  EXPECT_LT(err, 1e-6 * (1 + ref.wrench.norm()));
  // The bilateral model holds the flesh on the floor: it pulls the handle down (-z) by more.
  EXPECT_LT(held[2], ref.wrench[2] - 1.0);
}

}  // namespace
}  // namespace hapticd::hand
