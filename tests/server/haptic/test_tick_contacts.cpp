// The haptic tick's contacts (TickContacts, ProxyHand::integrate): each tick solves the model's
// contact rows together with the proxies' implicit step. Checked against a dense reference of the
// same tick (the system matrix written out, every active set of the normal rows enumerated), a
// release within one tick, and no allocation.
#include <gtest/gtest.h>

#include <Eigen/Dense>
#include <Eigen/SVD>
#include <cmath>
#include <limits>
#include <random>
#include <vector>

#include "allocation_counter.hpp"
#include "hand_models/contact_pgs.hpp"
#include "hand_models/rigid_handle.hpp"
#include "server/haptic/virtual_coupling.hpp"

namespace hapticd::haptic {
namespace {

constexpr double kPeriod = 1e-3;
constexpr double kMass = 0.05;

Eigen::Matrix3d ball_inertia(double mass) { return 0.4 * mass * 0.015 * 0.015 * Eigen::Matrix3d::Identity(); }

ProxyHand make_proxy(int handles) {
  ProxyHand p;
  std::vector<double> mass(handles, kMass);
  std::vector<Eigen::Matrix3d> inertia(handles, ball_inertia(kMass));
  p.configure(handles, mass.data(), inertia.data(), coupling_gains_for(1000.0, 1.0, kPeriod), DeviceLimits{}, {});
  return p;
}

// Puts every proxy at rest on its device at `p` (two samples at the same pose: zero device velocity).
void rest_on_device(ProxyHand& p, const std::vector<Eigen::Vector3d>& at, double& t) {
  for (int k = 0; k < 2; ++k) {
    t += kPeriod;
    for (int j = 0; j < p.handles(); ++j) p.set_device_pose(j, at[j], Eigen::Quaterniond::Identity());
    p.commit_sample(t, 0.05);
  }
}

// A model on `handles` handles with a stiff, damped, coupled free part and c contact rows of the
// structure the linearization gives (rows driven by the handles' motion through J, impulses acting
// back through J^T, a positive definite flesh compliance W), frictionless.
HapticModel random_model(int handles, int c, std::mt19937& rng, double step_s) {
  std::normal_distribution<double> g;
  const int n = 6 * handles, r = 3 * c;
  HapticModel m;
  m.handles = handles;
  m.step_s = step_s;
  m.t_end_ns = 1;
  const Eigen::MatrixXd L = Eigen::MatrixXd::NullaryExpr(n, n, [&] { return g(rng); });
  m.K = -(50.0 * (L * L.transpose() / n) + 20.0 * Eigen::MatrixXd::Identity(n, n));
  m.D = 0.02 * m.K;
  m.F0 = HapticVector::NullaryExpr(n, [&] { return 0.5 * g(rng); });
  for (int j = 0; j < handles; ++j) {
    m.x0[j].p_W = Eigen::Vector3d(0.003 * g(rng), 0.003 * g(rng), 0.003 * g(rng));
    m.v0[j] = 0.01 * Eigen::Vector3d(g(rng), g(rng), g(rng));
    m.w0[j] = 0.1 * Eigen::Vector3d(g(rng), g(rng), g(rng));
  }
  TickContacts& k = m.contacts;
  k.count = c;
  const Eigen::MatrixXd J = Eigen::MatrixXd::NullaryExpr(r, n, [&] { return g(rng); });
  const Eigen::MatrixXd F = Eigen::MatrixXd::NullaryExpr(r, r, [&] { return g(rng); });
  k.W = 0.05 * (F * F.transpose() / r) + 0.02 * Eigen::MatrixXd::Identity(r, r);
  k.U_K = J / step_s;
  k.U_D = 0.3 * J;
  k.G = J.transpose() / step_s;
  k.u0 = TickRowVector::NullaryExpr(r, [&] { return 0.02 * g(rng); });
  k.lambda0 = TickRowVector::Zero(r);
  for (int i = 0; i < c; ++i) k.bias[i] = 0.01 * g(rng), k.mu[i] = 0;
  return m;
}

struct DenseTick {
  Eigen::VectorXd v;       // the proxies' velocities after the tick
  Eigen::VectorXd lambda;  // the rows' impulses
};

// The tick of ProxyHand::integrate written out for proxies at rest on their devices (identity
// orientations): A v = b + h G lambda with A and b as integrate documents them, and the rows'
// velocities u = u0 + U_K (x - x0 + tau v) + U_D (v - v0) + W lambda = q + M lambda, v = v_free + X lambda.
struct DenseRows {
  Eigen::VectorXd v_free, q;
  Eigen::MatrixXd X, M;
};

DenseRows dense_rows(const HapticModel& m, const ProxyHand& p, const std::vector<Eigen::Vector3d>& at, double tau) {
  const int handles = m.handles, n = 6 * handles;
  const CouplingGains& gains = p.gains();
  const double h = kPeriod;
  Eigen::MatrixXd A = Eigen::MatrixXd::Zero(n, n);
  Eigen::VectorXd x_rel(n), v0(n);
  for (int j = 0; j < handles; ++j) {
    A.block<3, 3>(6 * j, 6 * j).diagonal().setConstant(kMass + h * gains.b_ns_m + h * h * gains.k_n_m);
    A.block<3, 3>(6 * j + 3, 6 * j + 3) = ball_inertia(kMass);
    A.block<3, 3>(6 * j + 3, 6 * j + 3).diagonal().array() += h * gains.b_nms_rad + h * h * gains.k_nm_rad;
    x_rel.segment<3>(6 * j) = at[j] - m.x0[j].p_W;
    x_rel.segment<3>(6 * j + 3).setZero();  // both orientations identity
    v0.segment<3>(6 * j) = m.v0[j];
    v0.segment<3>(6 * j + 3) = m.w0[j];
  }
  const Eigen::MatrixXd K = m.K, D = m.D;
  A -= h * D + h * tau * K;
  const Eigen::VectorXd b = h * (Eigen::VectorXd(m.F0) + K * x_rel - D * v0);
  const Eigen::PartialPivLU<Eigen::MatrixXd> lu(A);
  DenseRows d;
  d.v_free = lu.solve(b);
  const Eigen::MatrixXd G = m.contacts.G, U_K = m.contacts.U_K, U_D = m.contacts.U_D, W = m.contacts.W;
  d.X = lu.solve(h * G);
  d.M = W + (tau * U_K + U_D) * d.X;
  d.q = Eigen::VectorXd(m.contacts.u0) + U_K * (x_rel + tau * d.v_free) + U_D * (d.v_free - v0);
  return d;
}

// That tick's frictionless rows, every subset of the normal rows tried as the active set until one
// satisfies 0 <= lambda_n _|_ u_n - bias >= 0.
DenseTick dense_tick(const HapticModel& m, const ProxyHand& p, const std::vector<Eigen::Vector3d>& at, double tau) {
  const int c = m.contacts.count, r = 3 * c;
  const DenseRows d = dense_rows(m, p, at, tau);
  for (int set = 0; set < (1 << c); ++set) {
    std::vector<int> active;
    for (int i = 0; i < c; ++i)
      if (set & (1 << i)) active.push_back(3 * i);
    const int a = static_cast<int>(active.size());
    Eigen::MatrixXd M_aa(a, a);
    Eigen::VectorXd rhs(a);
    for (int i = 0; i < a; ++i) {
      rhs[i] = m.contacts.bias[active[i] / 3] - d.q[active[i]];
      for (int k = 0; k < a; ++k) M_aa(i, k) = d.M(active[i], active[k]);
    }
    const Eigen::VectorXd l_a = a > 0 ? Eigen::VectorXd(M_aa.lu().solve(rhs)) : Eigen::VectorXd();
    Eigen::VectorXd lambda = Eigen::VectorXd::Zero(r);
    for (int i = 0; i < a; ++i) lambda[active[i]] = l_a[i];
    const Eigen::VectorXd u = d.q + d.M * lambda;
    bool ok = true;
    for (int i = 0; i < c && ok; ++i) ok = lambda[3 * i] >= 0 && u[3 * i] - m.contacts.bias[i] >= -1e-12;
    if (ok) return {d.v_free + d.X * lambda, lambda};
  }
  ADD_FAILURE() << "no active set solves the problem";
  return {};
}

TEST(TickContacts, TheTickSolvesItsRowsAsTheEnumeratedLcpOfTheSameStepTo1e9) {
  std::mt19937 rng(17);
  int active_rows = 0, free_rows = 0;
  for (int trial = 0; trial < 40; ++trial) {
    const int handles = 1 + trial % 2, c = 1 + trial % 4;  // a stylus or two handles, 1 to 4 contacts
    const HapticModel m = random_model(handles, c, rng, 1.0 / 30);
    ProxyHand p = make_proxy(handles);
    std::vector<Eigen::Vector3d> at(handles);
    for (int j = 0; j < handles; ++j) at[j] = m.x0[j].p_W + Eigen::Vector3d(0.002, -0.001, 0.001 * (trial % 3 - 1));
    double t = 0;
    rest_on_device(p, at, t);
    const double lookahead = 0.02;
    p.integrate(m, kPeriod, lookahead);
    const DenseTick ref = dense_tick(m, p, at, lookahead);
    ASSERT_EQ(ref.lambda.size(), 3 * c);
    const Eigen::VectorXd lambda = p.contact_impulses();
    EXPECT_LT((lambda - ref.lambda).norm(), 1e-9 * (1 + ref.lambda.norm())) << "trial " << trial;
    for (int j = 0; j < handles; ++j) {
      EXPECT_LT((p.proxy_velocity(j) - ref.v.segment<3>(6 * j)).norm(), 1e-9 * (1 + ref.v.norm())) << "trial " << trial;
      EXPECT_LT((p.proxy_angular_velocity(j) - ref.v.segment<3>(6 * j + 3)).norm(), 1e-9 * (1 + ref.v.norm()))
          << "trial " << trial;
    }
    for (int i = 0; i < c; ++i) (ref.lambda[3 * i] > 0 ? active_rows : free_rows) += 1;
  }
  // The trials cover both sides of the complementarity.
  EXPECT_GT(active_rows, 10);
  EXPECT_GT(free_rows, 10);
}

// A stylus's model with no force of its own (F0, K, D zero, its anchor at rest): only rows act.
HapticModel bare_stylus_model(double step_s) {
  HapticModel m;
  m.handles = 1;
  m.step_s = step_s;
  m.t_end_ns = 1;
  m.F0 = HapticVector::Zero(6);
  m.K = HapticMatrix::Zero(6, 6);
  m.D = HapticMatrix::Zero(6, 6);
  m.v0[0].setZero();
  m.w0[0].setZero();
  return m;
}

// Rows of a rigid tool on a movable rigid body: the velocity of a point p of a body moving at (v, w)
// is v - [p]x w; a row along direction d reads d^T [I, -[p]x].
Eigen::Matrix<double, 1, 6> point_row(const Eigen::Vector3d& d, const Eigen::Vector3d& p) {
  Eigen::Matrix<double, 1, 6> row;
  row << d.transpose(), -d.transpose() * hand::skew(p);
  return row;
}

// ProxyHand::set_contact_sweeps (haptic-bench touch --tick-sweeps): a tick's contact solve runs at
// most the sweeps it is given, at least one, and the default's share of them on rows that need more.
TEST(TickContacts, ATicksContactSolveRunsAtMostTheSweepsItIsGiven) {
  std::mt19937 rng(7);
  const HapticModel m = random_model(1, 8, rng, 1.0 / 30);
  int most_by_default = 0;
  for (const int limit : {0, 1, 2, 5, kDefaultTickContactSweeps}) {
    ProxyHand p = make_proxy(1);
    if (limit != kDefaultTickContactSweeps) p.set_contact_sweeps(limit);
    double t = 0;
    rest_on_device(p, {Eigen::Vector3d(0.001, -0.002, -0.003)}, t);
    int most = 0;
    long sweeps = 0;
    for (int k = 0; k < 20; ++k) {
      p.integrate(m, kPeriod, 0.02 - k * kPeriod);
      most = std::max(most, p.contact_sweeps());
      sweeps += p.contact_sweeps();
    }
    EXPECT_EQ(p.contact_solves(), 20) << limit;
    EXPECT_EQ(p.contact_sweeps_total(), sweeps) << limit;
    EXPECT_GE(most, 1) << limit;
    EXPECT_LE(most, std::max(limit, 1)) << limit;
    if (limit == kDefaultTickContactSweeps) most_by_default = most;
  }
  EXPECT_GT(most_by_default, 5) << "the rows need more sweeps than the smaller limits give";
}

// A stylus's tool resting on a 0.2 kg rigid body at three points, mu 0.6: the rows' Delassus
// operator is the body's J_b M_b^-1 J_b^T plus the proxy's own response, both rigid, so three sticking
// contacts give nine rows of rank six (each pair's distance is fixed on both bodies). That is what the
// FEM stylus pressing the movable bunny gives the tick (two sticking points: six rows of rank five).
HapticModel tool_on_body(double step_s) {
  HapticModel m = bare_stylus_model(step_s);
  const std::vector<Eigen::Vector3d> points = {
      {0.005, 0, -0.01}, {-0.005, 0.002, -0.01}, {0, -0.005, -0.01}};  // on the tool, from its handle
  const Eigen::Vector3d body_com(0.001, 0.002, -0.03);
  const double body_mass = 0.2;
  const Eigen::Matrix3d body_inertia = Eigen::Vector3d(2e-4, 3e-4, 2.5e-4).asDiagonal();
  const int c = static_cast<int>(points.size()), r = 3 * c;
  Eigen::MatrixXd J_h(r, 6), J_b(r, 6);
  const Eigen::Vector3d frame[3] = {Eigen::Vector3d::UnitZ(), Eigen::Vector3d::UnitX(), Eigen::Vector3d::UnitY()};
  for (int i = 0; i < c; ++i)
    for (int k = 0; k < 3; ++k) {
      J_h.row(3 * i + k) = point_row(frame[k], points[i]);
      J_b.row(3 * i + k) = -point_row(frame[k], points[i] - body_com);  // the tool's velocity less the body's
    }
  Eigen::Matrix<double, 6, 6> M_b_inv = Eigen::Matrix<double, 6, 6>::Zero();
  M_b_inv.topLeftCorner<3, 3>() = Eigen::Matrix3d::Identity() / body_mass;
  M_b_inv.bottomRightCorner<3, 3>() = body_inertia.inverse();
  TickContacts& k = m.contacts;
  k.count = c;
  k.G = J_h.transpose() / step_s;
  k.U_K = J_h / step_s;
  k.U_D = TickRowByDof::Zero(r, 6);
  k.W = J_b * M_b_inv * J_b.transpose();
  k.u0 = TickRowVector::Zero(r);
  k.lambda0 = TickRowVector::Zero(r);
  for (int i = 0; i < c; ++i) k.bias[i] = 0, k.mu[i] = 0.6;
  return m;
}

// Partial pivoting answers such rows with impulses of 1e4-1e8 N s that fail every check; the tick's
// exact solve (ProxyHand::polish_contacts) passes the impulses among the redundant rows instead
// (ProxyHand::redistribute). Before it, the third case here (the tool 0.6 mm aside, one contact at
// its cone's edge) ended on its 8 sweeps, residual 2.1e-3 m/s.
TEST(TickContacts, AToolStuckOnARigidBodyByRedundantContactsIsSolvedExactly) {
  const HapticModel m = tool_on_body(1.0 / 30);
  const Eigen::JacobiSVD<Eigen::MatrixXd> svd(Eigen::MatrixXd(m.contacts.W));
  ASSERT_LT(svd.singularValues()[6], 1e-12 * svd.singularValues()[0]) << "the body's rows are redundant";
  const double lookahead = 0.02;
  int sticking = 0;
  // The tool 2 mm into the body and 0.2-0.6 mm aside: the contacts stop it and hold it from sliding.
  for (const double aside : {0.0002, 0.0004, 0.0006}) {
    ProxyHand p = make_proxy(1);
    std::vector<Eigen::Vector3d> at = {Eigen::Vector3d(aside, -0.5 * aside, -0.002)};
    double t = 0;
    rest_on_device(p, at, t);
    // Nor does the tick allocate on these rows.
    EXPECT_EQ(testing_util::allocations_in([&] { p.integrate(m, kPeriod, lookahead); }), 0);
    const DenseRows d = dense_rows(m, p, at, lookahead);
    const Eigen::VectorXd lambda = p.contact_impulses();
    // Checked by the contact library's own residual (complementarity, cone, the slide opposing
    // the slip), on the problem written out densely.
    hand::ContactProblem problem{d.M, d.q, Eigen::VectorXd::Zero(3), {0.6, 0.6, 0.6}};
    const double scale = d.M.diagonal().maxCoeff() * lambda.cwiseAbs().maxCoeff() + d.q.cwiseAbs().maxCoeff();
    EXPECT_LT(hand::contact_residual(problem, lambda), 1e-9 * scale) << "aside " << aside;
    EXPECT_EQ(p.contact_unconverged(), 0) << "aside " << aside;
    const Eigen::VectorXd v = d.v_free + d.X * lambda;
    EXPECT_LT((p.proxy_velocity(0) - v.head<3>()).norm(), 1e-9 * (1 + v.norm()));
    for (int i = 0; i < 3; ++i)
      sticking += lambda[3 * i] > 0 && lambda.segment<2>(3 * i + 1).norm() < 0.6 * (1 - 1e-6) * lambda[3 * i];
  }
  EXPECT_GE(sticking, 6) << "the cases hold the tool by sticking contacts";
}

// A rigid floor z >= 0 under a stylus as the rows of a model: the end-of-step gap z = z0 + h u_n
// (U_K = 1 / h along z), an impulse lambda pushes the handle up by lambda / h, the flesh adds nothing
// (W ~ 0).
HapticModel floor_model(double step_s) {
  HapticModel m = bare_stylus_model(step_s);
  TickContacts& k = m.contacts;
  k.count = 1;
  k.G = TickDofByRow::Zero(6, 3);
  k.G(2, 0) = 1.0 / step_s;
  k.U_K = TickRowByDof::Zero(3, 6);
  k.U_K(0, 2) = 1.0 / step_s;
  k.U_D = TickRowByDof::Zero(3, 6);
  k.W = 1e-6 * TickRowMatrix::Identity(3, 3);
  k.u0 = TickRowVector::Zero(3);
  k.lambda0 = TickRowVector::Zero(3);
  k.mu[0] = 0.5;
  return m;
}

TEST(TickContacts, AContactReleasesWithinOneTickWhenTheDeviceLiftsAway) {
  const HapticModel floor = floor_model(1.0 / 30);
  HapticModel free_space = floor;
  free_space.contacts.count = 0;
  ProxyHand p = make_proxy(1), q = make_proxy(1);
  double t = 0;
  // Pressed 2 mm into the floor for 0.3 s: the proxy rests on it and the device feels the coupling.
  std::vector<Eigen::Vector3d> at = {Eigen::Vector3d(0, 0, -0.002)};
  rest_on_device(p, at, t);
  ReplyWrench pressed;
  const long solves_before = p.contact_solves(), sweeps_before = p.contact_sweeps_total();
  long sweeps = 0;
  for (int k = 0; k < 300; ++k) {
    t += kPeriod;
    p.set_device_pose(0, at[0], Eigen::Quaterniond::Identity());
    p.commit_sample(t, 0.05);
    pressed = p.reply(0, 1.0, kPeriod);
    p.integrate(floor, kPeriod, 0.01);
    sweeps += p.contact_sweeps();
  }
  // The counters hapticd --stats and haptic-bench touch report: one solve a tick, its sweeps summed,
  // and on one row every tick's answer exact.
  EXPECT_EQ(p.contact_solves() - solves_before, 300);
  EXPECT_EQ(p.contact_sweeps_total() - sweeps_before, sweeps);
  EXPECT_GE(sweeps, 300);
  EXPECT_EQ(p.contact_unconverged(), 0);
  EXPECT_NEAR(p.proxy(0).p_W.z(), 0.0, 5e-5) << "the proxy rests on the floor";
  EXPECT_NEAR(pressed.f_D.z(), 1000.0 * 0.002, 0.1) << "the device feels the coupling's 2 mm";
  EXPECT_GT(p.contact_impulses()[0], 0.0);
  // The device leaves, 1 mm above the floor: the very next tick releases the contact, so the proxy
  // moves as it would with no floor at all (a second proxy in the same state, free space).
  q = p;
  at[0] = Eigen::Vector3d(0, 0, 0.001);
  t += kPeriod;
  for (ProxyHand* x : {&p, &q}) {
    x->set_device_pose(0, at[0], Eigen::Quaterniond::Identity());
    x->commit_sample(t, 0.05);
  }
  const long q_solves = q.contact_solves();
  p.integrate(floor, kPeriod, 0.01);
  q.integrate(free_space, kPeriod, 0.01);
  EXPECT_EQ(q.contact_solves(), q_solves) << "no rows, no solve";
  EXPECT_EQ(p.contact_impulses()[0], 0.0) << "released within the tick";
  EXPECT_LT((p.proxy_velocity(0) - q.proxy_velocity(0)).norm(), 1e-12);
  EXPECT_GT(p.proxy_velocity(0).z(), 0.0) << "the proxy follows the device up";
}

TEST(TickContacts, AFadedModelsContactsStillHoldTheProxyWhileTheSafeModelBringsItToItsDevice) {
  // A stale model fades to the safe model (weight 0), which pulls the proxy onto its device. Its
  // contacts still hold: the world, which follows the proxy, resumes at the surface and is not
  // driven 2 cm into the body it touches (with constraint contact that crushed the hand's flesh at
  // hundreds of newtons when a failed visual step recovered). Off the floor the proxy reaches its
  // device as with no model at all.
  const HapticModel floor = floor_model(1.0 / 30);
  HapticModel free_space = floor;
  free_space.contacts.count = 0;
  for (const double device_z : {-0.02, 0.01}) {
    ProxyHand p = make_proxy(1), q = make_proxy(1);
    double t = 0;
    std::vector<Eigen::Vector3d> at = {Eigen::Vector3d(0, 0, -0.002)};
    rest_on_device(p, at, t);
    for (int k = 0; k < 300; ++k) {
      t += kPeriod;
      p.set_device_pose(0, at[0], Eigen::Quaterniond::Identity());
      p.commit_sample(t, 0.05);
      p.reply(0, 1.0, kPeriod);
      p.integrate(floor, kPeriod, 0.01);
    }
    ASSERT_NEAR(p.proxy(0).p_W.z(), 0.0, 5e-5);
    q = p;
    at[0] = Eigen::Vector3d(0, 0, device_z);
    double lowest = 0;
    for (int k = 0; k < 300; ++k) {
      t += kPeriod;
      for (ProxyHand* x : {&p, &q}) {
        x->set_device_pose(0, at[0], Eigen::Quaterniond::Identity());
        x->commit_sample(t, 0.05);
        x->reply(0, 1.0, kPeriod);
      }
      p.integrate(floor, kPeriod, -0.05, 0.0);
      q.integrate(free_space, kPeriod, -0.05, 0.0);
      lowest = std::min(lowest, p.proxy(0).p_W.z());
    }
    std::printf("device at %+.0f mm: the faded floor's proxy at %+.4f mm (lowest %+.4f mm), without the floor %+.4f mm\n",
                1e3 * device_z, 1e3 * p.proxy(0).p_W.z(), 1e3 * lowest, 1e3 * q.proxy(0).p_W.z());
    EXPECT_EQ(p.resets(), 0);
    EXPECT_NEAR(q.proxy(0).p_W.z(), device_z, 1e-5) << "the safe model brings the proxy onto its device";
    if (device_z < 0) {
      EXPECT_GT(lowest, -1e-4) << "the faded model's floor let the proxy through";
    } else {
      EXPECT_NEAR(p.proxy(0).p_W.z(), device_z, 1e-5) << "the floor held a proxy that left it";
    }
  }
}

TEST(TickContacts, TheTickWithContactsAllocatesNothingForAStylusOrAPreparedGlove) {
  std::mt19937 rng(3);
  for (int handles : {1, 16}) {
    HapticModel m = random_model(handles, kMaxTickContacts, rng, 1.0 / 30);
    ProxyHand p = make_proxy(handles);
    if (handles >= kMinPreparedHandles) {
      std::vector<double> mass(handles, kMass);
      std::vector<Eigen::Matrix3d> inertia(handles, ball_inertia(kMass));
      ASSERT_TRUE(prepare_tick_solver(m, handles, mass.data(), inertia.data(), p.gains(), kPeriod));
      ASSERT_TRUE(m.contacts.proxy_prepared);
    }
    std::vector<Eigen::Vector3d> at(handles);
    for (int j = 0; j < handles; ++j) at[j] = m.x0[j].p_W;
    double t = 0;
    rest_on_device(p, at, t);
    const long allocations = testing_util::allocations_in([&] {
      for (int k = 0; k < 20; ++k) {
        t += kPeriod;
        for (int j = 0; j < handles; ++j) p.set_device_pose(j, at[j], Eigen::Quaterniond::Identity());
        p.commit_sample(t, 0.05);
        for (int j = 0; j < handles; ++j) p.reply(j, 1.0, kPeriod);
        p.integrate(m, kPeriod, 0.02 - k * kPeriod);
      }
    });
    EXPECT_EQ(allocations, 0) << handles << " handles";
    EXPECT_EQ(p.resets(), 0);
    EXPECT_EQ(p.solver_fallbacks(), 0) << handles << " handles";
    EXPECT_EQ(p.contact_impulses().size(), 3 * kMaxTickContacts);
  }
}

// One contact whose rows' velocity falls with the handle's displacement along them (U_K = -beta
// G^T): with the proxy's response the operator is (w - tau h beta / a) I, a the proxy's
// translational diagonal m + h b + h^2 k (K = D = 0), monotone only up to tau* = w a / (h beta).
HapticModel falling_rows_model(double w, double beta, double step_s) {
  HapticModel m = bare_stylus_model(step_s);
  TickContacts& k = m.contacts;
  k.count = 1;
  k.G = TickDofByRow::Zero(6, 3);
  k.G.topRows<3>().setIdentity();
  k.W = w * TickRowMatrix::Identity(3, 3);
  k.U_K = -beta * k.G.transpose();
  k.U_D = TickRowByDof::Zero(3, 6);
  k.u0 = TickRowVector::Zero(3);
  k.lambda0 = TickRowVector::Zero(3);
  k.bias[0] = 0, k.mu[0] = 0;
  return m;
}

TEST(TickContacts, TheLookaheadStopsWhereTheRowsOperatorStopsBeingMonotone) {
  const double mass = kMass, w = 1.0, step = 0.1;
  const Eigen::Matrix3d inertia = ball_inertia(kMass);
  const CouplingGains gains = coupling_gains_for(1000.0, 1.0, kPeriod);
  const double a = mass + kPeriod * gains.b_ns_m + kPeriod * kPeriod * gains.k_n_m;
  // tau* = 0.03 s: the step (0.1) and its half (0.05) are past it, a quarter (0.025) is within.
  const double beta = w * a / (kPeriod * 0.03);
  HapticModel m = falling_rows_model(w, beta, step);
  prepare_contact_lookahead(m, &mass, &inertia, gains, kPeriod);
  EXPECT_DOUBLE_EQ(m.contacts.max_lookahead_s, 0.025);
  // A tau* past the step: no bound.
  HapticModel free = falling_rows_model(w, w * a / (kPeriod * 0.2), step);
  prepare_contact_lookahead(free, &mass, &inertia, gains, kPeriod);
  EXPECT_EQ(free.contacts.max_lookahead_s, std::numeric_limits<double>::infinity());
  // Monotone at no lookahead at all: h at the least.
  HapticModel stiff = falling_rows_model(w, w * a / (kPeriod * 1e-4), step);
  prepare_contact_lookahead(stiff, &mass, &inertia, gains, kPeriod);
  EXPECT_DOUBLE_EQ(stiff.contacts.max_lookahead_s, kPeriod);
}

TEST(TickContacts, ATickPastTheBoundSolvesAtIt) {
  // The same tick with the model's step end 0.1 s ahead and a bound of 0.025 s, and with the step
  // end 0.025 s ahead and no bound: the same proxies.
  const double mass = kMass, w = 1.0;
  const Eigen::Matrix3d inertia = ball_inertia(kMass);
  const CouplingGains gains = coupling_gains_for(1000.0, 1.0, kPeriod);
  const double a = mass + kPeriod * gains.b_ns_m + kPeriod * kPeriod * gains.k_n_m;
  HapticModel bounded = falling_rows_model(w, w * a / (kPeriod * 0.03), 0.1);
  bounded.contacts.u0 = TickRowVector::Constant(3, -0.01);  // closing: the rows push
  prepare_contact_lookahead(bounded, &mass, &inertia, gains, kPeriod);
  ASSERT_DOUBLE_EQ(bounded.contacts.max_lookahead_s, 0.025);
  HapticModel unbounded = bounded;
  unbounded.contacts.max_lookahead_s = std::numeric_limits<double>::infinity();
  ProxyHand p = make_proxy(1), q = make_proxy(1);
  double tp = 0, tq = 0;
  rest_on_device(p, {Eigen::Vector3d::Zero()}, tp);
  rest_on_device(q, {Eigen::Vector3d::Zero()}, tq);
  for (int k = 0; k < 5; ++k) {
    p.integrate(bounded, kPeriod, 0.1);
    q.integrate(unbounded, kPeriod, 0.025);
  }
  EXPECT_GT(p.contact_impulses().head<1>().norm(), 0.0);
  EXPECT_EQ(p.proxy(0).p_W, q.proxy(0).p_W);
  EXPECT_EQ(p.proxy_velocity(0), q.proxy_velocity(0));
}

// The tick's last guards (ProxyHand::integrate) on a model the tick cannot follow, a proxy held by
// one falling row with the lookahead's bound left unprepared (max_lookahead_s infinite):
// - the row's operator w (1 - tau / tau*) nearly vanishing at the tick's lookahead (tau = 0.03 s,
//   tau* a millionth further): its impulse throws the proxy at about 200 m/s. The tick solves again at
//   tau = h, where the operator is 0.97 w, and gives the impulse of that solve: 0.01 / 0.97 N s;
// - a row closing at 10 km/s (a model far outside its linearization): too fast at either
//   lookahead, the proxy holds still for the tick. Neither resets.
TEST(TickContacts, ARowTheTickCannotFollowIsSolvedWithoutTheLookaheadThenHeld) {
  const double mass = kMass, w = 1.0, tau = 0.03;
  const CouplingGains gains = coupling_gains_for(1000.0, 1.0, kPeriod);
  const double a = mass + kPeriod * gains.b_ns_m + kPeriod * kPeriod * gains.k_n_m;
  HapticModel near_singular = falling_rows_model(w, w * a / (kPeriod * tau * (1 + 1e-6)), 0.1);
  near_singular.contacts.u0 = TickRowVector::Constant(3, -0.01);  // closing at 1 cm/s
  ProxyHand p = make_proxy(1);
  double t = 0;
  rest_on_device(p, {Eigen::Vector3d::Zero()}, t);
  p.integrate(near_singular, kPeriod, tau);
  EXPECT_EQ(p.lookahead_fallbacks(), 1);
  EXPECT_EQ(p.contact_holds(), 0);
  EXPECT_EQ(p.resets(), 0);
  // At tau = h the row's operator is w (1 - h / tau*) and its impulse closes the 1 cm/s.
  const double operator_at_h = w * (1 - kPeriod / (tau * (1 + 1e-6)));
  EXPECT_NEAR(p.contact_impulses()[0], 0.01 / operator_at_h, 1e-9);
  EXPECT_LT(p.proxy_velocity(0).norm(), 1.0);

  HapticModel far = falling_rows_model(w, w * a / (kPeriod * 0.2), 0.1);
  far.contacts.u0 = TickRowVector::Constant(3, -1e4);
  ProxyHand q = make_proxy(1);
  t = 0;
  rest_on_device(q, {Eigen::Vector3d::Zero()}, t);
  const Eigen::Vector3d before = q.proxy(0).p_W;
  q.integrate(far, kPeriod, tau);
  EXPECT_EQ(q.lookahead_fallbacks(), 1);
  EXPECT_EQ(q.contact_holds(), 1);
  EXPECT_EQ(q.resets(), 0);
  EXPECT_EQ(q.proxy_velocity(0), Eigen::Vector3d::Zero());
  EXPECT_EQ(q.proxy(0).p_W, before);
}

}  // namespace
}  // namespace hapticd::haptic
