#pragma once

// A 3-vector of doubles for the simulated device: the client side keeps no Eigen dependency for
// three numbers.

#include <cmath>

namespace hapticd::sim {

struct Vec3d {
  double x = 0.0;
  double y = 0.0;
  double z = 0.0;

  friend constexpr Vec3d operator+(Vec3d a, Vec3d b) noexcept { return {a.x + b.x, a.y + b.y, a.z + b.z}; }
  friend constexpr Vec3d operator-(Vec3d a, Vec3d b) noexcept { return {a.x - b.x, a.y - b.y, a.z - b.z}; }
  friend constexpr Vec3d operator*(double s, Vec3d a) noexcept { return {s * a.x, s * a.y, s * a.z}; }
  friend constexpr Vec3d operator*(Vec3d a, double s) noexcept { return s * a; }
  friend constexpr Vec3d operator/(Vec3d a, double s) noexcept { return {a.x / s, a.y / s, a.z / s}; }
  constexpr Vec3d& operator+=(Vec3d b) noexcept { return *this = *this + b; }
  friend constexpr bool operator==(Vec3d, Vec3d) = default;
};

constexpr double dot(Vec3d a, Vec3d b) noexcept { return a.x * b.x + a.y * b.y + a.z * b.z; }
inline double norm(Vec3d a) noexcept { return std::sqrt(dot(a, a)); }
inline bool is_finite(Vec3d a) noexcept { return std::isfinite(a.x) && std::isfinite(a.y) && std::isfinite(a.z); }

}  // namespace hapticd::sim
