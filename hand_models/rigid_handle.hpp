#pragma once
// Rigid handles of a deformable hand and the zero-rest-length coupling springs
// that tie them to the flesh (seed 004 section 4, eq. 4-5, Jacobians eq. 11 and
// Appendix A). Handle coordinates: position of the centre of mass p_WH, world
// orientation q_WH; velocities v_WH (m/s) and angular velocity w_WH (rad/s, world).
// Position Jacobians are taken with respect to (p_WH, theta), theta a small
// world-frame rotation R -> exp(theta) R; eq. 14 (quaternion form) is provided
// too and related to it by the matrix G of eq. 10 (tests check both).
#include <Eigen/Core>
#include <Eigen/Geometry>
#include <string>
#include <vector>

#include "hand_models/tet_mesh.hpp"

namespace hapticd::hand {

using Vector6d = Eigen::Matrix<double, 6, 1>;
using Matrix6d = Eigen::Matrix<double, 6, 6>;

// Constant part of a handle: the hand nodes inside a sphere around a seed point.
struct RigidHandle {
  std::string name;
  std::vector<int> nodes;             // coupled hand nodes
  std::vector<Eigen::Vector3d> r_B;   // spring anchors in the handle frame, m
  double mass_kg = 0;                 // sum of the nodes' lumped masses
  Eigen::Matrix3d inertia_B = Eigen::Matrix3d::Zero();  // about the centre of mass, handle frame, kg m^2
  Eigen::Vector3d p_WH_rest = Eigen::Vector3d::Zero();  // rest centre of mass (handle frame = world at rest)
};

// Collects the nodes of `mesh` inside the sphere (seed, radius), or takes
// `nodes` when given; throws std::invalid_argument if there is none (or a node
// is out of range). The inertia is regularised so a collinear node set still
// gives an invertible inertia.
RigidHandle make_handle(const TetMesh& mesh, const Eigen::VectorXd& node_mass, const Eigen::Vector3d& seed,
                        double radius, const std::vector<int>& nodes, const std::string& name);

// Where a handle sits in the rigid frame that drives it (a glove's tracked
// phalanx): the handle's rest pose expressed in the frame's rest pose. Both
// rest poses in the same coordinates (the hand frame); the handle's rest
// orientation is the identity there (RigidHandle::p_WH_rest).
struct FrameToHandle {
  Eigen::Vector3d p_F = Eigen::Vector3d::Zero();              // handle centre in frame coordinates, m
  Eigen::Quaterniond q_F = Eigen::Quaterniond::Identity();    // handle orientation in the frame
};
FrameToHandle frame_to_handle(const Eigen::Vector3d& frame_p_rest, const Eigen::Matrix3d& frame_R_rest,
                              const RigidHandle& handle);

struct HandleState {
  Eigen::Vector3d p_WH = Eigen::Vector3d::Zero();
  Eigen::Quaterniond q_WH = Eigen::Quaterniond::Identity();
  Eigen::Vector3d v_WH = Eigen::Vector3d::Zero();
  Eigen::Vector3d w_WH = Eigen::Vector3d::Zero();
};

// Force and Jacobians of one coupling spring between hand node A and anchor B.
struct SpringTerms {
  Eigen::Vector3d F_A;                  // force on the node, N (eq. 4)
  Vector6d W_B;                         // force and torque on the handle (F_B = -F_A, eq. 5)
  double k = 0, d = 0;                  // dF_A/dx_A = -k I, dF_A/dv_A = -d I
  Eigen::Matrix<double, 3, 6> dFA_dxh;  // w.r.t. (p_WH, theta)
  Eigen::Matrix<double, 3, 6> dFA_dvh;  // w.r.t. (v_WH, w_WH)
  Eigen::Matrix<double, 6, 3> dWB_dxA;
  Eigen::Matrix<double, 6, 3> dWB_dvA;
  Matrix6d dWB_dxh;
  Matrix6d dWB_dvh;
};

SpringTerms coupling_spring(const Eigen::Vector3d& x_A, const Eigen::Vector3d& v_A, const HandleState& handle,
                            const Eigen::Vector3d& r_B, double k, double d);

Eigen::Matrix3d skew(const Eigen::Vector3d& a);

// seed 004 eq. 14: d(R(q) r)/dq with q ordered (x, y, z, s), q treated as 4 free numbers.
Eigen::Matrix<double, 3, 4> d_rotated_d_quaternion(const Eigen::Quaterniond& q, const Eigen::Vector3d& r);
// The G of eq. 10: dq/dt = G w for a world-frame angular velocity w (q ordered x, y, z, s).
Eigen::Matrix<double, 4, 3> quaternion_rate_matrix(const Eigen::Quaterniond& q);

// The nearest surface a handle's part of the skin could reach that is not among its contacts: skin
// point r_W from the handle, gap_m from a surface whose normal n_W points out of it toward the
// point. Moved by (dx, dtheta), the point closes the gap by -n . (dx + dtheta x r) (the haptic
// tick's bound, ProxyHand::limit_to_clearance).
struct ClearancePlane {
  Eigen::Vector3d n_W = Eigen::Vector3d::UnitZ(), r_W = Eigen::Vector3d::Zero();
  double gap_m = 0;
};
// The planes kept per handle: the nearest surfaces in directions at least kClearanceSpread apart
// (the cosine between their normals below it).
constexpr int kClearancePlanes = 4;
constexpr double kClearanceSpread = 0.87;
// The share in [0, 1] of a further motion (move, turn) that a handle displaced by (dx, dtheta) from
// where `planes` were measured can make before it closes any of their gaps (a handle already past a
// plane may only move back from it).
double clearance_share(const ClearancePlane* planes, int count, const Eigen::Vector3d& dx,
                       const Eigen::Vector3d& dtheta, const Eigen::Vector3d& move, const Eigen::Vector3d& turn);
// How far ahead of a surface a hand's skin points are measured for their handles' clearance planes
// (World::clearance): a surface farther than this from every skin point of a handle is not among its
// planes, so a handle whose skin points move farther than this within one visual step may meet a
// surface nothing told the tick or the step about.
constexpr double kClearanceLook_m = 0.10;
// The share in [0, 1] of a further motion (move, turn) that a handle displaced by (dx, dtheta) from
// where its planes were measured can make while none of its skin points, at most radius_m from the
// handle, goes farther than kClearanceLook_m: |dx| + radius_m |dtheta| stays within it (a bound of
// each point's displacement dx + dtheta x r, exact for a pure move). A handle already beyond it may
// only move back toward where it was measured.
double free_travel_share(const Eigen::Vector3d& dx, const Eigen::Vector3d& dtheta, const Eigen::Vector3d& move,
                         const Eigen::Vector3d& turn, double radius_m);

// q advanced by a world-frame rotation vector: exp(theta) q, renormalised.
Eigen::Quaterniond rotate_by(const Eigen::Quaterniond& q, const Eigen::Vector3d& theta);
// Rotation vector of q_a q_b^-1 (shortest way), rad.
Eigen::Vector3d rotation_difference(const Eigen::Quaterniond& q_a, const Eigen::Quaterniond& q_b);

}  // namespace hapticd::hand
