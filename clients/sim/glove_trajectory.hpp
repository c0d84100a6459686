#pragma once

// Commanded motions of the simulated glove: the 20 joint angles the user's hand wants at time t
// (rad, HandJointAngles order) and where it wants the palm (device base frame D, metres, relative to
// an origin the caller picks; the palm's orientation is constant, the identity unless set).
//
// Postures (degrees; per finger abduction, flexion 1, 2, 3; rest = rest_joint_angles(), the
// skeleton's slightly flexed, spread posture the procedural hand is built in):
//   power grasp  thumb -25 30 20 15; index -4 55 65 35; middle 0 55 65 35; ring 4 55 65 35;
//                little 8 55 65 35: the long fingers wrapped round a ~4.5 cm cylinder, the thumb
//                closing over it.
//   pinch        thumb -14 31 10 -8; index -5 50 55 30; middle, ring, little at their rest
//                abduction and 20 30 20: the thumb's and index's fingertip points
//                (SkeletonPose::joints[f][3]) 1.63 cm apart, their flesh radii (0.85 + 0.78 cm)
//                in contact.
//   fist         long fingers MCP 90, PIP 100, DIP 70 (abduction index -4, middle 0, ring 4,
//                little 8); thumb 15 10 30 60: flexed across, its tip under the middle phalanges of
//                the index and middle fingers.
//   spread       every flexion 0 (straight fingers), abduction thumb -70, index -20, middle 0,
//                ring 15, little 30.
// Built-in motions (ramps are half-cosines, so commanded rates are continuous, C1):
//   grasp    rest for kGloveSettleS, close to the power grasp over kGloveRampS, hold.
//   pinch    rest for kGloveSettleS, to the pinch over kGloveRampS, hold.
//   release  the power grasp for kGloveSettleS, open to rest over kGloveRampS, hold.
//   fist     kGloveCycleS cycle, repeated: rest kGloveSettleS, close to the fist over kGloveRampS,
//            hold kGloveHoldS, open over kGloveRampS, rest for the remaining 0.5 s.
//   spread   the same cycle between rest and spread.
//   tap      rest for kGloveSettleS, then the index MCP flexion taps
//            rest + kGloveTapFlexionDeg sin^2(pi kGloveTapFrequencyHz (t - kGloveSettleS)): up to 30
//            degrees and back 4 times a second; all else at rest.
//   FILE     CSV rows t_s then the 20 angles in degrees in HandJointAngles order (21 columns),
//            optionally then the palm x y z in m (24 columns; every row the same); an optional
//            header line naming the columns exactly as glove_csv_column_name(); '#' comments and
//            blank lines skipped; t strictly increasing from >= 0, angles within +-180 degrees,
//            palm within the protocol's 100 m. Interpolated linearly, held before the first and
//            after the last row; the palm column values are added to the origin.

#include <Eigen/Geometry>
#include <string>
#include <utility>
#include <vector>

#include "clients/sim/glove_model.hpp"
#include "clients/sim/vec3.hpp"

namespace hapticd::sim {

inline constexpr double kGloveSettleS = 0.5;
inline constexpr double kGloveRampS = 1.0;
inline constexpr double kGloveHoldS = 1.0;
inline constexpr double kGloveCycleS = 4.0;
inline constexpr double kGloveTapFrequencyHz = 4.0;
inline constexpr double kGloveTapFlexionDeg = 30.0;

hand::HandJointAngles power_grasp_posture();
hand::HandJointAngles pinch_posture();
hand::HandJointAngles fist_posture();
hand::HandJointAngles spread_posture();

// Column c (0-based) of a glove CSV: "t_s", "thumb_abduction_deg", "thumb_flexion1_deg", ...,
// "little_flexion3_deg", "palm_x_m", "palm_y_m", "palm_z_m"; "?" beyond 23.
std::string glove_csv_column_name(int column);

class GloveTrajectory {
 public:
  enum class Kind { kGrasp, kPinch, kRelease, kFist, kSpread, kTap, kFile };

  static GloveTrajectory grasp(Vec3d origin = {});
  static GloveTrajectory pinch(Vec3d origin = {});
  static GloveTrajectory release(Vec3d origin = {});
  static GloveTrajectory fist(Vec3d origin = {});
  static GloveTrajectory spread(Vec3d origin = {});
  static GloveTrajectory tap(Vec3d origin = {});
  // Throws std::runtime_error "path:line:column: what was expected" for a bad row ("path:line:"
  // when the row's shape is wrong as a whole), or naming the file when it cannot be read or holds
  // no row.
  static GloveTrajectory from_csv(const std::string& path, Vec3d origin = {});
  // The same from samples in memory (a script's motion): times strictly increasing from >= 0, angles
  // in rad within +-pi, palm offsets (added to the origin) within the protocol's 100 m, all finite.
  // Throws std::invalid_argument naming the first bad sample.
  struct Sample {
    double t_s = 0;
    JointVector q_rad = JointVector::Zero();
    Vec3d palm_m;
  };
  static GloveTrajectory from_samples(std::string name, const std::vector<Sample>& samples, Vec3d origin = {});
  // A built-in name (grasp, pinch, release, fist, spread, tap) or else a CSV file path.
  static GloveTrajectory parse(const std::string& spec, Vec3d origin = {});

  // Commanded joint angles at t_s >= 0 (t < 0 is held at t = 0), rad. Never allocates.
  [[nodiscard]] JointVector angles(double t_s) const noexcept;
  // Their rates, by a central difference of h = 1 us (exact on linear CSV segments).
  [[nodiscard]] JointVector angle_rates(double t_s) const noexcept;
  // Commanded palm position in D and its rate.
  [[nodiscard]] Vec3d palm_position(double t_s) const noexcept;
  [[nodiscard]] Vec3d palm_velocity(double t_s) const noexcept;
  // The palm's orientation in D (constant over the run).
  [[nodiscard]] const Eigen::Quaterniond& palm_orientation() const noexcept { return palm_q_; }
  void set_palm_orientation(const Eigen::Quaterniond& q) { palm_q_ = q.normalized(); }

  [[nodiscard]] Kind kind() const noexcept { return kind_; }
  [[nodiscard]] const std::string& name() const noexcept { return name_; }
  [[nodiscard]] Vec3d origin() const noexcept { return origin_; }
  [[nodiscard]] bool file_has_palm() const noexcept { return file_has_palm_; }

 private:
  struct Knot {
    double t_s;
    JointVector q_rad;
    Vec3d p_m;
  };

  GloveTrajectory(Kind kind, std::string name, Vec3d origin) : kind_(kind), name_(std::move(name)), origin_(origin) {}
  [[nodiscard]] Vec3d palm_offset(double t_s) const noexcept;

  Kind kind_;
  std::string name_;
  Vec3d origin_;
  Eigen::Quaterniond palm_q_ = Eigen::Quaterniond::Identity();
  bool file_has_palm_ = false;
  std::vector<Knot> knots_;  // kFile only
};

}  // namespace hapticd::sim
