#include <gtest/gtest.h>
#include <unistd.h>

#include <Eigen/Geometry>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <numbers>
#include <random>
#include <string>

#include "allocation_counter.hpp"
#include "clients/sim/glove_model.hpp"
#include "clients/sim/glove_servo.hpp"
#include "clients/sim/glove_simulation.hpp"
#include "clients/sim/glove_trajectory.hpp"
#include "protocol/codec.hpp"

// The simulated glove's hand: frame layout, forward kinematics, the Jacobian against finite
// differences of the skeleton, the joint impedance against its closed forms, and a fingertip force
// deflecting a finger by what the Jacobian and the stiffness predict.

namespace hapticd::sim {
namespace {

constexpr double kDeg = std::numbers::pi / 180.0;
const GloveParams kParams;  // the documented defaults

// A posture drawn around rest: +-40 degrees on every joint.
hand::HandJointAngles random_posture(std::mt19937& rng) {
  std::uniform_real_distribution<double> u(-40.0 * kDeg, 40.0 * kDeg);
  hand::HandJointAngles a = hand::rest_joint_angles();
  for (auto& finger : a.finger)
    for (double& q : finger) q += u(rng);
  return a;
}

Eigen::Vector3d vee(const Eigen::Matrix3d& S) { return {S(2, 1), S(0, 2), S(1, 0)}; }

// The 6 x 20 Jacobian of phalanx i by central differences of skeleton_pose: linear rows from the
// segment centre, angular rows from vee(dR/dq R^T).
Eigen::Matrix<double, 6, hand::kHandJointDofs> finite_difference_jacobian(const hand::HandJointAngles& a, bool left,
                                                                          int i, double h = 1e-6) {
  Eigen::Matrix<double, 6, hand::kHandJointDofs> J;
  const hand::SkeletonPose at = hand::skeleton_pose(a, left);
  for (int j = 0; j < hand::kHandJointDofs; ++j) {
    JointVector plus = a.vector(), minus = a.vector();
    plus[j] += h;
    minus[j] -= h;
    const hand::SkeletonPose p = hand::skeleton_pose(hand::HandJointAngles::from_vector(plus), left);
    const hand::SkeletonPose m = hand::skeleton_pose(hand::HandJointAngles::from_vector(minus), left);
    J.block<3, 1>(0, j) = (p.centre[i] - m.centre[i]) / (2.0 * h);
    J.block<3, 1>(3, j) = vee((p.R[i] - m.R[i]) / (2.0 * h) * at.R[i].transpose());
  }
  return J;
}

// --- Frames ----------------------------------------------------------------------------------------

TEST(GloveFrames, SixteenFramesArePalmThenEveryPhalanxSixArePalmThenTheDistalOnes) {
  EXPECT_EQ(glove_frame_phalanx(16, 0), -1);
  for (int i = 0; i < 15; ++i) EXPECT_EQ(glove_frame_phalanx(16, 1 + i), i);
  EXPECT_EQ(glove_frame_phalanx(16, 16), -1);
  EXPECT_EQ(glove_frame_phalanx(6, 0), -1);
  for (int f = 0; f < 5; ++f) EXPECT_EQ(glove_frame_phalanx(6, 1 + f), 3 * f + 2);
  EXPECT_EQ(glove_frame_phalanx(6, 6), -1);
  EXPECT_EQ(glove_frame_phalanx(5, 1), -1) << "only 16 and 6";
  EXPECT_EQ(glove_frame_group(16, 0), kPalmGroup);
  EXPECT_EQ(glove_frame_group(16, 6), 1) << "index distal";
  EXPECT_EQ(glove_frame_group(6, 5), 4) << "little distal";
  EXPECT_EQ(glove_frame_name(16, 0), "palm");
  EXPECT_EQ(glove_frame_name(16, 1), "thumb_proximal");
  EXPECT_EQ(glove_frame_name(16, 8), "middle_middle");
  EXPECT_EQ(glove_frame_name(16, 15), "little_distal");
  EXPECT_EQ(glove_frame_name(6, 2), "index_distal");
}

TEST(GloveFrames, TheHelloDeclaresAGloveWithEveryFrameInIdOrder) {
  for (int frames : {16, 6}) {
    const protocol::Hello h = glove_hello(frames, "glove_tests", 1000);
    EXPECT_EQ(h.device_kind, protocol::DeviceKind::kGlove);
    EXPECT_EQ(h.requested_rate_hz, 1000u);
    EXPECT_EQ(h.client_name.view(), "glove_tests");
    ASSERT_EQ(h.frames.size(), static_cast<std::size_t>(frames));
    for (int id = 0; id < frames; ++id) {
      EXPECT_EQ(h.frames[id].id, id);
      EXPECT_EQ(h.frames[id].dof, 6);
      EXPECT_EQ(h.frames[id].name.view(), glove_frame_name(frames, id));
    }
    EXPECT_EQ(protocol::validate(h), protocol::RejectReason::kNone);
  }
  EXPECT_THROW((void)glove_hello(5, "x", 1000), std::invalid_argument);
  EXPECT_THROW((void)glove_hello(16, std::string(65, 'x'), 1000), std::invalid_argument);
}

// --- Forward kinematics -----------------------------------------------------------------------------

TEST(GloveKinematics, FramePosesAreTheSkeletonsSegmentFramesComposedWithThePalmPose) {
  std::mt19937 rng(7);
  const RigidPose palm{Eigen::Vector3d(0.1, -0.2, 0.3),
                       Eigen::Quaterniond(Eigen::AngleAxisd(0.7, Eigen::Vector3d(1.0, 2.0, -0.5).normalized()))};
  const Eigen::Matrix3d R_palm = palm.q.toRotationMatrix();
  for (bool left : {false, true})
    for (int frames : {16, 6}) {
      const hand::HandJointAngles a = random_posture(rng);
      const hand::SkeletonPose s = hand::skeleton_pose(a, left);
      const auto poses = glove_frame_poses(s, palm, frames);
      EXPECT_EQ(poses[0].p_m, palm.p_m);
      EXPECT_EQ(poses[0].q.coeffs(), palm.q.coeffs());
      for (int id = 1; id < frames; ++id) {
        const int i = glove_frame_phalanx(frames, id);
        EXPECT_LT((poses[id].p_m - (palm.p_m + R_palm * s.centre[i])).norm(), 1e-15) << id;
        EXPECT_LT((poses[id].q.toRotationMatrix() - R_palm * s.R[i]).norm(), 1e-15) << id;
        // The segment's far joint lies half a bone length along the frame's y axis.
        const int f = i / 3, k = i % 3;
        const Eigen::Vector3d far_joint =
            poses[id].p_m + poses[id].q * Eigen::Vector3d(0.0, 0.5 * hand::finger_geometry()[f].length[k], 0.0);
        EXPECT_LT((far_joint - (palm.p_m + R_palm * s.joints[f][k + 1])).norm(), 1e-15) << id;
      }
      for (int id = frames; id < kMaxGloveFrames; ++id) EXPECT_EQ(poses[id].p_m, Eigen::Vector3d::Zero());
    }
}

TEST(GloveKinematics, ALeftHandsFramesAreTheMirrorImageOfTheRightHands) {
  std::mt19937 rng(8);
  const hand::HandJointAngles a = random_posture(rng);
  const auto right = glove_frame_poses(hand::skeleton_pose(a, false), {}, 16);
  const auto left = glove_frame_poses(hand::skeleton_pose(a, true), {}, 16);
  const Eigen::Matrix3d M = Eigen::Vector3d(-1.0, 1.0, 1.0).asDiagonal();
  for (int id = 1; id < 16; ++id) {
    EXPECT_EQ(left[id].p_m, M * right[id].p_m) << id;
    EXPECT_LT((left[id].q.toRotationMatrix() - M * right[id].q.toRotationMatrix() * M).norm(), 1e-15) << id;
  }
}

// --- Jacobian -------------------------------------------------------------------------------------

TEST(GloveJacobian, MatchesFiniteDifferencesOfTheSkeletonForBothHands) {
  std::mt19937 rng(11);
  double worst = 0.0;
  for (int trial = 0; trial < 6; ++trial)
    for (bool left : {false, true}) {
      const hand::HandJointAngles a = trial == 0 ? hand::rest_joint_angles() : random_posture(rng);
      const auto J = phalanx_jacobians(a, hand::skeleton_pose(a, left), left);
      for (int i = 0; i < hand::kHandPhalanges; ++i) {
        const Eigen::Matrix<double, 6, hand::kHandJointDofs> fd = finite_difference_jacobian(a, left, i);
        Eigen::Matrix<double, 6, hand::kHandJointDofs> analytic =
            Eigen::Matrix<double, 6, hand::kHandJointDofs>::Zero();
        analytic.block<6, 4>(0, 4 * (i / 3)) = J[i];
        // Central differences of h = 1e-6 rad: O(h^2) truncation, ~1e-10 round-off.
        const double error = (analytic - fd).cwiseAbs().maxCoeff();
        worst = std::max(worst, error);
        EXPECT_LT(error, 1e-8) << "phalanx " << i << (left ? " left" : " right") << "\nanalytic\n"
                               << analytic << "\nfinite differences\n"
                               << fd;
      }
    }
  EXPECT_GT(worst, 0.0) << "the comparison must look at numbers";
}

TEST(GloveJacobian, TorquesAreTheTransposeTimesTheWrenchesAndMatchVirtualWork) {
  // tau . dq = sum_i (f_i . dp_i + t_i . dtheta_i) for a small joint move: the torques do the
  // wrenches' work.
  std::mt19937 rng(12);
  std::normal_distribution<double> n(0.0, 1.0);
  const hand::HandJointAngles a = random_posture(rng);
  const hand::SkeletonPose s = hand::skeleton_pose(a);
  std::array<Wrench6, hand::kHandPhalanges> w;
  for (Wrench6& x : w) x << n(rng), n(rng), n(rng), 0.01 * n(rng), 0.01 * n(rng), 0.01 * n(rng);
  const JointVector tau = joint_torques(phalanx_jacobians(a, s, false), w);
  JointVector dq;
  for (int j = 0; j < hand::kHandJointDofs; ++j) dq[j] = 1e-7 * n(rng);
  const hand::SkeletonPose plus = hand::skeleton_pose(hand::HandJointAngles::from_vector(a.vector() + dq));
  const hand::SkeletonPose minus = hand::skeleton_pose(hand::HandJointAngles::from_vector(a.vector() - dq));
  double work = 0.0;
  for (int i = 0; i < hand::kHandPhalanges; ++i) {
    const Eigen::Vector3d dp = 0.5 * (plus.centre[i] - minus.centre[i]);
    const Eigen::Vector3d dtheta = vee(0.5 * (plus.R[i] - minus.R[i]) * s.R[i].transpose());
    work += w[i].head<3>().dot(dp) + w[i].tail<3>().dot(dtheta);
  }
  EXPECT_NEAR(tau.dot(dq), work, 1e-6 * std::abs(work));
}

// --- Joint impedance --------------------------------------------------------------------------------

TEST(GloveImpedance, AConstantJointTorqueDeflectsEachJointByTorqueOverStiffness) {
  JointState s;
  const JointVector q_C = hand::rest_joint_angles().vector();
  s.q_rad = q_C;
  JointVector tau;
  for (int j = 0; j < hand::kHandJointDofs; ++j) tau[j] = 0.01 * (j % 7 - 3);  // -0.03 .. 0.03 N m
  for (int n = 0; n < 3000; ++n) step_joints(kParams, s, q_C, JointVector::Zero(), tau, 1e-3);
  for (int j = 0; j < hand::kHandJointDofs; ++j) {
    const double expected = tau[j] / kParams.of_dof(j).stiffness_n_m_per_rad;
    EXPECT_NEAR(s.q_rad[j] - q_C[j], expected, 1e-12) << "joint " << j;
    EXPECT_NEAR(s.qd_rad_s[j], 0.0, 1e-12);
  }
  EXPECT_NEAR(s.q_rad[5] - q_C[5], 0.01 * (5 - 3) / 2.0, 1e-12) << "index MCP: 0.02 N m / 2 N m/rad = 10 mrad";
}

// Step of q_C by A at t = 0 (commanded rate 0): I q'' + b q' + k q = k A, underdamped:
// q = A [1 - e^{-zeta w t} (cos w_d t + zeta / sqrt(1 - zeta^2) sin w_d t)].
double step_closed_form(const JointImpedance& p, double A, double t) {
  const double w = std::sqrt(p.stiffness_n_m_per_rad / p.inertia_kg_m2);
  const double zeta = p.damping_n_m_s_per_rad / (2.0 * std::sqrt(p.stiffness_n_m_per_rad * p.inertia_kg_m2));
  const double wd = w * std::sqrt(1.0 - zeta * zeta);
  return A *
         (1.0 - std::exp(-zeta * w * t) * (std::cos(wd * t) + zeta / std::sqrt(1.0 - zeta * zeta) * std::sin(wd * t)));
}

// Largest |simulated - closed form| over 0.1 s of a 0.1 rad step, per joint kind (0..3).
std::array<double, 4> step_response_errors(double dt) {
  const double A = 0.1;
  JointState s;
  const JointVector q_C = JointVector::Constant(A);
  std::array<double, 4> worst{};
  const int steps = static_cast<int>(std::lround(0.1 / dt));
  for (int n = 1; n <= steps; ++n) {
    step_joints(kParams, s, q_C, JointVector::Zero(), JointVector::Zero(), dt);
    for (int k = 0; k < 4; ++k)
      worst[k] = std::max(worst[k], std::abs(s.q_rad[4 + k] - step_closed_form(kParams.joint[k], A, n * dt)));
  }
  return worst;
}

TEST(GloveImpedance, TheDocumentedParametersAreWellDampedFingers) {
  // glove_model.hpp's table: natural frequency and damping ratio of each joint kind.
  const double expected_hz[4] = {15.9, 22.5, 35.6, 50.3}, expected_zeta[4] = {0.70, 0.71, 0.67, 0.70};
  for (int k = 0; k < 4; ++k) {
    const JointImpedance& p = kParams.joint[k];
    const double w = std::sqrt(p.stiffness_n_m_per_rad / p.inertia_kg_m2);
    EXPECT_NEAR(w / (2.0 * std::numbers::pi), expected_hz[k], 0.05) << k;
    EXPECT_NEAR(p.damping_n_m_s_per_rad / (2.0 * std::sqrt(p.stiffness_n_m_per_rad * p.inertia_kg_m2)),
                expected_zeta[k], 0.005)
        << k;
    EXPECT_GE(p.stiffness_n_m_per_rad, 0.5);
    EXPECT_LE(p.stiffness_n_m_per_rad, 3.0);
  }
  const DeviceParams& palm = kParams.palm;
  EXPECT_NEAR(palm.arm_damping_n_s_per_m / (2.0 * std::sqrt(palm.arm_stiffness_n_per_m * palm.mass_kg)), 0.56, 0.005);
}

TEST(GloveImpedance, AStepResponseFollowsTheSecondOrderClosedFormAtFirstOrderInDt) {
  const std::array<double, 4> e1 = step_response_errors(1e-5), e2 = step_response_errors(0.5e-5);
  for (int k = 0; k < 4; ++k) {
    EXPECT_LT(e1[k], 0.01 * 0.1) << "joint kind " << k << ": within 1 % of the step at dt = 10 us";
    EXPECT_NEAR(e1[k] / e2[k], 2.0, 0.1) << "joint kind " << k << ": implicit Euler is first order";
  }
}

TEST(GloveImpedance, AtTheServoRateAStepOvershootsAsTheDiscreteStepSaysAndSettles) {
  // At 1 kHz implicit Euler damps the faster joints visibly (w dt up to 0.32). Its step maps the
  // error e = q - q_C and the rate v as
  //   [e, v]_{n+1} = M [e, v]_n,  M = [[1 - dt^2 k / D, dt I / D], [-dt k / D, I / D]],
  //   D = I + dt b + dt^2 k,
  // whose eigenvalues r e^{+-i theta} give the overshoot of a step, r^{pi / theta} (the continuous
  // exp(-pi zeta / sqrt(1 - zeta^2)) with e^{-zeta w dt} -> r and w_d dt -> theta), below the
  // continuous one. After 5 / (zeta w) every joint is within 1 % of the command.
  const double A = 0.1, dt = 1e-3;
  JointState s;
  const JointVector q_C = JointVector::Constant(A);
  std::array<double, 4> peak{};
  for (int n = 1; n <= 300; ++n) {
    step_joints(kParams, s, q_C, JointVector::Zero(), JointVector::Zero(), dt);
    for (int k = 0; k < 4; ++k) {
      peak[k] = std::max(peak[k], s.q_rad[4 + k]);
      const JointImpedance& p = kParams.joint[k];
      const double zeta_w = p.damping_n_m_s_per_rad / (2.0 * p.inertia_kg_m2);
      if (n * dt > 5.0 / zeta_w) {
        EXPECT_NEAR(s.q_rad[4 + k], A, 0.01 * A) << k << " at " << n * dt << " s";
      }
    }
  }
  for (int k = 0; k < 4; ++k) {
    const JointImpedance& p = kParams.joint[k];
    const double I = p.inertia_kg_m2, K = p.stiffness_n_m_per_rad, b = p.damping_n_m_s_per_rad;
    const double D = I + dt * b + dt * dt * K;
    const double trace = 1.0 - dt * dt * K / D + I / D, det = I / D;
    const double r = std::sqrt(det), theta = std::atan2(std::sqrt(det - 0.25 * trace * trace), 0.5 * trace);
    const double discrete = std::pow(r, std::numbers::pi / theta);
    const double zeta = b / (2.0 * std::sqrt(K * I));
    const double continuous = std::exp(-std::numbers::pi * zeta / std::sqrt(1.0 - zeta * zeta));
    EXPECT_NEAR(peak[k] / A - 1.0, discrete, 0.002) << "joint kind " << k;
    EXPECT_LT(discrete, continuous) << "numerical damping only removes energy";
    EXPECT_GT(discrete, 0.5 * continuous) << "but keeps the finger's character at the servo rate";
  }
}

TEST(GloveImpedance, StepJointsReturnsTheWorkOfTheExternalTorque) {
  JointState s;
  JointVector tau = JointVector::Zero();
  tau[5] = 0.05;
  const JointVector before = s.q_rad;
  const double work = step_joints(kParams, s, JointVector::Zero(), JointVector::Zero(), tau, 1e-3);
  EXPECT_DOUBLE_EQ(work, tau.dot(s.q_rad - before));
  EXPECT_GT(work, 0.0);
}

// --- A fingertip force on the simulated hand -------------------------------------------------------

class GloveHold : public ::testing::Test {
 protected:
  void TearDown() override { std::filesystem::remove_all(dir_); }
  // A trajectory holding `a` (one CSV row).
  GloveTrajectory hold(const hand::HandJointAngles& a) {
    std::filesystem::create_directories(dir_);
    const std::string path = (dir_ / "hold.csv").string();
    std::ofstream out(path);
    out.precision(17);
    out << 0.0;
    for (int j = 0; j < hand::kHandJointDofs; ++j) out << ',' << a.vector()[j] / kDeg;
    out << '\n';
    out.close();
    return GloveTrajectory::from_csv(path);
  }
  const std::filesystem::path dir_ =
      std::filesystem::temp_directory_path() / ("hapticd_glove_tests_" + std::to_string(::getpid()));
};

TEST_F(GloveHold, AnOpposingFingertipForceReducesTheFlexionByWhatTheJacobianAndStiffnessPredict) {
  // The power grasp held; the server pushes the index's distal phalanx dorsally (along its frame's
  // +z, the pad pushed back) with 1 N, and the palm with 2 N. At rest the joints satisfy
  //   K (q - q_C) = J(q)^T f,
  // solved here by fixed-point iteration with the Jacobian from finite differences of the skeleton
  // (independent of phalanx_jacobians), with the force fixed in D as the simulation holds it.
  for (bool left : {false, true}) {
    const hand::HandJointAngles grasp = power_grasp_posture();
    GloveTrajectory trajectory = hold(grasp);
    const Eigen::Quaterniond q_palm(Eigen::AngleAxisd(0.4, Eigen::Vector3d(0.3, -1.0, 0.2).normalized()));
    trajectory.set_palm_orientation(q_palm);
    GloveSimulation sim(trajectory, kParams, 16, left, 1e-3);
    const int index_distal = 1 + 5;
    const Eigen::Vector3d f_D = sim.frame_poses()[index_distal].q * Eigen::Vector3d::UnitZ();
    sim.set_wrench(index_distal, {f_D.x(), f_D.y(), f_D.z()}, {}, true);
    sim.set_wrench(0, {0.0, 0.0, 2.0}, {}, false);
    for (int n = 0; n < 3000; ++n) {
      sim.advance();
      sim.record_tick();
    }

    const Eigen::Vector3d f_H = q_palm.conjugate() * f_D;
    JointVector q = grasp.vector();
    for (int iteration = 0; iteration < 50; ++iteration) {
      const auto J = finite_difference_jacobian(hand::HandJointAngles::from_vector(q), left, 5);
      const JointVector tau = J.topRows<3>().transpose() * f_H;
      for (int j = 0; j < hand::kHandJointDofs; ++j)
        q[j] = grasp.vector()[j] + tau[j] / kParams.of_dof(j).stiffness_n_m_per_rad;
    }
    const JointVector deflection = sim.joints().q_rad - grasp.vector();
    EXPECT_LT((sim.joints().q_rad - q).cwiseAbs().maxCoeff(), 1e-8) << "simulated\n"
                                                                    << deflection.transpose() << "\npredicted\n"
                                                                    << (q - grasp.vector()).transpose();
    // The index opens: each of its flexions is reduced, by milliradians to a few centiradians; the
    // other fingers do not move at all.
    for (int k = 1; k < 4; ++k) {
      EXPECT_LT(deflection[4 + k], -1e-3) << "index flexion " << k;
      EXPECT_GT(deflection[4 + k], -0.1) << "index flexion " << k;
    }
    for (int j = 0; j < hand::kHandJointDofs; ++j)
      if (j / 4 != 1) {
        EXPECT_EQ(deflection[j], 0.0) << j;
      }
    // The palm: displaced by f / k_arm along +z.
    EXPECT_NEAR(sim.palm().p_DT_m.z, 2.0 / kParams.palm.arm_stiffness_n_per_m, 1e-9);
    // The figures: the index held 1 N and was in contact every tick, its lag the largest deflection.
    const GloveGroupFigures index = sim.group_figures(1);
    EXPECT_DOUBLE_EQ(index.force_max_n, 1.0);
    EXPECT_NEAR(index.force_rms_n, 1.0, 1e-12);
    EXPECT_EQ(index.contact_fraction, 1.0);
    // The largest over the run: the force arrives as a step, so the joints overshoot their rest
    // deflection by at most the continuous step overshoot (< 6 %).
    const double rest_lag = (q - grasp.vector()).segment<4>(4).cwiseAbs().maxCoeff();
    EXPECT_GE(index.joint_lag_max_rad, rest_lag - 1e-8);
    EXPECT_LE(index.joint_lag_max_rad, 1.06 * rest_lag);
    EXPECT_EQ(sim.group_figures(2).joint_lag_max_rad, 0.0);
    EXPECT_EQ(sim.group_figures(2).force_max_n, 0.0);
    EXPECT_EQ(sim.group_figures(kPalmGroup).force_max_n, 2.0);
    EXPECT_EQ(sim.group_figures(kPalmGroup).contact_fraction, 0.0);
    EXPECT_NEAR(sim.force_max_n(), (f_D + Eigen::Vector3d(0.0, 0.0, 2.0)).norm(), 1e-12);
    // Penetration: the distal frame's distance from where the commanded posture puts it.
    const auto commanded = glove_frame_poses(hand::skeleton_pose(grasp, left), {Eigen::Vector3d::Zero(), q_palm}, 16);
    const auto actual = sim.frame_poses();
    // The palm's 1 cm (2 N / 200 N/m along z) is part of it; over the run the palm overshoots by
    // exp(-pi zeta / sqrt(1 - zeta^2)) = 12 % (zeta 0.56) and the finger by < 6 %.
    const Eigen::Vector3d at_rest = actual[index_distal].p_m - commanded[index_distal].p_m;
    const Eigen::Vector3d palm_part(0.0, 0.0, 2.0 / kParams.palm.arm_stiffness_n_per_m);
    EXPECT_GE(sim.penetration_max_m(), at_rest.norm() - 1e-9);
    EXPECT_LE(sim.penetration_max_m(), 1.12 * palm_part.norm() + 1.06 * (at_rest - palm_part).norm());
    EXPECT_GT((at_rest - palm_part).norm(), 1e-3) << "the finger's own deflection: millimetres";
    EXPECT_EQ(sim.contact_ticks(), 3000u);
  }
}

TEST_F(GloveHold, AForceAgainstTheClosingFingersSlowsThem) {
  // The grasp closes the fingers over 1 s; a 1 N push on the index's distal pad, along the pad's
  // normal (the distal frame's +z, updated every step like a contact's normal), opposes flexion
  // at all three joints of a finger curling into the grasp, and keeps its flexion behind the free
  // hand's all the way.
  GloveSimulation free_hand(GloveTrajectory::grasp(), kParams, 6, false, 1e-3);
  GloveSimulation pushed(GloveTrajectory::grasp(), kParams, 6, false, 1e-3);
  double smallest_gap = 1.0;
  for (int n = 1; n <= 2000; ++n) {
    const Eigen::Vector3d f = pushed.frame_poses()[2].q * Eigen::Vector3d::UnitZ();
    pushed.set_wrench(2, {f.x(), f.y(), f.z()}, {}, true);
    free_hand.advance();
    pushed.advance();
    if (n * 1e-3 < 0.55) continue;  // look once the grasp moves
    const double flex_free = free_hand.joints().q_rad.segment<3>(5).sum();
    const double flex_pushed = pushed.joints().q_rad.segment<3>(5).sum();
    smallest_gap = std::min(smallest_gap, flex_free - flex_pushed);
  }
  EXPECT_GT(smallest_gap, 0.03) << "summed index flexion behind by at least 30 mrad throughout";
  EXPECT_LT(pushed.passivity_energy_j(), 0.0) << "the fingers closed against the force: it took energy out";
}

TEST(GloveSimulation, StartsAtTheCommandAndSendsThePosesOfItsFrames) {
  GloveTrajectory trajectory = GloveTrajectory::pinch({0.01, 0.02, 0.03});
  const Eigen::Quaterniond q(Eigen::AngleAxisd(-0.3, Eigen::Vector3d::UnitX()));
  trajectory.set_palm_orientation(q);
  GloveSimulation sim(trajectory, kParams, 6, true, 1e-3);
  const auto expected = glove_frame_poses(hand::skeleton_pose(hand::rest_joint_angles(), true),
                                          {Eigen::Vector3d(0.01, 0.02, 0.03), trajectory.palm_orientation()}, 6);
  const auto poses = sim.frame_poses();
  for (int id = 0; id < 6; ++id) {
    EXPECT_EQ(poses[id].p_m, expected[id].p_m) << id;
    EXPECT_EQ(poses[id].q.coeffs(), expected[id].q.coeffs()) << id;
  }
  // On the wire: every frame, ids in order, float32 of the same numbers.
  GloveServo servo(sim);
  protocol::PoseSample pose;
  servo.write_pose(pose);
  ASSERT_EQ(pose.poses.size(), 6u);
  for (int id = 0; id < 6; ++id) {
    EXPECT_EQ(pose.poses[id].frame, id);
    EXPECT_EQ(pose.poses[id].position_m.x, static_cast<float>(expected[id].p_m.x()));
    EXPECT_EQ(pose.poses[id].position_m.z, static_cast<float>(expected[id].p_m.z()));
    EXPECT_EQ(pose.poses[id].orientation.w, static_cast<float>(expected[id].q.w()));
    EXPECT_EQ(pose.poses[id].orientation.y, static_cast<float>(expected[id].q.y()));
  }
  EXPECT_THROW(GloveSimulation(GloveTrajectory::grasp(), kParams, 15, false, 1e-3), std::invalid_argument);
}

TEST(GloveSimulation, PerFingerFiguresSumTheFingersFramesAndCountContactPerFinger) {
  // 16 frames: the middle finger's three phalanges push (1,0,0), (0,2,0), (0,0,2) N: |sum| = 3 N;
  // its distal one reports contact for the second half of the ticks. The ring finger's proximal
  // phalanx alone: (0,0,-4) N. The servo's apply() takes the reply's per-frame flags.
  GloveSimulation sim(GloveTrajectory::spread(), kParams, 16, false, 1e-3);
  GloveServo servo(sim);
  protocol::ForceSample reply;
  const auto add = [&](int frame, protocol::Vec3 f, bool contact) {
    protocol::FrameWrench w;
    w.frame = static_cast<std::uint16_t>(frame);
    w.flags = contact ? protocol::ForceFlags::kInContact : 0;
    w.wrench.force_n = f;
    reply.wrenches.push_back(w);
  };
  for (int n = 0; n < 1000; ++n) {
    reply.wrenches.clear();
    add(7, {1, 0, 0}, false);
    add(8, {0, 2, 0}, false);
    add(9, {0, 0, 2}, n >= 500);
    add(10, {0, 0, -4}, false);
    add(42, {100, 0, 0}, true);  // not a frame of this glove: ignored
    servo.apply(reply);
    servo.advance(1.0);
    servo.end_tick(true);
  }
  const GloveGroupFigures middle = sim.group_figures(2), ring = sim.group_figures(3), thumb = sim.group_figures(0);
  EXPECT_DOUBLE_EQ(middle.force_max_n, 3.0);
  EXPECT_DOUBLE_EQ(middle.force_rms_n, 3.0);
  EXPECT_DOUBLE_EQ(middle.contact_fraction, 0.5);
  EXPECT_DOUBLE_EQ(ring.force_max_n, 4.0);
  EXPECT_EQ(ring.contact_fraction, 0.0);
  EXPECT_EQ(thumb.force_max_n, 0.0);
  EXPECT_EQ(thumb.force_rms_n, 0.0);
  // The whole hand: |(1, 2, -2)| = 3 N; in contact when any frame is.
  EXPECT_DOUBLE_EQ(sim.force_max_n(), 3.0);
  EXPECT_EQ(sim.contact_ticks(), 500u);
  ServoResult r;
  servo.summarize(r);
  EXPECT_EQ(r.contact_ticks, 500u);
  EXPECT_DOUBLE_EQ(r.force_max_n, 3.0);
  EXPECT_EQ(r.passivity_energy_j, sim.passivity_energy_j());
}

TEST(GloveSimulation, TheServoDevicesTickAllocatesNothing) {
  // What the servo loop calls per tick (advance, write_pose, apply, end_tick with the trace
  // reserved by begin) stays off the heap once the run started, as the stylus's does.
  GloveSimulation sim(GloveTrajectory::fist(), kParams, 16, true, 1e-3);
  std::vector<GloveTraceRow> trace;
  GloveServo servo(sim, &trace);
  servo.begin(500);
  protocol::PoseSample pose;
  protocol::ForceSample reply;
  for (int id = 0; id < 16; ++id) {
    protocol::FrameWrench w;
    w.frame = static_cast<std::uint16_t>(id);
    w.wrench.force_n = {0.1f, 0.2f, 0.3f};
    w.flags = protocol::ForceFlags::kInContact;
    reply.wrenches.push_back(w);
  }
  const long during = testing_util::allocations_in([&] {
    for (int n = 0; n < 500; ++n) {
      servo.advance(1.0);
      servo.write_pose(pose);
      servo.apply(reply);
      servo.end_tick(true);
    }
  });
  EXPECT_EQ(during, 0);
  EXPECT_EQ(trace.size(), 500u);
  EXPECT_EQ(sim.contact_ticks(), 500u);
  EXPECT_EQ(testing_util::allocations_in([] { ::operator delete(::operator new(sizeof(int))); }), 1)
      << "the counter counts";
}

}  // namespace
}  // namespace hapticd::sim
