#include "clients/sim/trajectory.hpp"

#include <algorithm>
#include <charconv>
#include <cmath>
#include <fstream>
#include <numbers>
#include <stdexcept>
#include <utility>

#include "protocol/limits.hpp"

namespace hapticd::sim {
namespace {

constexpr double kTwoPi = 2.0 * std::numbers::pi;

// 0 -> 1 over u in [0, 1] with zero slope at both ends.
double half_cosine(double u) noexcept { return 0.5 * (1.0 - std::cos(std::numbers::pi * std::clamp(u, 0.0, 1.0))); }

// Height above the origin during one press cycle started at 0.
double press_height(double t) noexcept {
  const double down_start = kSettleS, up_start = kSettleS + kPressRampS + kPressHoldS;
  if (t < up_start) return kApproachHeightM - kPressDepthM * half_cosine((t - down_start) / kPressRampS);
  return kApproachHeightM - kPressDepthM * (1.0 - half_cosine((t - up_start) / kPressRampS));
}

Vec3d stroke_offset(double t) noexcept {
  const double slide_start = kSettleS + kPressRampS;
  if (t < slide_start) return {0.0, 0.0, press_height(t)};
  return {kStrokeAmplitudeM * std::sin(kTwoPi * kStrokeFrequencyHz * (t - slide_start)), 0.0,
          kApproachHeightM - kPressDepthM};
}

std::string_view trim(std::string_view s) {
  const auto first = s.find_first_not_of(" \t\r");
  if (first == std::string_view::npos) return {};
  return s.substr(first, s.find_last_not_of(" \t\r") - first + 1);
}

}  // namespace

Trajectory Trajectory::press(Vec3d origin) { return {Kind::kPress, "press", origin}; }
Trajectory Trajectory::stroke(Vec3d origin) { return {Kind::kStroke, "stroke", origin}; }
Trajectory Trajectory::press_stroke(Vec3d origin) { return {Kind::kPressStroke, "press-stroke", origin}; }
Trajectory Trajectory::tap(Vec3d origin) { return {Kind::kTap, "tap", origin}; }
Trajectory Trajectory::circle(Vec3d origin) { return {Kind::kCircle, "circle", origin}; }

Trajectory Trajectory::parse(const std::string& spec, Vec3d origin) {
  if (spec == "press") return press(origin);
  if (spec == "stroke") return stroke(origin);
  if (spec == "press-stroke") return press_stroke(origin);
  if (spec == "tap") return tap(origin);
  if (spec == "circle") return circle(origin);
  return from_csv(spec, origin);
}

Trajectory Trajectory::from_csv(const std::string& path, Vec3d origin) {
  std::ifstream in(path);
  if (!in)
    throw std::runtime_error("cannot read trajectory file '" + path +
                             "' (expected press, stroke, press-stroke, tap, circle or a CSV file)");
  Trajectory trajectory(Kind::kFile, path, origin);
  std::string line;
  for (int number = 1; std::getline(in, line); ++number) {
    const std::string_view text = trim(line);
    if (text.empty() || text.front() == '#') continue;
    const auto fail = [&](const std::string& what) {
      throw std::runtime_error(path + ":" + std::to_string(number) + ": " + what);
    };
    std::string_view fields[4];
    std::size_t count = 0;
    for (std::string_view rest = text;; ++count) {
      const auto comma = rest.find(',');
      if (count < 4) fields[count] = trim(rest.substr(0, comma));
      if (comma == std::string_view::npos) break;
      rest.remove_prefix(comma + 1);
    }
    ++count;
    const bool header = fields[0] == "t_s" && fields[1] == "x_m" && fields[2] == "y_m" && fields[3] == "z_m";
    if (count == 4 && header) {
      if (!trajectory.knots_.empty()) fail("the header t_s,x_m,y_m,z_m must come before the first row");
      continue;
    }
    if (count != 4)
      fail("expected 4 comma-separated numbers t_s,x_m,y_m,z_m, found " + std::to_string(count) + " fields");
    double values[4];
    static constexpr const char* kNames[4] = {"t_s", "x_m", "y_m", "z_m"};
    for (std::size_t i = 0; i < 4; ++i) {
      const std::string_view f = fields[i];
      const auto [end, ec] = std::from_chars(f.data(), f.data() + f.size(), values[i]);
      if (f.empty() || ec != std::errc() || end != f.data() + f.size())
        fail(std::string(kNames[i]) + ": '" + std::string(f) + "' is not a number");
      if (!std::isfinite(values[i])) fail(std::string(kNames[i]) + " is not finite");
    }
    if (values[0] < 0.0) fail("t_s must be >= 0, got " + std::string(fields[0]));
    if (!trajectory.knots_.empty() && values[0] <= trajectory.knots_.back().t_s)
      fail("t_s " + std::string(fields[0]) + " is not after the previous row's");
    for (std::size_t i = 1; i < 4; ++i)
      if (std::abs(values[i]) > protocol::kMaxPositionM)
        fail(std::string(kNames[i]) + " " + std::string(fields[i]) + " is beyond the protocol's " +
             std::to_string(static_cast<int>(protocol::kMaxPositionM)) + " m");
    trajectory.knots_.push_back({values[0], {values[1], values[2], values[3]}});
  }
  if (trajectory.knots_.empty()) throw std::runtime_error(path + ": no trajectory rows (t_s,x_m,y_m,z_m)");
  return trajectory;
}

Vec3d Trajectory::position(double t_s) const noexcept { return origin_ + offset(std::max(0.0, t_s)); }

Vec3d Trajectory::velocity(double t_s) const noexcept {
  constexpr double h = 1e-6;
  const double t0 = std::max(0.0, t_s - h), t1 = std::max(0.0, t_s) + h;
  return (offset(t1) - offset(t0)) / (t1 - t0);
}

Vec3d Trajectory::offset(double t) const noexcept {
  switch (kind_) {
    case Kind::kPress:
      return {0.0, 0.0, press_height(std::fmod(t, kPressCycleS))};
    case Kind::kStroke:
      return stroke_offset(t);
    case Kind::kPressStroke:
      return t < kPressCycleS ? Vec3d{0.0, 0.0, press_height(t)} : stroke_offset(t - kPressCycleS);
    case Kind::kTap: {
      if (t < kSettleS) return {0.0, 0.0, kApproachHeightM};
      const double u = std::fmod(t - kSettleS, 1.0 / kTapFrequencyHz);
      const double s = u < kTapDurationS ? std::sin(std::numbers::pi * u / kTapDurationS) : 0.0;
      return {0.0, 0.0, kApproachHeightM - kPressDepthM * s * s};
    }
    case Kind::kCircle: {
      const double phase = kTwoPi * kCircleFrequencyHz * t;
      return {kCircleRadiusM * std::cos(phase), kCircleRadiusM * std::sin(phase), kApproachHeightM - kPressDepthM};
    }
    case Kind::kFile: {
      if (t <= knots_.front().t_s) return knots_.front().p_m;
      if (t >= knots_.back().t_s) return knots_.back().p_m;
      const auto after =
          std::upper_bound(knots_.begin(), knots_.end(), t, [](double time, const Knot& k) { return time < k.t_s; });
      const Knot& a = *(after - 1);
      const Knot& b = *after;
      const double w = (t - a.t_s) / (b.t_s - a.t_s);
      return a.p_m + w * (b.p_m - a.p_m);
    }
  }
  return {};
}

}  // namespace hapticd::sim
