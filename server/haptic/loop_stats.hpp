#pragma once
// Allocation-free timing statistics for the loops: a histogram of 1 us bins up
// to 50 ms (beyond: the last bin), so the haptic thread can record every tick
// and percentiles come out without storing samples.
#include <algorithm>
#include <array>
#include <cstdint>

#include "protocol/percentile.hpp"

namespace hapticd::haptic {

class MicrosecondHistogram {
 public:
  static constexpr int kBins = 50000;
  void add(double us) {
    const int bin = std::clamp(static_cast<int>(us), 0, kBins - 1);
    ++bins_[bin];
    ++count_;
    max_us_ = std::max(max_us_, us);
  }
  // The p-th percentile (0..100), us, by the one definition (protocol/percentile.hpp: linear
  // interpolation between order statistics), each order statistic read as its bin's upper edge (at
  // most max_us()): for samples in [0, 50 ms) it is at least stats::percentile of the samples added
  // and at most one bin (1 us) above it. 0 when empty. No allocation: the haptic thread calls it.
  double percentile(double p) const {
    if (count_ == 0) return 0;
    const stats::PercentileRank k = stats::percentile_rank(p, count_);
    double x_lo = max_us_, x_hi = max_us_;
    bool have_lo = false;
    std::uint64_t seen = 0;
    for (int b = 0; b < kBins; ++b) {
      if (bins_[b] == 0) continue;
      seen += bins_[b];
      const double upper_edge = std::min(static_cast<double>(b + 1), max_us_);
      if (!have_lo && seen > k.lo) {
        x_lo = upper_edge;
        have_lo = true;
      }
      if (seen > k.hi) {
        x_hi = upper_edge;
        break;
      }
    }
    return x_lo + k.frac * (x_hi - x_lo);
  }
  std::uint64_t count() const { return count_; }
  double max_us() const { return max_us_; }

 private:
  std::array<std::uint32_t, kBins> bins_{};
  std::uint64_t count_ = 0;
  double max_us_ = 0;
};

}  // namespace hapticd::haptic
