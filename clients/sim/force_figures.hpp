#pragma once

// Running statistics of a force magnitude sampled once per servo tick: the largest and the RMS.
#include <algorithm>
#include <cmath>
#include <cstdint>

namespace hapticd::sim {

struct ForceFigures {
  double max_n = 0.0;
  double sq_sum = 0.0;
  void add(double f_n) noexcept {
    max_n = std::max(max_n, f_n);
    sq_sum += f_n * f_n;
  }
  // RMS over `ticks` samples (0 without any).
  [[nodiscard]] double rms_n(std::uint64_t ticks) const noexcept {
    return ticks == 0 ? 0.0 : std::sqrt(sq_sum / static_cast<double>(ticks));
  }
};

}  // namespace hapticd::sim
