#pragma once
// The standard hand skeleton shared by the procedural FEM hand (its bones and
// handle frames) and the simulated glove (its forward kinematics), so the
// frames a glove tracks are the frames the hand's handles sit on.
//
// 20 finger DoF (seed 002 section 3): each finger has a 2-DoF base joint
// (abduction and flexion: MCP for the long fingers, the trapeziometacarpal
// joint for the thumb) and two 1-DoF flexion joints (PIP and DIP; the thumb's
// MCP and IP). The palm is one rigid frame, the hand frame itself.
//
// Hand frame (right hand): origin at the palm centre, fingers along +y, palmar
// side -z, dorsal +z, thumb on the -x side. A left hand is the mirror image
// (x -> -x); its frames stay right-handed (R -> M R M, M = diag(-1, 1, 1)).
// Segment frames: y along the bone toward the tip, z dorsal, x = y cross z.
#include <Eigen/Core>
#include <array>
#include <string>

namespace hapticd::hand {

inline constexpr int kHandFingers = 5;
inline constexpr int kHandPhalanges = 15;  // finger-major: thumb, index, middle, ring, little; proximal, middle, distal
inline constexpr int kHandJointDofs = 20;

// The palm as a box centred on the hand frame's origin, the rigid hands' (seeds 001 and 002 give no
// sizes): the procedural hand's palm (procedural_hand.cpp) with its trapezoid's mean width. Half
// extents along x, y, z, m.
inline constexpr double kPalmHalfWidth_m = 0.037, kPalmHalfLength_m = 0.045, kPalmHalfThickness_m = 0.0125;

// Fixed geometry of one finger (right hand frame), m and rad.
struct FingerGeometry {
  Eigen::Vector3d base;           // base joint position
  double roll;                    // about the bone axis, turning the dorsal side radially (thumb pronation)
  std::array<double, 3> length;   // joint to joint, the last to the fingertip
  std::array<double, 4> radius;   // flesh radius at the base, 2nd joint, 3rd joint, fingertip
};

// Joint angles, rad. Per finger: abduction (the bone's yaw about the palm
// normal, + toward +x, i.e. toward the little finger on a right hand) and the
// flexion of its three joints (+ toward palmar); flexion 0 at every joint is a
// straight finger in the palm plane.
struct HandJointAngles {
  std::array<std::array<double, 4>, kHandFingers> finger{};
  // The 20 values in finger-major order (abduction, flexion 1, 2, 3 per finger).
  Eigen::Matrix<double, kHandJointDofs, 1> vector() const;
  static HandJointAngles from_vector(const Eigen::Matrix<double, kHandJointDofs, 1>& q);
};

struct SkeletonPose {
  std::array<std::array<Eigen::Vector3d, 4>, kHandFingers> joints;  // base, 2nd, 3rd joint, fingertip
  std::array<Eigen::Matrix3d, kHandPhalanges> R;                    // segment frames
  std::array<Eigen::Vector3d, kHandPhalanges> centre;               // segment midpoints
};

const std::array<FingerGeometry, kHandFingers>& finger_geometry();
// The posture the procedural hand is built in: fingers spread a little and slightly flexed.
HandJointAngles rest_joint_angles();
// Forward kinematics in the hand frame (mirrored for a left hand).
SkeletonPose skeleton_pose(const HandJointAngles& angles, bool left = false);

// The joint angles whose segment frames (SkeletonPose::R, in the hand frame) these are: the inverse
// of skeleton_pose for the orientations (a glove's tracked phalanx frames relative to its palm).
// The abduction is read from each proximal segment's side axis, so it holds at any flexion; frames
// that no angles produce (noise, another skeleton) give the angles of their bones' directions.
HandJointAngles joint_angles_from_segments(const std::array<Eigen::Matrix3d, kHandPhalanges>& R, bool left = false);

// The posture a 6-frame glove's distal segments (SkeletonPose::R of phalanx 3 f + 2, in the hand
// frame) give: each finger's abduction from its distal bone and its whole flexion from the distal's
// pitch, shared 3 : 3 : 2 among its three joints (the distal joint bending about two thirds of the
// middle one, the usual coupling of a curling finger). Exact for postures whose flexions are so shared.
// The pitch tells the whole flexion up to whole turns: it is taken within half a turn of `near`'s (the
// last posture: a fist curls a finger past a half turn), or in (-pi, pi] without it.
HandJointAngles joint_angles_from_distal(const std::array<Eigen::Matrix3d, kHandFingers>& R, bool left = false,
                                         const HandJointAngles* near = nullptr);

const char* finger_name(int finger);    // "thumb" ... "little"
const char* phalanx_name(int phalanx);  // "proximal", "middle", "distal"

}  // namespace hapticd::hand
