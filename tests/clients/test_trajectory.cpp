#include <gtest/gtest.h>
#include <unistd.h>

#include <cmath>
#include <filesystem>
#include <fstream>
#include <numbers>
#include <stdexcept>
#include <string>

#include "clients/sim/trajectory.hpp"

namespace hapticd::sim {
namespace {

// Positions are sums of a few doubles: exact to a few ulps of 0.03 m.
constexpr double kTol = 1e-12;

TEST(Trajectory, PressStartsThreeCentimetresUpGoesTwoDownHoldsAndReturns) {
  const Trajectory t = Trajectory::press();
  EXPECT_NEAR(t.position(0.0).z, 0.03, kTol);
  EXPECT_NEAR(t.position(0.5).z, 0.03, kTol) << "settled before moving";
  EXPECT_NEAR(t.position(1.0).z, 0.02, kTol) << "half-way down at the middle of the 1 s ramp";
  for (double s : {1.5, 2.0, 2.5}) EXPECT_NEAR(t.position(s).z, 0.01, kTol) << "held 2 cm down at t = " << s;
  EXPECT_NEAR(t.position(3.0).z, 0.02, kTol);
  EXPECT_NEAR(t.position(3.5).z, 0.03, kTol) << "released";
  double lowest = 1.0, fastest = 0.0;
  for (int i = 0; i <= 40000; ++i) {
    const double s = i * 1e-4;
    lowest = std::min(lowest, t.position(s).z);
    fastest = std::max(fastest, std::abs(t.velocity(s).z));
    EXPECT_EQ(t.position(s).x, 0.0);
    EXPECT_EQ(t.position(s).y, 0.0);
  }
  EXPECT_NEAR(lowest, 0.01, kTol) << "the press depth is 2 cm";
  // Half-cosine ramp of depth d over T: peak speed pi d / (2 T); the difference quotient is
  // O(h^2) = 1e-12 off.
  EXPECT_NEAR(fastest, std::numbers::pi * 0.02 / 2.0, 1e-8);
  for (double s : {0.3, 1.2, 2.7, 3.9}) EXPECT_NEAR(t.position(s + 4.0).z, t.position(s).z, kTol) << "4 s cycle";
}

TEST(Trajectory, StrokeSlidesTwoCentimetresEachWayAtHalfAHertzWhileHeldDown) {
  const Trajectory t = Trajectory::stroke();
  EXPECT_NEAR(t.position(0.0).z, 0.03, kTol);
  EXPECT_NEAR(t.position(1.5).z, 0.01, kTol);
  EXPECT_NEAR(t.position(1.5).x, 0.0, kTol);
  EXPECT_NEAR(t.position(2.0).x, 0.02, kTol) << "a quarter of the 2 s period";
  EXPECT_NEAR(t.position(3.0).x, -0.02, kTol);
  EXPECT_NEAR(t.position(3.5).x, 0.0, kTol);
  for (double s = 1.5; s < 6.0; s += 0.01) EXPECT_NEAR(t.position(s).z, 0.01, kTol);
}

TEST(Trajectory, PressStrokeIsOnePressCycleThenAStroke) {
  const Trajectory ps = Trajectory::press_stroke(), press = Trajectory::press(), stroke = Trajectory::stroke();
  for (double s = 0.0; s < 4.0; s += 0.01) EXPECT_EQ(ps.position(s), press.position(s));
  for (double s = 4.0; s < 10.0; s += 0.01) EXPECT_EQ(ps.position(s), stroke.position(s - 4.0));
}

TEST(Trajectory, TapDipsTwoCentimetresTwicePerSecond) {
  const Trajectory t = Trajectory::tap();
  EXPECT_NEAR(t.position(0.3).z, 0.03, kTol);
  EXPECT_NEAR(t.position(0.6).z, 0.01, kTol) << "bottom of the first 0.2 s dip";
  EXPECT_NEAR(t.position(0.8).z, 0.03, kTol) << "back up between dips";
  EXPECT_NEAR(t.position(1.1).z, 0.01, kTol);
  // Count the dips in 0..2.5 s: at 0.5, 1.0, 1.5, 2.0 s.
  int dips = 0;
  bool down = false;
  for (double s = 0.0; s < 2.5; s += 1e-3) {
    const bool now_down = t.position(s).z < 0.02;
    dips += now_down && !down;
    down = now_down;
  }
  EXPECT_EQ(dips, 4);
}

TEST(Trajectory, CircleHasATwoCentimetreRadiusAtAFixedDepth) {
  const Vec3d origin{0.1, -0.2, 0.3};
  const Trajectory t = Trajectory::circle(origin);
  for (double s = 0.0; s < 4.0; s += 0.013) {
    const Vec3d p = t.position(s) - origin;
    EXPECT_NEAR(std::hypot(p.x, p.y), 0.02, kTol);
    EXPECT_NEAR(p.z, 0.01, kTol);
  }
  EXPECT_NEAR(t.position(0.5).y - origin.y, 0.02, kTol) << "a quarter turn in 0.5 s: 0.5 Hz";
  const Vec3d after_one_turn = t.position(2.0) - t.position(0.0);
  EXPECT_NEAR(norm(after_one_turn), 0.0, kTol);
  EXPECT_NEAR(norm(t.velocity(0.7)), 2.0 * std::numbers::pi * 0.5 * 0.02, 1e-9);
}

TEST(Trajectory, BuiltInNamesParseAndNegativeTimeHoldsTheStart) {
  EXPECT_EQ(Trajectory::parse("press").kind(), Trajectory::Kind::kPress);
  EXPECT_EQ(Trajectory::parse("stroke").kind(), Trajectory::Kind::kStroke);
  EXPECT_EQ(Trajectory::parse("press-stroke").kind(), Trajectory::Kind::kPressStroke);
  EXPECT_EQ(Trajectory::parse("tap").kind(), Trajectory::Kind::kTap);
  EXPECT_EQ(Trajectory::parse("circle").kind(), Trajectory::Kind::kCircle);
  const Trajectory t = Trajectory::press({1.0, 2.0, 3.0});
  EXPECT_EQ(t.position(-1.0), t.position(0.0));
  EXPECT_NEAR(t.position(0.0).z, 3.03, kTol);
}

class CsvTrajectory : public ::testing::Test {
 protected:
  void TearDown() override { std::filesystem::remove_all(dir_); }
  std::string write(const std::string& name, const std::string& text) {
    std::filesystem::create_directories(dir_);
    const std::string path = (dir_ / name).string();
    std::ofstream(path) << text;
    return path;
  }
  // The message of the error from_csv throws, or "" when it does not.
  static std::string error_of(const std::string& path) {
    try {
      (void)Trajectory::from_csv(path);
    } catch (const std::runtime_error& e) {
      return e.what();
    }
    return "";
  }

  const std::filesystem::path dir_ =
      std::filesystem::temp_directory_path() / ("hapticd_client_tests_" + std::to_string(::getpid()));
};

TEST_F(CsvTrajectory, RowsAreInterpolatedLinearlyAndHeldOutside) {
  const std::string path = write("good.csv",
                                 "# a press and a slide\r\n"
                                 "t_s,x_m,y_m,z_m\r\n"
                                 "\n"
                                 "0.5, 0.0, 0.0, 0.03\n"
                                 "1.5, 0.0, 0.0, 0.01\n"
                                 "2.5, 0.02, -0.01, 0.01\n");
  const Trajectory t = Trajectory::from_csv(path, {0.0, 0.0, 1.0});
  EXPECT_EQ(t.kind(), Trajectory::Kind::kFile);
  EXPECT_EQ(t.name(), path);
  EXPECT_NEAR(t.position(0.0).z, 1.03, kTol) << "held before the first row";
  EXPECT_NEAR(t.position(1.0).z, 1.02, kTol);
  EXPECT_NEAR(t.position(2.0).x, 0.01, kTol);
  EXPECT_NEAR(t.position(2.0).y, -0.005, kTol);
  EXPECT_NEAR(t.position(9.0).x, 0.02, kTol) << "held after the last row";
  EXPECT_NEAR(t.velocity(1.0).z, -0.02, 1e-9) << "the segment's slope";
  EXPECT_EQ(Trajectory::parse(path).kind(), Trajectory::Kind::kFile);
}

TEST_F(CsvTrajectory, ASingleRowHoldsStill) {
  const Trajectory t = Trajectory::from_csv(write("one.csv", "0,0.1,0.2,0.3\n"));
  EXPECT_EQ(t.position(5.0), (Vec3d{0.1, 0.2, 0.3}));
  EXPECT_EQ(t.velocity(5.0), (Vec3d{}));
}

TEST_F(CsvTrajectory, BadRowsAreNamedByFileAndLine) {
  const std::string header = "t_s,x_m,y_m,z_m\n0,0,0,0\n";
  struct Case {
    const char* name;
    std::string text;
    std::string expected;  // after "path:"
  };
  const Case cases[] = {
      {"fields.csv", header + "1,0,0\n", "3: expected 4 comma-separated numbers t_s,x_m,y_m,z_m, found 3 fields"},
      {"extra.csv", header + "1,0,0,0,0\n", "3: expected 4 comma-separated numbers t_s,x_m,y_m,z_m, found 5 fields"},
      {"word.csv", header + "1,0,zero,0\n", "3: y_m: 'zero' is not a number"},
      {"trailing.csv", header + "1,0,0,0.1m\n", "3: z_m: '0.1m' is not a number"},
      {"empty_field.csv", header + "1,,0,0\n", "3: x_m: '' is not a number"},
      {"nan.csv", header + "1,nan,0,0\n", "3: x_m is not finite"},
      {"order.csv", header + "# comment\n0,1,1,1\n", "4: t_s 0 is not after the previous row's"},
      {"negative.csv", "-1,0,0,0\n", "1: t_s must be >= 0, got -1"},
      {"far.csv", header + "1,0,0,101\n", "3: z_m 101 is beyond the protocol's 100 m"},
      {"late_header.csv", header + "t_s,x_m,y_m,z_m\n", "3: the header t_s,x_m,y_m,z_m must come before the first row"},
  };
  for (const Case& c : cases) {
    const std::string path = write(c.name, c.text);
    EXPECT_EQ(error_of(path), path + ":" + c.expected) << c.name;
  }
  const std::string empty = write("empty.csv", "# nothing\nt_s,x_m,y_m,z_m\n\n");
  EXPECT_EQ(error_of(empty), empty + ": no trajectory rows (t_s,x_m,y_m,z_m)");
  const std::string missing = error_of("/nonexistent/trajectory.csv");
  EXPECT_NE(missing.find("cannot read trajectory file '/nonexistent/trajectory.csv'"), std::string::npos) << missing;
  EXPECT_NE(missing.find("press, stroke, press-stroke, tap, circle"), std::string::npos)
      << "a mistyped built-in name must say which names exist";
}

}  // namespace
}  // namespace hapticd::sim
