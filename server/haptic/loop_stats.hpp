#pragma once
// Allocation-free timing statistics for the loops: a histogram of 1 us bins up
// to 50 ms (beyond: the last bin), so the haptic thread can record every tick
// and percentiles come out without storing samples.
#include <algorithm>
#include <array>
#include <cstdint>

namespace hapticd {

class MicrosecondHistogram {
 public:
  static constexpr int kBins = 50000;
  void add(double us) {
    const int bin = std::clamp(static_cast<int>(us), 0, kBins - 1);
    ++bins_[bin];
    ++count_;
    max_us_ = std::max(max_us_, us);
  }
  // The p-th percentile (0..100), us, to the bin's upper edge; 0 when empty.
  double percentile(double p) const {
    if (count_ == 0) return 0;
    const auto rank = static_cast<std::uint64_t>(std::max(1.0, p / 100.0 * static_cast<double>(count_) + 0.5));
    std::uint64_t seen = 0;
    for (int b = 0; b < kBins; ++b) {
      seen += bins_[b];
      if (seen >= rank) return std::min(static_cast<double>(b + 1), max_us_);
    }
    return max_us_;
  }
  std::uint64_t count() const { return count_; }
  double max_us() const { return max_us_; }

 private:
  std::array<std::uint32_t, kBins> bins_{};
  std::uint64_t count_ = 0;
  double max_us_ = 0;
};

}  // namespace hapticd
