// The one percentile (protocol/percentile.hpp) against values computed by hand from its definition:
// rank r = p / 100 (n - 1), x_lo + (r - lo) (x_hi - x_lo).
#include <gtest/gtest.h>

#include <cmath>
#include <limits>
#include <vector>

#include "protocol/percentile.hpp"

namespace hapticd::stats {
namespace {

// p / 100 (n - 1) and the interpolation round once or twice: a few ulps of values near 10.
constexpr double kTol = 1e-12;

struct Case {
  const char* what;
  std::vector<double> sample;
  double p;
  double expected;  // by hand
};

TEST(Percentile, MatchesTheHandComputedTable) {
  const std::vector<Case> cases = {
      // {1..5}: r = p / 100 * 4.
      {"1..5 p0: the minimum", {1, 2, 3, 4, 5}, 0, 1.0},
      {"1..5 p25: r = 1", {1, 2, 3, 4, 5}, 25, 2.0},
      {"1..5 p50: r = 2", {1, 2, 3, 4, 5}, 50, 3.0},
      {"1..5 p90: r = 3.6, 4 + 0.6 (5 - 4)", {1, 2, 3, 4, 5}, 90, 4.6},
      {"1..5 p99.9: r = 3.996", {1, 2, 3, 4, 5}, 99.9, 4.996},
      {"1..5 p100: the maximum", {1, 2, 3, 4, 5}, 100, 5.0},
      // An even count: the median is the mean of the two middle samples.
      {"1..4 p50: r = 1.5", {1, 2, 3, 4}, 50, 2.5},
      {"1..4 p25: r = 0.75", {1, 2, 3, 4}, 25, 1.75},
      // A single sample is every percentile.
      {"single p0", {7}, 0, 7.0},
      {"single p50", {7}, 50, 7.0},
      {"single p99", {7}, 99, 7.0},
      {"single p100", {7}, 100, 7.0},
      // Unsorted input: the same as {1..5}.
      {"unsorted p0", {5, 1, 4, 2, 3}, 0, 1.0},
      {"unsorted p50", {5, 1, 4, 2, 3}, 50, 3.0},
      {"unsorted p90", {5, 1, 4, 2, 3}, 90, 4.6},
      {"unsorted p100", {5, 1, 4, 2, 3}, 100, 5.0},
      // Ties: sorted {2, 2, 2, 9}, r = p / 100 * 3.
      {"ties p50: r = 1.5, between two 2s", {2, 9, 2, 2}, 50, 2.0},
      {"ties p75: r = 2.25, 2 + 0.25 (9 - 2)", {2, 9, 2, 2}, 75, 3.75},
      {"ties p100", {2, 9, 2, 2}, 100, 9.0},
      {"all equal p37", {4, 4, 4}, 37, 4.0},
      // Two samples: a straight line from the first to the second.
      {"two p10: r = 0.1", {20, 10}, 10, 11.0},
      // Negative values are samples like any other.
      {"negative p50", {-3, -1, -2}, 50, -2.0},
      // p outside [0, 100] is clamped.
      {"p -5 is p0", {1, 2, 3, 4, 5}, -5, 1.0},
      {"p 150 is p100", {1, 2, 3, 4, 5}, 150, 5.0},
      {"p NaN is p0", {1, 2, 3, 4, 5}, std::numeric_limits<double>::quiet_NaN(), 1.0},
  };
  for (const Case& c : cases) EXPECT_NEAR(percentile(c.sample, c.p), c.expected, kTol) << c.what;
}

TEST(Percentile, OfAnEmptySampleIsNaN) {
  EXPECT_TRUE(std::isnan(percentile({}, 50)));
  EXPECT_TRUE(std::isnan(percentile_of_sorted({}, 0)));
  EXPECT_TRUE(std::isnan(median({})));
}

TEST(Percentile, OfSortedAndMedianAgreeWithPercentile) {
  const std::vector<double> sorted = {0.5, 1, 1, 3, 8, 13, 21};
  for (double p : {0.0, 10.0, 33.3, 50.0, 90.0, 99.0, 100.0})
    EXPECT_EQ(percentile_of_sorted(sorted, p), percentile({21, 1, 13, 0.5, 8, 1, 3}, p)) << p;
  EXPECT_EQ(median({21, 1, 13, 0.5, 8, 1, 3}), 3.0);  // the 4th of 7
}

TEST(Percentile, RankNamesTheOrderStatisticsAndTheFraction) {
  constexpr PercentileRank r = percentile_rank(90, 5);  // r = 3.6
  static_assert(r.lo == 3 && r.hi == 4);
  EXPECT_NEAR(r.frac, 0.6, kTol);
  constexpr PercentileRank top = percentile_rank(100, 5);  // r = 4: no sample above the last
  static_assert(top.lo == 4 && top.hi == 4 && top.frac == 0.0);
  constexpr PercentileRank one = percentile_rank(73, 1);
  static_assert(one.lo == 0 && one.hi == 0 && one.frac == 0.0);
}

}  // namespace
}  // namespace hapticd::stats
