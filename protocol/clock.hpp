#pragma once

// The one clock of the wire: every *_ns timestamp is read from here by its sender. CLOCK_MONOTONIC
// never jumps with NTP or the wall clock, so differences on one machine are true durations;
// across machines only round trips (echoed timestamps) are meaningful.

#include <time.h>

#include <cstdint>

namespace hapticd::protocol {

inline std::uint64_t now_ns() noexcept {
  timespec t{};
  ::clock_gettime(CLOCK_MONOTONIC, &t);  // vDSO: no system call, no allocation, no lock
  return static_cast<std::uint64_t>(t.tv_sec) * 1'000'000'000ull + static_cast<std::uint64_t>(t.tv_nsec);
}

}  // namespace hapticd::protocol
