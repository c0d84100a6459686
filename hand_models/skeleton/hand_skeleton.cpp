#include "hand_models/skeleton/hand_skeleton.hpp"

#include <Eigen/Geometry>

#include <cmath>
#include <numbers>

namespace hapticd::hand {
namespace {

constexpr double kCm = 0.01;
double deg(double d) { return d * std::numbers::pi / 180.0; }

}  // namespace

Eigen::Matrix<double, kHandJointDofs, 1> HandJointAngles::vector() const {
  Eigen::Matrix<double, kHandJointDofs, 1> q;
  for (int f = 0; f < kHandFingers; ++f)
    for (int k = 0; k < 4; ++k) q[4 * f + k] = finger[f][k];
  return q;
}

HandJointAngles HandJointAngles::from_vector(const Eigen::Matrix<double, kHandJointDofs, 1>& q) {
  HandJointAngles a;
  for (int f = 0; f < kHandFingers; ++f)
    for (int k = 0; k < 4; ++k) a.finger[f][k] = q[4 * f + k];
  return a;
}

const std::array<FingerGeometry, kHandFingers>& finger_geometry() {
  // An adult right hand, palm 9 x 8 cm, hand length about 18.7 cm.
  static const std::array<FingerGeometry, kHandFingers> kGeometry = {{
      {Eigen::Vector3d(-2.3, -2.8, -0.25) * kCm, deg(50.0), {4.5 * kCm, 3.0 * kCm, 2.5 * kCm},
       {1.15 * kCm, 1.0 * kCm, 0.92 * kCm, 0.85 * kCm}},
      {Eigen::Vector3d(-2.9, 4.3, 0.15) * kCm, 0.0, {4.0 * kCm, 2.5 * kCm, 2.0 * kCm},
       {0.95 * kCm, 0.88 * kCm, 0.82 * kCm, 0.78 * kCm}},
      {Eigen::Vector3d(-0.95, 4.5, 0.15) * kCm, 0.0, {4.5 * kCm, 3.0 * kCm, 2.2 * kCm},
       {1.0 * kCm, 0.92 * kCm, 0.85 * kCm, 0.8 * kCm}},
      {Eigen::Vector3d(1.05, 4.3, 0.15) * kCm, 0.0, {4.2 * kCm, 2.8 * kCm, 2.1 * kCm},
       {0.95 * kCm, 0.87 * kCm, 0.82 * kCm, 0.78 * kCm}},
      {Eigen::Vector3d(2.95, 3.9, 0.1) * kCm, 0.0, {3.4 * kCm, 2.0 * kCm, 1.8 * kCm},
       {0.86 * kCm, 0.82 * kCm, 0.8 * kCm, 0.78 * kCm}},
  }};
  return kGeometry;
}

HandJointAngles rest_joint_angles() {
  // Yaws spread the fingers so their gaps grow toward the tips; the thumb leaves
  // the palm about 45 degrees from the index, a little toward palmar.
  HandJointAngles a;
  a.finger[0] = {deg(-54.0), deg(4.0), deg(3.0), deg(3.0)};
  a.finger[1] = {deg(-9.0), 0.0, deg(6.0), deg(6.0)};
  a.finger[2] = {0.0, 0.0, deg(6.0), deg(6.0)};
  a.finger[3] = {deg(8.0), 0.0, deg(6.0), deg(6.0)};
  a.finger[4] = {deg(16.0), 0.0, deg(6.0), deg(6.0)};
  return a;
}

SkeletonPose skeleton_pose(const HandJointAngles& angles, bool left) {
  SkeletonPose s;
  const Eigen::Matrix3d M = Eigen::Vector3d(-1.0, 1.0, 1.0).asDiagonal();
  for (int f = 0; f < kHandFingers; ++f) {
    const FingerGeometry& g = finger_geometry()[f];
    const double yaw = angles.finger[f][0];
    Eigen::Vector3d joint = g.base;
    s.joints[f][0] = joint;
    double pitch = 0.0;  // elevation of the bone axis above the palm plane
    for (int k = 0; k < 3; ++k) {
      pitch -= angles.finger[f][k + 1];
      const Eigen::Vector3d axis(std::sin(yaw) * std::cos(pitch), std::cos(yaw) * std::cos(pitch), std::sin(pitch));
      // The axis turned 90 degrees further up in pitch: the dorsal side of an unrolled finger.
      const Eigen::Vector3d dorsal0(-std::sin(yaw) * std::sin(pitch), -std::cos(yaw) * std::sin(pitch),
                                    std::cos(pitch));
      const Eigen::Vector3d side0 = axis.cross(dorsal0);
      const Eigen::Vector3d dorsal = std::cos(g.roll) * dorsal0 - std::sin(g.roll) * side0;
      Eigen::Matrix3d R;
      R.col(0) = axis.cross(dorsal);
      R.col(1) = axis;
      R.col(2) = dorsal;
      const Eigen::Vector3d next = joint + g.length[k] * axis;
      s.R[3 * f + k] = R;
      s.centre[3 * f + k] = 0.5 * (joint + next);
      s.joints[f][k + 1] = next;
      joint = next;
    }
  }
  if (left) {
    for (auto& finger : s.joints)
      for (Eigen::Vector3d& j : finger) j.x() = -j.x();
    for (int i = 0; i < kHandPhalanges; ++i) {
      s.centre[i].x() = -s.centre[i].x();
      s.R[i] = M * s.R[i] * M;
    }
  }
  return s;
}

HandJointAngles joint_angles_from_segments(const std::array<Eigen::Matrix3d, kHandPhalanges>& R_in, bool left) {
  // skeleton_pose: a segment's frame is R = [side x dorsal-roll..]: its side axis, rolled by the
  // finger's roll about the bone, is side0 = (cos yaw, -sin yaw, 0) whatever the pitch, and its bone
  // axis is (sin yaw cos pitch, cos yaw cos pitch, sin pitch), pitch = -(flexions so far).
  const Eigen::Matrix3d M = Eigen::Vector3d(-1.0, 1.0, 1.0).asDiagonal();
  HandJointAngles a;
  for (int f = 0; f < kHandFingers; ++f) {
    const double roll = finger_geometry()[f].roll;
    double yaw = 0.0, pitch_before = 0.0;
    for (int k = 0; k < 3; ++k) {
      const Eigen::Matrix3d R = left ? Eigen::Matrix3d(M * R_in[3 * f + k] * M) : R_in[3 * f + k];
      if (k == 0) {
        const Eigen::Vector3d side0 = std::cos(roll) * R.col(0) - std::sin(roll) * R.col(2);
        yaw = std::atan2(-side0.y(), side0.x());
        a.finger[f][0] = yaw;
      }
      const Eigen::Vector3d axis = R.col(1);
      const double pitch = std::atan2(axis.z(), std::sin(yaw) * axis.x() + std::cos(yaw) * axis.y());
      // Each joint's turn, within (-pi, pi]: the bones' pitches wrap once a finger curls past a half turn.
      a.finger[f][k + 1] = std::remainder(pitch_before - pitch, 2.0 * std::numbers::pi);
      pitch_before = pitch;
    }
  }
  return a;
}

HandJointAngles joint_angles_from_distal(const std::array<Eigen::Matrix3d, kHandFingers>& R_distal, bool left,
                                         const HandJointAngles* near) {
  // Every segment of a finger given its distal's frame: the base joint takes the abduction and the
  // whole flexion (the side axis does not depend on the pitch), the others none; then shared.
  std::array<Eigen::Matrix3d, kHandPhalanges> R;
  for (int i = 0; i < kHandPhalanges; ++i) R[i] = R_distal[i / 3];
  HandJointAngles a = joint_angles_from_segments(R, left);
  for (int f = 0; f < kHandFingers; ++f) {
    std::array<double, 4>& finger = a.finger[f];
    double total = finger[1] + finger[2] + finger[3];
    if (near) {
      const double was = near->finger[f][1] + near->finger[f][2] + near->finger[f][3];
      total = was + std::remainder(total - was, 2.0 * std::numbers::pi);
    }
    finger[1] = 3.0 / 8.0 * total;
    finger[2] = 3.0 / 8.0 * total;
    finger[3] = 2.0 / 8.0 * total;
  }
  return a;
}

const char* finger_name(int finger) {
  static constexpr const char* kNames[] = {"thumb", "index", "middle", "ring", "little"};
  return finger >= 0 && finger < kHandFingers ? kNames[finger] : "?";
}

const char* phalanx_name(int phalanx) {
  static constexpr const char* kNames[] = {"proximal", "middle", "distal"};
  return phalanx >= 0 && phalanx < 3 ? kNames[phalanx] : "?";
}

}  // namespace hapticd::hand
