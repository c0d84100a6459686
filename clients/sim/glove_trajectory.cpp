#include "clients/sim/glove_trajectory.hpp"

#include <algorithm>
#include <charconv>
#include <cmath>
#include <fstream>
#include <numbers>
#include <stdexcept>
#include <string_view>

#include "protocol/limits.hpp"

namespace hapticd::sim {
namespace {

constexpr double kRadPerDeg = std::numbers::pi / 180.0;
constexpr int kTimeColumns = 1;
constexpr int kAngleColumns = hand::kHandJointDofs;
constexpr int kPalmColumns = 3;
constexpr double kMaxCsvAngleDeg = 180.0;

hand::HandJointAngles from_degrees(const std::array<std::array<double, 4>, hand::kHandFingers>& deg) {
  hand::HandJointAngles a;
  for (int f = 0; f < hand::kHandFingers; ++f)
    for (int k = 0; k < 4; ++k) a.finger[f][k] = deg[f][k] * kRadPerDeg;
  return a;
}

// 0 -> 1 over u in [0, 1] with zero slope at both ends.
double half_cosine(double u) noexcept { return 0.5 * (1.0 - std::cos(std::numbers::pi * std::clamp(u, 0.0, 1.0))); }

// From a to b starting at t0 over kGloveRampS.
JointVector ramp(const JointVector& a, const JointVector& b, double t, double t0) noexcept {
  return a + half_cosine((t - t0) / kGloveRampS) * (b - a);
}

// One kGloveCycleS cycle between rest and `target`, started at 0.
JointVector cycle(const JointVector& rest, const JointVector& target, double t) noexcept {
  const double open_start = kGloveSettleS + kGloveRampS + kGloveHoldS;
  if (t < open_start) return ramp(rest, target, t, kGloveSettleS);
  return ramp(target, rest, t, open_start);
}

std::string_view trim(std::string_view s) {
  const auto first = s.find_first_not_of(" \t\r");
  if (first == std::string_view::npos) return {};
  return s.substr(first, s.find_last_not_of(" \t\r") - first + 1);
}

// The postures as joint vectors, built once.
struct Postures {
  JointVector rest = hand::rest_joint_angles().vector();
  JointVector grasp = power_grasp_posture().vector();
  JointVector pinch = pinch_posture().vector();
  JointVector fist = fist_posture().vector();
  JointVector spread = spread_posture().vector();
};
const Postures& postures() {
  static const Postures kPostures;
  return kPostures;
}

}  // namespace

hand::HandJointAngles power_grasp_posture() {
  return from_degrees({{{-25, 30, 20, 15}, {-4, 55, 65, 35}, {0, 55, 65, 35}, {4, 55, 65, 35}, {8, 55, 65, 35}}});
}

hand::HandJointAngles pinch_posture() {
  hand::HandJointAngles a = hand::rest_joint_angles();
  const hand::HandJointAngles p =
      from_degrees({{{-14, 31, 10, -8}, {-5, 50, 55, 30}, {0, 20, 30, 20}, {0, 20, 30, 20}, {0, 20, 30, 20}}});
  for (int f = 0; f < hand::kHandFingers; ++f)
    for (int k = f < 2 ? 0 : 1; k < 4; ++k) a.finger[f][k] = p.finger[f][k];  // middle..little keep their abduction
  return a;
}

hand::HandJointAngles fist_posture() {
  return from_degrees({{{15, 10, 30, 60}, {-4, 90, 100, 70}, {0, 90, 100, 70}, {4, 90, 100, 70}, {8, 90, 100, 70}}});
}

hand::HandJointAngles spread_posture() {
  return from_degrees({{{-70, 0, 0, 0}, {-20, 0, 0, 0}, {0, 0, 0, 0}, {15, 0, 0, 0}, {30, 0, 0, 0}}});
}

std::string glove_csv_column_name(int column) {
  static constexpr const char* kJoint[4] = {"abduction", "flexion1", "flexion2", "flexion3"};
  static constexpr const char* kPalm[3] = {"palm_x_m", "palm_y_m", "palm_z_m"};
  if (column == 0) return "t_s";
  if (column >= 1 && column <= kAngleColumns)
    return std::string(hand::finger_name((column - 1) / 4)) + "_" + kJoint[(column - 1) % 4] + "_deg";
  if (column > kAngleColumns && column < kTimeColumns + kAngleColumns + kPalmColumns)
    return kPalm[column - kTimeColumns - kAngleColumns];
  return "?";
}

GloveTrajectory GloveTrajectory::grasp(Vec3d origin) { return {Kind::kGrasp, "grasp", origin}; }
GloveTrajectory GloveTrajectory::pinch(Vec3d origin) { return {Kind::kPinch, "pinch", origin}; }
GloveTrajectory GloveTrajectory::release(Vec3d origin) { return {Kind::kRelease, "release", origin}; }
GloveTrajectory GloveTrajectory::fist(Vec3d origin) { return {Kind::kFist, "fist", origin}; }
GloveTrajectory GloveTrajectory::spread(Vec3d origin) { return {Kind::kSpread, "spread", origin}; }
GloveTrajectory GloveTrajectory::tap(Vec3d origin) { return {Kind::kTap, "tap", origin}; }

GloveTrajectory GloveTrajectory::parse(const std::string& spec, Vec3d origin) {
  if (spec == "grasp") return grasp(origin);
  if (spec == "pinch") return pinch(origin);
  if (spec == "release") return release(origin);
  if (spec == "fist") return fist(origin);
  if (spec == "spread") return spread(origin);
  if (spec == "tap") return tap(origin);
  return from_csv(spec, origin);
}

GloveTrajectory GloveTrajectory::from_csv(const std::string& path, Vec3d origin) {
  std::ifstream in(path);
  if (!in)
    throw std::runtime_error("cannot read glove trajectory file '" + path +
                             "' (expected grasp, pinch, release, fist, spread, tap or a CSV file)");
  constexpr int kShort = kTimeColumns + kAngleColumns, kLong = kShort + kPalmColumns;
  GloveTrajectory trajectory(Kind::kFile, path, origin);
  int columns = 0;  // fixed by the header or the first row
  bool header_seen = false;
  std::string line;
  for (int number = 1; std::getline(in, line); ++number) {
    const std::string_view text = trim(line);
    if (text.empty() || text.front() == '#') continue;
    const std::string where = path + ":" + std::to_string(number) + ":";
    const auto fail_row = [&](const std::string& what) { throw std::runtime_error(where + " " + what); };
    const auto fail = [&](int column, const std::string& what) {  // column 0-based, reported 1-based
      throw std::runtime_error(where + std::to_string(column + 1) + ": " + glove_csv_column_name(column) + ": " + what);
    };
    std::string_view fields[kLong];
    int count = 0;
    for (std::string_view rest = text;; ++count) {
      const auto comma = rest.find(',');
      if (count < kLong) fields[count] = trim(rest.substr(0, comma));
      if (comma == std::string_view::npos) break;
      rest.remove_prefix(comma + 1);
    }
    ++count;
    const std::string shape = "expected " + std::to_string(kShort) +
                              " comma-separated fields (t_s and 20 joint angles in degrees) or " +
                              std::to_string(kLong) + " (then palm x, y, z in m)";
    if (fields[0] == "t_s") {  // a header
      if (!trajectory.knots_.empty() || columns != 0) fail_row("a header line must come once, before the first row");
      if (count != kShort && count != kLong) fail_row(shape + ", found " + std::to_string(count) + " in the header");
      for (int c = 1; c < count; ++c)
        if (fields[c] != glove_csv_column_name(c))
          fail(c, "header names '" + std::string(fields[c]) + "', expected '" + glove_csv_column_name(c) + "'");
      columns = count;
      header_seen = true;
      continue;
    }
    if (columns == 0) {
      if (count != kShort && count != kLong) fail_row(shape + ", found " + std::to_string(count));
      columns = count;
    } else if (count != columns) {
      fail_row("found " + std::to_string(count) + " fields, expected " + std::to_string(columns) +
               (header_seen ? " as the header says" : " like the rows before") + " (column " +
               std::to_string(std::min(count, columns) + 1) + " " + (count < columns ? "missing" : "extra") + ")");
    }
    double values[kLong];
    for (int c = 0; c < count; ++c) {
      const std::string_view f = fields[c];
      const auto [end, ec] = std::from_chars(f.data(), f.data() + f.size(), values[c]);
      if (f.empty() || ec != std::errc() || end != f.data() + f.size())
        fail(c, "'" + std::string(f) + "' is not a number");
      if (!std::isfinite(values[c])) fail(c, "'" + std::string(f) + "' is not finite");
    }
    if (values[0] < 0.0) fail(0, "must be >= 0, got " + std::string(fields[0]));
    if (!trajectory.knots_.empty() && values[0] <= trajectory.knots_.back().t_s)
      fail(0, std::string(fields[0]) + " is not after the previous row's");
    Knot knot{values[0], JointVector::Zero(), {}};
    for (int j = 0; j < kAngleColumns; ++j) {
      const double deg = values[kTimeColumns + j];
      if (std::abs(deg) > kMaxCsvAngleDeg)
        fail(kTimeColumns + j, std::string(fields[kTimeColumns + j]) + " degrees is beyond +-180");
      knot.q_rad[j] = deg * kRadPerDeg;
    }
    if (count == kLong) {
      for (int c = kShort; c < kLong; ++c)
        if (std::abs(values[c]) > protocol::kMaxPositionM)
          fail(c, std::string(fields[c]) + " is beyond the protocol's " +
                      std::to_string(static_cast<int>(protocol::kMaxPositionM)) + " m");
      knot.p_m = {values[kShort], values[kShort + 1], values[kShort + 2]};
    }
    trajectory.knots_.push_back(knot);
  }
  if (trajectory.knots_.empty()) throw std::runtime_error(path + ": no glove trajectory rows (t_s and 20 angles)");
  trajectory.file_has_palm_ = columns == kLong;
  return trajectory;
}

GloveTrajectory GloveTrajectory::from_samples(std::string name, const std::vector<Sample>& samples, Vec3d origin) {
  if (samples.empty()) throw std::invalid_argument(name + ": no glove trajectory samples");
  GloveTrajectory trajectory(Kind::kFile, std::move(name), origin);
  for (std::size_t i = 0; i < samples.size(); ++i) {
    const Sample& s = samples[i];
    const auto fail = [&](const std::string& what) {
      throw std::invalid_argument(trajectory.name_ + ": sample " + std::to_string(i) + ": " + what);
    };
    if (!std::isfinite(s.t_s) || s.t_s < 0) fail("t_s must be finite and >= 0");
    if (i > 0 && s.t_s <= samples[i - 1].t_s) fail("t_s must increase strictly");
    if (!s.q_rad.allFinite() || s.q_rad.cwiseAbs().maxCoeff() > std::numbers::pi)
      fail("angles must be within +-pi rad");
    const Eigen::Vector3d palm(s.palm_m.x, s.palm_m.y, s.palm_m.z);
    if (!palm.allFinite() || palm.cwiseAbs().maxCoeff() > protocol::kMaxPositionM)
      fail("the palm offset must be finite and within the protocol's " +
           std::to_string(static_cast<int>(protocol::kMaxPositionM)) + " m");
    trajectory.knots_.push_back({s.t_s, s.q_rad, s.palm_m});
  }
  trajectory.file_has_palm_ = true;
  return trajectory;
}

JointVector GloveTrajectory::angles(double t_s) const noexcept {
  const double t = std::max(0.0, t_s);
  const Postures& p = postures();
  switch (kind_) {
    case Kind::kGrasp:
      return ramp(p.rest, p.grasp, t, kGloveSettleS);
    case Kind::kPinch:
      return ramp(p.rest, p.pinch, t, kGloveSettleS);
    case Kind::kRelease:
      return ramp(p.grasp, p.rest, t, kGloveSettleS);
    case Kind::kFist:
      return cycle(p.rest, p.fist, std::fmod(t, kGloveCycleS));
    case Kind::kSpread:
      return cycle(p.rest, p.spread, std::fmod(t, kGloveCycleS));
    case Kind::kTap: {
      JointVector q = p.rest;
      if (t > kGloveSettleS) {
        const double s = std::sin(std::numbers::pi * kGloveTapFrequencyHz * (t - kGloveSettleS));
        q[4 * 1 + 1] += kGloveTapFlexionDeg * kRadPerDeg * s * s;  // index, flexion 1 (MCP)
      }
      return q;
    }
    case Kind::kFile: {
      if (t <= knots_.front().t_s) return knots_.front().q_rad;
      if (t >= knots_.back().t_s) return knots_.back().q_rad;
      const auto after =
          std::upper_bound(knots_.begin(), knots_.end(), t, [](double time, const Knot& k) { return time < k.t_s; });
      const Knot& a = *(after - 1);
      const Knot& b = *after;
      const double w = (t - a.t_s) / (b.t_s - a.t_s);
      return a.q_rad + w * (b.q_rad - a.q_rad);
    }
  }
  return p.rest;
}

JointVector GloveTrajectory::angle_rates(double t_s) const noexcept {
  constexpr double h = 1e-6;
  const double t0 = std::max(0.0, t_s - h), t1 = std::max(0.0, t_s) + h;
  return (angles(t1) - angles(t0)) / (t1 - t0);
}

Vec3d GloveTrajectory::palm_position(double t_s) const noexcept { return origin_ + palm_offset(std::max(0.0, t_s)); }

Vec3d GloveTrajectory::palm_velocity(double t_s) const noexcept {
  constexpr double h = 1e-6;
  const double t0 = std::max(0.0, t_s - h), t1 = std::max(0.0, t_s) + h;
  return (palm_offset(t1) - palm_offset(t0)) / (t1 - t0);
}

Vec3d GloveTrajectory::palm_offset(double t) const noexcept {
  if (kind_ != Kind::kFile || !file_has_palm_) return {};
  if (t <= knots_.front().t_s) return knots_.front().p_m;
  if (t >= knots_.back().t_s) return knots_.back().p_m;
  const auto after =
      std::upper_bound(knots_.begin(), knots_.end(), t, [](double time, const Knot& k) { return time < k.t_s; });
  const Knot& a = *(after - 1);
  const Knot& b = *after;
  const double w = (t - a.t_s) / (b.t_s - a.t_s);
  return a.p_m + w * (b.p_m - a.p_m);
}

}  // namespace hapticd::sim
