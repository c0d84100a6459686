#pragma once

// Commanded tip trajectories of the simulated stylus: where the user's hand wants the tip at time
// t. Positions p_DC in the device base frame D (metres, z up), relative to an origin the caller
// picks (the point the server's workspace maps to the scene).
//
// Built-in shapes (h = kApproachHeightM above the origin, d = kPressDepthM; smooth ramps are
// half-cosines so the commanded velocity is continuous):
//   press         4 s cycle, repeated: hold at h 0.5 s, down by d over 1 s, hold 1 s, up over 1 s,
//                 hold 0.5 s.
//   stroke        hold at h 0.5 s, down by d over 1 s, then slide x = ±kStrokeAmplitudeM at
//                 kStrokeFrequencyHz, held down.
//   press-stroke  one press cycle (4 s), then stroke.
//   tap           hold at h 0.5 s, then every 1 / kTapFrequencyHz a kTapDurationS dip of d
//                 (sin^2 profile), at rest at h between dips.
//   circle        horizontal circle of radius kCircleRadiusM at kCircleFrequencyHz, at depth
//                 h - d, starting at (+r, 0).
//   FILE          CSV rows t_s,x_m,y_m,z_m (optional header line with exactly those names, '#'
//                 comments and blank lines skipped), t strictly increasing, interpolated
//                 linearly, held before the first and after the last row; origin added.

#include <cstddef>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include "clients/sim/vec3.hpp"

namespace hapticd::sim {

inline constexpr double kApproachHeightM = 0.03;
inline constexpr double kPressDepthM = 0.02;
inline constexpr double kSettleS = 0.5;      // hold at h before the first move
inline constexpr double kPressRampS = 1.0;   // down or up
inline constexpr double kPressHoldS = 1.0;   // held down
inline constexpr double kPressCycleS = 4.0;  // settle + down + hold + up + 0.5 s rest
inline constexpr double kStrokeAmplitudeM = 0.02;
inline constexpr double kStrokeFrequencyHz = 0.5;
inline constexpr double kTapFrequencyHz = 2.0;
inline constexpr double kTapDurationS = 0.2;
inline constexpr double kCircleRadiusM = 0.02;
inline constexpr double kCircleFrequencyHz = 0.5;

class Trajectory {
 public:
  enum class Kind { kPress, kStroke, kPressStroke, kTap, kCircle, kFile };

  static Trajectory press(Vec3d origin = {});
  static Trajectory stroke(Vec3d origin = {});
  static Trajectory press_stroke(Vec3d origin = {});
  static Trajectory tap(Vec3d origin = {});
  static Trajectory circle(Vec3d origin = {});
  // Throws std::runtime_error naming "path:line: what was expected" for a bad row, or the file
  // when it cannot be read or holds no row.
  static Trajectory from_csv(const std::string& path, Vec3d origin = {});
  // A built-in name (press, stroke, press-stroke, tap, circle) or else a CSV file path.
  static Trajectory parse(const std::string& spec, Vec3d origin = {});

  // Commanded tip position p_DC at t_s >= 0 (t < 0 is held at t = 0). Never allocates.
  [[nodiscard]] Vec3d position(double t_s) const noexcept;
  // Its time derivative, by a central difference (exact for the piecewise-linear CSV segments,
  // O(h^2) with h = 1 us for the smooth shapes).
  [[nodiscard]] Vec3d velocity(double t_s) const noexcept;

  [[nodiscard]] Kind kind() const noexcept { return kind_; }
  [[nodiscard]] const std::string& name() const noexcept { return name_; }
  [[nodiscard]] Vec3d origin() const noexcept { return origin_; }

 private:
  struct Knot {
    double t_s;
    Vec3d p_m;
  };

  Trajectory(Kind kind, std::string name, Vec3d origin) : kind_(kind), name_(std::move(name)), origin_(origin) {}
  [[nodiscard]] Vec3d offset(double t_s) const noexcept;  // position minus origin

  Kind kind_;
  std::string name_;
  Vec3d origin_;
  std::vector<Knot> knots_;  // kFile only
};

}  // namespace hapticd::sim
