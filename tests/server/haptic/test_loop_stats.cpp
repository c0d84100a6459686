// MicrosecondHistogram's percentile against the one percentile (protocol/percentile.hpp) of the same
// samples: the same definition, each order statistic read as its 1 us bin's upper edge, so at least
// the exact value and at most one bin above it.
#include <gtest/gtest.h>

#include <memory>
#include <random>
#include <vector>

#include "protocol/percentile.hpp"
#include "server/haptic/loop_stats.hpp"

namespace hapticd::haptic {
namespace {

constexpr double kPercents[] = {0, 1, 10, 25, 50, 75, 90, 99, 99.9, 100};

void expect_within_one_bin(const std::vector<double>& samples) {
  auto h = std::make_unique<MicrosecondHistogram>();  // 200 kB: not on the stack
  for (double us : samples) h->add(us);
  for (double p : kPercents) {
    const double exact = stats::percentile(samples, p);
    // 1e-9: the interpolation of the bin edges rounds differently from that of the samples.
    EXPECT_GE(h->percentile(p), exact - 1e-9) << "p" << p;
    EXPECT_LE(h->percentile(p), exact + 1.0) << "p" << p;
  }
}

TEST(MicrosecondHistogram, PercentilesByHandOnHalfMicrosecondSamples) {
  // {1.5, ..., 5.5}: bins 1..5, read as 2, 3, 4, 5 and 5.5 (the maximum caps the last).
  auto h = std::make_unique<MicrosecondHistogram>();
  for (double us : {4.5, 1.5, 3.5, 5.5, 2.5}) h->add(us);
  EXPECT_DOUBLE_EQ(h->percentile(0), 2.0);    // exact 1.5
  EXPECT_DOUBLE_EQ(h->percentile(50), 4.0);   // exact 3.5
  EXPECT_DOUBLE_EQ(h->percentile(90), 5.3);   // r = 3.6: 5 + 0.6 (5.5 - 5); exact 5.1
  EXPECT_DOUBLE_EQ(h->percentile(100), 5.5);  // exact 5.5
}

TEST(MicrosecondHistogram, EmptyIsZero) {
  auto h = std::make_unique<MicrosecondHistogram>();
  EXPECT_EQ(h->percentile(50), 0.0);
}

TEST(MicrosecondHistogram, AgreesWithThePercentileWithinOneBin) {
  expect_within_one_bin({1, 2, 3, 4, 5});              // on the bin edges
  expect_within_one_bin({42.25});                      // a single sample
  expect_within_one_bin({9.9, 0.2, 3.7, 3.9, 7.1, 7.1, 7.1, 1000.25});  // unsorted, ties, one far out
  // Tick-like timings: a lognormal body around 20 us with a tail into milliseconds.
  std::mt19937 rng(7);
  std::lognormal_distribution<double> tick(3.0, 0.8);
  std::vector<double> ticks(20000);
  for (double& us : ticks) us = tick(rng);
  expect_within_one_bin(ticks);
}

}  // namespace
}  // namespace hapticd::haptic
