#include <gtest/gtest.h>
#include <unistd.h>

#include <cmath>
#include <filesystem>
#include <fstream>
#include <numbers>
#include <stdexcept>
#include <string>

#include "clients/sim/glove_trajectory.hpp"

// The glove's commanded motions: each built-in reaches its documented posture at its documented
// time, with continuous rates; CSV files are interpolated, and bad ones are named by line and
// column.

namespace hapticd::sim {
namespace {

constexpr double kDeg = std::numbers::pi / 180.0;
constexpr double kTol = 1e-12;  // a few ulps of an angle

// Joint j of finger f in degrees.
double deg(const JointVector& q, int f, int k) { return q[4 * f + k] / kDeg; }

void expect_posture(const JointVector& q, const hand::HandJointAngles& expected, const std::string& what) {
  EXPECT_LT((q - expected.vector()).cwiseAbs().maxCoeff(), kTol) << what;
}

// The largest jump of the commanded rate across [t0, t1] sampled every 0.1 ms. A C1 motion's rates
// change by |q''| 0.1 ms between samples, below 0.02 rad/s for these (the tap's 165 rad/s^2 is the
// largest); a kink (C0 only) would jump by the order of the rate itself, ~1 rad/s.
constexpr double kSmoothRateJump = 0.05;
double largest_rate_jump(const GloveTrajectory& t, double t0, double t1) {
  double worst = 0.0;
  JointVector before = t.angle_rates(t0);
  for (double s = t0 + 1e-4; s <= t1; s += 1e-4) {
    const JointVector now = t.angle_rates(s);
    worst = std::max(worst, (now - before).cwiseAbs().maxCoeff());
    before = now;
  }
  return worst;
}

TEST(GlovePostures, AreTheDocumentedAngles) {
  const JointVector fist = fist_posture().vector();
  for (int f = 1; f < 5; ++f) {
    EXPECT_NEAR(deg(fist, f, 1), 90.0, kTol) << "MCP";
    EXPECT_NEAR(deg(fist, f, 2), 100.0, kTol) << "PIP";
    EXPECT_NEAR(deg(fist, f, 3), 70.0, kTol) << "DIP";
  }
  EXPECT_NEAR(deg(fist, 0, 0), 15.0, kTol) << "the thumb turned across the palm";
  EXPECT_NEAR(deg(fist, 0, 3), 60.0, kTol);
  const JointVector spread = spread_posture().vector();
  const double abduction[5] = {-70, -20, 0, 15, 30};
  for (int f = 0; f < 5; ++f) {
    EXPECT_NEAR(deg(spread, f, 0), abduction[f], kTol);
    for (int k = 1; k < 4; ++k) EXPECT_EQ(spread[4 * f + k], 0.0) << "straight fingers";
  }
  const JointVector grasp = power_grasp_posture().vector();
  EXPECT_NEAR(deg(grasp, 2, 1), 55.0, kTol);
  EXPECT_NEAR(deg(grasp, 2, 2), 65.0, kTol);
  EXPECT_NEAR(deg(grasp, 2, 3), 35.0, kTol);
  EXPECT_NEAR(deg(grasp, 0, 0), -25.0, kTol);
}

TEST(GlovePostures, ThePinchBringsTheThumbAndIndexTipsTogether) {
  for (bool left : {false, true}) {
    const hand::SkeletonPose p = hand::skeleton_pose(pinch_posture(), left);
    const double gap = (p.joints[0][3] - p.joints[1][3]).norm();
    EXPECT_NEAR(gap, 0.0163, 0.0001) << "bone ends 1.63 cm apart: the pads' flesh radii in contact";
    const hand::SkeletonPose rest = hand::skeleton_pose(hand::rest_joint_angles(), left);
    EXPECT_GT((rest.joints[0][3] - rest.joints[1][3]).norm(), 0.1) << "11 cm apart at rest";
  }
  // The other fingers keep their rest abduction, slightly flexed.
  const JointVector pinch = pinch_posture().vector(), rest = hand::rest_joint_angles().vector();
  for (int f = 2; f < 5; ++f) {
    EXPECT_EQ(pinch[4 * f], rest[4 * f]);
    EXPECT_NEAR(deg(pinch, f, 1), 20.0, kTol);
  }
}

TEST(GlovePostures, TheGraspAndFistCurlTheFingertipsToThePalmarSide) {
  // Fingertips (bone ends) in the hand frame: palmar is -z. Power grasp: the long fingertips 5-7 cm
  // below the palm plane, wrapped back to within 4 cm of the knuckles (y 3-4 cm). Fist: the tips
  // back at the palm (z -1.2..-1.7 cm, y 1.1..1.7 cm), the thumb tip under the middle phalanges.
  const hand::SkeletonPose g = hand::skeleton_pose(power_grasp_posture());
  for (int f = 1; f < 5; ++f) {
    EXPECT_LT(g.joints[f][3].z(), -0.05) << hand::finger_name(f);
    EXPECT_GT(g.joints[f][3].z(), -0.075) << hand::finger_name(f);
    EXPECT_NEAR(g.joints[f][3].y(), 0.035, 0.005) << hand::finger_name(f);
  }
  const hand::SkeletonPose fist = hand::skeleton_pose(fist_posture());
  for (int f = 1; f < 5; ++f) {
    EXPECT_NEAR(fist.joints[f][3].z(), -0.0145, 0.003) << hand::finger_name(f);
    EXPECT_NEAR(fist.joints[f][3].y(), 0.014, 0.003) << hand::finger_name(f);
  }
  const Eigen::Vector3d thumb_tip = fist.joints[0][3];
  for (int f : {1, 2}) EXPECT_LT(thumb_tip.z(), fist.centre[3 * f + 1].z() - 0.01) << "below " << hand::finger_name(f);
  EXPECT_GT(thumb_tip.x(), fist.centre[3 * 1 + 1].x()) << "across, past the index";
  EXPECT_LT(thumb_tip.x(), fist.centre[3 * 2 + 1].x() + 0.01) << "short of the middle finger's far side";
}

TEST(GloveTrajectory, GraspPinchAndReleaseMoveBetweenTheirPosturesOverASecondAndHold) {
  struct Case {
    GloveTrajectory trajectory;
    hand::HandJointAngles from, to;
  };
  const Case cases[] = {{GloveTrajectory::grasp(), hand::rest_joint_angles(), power_grasp_posture()},
                        {GloveTrajectory::pinch(), hand::rest_joint_angles(), pinch_posture()},
                        {GloveTrajectory::release(), power_grasp_posture(), hand::rest_joint_angles()}};
  for (const Case& c : cases) {
    const GloveTrajectory& t = c.trajectory;
    const std::string& name = t.name();
    expect_posture(t.angles(0.0), c.from, name + " at 0 s");
    expect_posture(t.angles(0.5), c.from, name + " held until 0.5 s");
    // Half-way through the half-cosine ramp: the mean of the two postures.
    EXPECT_LT((t.angles(1.0) - 0.5 * (c.from.vector() + c.to.vector())).cwiseAbs().maxCoeff(), kTol) << name;
    for (double s : {1.5, 2.0, 10.0}) expect_posture(t.angles(s), c.to, name + " held from 1.5 s");
    // Peak rate of a half-cosine ramp of amplitude A over T: pi A / (2 T), at its middle.
    const JointVector A = c.to.vector() - c.from.vector();
    EXPECT_LT((t.angle_rates(1.0) - std::numbers::pi / 2.0 * A).cwiseAbs().maxCoeff(), 1e-8) << name;
    EXPECT_LT(t.angle_rates(0.5).cwiseAbs().maxCoeff(), 1e-5) << name << ": starts with zero rate";
    EXPECT_LT(t.angle_rates(1.5).cwiseAbs().maxCoeff(), 1e-5) << name << ": ends with zero rate";
    EXPECT_LT(largest_rate_jump(t, 0.0, 2.0), kSmoothRateJump) << name << ": continuous rates (C1)";
    EXPECT_EQ(t.palm_position(1.0), (Vec3d{})) << "the palm stays at the origin";
  }
}

TEST(GloveTrajectory, FistAndSpreadCycleEveryFourSeconds) {
  const GloveTrajectory fist = GloveTrajectory::fist(), spread = GloveTrajectory::spread();
  for (double cycle : {0.0, 4.0, 8.0}) {
    expect_posture(fist.angles(cycle + 0.2), hand::rest_joint_angles(), "fist: rest before closing");
    expect_posture(fist.angles(cycle + 2.0), fist_posture(), "fist: held closed 1.5..2.5 s");
    expect_posture(fist.angles(cycle + 2.5), fist_posture(), "fist: still closed at 2.5 s");
    expect_posture(fist.angles(cycle + 3.6), hand::rest_joint_angles(), "fist: open again from 3.5 s");
    expect_posture(spread.angles(cycle + 2.0), spread_posture(), "spread: held 1.5..2.5 s");
    expect_posture(spread.angles(cycle + 3.9), hand::rest_joint_angles(), "spread: back at rest");
  }
  EXPECT_NEAR(deg(fist.angles(2.0), 1, 1), 90.0, kTol) << "index MCP 90 degrees";
  EXPECT_NEAR(deg(fist.angles(3.0), 1, 2), 0.5 * (100.0 + 6.0), 1e-10) << "PIP half-way open at 3 s (rest 6)";
  EXPECT_LT(largest_rate_jump(fist, 0.0, 8.5), kSmoothRateJump) << "C1, across the cycle boundary too";
  EXPECT_LT(largest_rate_jump(spread, 0.0, 8.5), kSmoothRateJump);
}

TEST(GloveTrajectory, TapFlexesTheIndexMcpThirtyDegreesFourTimesASecond) {
  const GloveTrajectory t = GloveTrajectory::tap();
  const JointVector rest = hand::rest_joint_angles().vector();
  expect_posture(t.angles(0.4), hand::rest_joint_angles(), "at rest first");
  EXPECT_NEAR(deg(t.angles(0.5 + 0.125), 1, 1), 30.0, 1e-9) << "top of the first tap";
  EXPECT_NEAR(deg(t.angles(0.5 + 0.25), 1, 1), 0.0, 1e-9) << "back at rest after 0.25 s";
  int taps = 0;
  bool up = false;
  double highest = 0.0;
  for (double s = 0.0; s < 1.5; s += 1e-4) {
    const JointVector q = t.angles(s);
    JointVector others = q - rest;
    others[5] = 0.0;
    EXPECT_EQ(others.cwiseAbs().maxCoeff(), 0.0) << "only the index MCP moves, t = " << s;
    highest = std::max(highest, deg(q, 1, 1));
    const bool now_up = deg(q, 1, 1) > 15.0;
    taps += now_up && !up;
    up = now_up;
  }
  EXPECT_EQ(taps, 4) << "taps starting at 0.5, 0.75, 1.0 and 1.25 s";
  EXPECT_NEAR(highest, 30.0, 1e-4);
  EXPECT_LT(largest_rate_jump(t, 0.0, 1.5), kSmoothRateJump) << "sin^2 starts and ends with zero rate";
  // Peak rate of A sin^2(pi f t): pi f A.
  EXPECT_NEAR(t.angle_rates(0.5 + 0.0625)[5], std::numbers::pi * 4.0 * 30.0 * kDeg, 1e-8);
}

TEST(GloveTrajectory, BuiltInNamesParseAndTheOriginPlacesThePalm) {
  EXPECT_EQ(GloveTrajectory::parse("grasp").kind(), GloveTrajectory::Kind::kGrasp);
  EXPECT_EQ(GloveTrajectory::parse("pinch").kind(), GloveTrajectory::Kind::kPinch);
  EXPECT_EQ(GloveTrajectory::parse("release").kind(), GloveTrajectory::Kind::kRelease);
  EXPECT_EQ(GloveTrajectory::parse("fist").kind(), GloveTrajectory::Kind::kFist);
  EXPECT_EQ(GloveTrajectory::parse("spread").kind(), GloveTrajectory::Kind::kSpread);
  EXPECT_EQ(GloveTrajectory::parse("tap").kind(), GloveTrajectory::Kind::kTap);
  const GloveTrajectory t = GloveTrajectory::grasp({0.1, 0.2, 0.3});
  EXPECT_EQ(t.palm_position(3.0), (Vec3d{0.1, 0.2, 0.3}));
  EXPECT_EQ(t.palm_velocity(3.0), (Vec3d{}));
  EXPECT_EQ(t.angles(-1.0), t.angles(0.0));
  EXPECT_EQ(t.palm_orientation().coeffs(), Eigen::Quaterniond::Identity().coeffs());
}

class GloveCsv : public ::testing::Test {
 protected:
  void TearDown() override { std::filesystem::remove_all(dir_); }
  std::string write(const std::string& name, const std::string& text) {
    std::filesystem::create_directories(dir_);
    const std::string path = (dir_ / name).string();
    std::ofstream(path) << text;
    return path;
  }
  static std::string error_of(const std::string& path) {
    try {
      (void)GloveTrajectory::from_csv(path);
    } catch (const std::runtime_error& e) {
      return e.what();
    }
    return "";
  }
  // A row: time, then every angle `a` degrees except angle `j` (0-based) set to `aj`.
  static std::string row(const std::string& t, double a, int j = -1, const std::string& aj = "", int extra = 0) {
    std::string r = t;
    for (int i = 0; i < 20; ++i) r += "," + (i == j ? aj : std::to_string(a));
    for (int i = 0; i < extra; ++i) r += ",0.5";
    return r + "\n";
  }
  static std::string header(bool palm = false) {
    std::string h = "t_s";
    for (int c = 1; c < (palm ? 24 : 21); ++c) h += "," + glove_csv_column_name(c);
    return h + "\n";
  }

  const std::filesystem::path dir_ =
      std::filesystem::temp_directory_path() / ("hapticd_glove_csv_tests_" + std::to_string(::getpid()));
};

TEST_F(GloveCsv, ColumnNamesFollowHandJointAnglesOrder) {
  EXPECT_EQ(glove_csv_column_name(0), "t_s");
  EXPECT_EQ(glove_csv_column_name(1), "thumb_abduction_deg");
  EXPECT_EQ(glove_csv_column_name(6), "index_flexion1_deg");
  EXPECT_EQ(glove_csv_column_name(20), "little_flexion3_deg");
  EXPECT_EQ(glove_csv_column_name(21), "palm_x_m");
  EXPECT_EQ(glove_csv_column_name(23), "palm_z_m");
  EXPECT_EQ(glove_csv_column_name(24), "?");
}

TEST_F(GloveCsv, RowsInDegreesAreInterpolatedLinearlyAndThePalmColumnsAddToTheOrigin) {
  const std::string angles =
      write("angles.csv", "# two postures\n" + header() + "\n" + row("0.5", 0.0) + row("1.5", 20.0));
  const GloveTrajectory t = GloveTrajectory::from_csv(angles, {0.0, 0.0, 1.0});
  EXPECT_EQ(t.kind(), GloveTrajectory::Kind::kFile);
  EXPECT_FALSE(t.file_has_palm());
  EXPECT_EQ(t.angles(0.0), JointVector::Zero()) << "held before the first row";
  EXPECT_LT((t.angles(1.0) - JointVector::Constant(10.0 * kDeg)).cwiseAbs().maxCoeff(), kTol);
  EXPECT_LT((t.angles(9.0) - JointVector::Constant(20.0 * kDeg)).cwiseAbs().maxCoeff(), kTol);
  EXPECT_LT((t.angle_rates(1.0) - JointVector::Constant(20.0 * kDeg)).cwiseAbs().maxCoeff(), 1e-8) << "20 deg/s";
  EXPECT_EQ(t.palm_position(1.0), (Vec3d{0.0, 0.0, 1.0})) << "no palm columns: at the origin";

  std::string rows = header(true);
  rows += "0";
  for (int i = 0; i < 20; ++i) rows += ",0";
  rows += ",0.0,0.0,0.0\n1";
  for (int i = 0; i < 20; ++i) rows += ",-10";
  rows += ",0.02,-0.04,0.1\n";
  const GloveTrajectory p = GloveTrajectory::from_csv(write("palm.csv", rows), {0.0, 0.0, 1.0});
  EXPECT_TRUE(p.file_has_palm());
  const Vec3d half = p.palm_position(0.5);
  EXPECT_NEAR(half.x, 0.01, kTol);
  EXPECT_NEAR(half.y, -0.02, kTol);
  EXPECT_NEAR(half.z, 1.05, kTol);
  EXPECT_NEAR(p.palm_velocity(0.5).z, 0.1, 1e-8);
  EXPECT_NEAR(p.angles(0.5)[19], -5.0 * kDeg, kTol);
  EXPECT_EQ(GloveTrajectory::parse(angles).kind(), GloveTrajectory::Kind::kFile);
}

TEST_F(GloveCsv, BadFilesAreNamedByLineAndColumn) {
  const std::string first = header() + row("0", 0.0);  // lines 1-2
  struct Case {
    const char* name;
    std::string text;
    std::string expected;  // after "path:"
  };
  const Case cases[] = {
      {"word.csv", first + row("1", 0.0, 5, "abc"), "3:7: index_flexion1_deg: 'abc' is not a number"},
      {"unit.csv", first + row("1", 0.0, 19, "10deg"), "3:21: little_flexion3_deg: '10deg' is not a number"},
      {"empty_field.csv", first + row("1", 0.0, 0, ""), "3:2: thumb_abduction_deg: '' is not a number"},
      {"nan.csv", first + row("1", 0.0, 2, "nan"), "3:4: thumb_flexion2_deg: 'nan' is not finite"},
      {"time.csv", first + row("x", 0.0), "3:1: t_s: 'x' is not a number"},
      {"order.csv", first + "# comment\n" + row("0", 0.0), "4:1: t_s: 0 is not after the previous row's"},
      {"negative.csv", row("-1", 0.0), "1:1: t_s: must be >= 0, got -1"},
      {"angle.csv", first + row("1", 0.0, 3, "200"), "3:5: thumb_flexion3_deg: 200 degrees is beyond +-180"},
      {"short.csv", "0,1,2,3\n",
       "1: expected 21 comma-separated fields (t_s and 20 joint angles in degrees) "
       "or 24 (then palm x, y, z in m), found 4"},
      {"short_after_header.csv", header() + "0,1,2,3\n",
       "2: found 4 fields, expected 21 as the header says (column 5 missing)"},
      {"ragged.csv", row("0", 0.0) + row("1", 0.0, -1, "", 3),
       "2: found 24 fields, expected 21 like the rows before (column 22 extra)"},
      {"ragged2.csv", row("0", 0.0, -1, "", 3) + row("1", 0.0),
       "2: found 21 fields, expected 24 like the rows before (column 22 missing)"},
      {"header_name.csv", "t_s,thumb_abduction_deg,thumb_flex1_deg" + header().substr(header().find(",thumb_flexion2")),
       "1:3: thumb_flexion1_deg: header names 'thumb_flex1_deg', expected 'thumb_flexion1_deg'"},
      {"late_header.csv", first + header(), "3: a header line must come once, before the first row"},
      {"header_count.csv", "t_s,thumb_abduction_deg\n",
       "1: expected 21 comma-separated fields (t_s and 20 joint angles in degrees) or 24 (then palm x, y, z in m), "
       "found 2 in the header"},
  };
  for (const Case& c : cases) {
    const std::string path = write(c.name, c.text);
    EXPECT_EQ(error_of(path), path + ":" + c.expected) << c.name;
  }
  // A palm coordinate beyond the protocol's bound.
  std::string far = row("0", 0.0, -1, "", 3);
  far.replace(far.rfind(",0.5"), 4, ",101");
  const std::string far_path = write("far.csv", far);
  EXPECT_EQ(error_of(far_path), far_path + ":1:24: palm_z_m: 101 is beyond the protocol's 100 m");

  const std::string empty = write("empty.csv", "# nothing\n" + header() + "\n");
  EXPECT_EQ(error_of(empty), empty + ": no glove trajectory rows (t_s and 20 angles)");
  const std::string missing = error_of("/nonexistent/glove.csv");
  EXPECT_NE(missing.find("cannot read glove trajectory file '/nonexistent/glove.csv'"), std::string::npos) << missing;
  EXPECT_NE(missing.find("grasp, pinch, release, fist, spread, tap"), std::string::npos)
      << "a mistyped built-in name must say which names exist";
}

TEST(GloveTrajectory, SamplesInMemoryAreInterpolatedLikeAFilesRowsAndBadOnesAreNamed) {
  // Two samples: angle 3 (thumb flexion 3) from 0 to 0.4 rad and the palm from 0 to 2 cm up over
  // 0.5 s; held before and after; the origin added to the palm.
  JointVector q1 = JointVector::Zero();
  q1[3] = 0.4;
  const GloveTrajectory t =
      GloveTrajectory::from_samples("script", {{0.5, JointVector::Zero(), {}}, {1.0, q1, {0, 0, 0.02}}}, {1, 2, 3});
  EXPECT_EQ(t.kind(), GloveTrajectory::Kind::kFile);
  EXPECT_TRUE(t.file_has_palm());
  EXPECT_EQ(t.name(), "script");
  EXPECT_NEAR(t.angles(0.0)[3], 0.0, 1e-15);
  EXPECT_NEAR(t.angles(0.75)[3], 0.2, 1e-12);
  EXPECT_NEAR(t.angles(2.0)[3], 0.4, 1e-15);
  EXPECT_NEAR(t.angle_rates(0.75)[3], 0.8, 1e-6);
  EXPECT_NEAR(t.palm_position(0.75).z, 3.01, 1e-12);
  EXPECT_NEAR(t.palm_velocity(0.75).z, 0.04, 1e-6);
  EXPECT_NEAR(t.palm_position(5.0).x, 1.0, 1e-15);
  auto error_of = [](const std::vector<GloveTrajectory::Sample>& samples) {
    try {
      GloveTrajectory::from_samples("bad", samples);
    } catch (const std::invalid_argument& e) {
      return std::string(e.what());
    }
    return std::string("no error");
  };
  JointVector wild = JointVector::Zero();
  wild[7] = 4.0;
  EXPECT_EQ(error_of({}), "bad: no glove trajectory samples");
  EXPECT_EQ(error_of({{-1, JointVector::Zero(), {}}}), "bad: sample 0: t_s must be finite and >= 0");
  EXPECT_EQ(error_of({{0, JointVector::Zero(), {}}, {0, JointVector::Zero(), {}}}),
            "bad: sample 1: t_s must increase strictly");
  EXPECT_EQ(error_of({{0, wild, {}}}), "bad: sample 0: angles must be within +-pi rad");
  EXPECT_EQ(error_of({{0, JointVector::Zero(), {0, 0, NAN}}}),
            "bad: sample 0: the palm offset must be finite and within the protocol's 100 m");
}

}  // namespace
}  // namespace hapticd::sim
