// The spring hand of seed 002 (hand_models/spring): its laws against their formulas and closed
// forms, and its ODE rig against the skeleton it is built on, following the tracked hand, and
// at the stability bound it reports.
#include <gtest/gtest.h>

#include <cmath>
#include <numbers>

#include "hand_models/spring/spring_hand_rig.hpp"
#include "hand_models/spring/spring_law.hpp"

namespace hapticd::hand::spring {
namespace {

constexpr double kPi = std::numbers::pi;

struct OdeWorld {
  OdeWorld() {
    ensure_ode_for_this_thread();
    world = dWorldCreate();
    space = dSimpleSpaceCreate(nullptr);
    dWorldSetGravity(world, 0, 0, 0);
  }
  ~OdeWorld() {
    dSpaceDestroy(space);
    dWorldDestroy(world);
  }
  dWorldID world;
  dSpaceID space;
};

// theta(t) of I theta'' + b theta' + k theta = k theta0 from rest at 0 (underdamped).
double damped_step_response(double I, double k, double b, double theta0, double t) {
  const double wn = std::sqrt(k / I), zeta = b / (2 * std::sqrt(k * I)), wd = wn * std::sqrt(1 - zeta * zeta);
  return theta0 * (1 - std::exp(-zeta * wn * t) * (std::cos(wd * t) + zeta * wn / wd * std::sin(wd * t)));
}

// A ball of mass m, radius r, at distance L from a hinge on the static world, driven by the joint
// spring toward theta0 for `seconds`: the largest deviation from the closed form.
double joint_spring_deviation(double h, double seconds) {
  OdeWorld w;
  constexpr double m = 0.01, r = 0.005, L = 0.04, theta0 = 0.5;
  const SpringGains g{0.2, 2e-3};
  dBodyID b = dBodyCreate(w.world);
  dMass mass;
  dMassSetSphereTotal(&mass, m, r);
  dBodySetMass(b, &mass);
  dBodySetPosition(b, 0, L, 0);
  dJointID j = dJointCreateHinge(w.world, nullptr);
  dJointAttach(j, b, nullptr);
  dJointSetHingeAnchor(j, 0, 0, 0);
  dJointSetHingeAxis(j, 1, 0, 0);
  const double I = m * L * L + 0.4 * m * r * r;
  double worst = 0;
  const int steps = static_cast<int>(std::lround(seconds / h));
  for (int k = 1; k <= steps; ++k) {
    dJointAddHingeTorque(j, joint_spring_torque(g, theta0, dJointGetHingeAngle(j), dJointGetHingeAngleRate(j), 0.0));
    dWorldStep(w.world, h);
    worst = std::max(worst, std::abs(dJointGetHingeAngle(j) - damped_step_response(I, g.k, g.b, theta0, k * h)));
  }
  return worst;
}

TEST(SpringLaw, AJointSpringOnAHingeFollowsTheDampedOscillatorsClosedForm) {
  // I = 1.6e-5 kg m^2: w_n = 112 rad/s, zeta = 0.56; 0.2 s is 3.5 periods.
  const double coarse = joint_spring_deviation(1e-4, 0.2), fine = joint_spring_deviation(5e-5, 0.2);
  EXPECT_LT(coarse, 0.01 * 0.5);
  // ODE's semi-implicit Euler is first order: half the step, half the deviation.
  EXPECT_NEAR(coarse / fine, 2.0, 0.2) << coarse << " " << fine;
}

TEST(SpringLaw, ThePalmsRestoringTorqueTurnsTheSpringPalmTheSmallerWayTowardTheTrackedOne) {
  const double k_R = 3.0;
  const Eigen::Quaterniond q_s(Eigen::AngleAxisd(0.9, Eigen::Vector3d(1, 2, -1).normalized()));
  const Eigen::Vector3d a_local = Eigen::Vector3d(0.3, -0.5, 0.8).normalized();
  const Eigen::Vector3d a_W = q_s * a_local;
  // 0.7 rad about a (in the spring palm's frame): k_R 0.7 about a, in the world.
  const Eigen::Quaterniond q_t = q_s * Eigen::Quaterniond(Eigen::AngleAxisd(0.7, a_local));
  EXPECT_LT((palm_restoring_torque(k_R, q_s, q_t) - k_R * 0.7 * a_W).norm(), 1e-12);
  // The same orientation given by the other sign of its quaternion: the same torque.
  const Eigen::Quaterniond q_t_negated(-q_t.w(), -q_t.x(), -q_t.y(), -q_t.z());
  EXPECT_LT((palm_restoring_torque(k_R, q_s, q_t_negated) - k_R * 0.7 * a_W).norm(), 1e-12);
  // 3.6 rad about a is 2 pi - 3.6 = 2.68 rad about -a: that way, past pi.
  const Eigen::Quaterniond q_far = q_s * Eigen::Quaterniond(Eigen::AngleAxisd(3.6, a_local));
  EXPECT_LT((palm_restoring_torque(k_R, q_s, q_far) + k_R * (2 * kPi - 3.6) * a_W).norm(), 1e-12);
  // Just either side of pi: the torque's direction flips, its magnitude stays near k_R pi.
  const Eigen::Vector3d below =
      palm_restoring_torque(k_R, q_s, q_s * Eigen::Quaterniond(Eigen::AngleAxisd(kPi - 1e-3, a_local)));
  const Eigen::Vector3d above =
      palm_restoring_torque(k_R, q_s, q_s * Eigen::Quaterniond(Eigen::AngleAxisd(kPi + 1e-3, a_local)));
  EXPECT_NEAR(below.dot(a_W), k_R * (kPi - 1e-3), 1e-9);
  EXPECT_NEAR(above.dot(a_W), -k_R * (kPi - 1e-3), 1e-9);
  EXPECT_EQ(palm_restoring_torque(k_R, q_s, q_s).norm(), 0.0);
}

TEST(SpringLaw, ThePalmsDampingTorqueOpposesTheRelativeAngularVelocityPerSimulationStep) {
  const double b_R = 0.4, h = 1e-3;
  // The spring palm still; the tracked palm turned 0.05 rad about z between two readings 5 steps
  // apart: 10 rad/s, which the damper follows with b_R 10 N m about +z.
  const Eigen::Quaterniond still = Eigen::Quaterniond::Identity();
  const Eigen::Quaterniond turned(Eigen::AngleAxisd(0.05, Eigen::Vector3d::UnitZ()));
  EXPECT_LT((palm_damping_torque(b_R, still, turned, 5, h) - b_R * 10.0 * Eigen::Vector3d::UnitZ()).norm(), 1e-9);
  // Both turning: for small rotations, -b_R (w_s - w_t) to second order in the step's angles.
  const Eigen::Vector3d w_s(3.0, -1.0, 2.0), w_t(-2.0, 4.0, 1.0);
  const Eigen::Quaterniond q_ws(Eigen::AngleAxisd(w_s.norm() * h, w_s.normalized()));
  const Eigen::Quaterniond q_wt(Eigen::AngleAxisd(w_t.norm() * 4 * h, w_t.normalized()));  // 4 steps
  // The rotation vector of exp(h w_s) exp(-h w_t) to second order (Baker-Campbell-Hausdorff):
  // h (w_s - w_t) - h^2 (w_s x w_t) / 2; the third-order terms are ~1e-6 rad/s here.
  const Eigen::Vector3d expected = -b_R * (w_s - w_t - 0.5 * h * w_s.cross(w_t));
  EXPECT_LT((palm_damping_torque(b_R, q_ws, q_wt, 4, h) - expected).norm(), 2e-5);
  EXPECT_GT((expected + b_R * (w_s - w_t)).norm(), 1e-3) << "the second-order term is resolved";
  // The tracked rotation over its readings is taken the smaller way: 2 pi - 0.05 about -z is 0.05 about z.
  const Eigen::Quaterniond long_way(Eigen::AngleAxisd(2 * kPi - 0.05, -Eigen::Vector3d::UnitZ()));
  EXPECT_LT((palm_damping_torque(b_R, still, long_way, 5, h) - b_R * 10.0 * Eigen::Vector3d::UnitZ()).norm(), 1e-9);
}

TrackedHand posed_hand(bool left) {
  TrackedHand t;
  t.p_W = Eigen::Vector3d(0.1, -0.2, 0.3);
  t.q_W = Eigen::Quaterniond(Eigen::AngleAxisd(0.8, Eigen::Vector3d(0.2, 1.0, 0.4).normalized()));
  t.angles = rest_joint_angles();
  for (int f = 0; f < kHandFingers; ++f)
    for (int k = 1; k < 4; ++k) t.angles.finger[f][k] += 0.1 * k + 0.05 * f;
  (void)left;
  return t;
}

TEST(SpringHandRig, IsBuiltOnTheSkeletonWithItsJointAnglesReadBack) {
  for (const bool left : {false, true}) {
    OdeWorld w;
    const TrackedHand t = posed_hand(left);
    SpringHandRig rig(w.world, w.space, SpringHandParams{}, left, t);
    const SkeletonPose s = skeleton_pose(t.angles, left);
    const Eigen::Matrix3d R = t.q_W.toRotationMatrix();
    EXPECT_LT((rig.joint_angles().vector() - t.angles.vector()).norm(), 1e-9) << left;
    EXPECT_LT((rig.palm_position() - t.p_W).norm(), 1e-12);
    for (int i = 0; i < kHandPhalanges; ++i) {
      const Eigen::Isometry3d T = rig.phalanx_pose(i);
      EXPECT_LT((T.linear() - R * s.R[i]).norm(), 1e-9) << i;
      // The body on its bone: the segment from its joint to the next, through the body's y axis.
      const int f = i / 3, k = i % 3;
      const Eigen::Vector3d a = t.p_W + R * s.joints[f][k], b = t.p_W + R * s.joints[f][k + 1];
      EXPECT_LT((a - T.translation()).cross(b - a).norm() / (b - a).norm(), 1e-9) << i;
    }
    for (int f = 0; f < kHandFingers; ++f) EXPECT_LT((rig.tip_W(f) - (t.p_W + R * s.joints[f][3])).norm(), 1e-12);
    // Each hinge turns its segment the way the skeleton's angle does: a small rotation about the
    // hinge applied to the build pose is what the skeleton gives for the angle plus that rotation.
    for (int dof = 0; dof < kHandJointDofs; ++dof) {
      const int f = dof / 4, segment = 3 * f + std::max(dof % 4 - 1, 0);
      Eigen::Matrix<double, kHandJointDofs, 1> q = t.angles.vector();
      q[dof] += 1e-4;
      const Eigen::Matrix3d turned = R * skeleton_pose(HandJointAngles::from_vector(q), left).R[segment];
      const Eigen::Matrix3d by_hinge =
          Eigen::AngleAxisd(1e-4, rig.joint_axis_W(dof)).toRotationMatrix() * R * s.R[segment];
      EXPECT_LT((turned - by_hinge).norm(), 1e-9) << dof;
    }
  }
}

TEST(SpringHandRig, PlacedOnAPoseItHasThatPosesJointAnglesAtRest) {
  OdeWorld w;
  TrackedHand start;
  start.angles = rest_joint_angles();
  SpringHandRig rig(w.world, w.space, SpringHandParams{}, false, start);
  dBodySetLinearVel(rig.phalanx_body(4), 1, 2, 3);
  const TrackedHand t = posed_hand(false);
  rig.place(t);
  EXPECT_LT((rig.joint_angles().vector() - t.angles.vector()).norm(), 1e-9);
  EXPECT_LT(rig.joint_rates().norm(), 1e-12);
  const SkeletonPose s = skeleton_pose(t.angles);
  for (int f = 0; f < kHandFingers; ++f) EXPECT_LT((rig.tip_W(f) - (t.p_W + t.q_W * s.joints[f][3])).norm(), 1e-9);
  // Held there by its springs: the first step moves nothing.
  rig.set_tracked(t);
  rig.apply_springs(rig.max_stable_step());
  dWorldStep(w.world, rig.max_stable_step());
  EXPECT_LT((rig.joint_angles().vector() - t.angles.vector()).norm(), 1e-9);
  EXPECT_LT((rig.palm_position() - t.p_W).norm(), 1e-12);
}

struct FollowResult {
  double joint_error = 0, palm_error_m = 0, palm_angle = 0, tip_error_m = 0, largest_joint_error = 0;
  bool diverged = false;
  double h_s = 0;
};

// The rig built at rest, then tracked to posed_hand() at once; ODE stepped at h for `seconds`.
FollowResult follow(double h_factor, double seconds, bool left = false) {
  OdeWorld w;
  TrackedHand start;
  start.angles = rest_joint_angles();
  SpringHandRig rig(w.world, w.space, SpringHandParams{}, left, start);
  const double h = h_factor * rig.max_stable_step();
  const TrackedHand goal = posed_hand(left);
  rig.set_tracked(goal);
  rig.set_tracked(goal);  // held: the tracked hand is still
  FollowResult r;
  for (int k = 0; k < static_cast<int>(seconds / h); ++k) {
    rig.apply_springs(h);
    dWorldStep(w.world, h);
    const double e = (rig.joint_angles().vector() - goal.angles.vector()).cwiseAbs().maxCoeff();
    r.largest_joint_error = std::max(r.largest_joint_error, e);
    // Diverging: stop before ODE meets a NaN (it aborts the process).
    if (!(r.largest_joint_error < kPi) || !(rig.joint_rates().cwiseAbs().maxCoeff() < 1e3)) {
      r.diverged = true;
      break;
    }
  }
  r.h_s = h;
  r.joint_error = (rig.joint_angles().vector() - goal.angles.vector()).cwiseAbs().maxCoeff();
  r.palm_error_m = (rig.palm_position() - goal.p_W).norm();
  r.palm_angle = rig.palm_orientation().angularDistance(goal.q_W);
  const SkeletonPose s = skeleton_pose(goal.angles, left);
  for (int f = 0; f < kHandFingers; ++f)
    r.tip_error_m = std::max(r.tip_error_m, (rig.tip_W(f) - (goal.p_W + goal.q_W * s.joints[f][3])).norm());
  return r;
}

TEST(SpringHandRig, TheSpringHandSettlesOnTheTrackedHand) {
  for (const bool left : {false, true}) {
    // A jump of 0.1-0.5 rad at every flexion joint, 0.37 m and 0.8 rad at the palm.
    const FollowResult r = follow(1.0, 3.0, left);
    EXPECT_LT(r.joint_error, 1e-3) << left;
    EXPECT_LT(r.palm_error_m, 1e-4);
    EXPECT_LT(r.palm_angle, 1e-3);
    EXPECT_LT(r.tip_error_m, 1e-4);
    std::printf("%s hand: stable step %.3g ms, largest joint error on the way %.2f rad\n", left ? "left" : "right",
                1e3 * r.h_s, r.largest_joint_error);
  }
}

TEST(SpringHandRig, ItsStableStepIsWithinAFactorOfThreeOfWhereTheExplicitSpringsDiverge) {
  OdeWorld w;
  const double h = SpringHandRig(w.world, w.space, SpringHandParams{}, false, TrackedHand{}).max_stable_step();
  EXPECT_GT(h, 1e-4);
  EXPECT_LT(h, 1e-2);
  // The bound keeps a margin of 2 for one spring on one body; the hand's coupled bodies keep some.
  const FollowResult margin = follow(1.5, 1.0), past = follow(3.0, 1.0);
  EXPECT_FALSE(margin.diverged);
  EXPECT_LT(margin.joint_error, 0.05);
  EXPECT_TRUE(past.diverged) << "three times the bound: joint error " << past.joint_error << " rad after 1 s";
}

TEST(SpringHandRig, TheGloveForceOfAFingerHeldStraightIsSection45sFormula) {
  OdeWorld w;
  TrackedHand straight;
  for (int f = 0; f < kHandFingers; ++f) straight.angles.finger[f] = {0.0, 0.0, 0.0, 0.0};
  SpringHandParams p;
  p.feedback_a = {1.0, 0.5, 0.25, 2.0};
  SpringHandRig rig(w.world, w.space, p, false, straight);
  // The tracked index flexed 0.2 rad at each joint and held there; the spring index still straight.
  TrackedHand flexed = straight;
  flexed.angles.finger[1] = {0.0, 0.2, 0.2, 0.2};
  rig.set_tracked(flexed);
  rig.set_tracked(flexed);
  rig.apply_springs(1e-3);
  // By hand: the index (skeleton: base (-2.9, 4.3, 0.15) cm, bones 4.0, 2.5, 2.0 cm) lies along +y;
  // its flexion axis is -x, so axis x d points palmar (-z) with |f_tau_k| = tau / |d_k|, tau = 0.1
  // N m, |d| = 8.5, 4.5, 2.0 cm; the actuator pulls dorsal (+z).
  const double tau = p.joint.k * 0.2;
  const double f_tau_z = -(1.0 * tau / 0.085 + 0.5 * tau / 0.045 + 0.25 * tau / 0.020);
  // The fingertip spring without the palm: k_tip times the tracked tip's drop below the straight one.
  const double drop = 0.040 * std::sin(0.2) + 0.025 * std::sin(0.4) + 0.020 * std::sin(0.6);
  const double f_ls_z = -p.tip.k * drop;
  EXPECT_NEAR(rig.tip_force_without_palm(1).z(), f_ls_z, 1e-9);
  EXPECT_NEAR(rig.feedback(1, true), -(f_tau_z + 2.0 * f_ls_z), 1e-9);
  EXPECT_GT(rig.feedback(1, true), 0.0) << "it resists the flexion the object stops";
  EXPECT_EQ(rig.feedback(1, false), 0.0) << "a finger that touches nothing: no force (section 4.6.2)";
  EXPECT_NEAR(rig.feedback(2, true), 0.0, 1e-12) << "the middle finger is where it is tracked";
}

}  // namespace
}  // namespace hapticd::hand::spring
