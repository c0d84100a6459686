#pragma once

// The one definition of a percentile in hapticd: the Stats message's p50 / p99 fields, hapticd's
// --stats histograms, the clients' round-trip summaries and every haptic-bench figure use it.
//
// Definition (linear interpolation between order statistics; Hyndman and Fan's type 7, NumPy's
// default "linear", Excel's PERCENTILE.INC): for n samples sorted ascending x_0 <= ... <= x_{n-1}
// and p in [0, 100], the rank is r = p / 100 * (n - 1) and the p-th percentile is
//   x_lo + (r - lo) (x_hi - x_lo),   lo = floor(r), hi = min(lo + 1, n - 1).
// So p0 is the minimum, p100 the maximum, p50 the usual median (the mean of the two middle samples
// of an even count). p outside [0, 100] is clamped into it (NaN to 0); an empty sample has no percentile (NaN).
//
// Header-only and allocation-free except percentile(), which sorts a copy: the haptic thread may call
// percentile_rank() (MicrosecondHistogram does).

#include <algorithm>
#include <cmath>
#include <cstddef>
#include <limits>
#include <span>
#include <utility>
#include <vector>

namespace hapticd::stats {

// Where the p-th percentile of n >= 1 sorted samples falls: between the 0-based order statistics
// lo and hi, a fraction `frac` of the way from lo to hi.
struct PercentileRank {
  std::size_t lo = 0, hi = 0;
  double frac = 0.0;
};

constexpr PercentileRank percentile_rank(double p, std::size_t n) noexcept {
  if (n == 0) return {};
  const double q = p > 0.0 ? std::min(p, 100.0) : 0.0;  // a NaN p reads as 0, never as an index
  const double r = q / 100.0 * static_cast<double>(n - 1);
  const auto lo = std::min(static_cast<std::size_t>(r), n - 1);  // r >= 0: truncation is floor
  return {lo, std::min(lo + 1, n - 1), r - static_cast<double>(lo)};
}

// The p-th percentile (p in [0, 100]) of an ascending sample; NaN for an empty one.
inline double percentile_of_sorted(std::span<const double> sorted, double p) noexcept {
  if (sorted.empty()) return std::numeric_limits<double>::quiet_NaN();
  const PercentileRank k = percentile_rank(p, sorted.size());
  return sorted[k.lo] + k.frac * (sorted[k.hi] - sorted[k.lo]);
}

// The p-th percentile (p in [0, 100]) of a sample in any order (sorts its copy); NaN for an empty one.
inline double percentile(std::vector<double> values, double p) {
  std::sort(values.begin(), values.end());
  return percentile_of_sorted(values, p);
}

// The median: percentile(values, 50).
inline double median(std::vector<double> values) { return percentile(std::move(values), 50.0); }

}  // namespace hapticd::stats
