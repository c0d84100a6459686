// A two-finger grasp with constraint contact and Coulomb friction: two fingers
// of flesh (one hand model, a handle each) squeeze a 100 g box off a floor,
// lift it 5 cm and hold it 5 s. With mu = 0.8 it holds (slip < 2 mm); with
// mu = 0.05 and the same squeeze (friction 2 mu N below its weight) it slips out.
#include <gtest/gtest.h>

#include <cstdio>

#include "hand_models/box_mesh.hpp"
#include "hand_models/coupled_solver.hpp"
#include "hand_models/hand_model.hpp"

namespace hapticd::hand {
namespace {

constexpr double kHalf = 0.015;  // the box: a 3 cm cube of 100 g
constexpr double kBoxMass = 0.1;
constexpr double kFloor = -kHalf;

// Two 2 x 2 x 3 cm fingers either side of the box, 0.5 mm away, one mesh.
HandModel two_fingers() {
  TetMesh left = make_box_mesh({0.02, 0.02, 0.03}, {4, 4, 6}, Eigen::Vector3d(-kHalf - 0.0205, -0.01, -0.012));
  const TetMesh right = make_box_mesh({0.02, 0.02, 0.03}, {4, 4, 6}, Eigen::Vector3d(kHalf + 0.0005, -0.01, -0.012));
  const int offset = left.num_nodes();
  for (const Eigen::Vector3d& x : right.X) left.X.push_back(x);
  for (Tet t : right.tets) {
    for (int& i : t) i += offset;
    left.tets.push_back(t);
  }
  HandConfig c;
  c.material.youngs_modulus_pa = 1e5;
  // Each handle holds its finger's outer face (the finger's "bone").
  c.handles = {{"left", Eigen::Vector3d(-kHalf - 0.0205, 0, 0.003), 0.012, {}},
               {"right", Eigen::Vector3d(kHalf + 0.0205, 0, 0.003), 0.012, {}}};
  return HandModel(std::move(left), c);
}

struct Box {
  Eigen::Vector3d p = Eigen::Vector3d::Zero(), v = Eigen::Vector3d::Zero(), w = Eigen::Vector3d::Zero();
};

// Constraint contacts of every finger node within 2 mm of the box (an axis-aligned
// cube: its rotation stays below a degree here), and the box's floor supports.
void collide(const HandModel& model, HandState& s, const Box& box, double mu) {
  s.contacts.clear();
  s.supports.clear();
  ContactBody body;
  body.mass_kg = kBoxMass;
  body.inertia_W = kBoxMass * (2 * kHalf) * (2 * kHalf) / 6 * Eigen::Matrix3d::Identity();
  body.p_com_W = box.p;
  body.v_W = box.v;
  body.w_W = box.w;
  s.bodies = {body};
  for (int i = 0; i < model.num_nodes(); ++i) {
    const Eigen::Vector3d q = s.x.segment<3>(3 * i) - box.p;
    const Eigen::Vector3d gap = q.cwiseAbs() - Eigen::Vector3d::Constant(kHalf);
    if (gap.maxCoeff() > 0.002) continue;
    Eigen::Index k;
    gap.maxCoeff(&k);  // the face the node is nearest to (least inside / least outside)
    PointContact c;
    const auto [tet, local] = model.node_tet(i);
    c.tet = tet;
    c.bary = Eigen::Vector4d::Unit(local);
    c.n_W = (q[k] >= 0 ? 1.0 : -1.0) * Eigen::Vector3d::Unit(k);
    c.depth_m = -gap[k];
    c.friction = mu;
    c.body = 0;
    c.constraint = true;
    s.contacts.push_back(c);
  }
  for (double sx : {-1.0, 1.0})
    for (double sy : {-1.0, 1.0}) {
      const Eigen::Vector3d corner = box.p + Eigen::Vector3d(sx * kHalf, sy * kHalf, -kHalf);
      if (corner.z() - kFloor > 0.002) continue;
      BodySupport b;
      b.p_W = corner;
      b.depth_m = kFloor - corner.z();
      b.friction = 0.5;
      s.supports.push_back(b);
    }
}

struct GraspResult {
  double lifted = 0;  // box height when the lift ends, m
  double slip = 0;    // its drop relative to the fingers over the 5 s hold, m
  double final_z = 0;
};

// Squeeze 0.4 s, lift 5 cm in 1 s, hold 5 s.
GraspResult grasp_lift_hold(double mu) {
  GraspResult out;
  double& lifted = out.lifted;
  const HandModel model = two_fingers();
  HandState s = make_rest_state(model);
  auto solver = make_solver(SolverKind::schur_cholmod);
  const double h = model.config().dt_s, squeeze = 0.004;
  Box box;
  std::vector<HandleState> rest = s.handles;
  double rel_start = 0, rel = 0;
  const int steps = static_cast<int>(6.4 / h);
  for (int k = 0; k < steps; ++k) {
    const double t = (k + 1) * h;
    const double in = squeeze * std::min(1.0, t / 0.4), up = 0.05 * std::clamp(t - 0.4, 0.0, 1.0);
    for (int j = 0; j < 2; ++j) {
      HandleTarget target;
      target.p_W = rest[j].p_WH + Eigen::Vector3d(j == 0 ? in : -in, 0, up);
      set_target(s, j, target);
    }
    collide(model, s, box, mu);
    EXPECT_EQ(step(model, s, *solver), StepStatus::ok) << "t " << t;
    box.v += s.bodies[0].dv_W;
    box.w += s.bodies[0].dw_W;
    box.p += h * box.v;
    const double fingers_z = 0.5 * (s.handles[0].p_WH.z() + s.handles[1].p_WH.z());
    rel = box.p.z() - fingers_z;
    if (std::abs(t - 1.4) < 0.5 * h) rel_start = rel;
    if (std::abs(t - 1.4) < 0.5 * h) lifted = box.p.z();
  }
  std::printf("mu %.2f: box lifted to %.4f m, dropped %.3f mm relative to the fingers over the 5 s hold\n", mu,
              lifted, 1e3 * (rel_start - rel));
  out.slip = rel_start - rel;
  out.final_z = box.p.z();
  return out;
}

TEST(Grasp, TwoFingersLiftAHundredGramBoxWithMu08AndHoldItFiveSeconds) {
  const GraspResult r = grasp_lift_hold(0.8);
  EXPECT_GT(r.lifted, 0.04);           // it came up with the fingers (5 cm lift)
  EXPECT_LT(std::abs(r.slip), 0.002);  // and stayed: slip < 2 mm over 5 s
}

TEST(Grasp, TheSameSqueezeWithMu005LetsTheBoxSlipOut) {
  const GraspResult r = grasp_lift_hold(0.05);
  EXPECT_LT(r.lifted, 0.02);   // the fingers went up 5 cm without it
  EXPECT_LT(r.final_z, 0.002);  // and it is back on the floor
}

}  // namespace
}  // namespace hapticd::hand
