#pragma once
#include <CLI/CLI.hpp>

namespace hapticd::bench {
// `haptic-bench touch`: contacts that make and break (issue 17): the simulated stylus's press, hold
// and lift on the movable bunny and the simulated glove's grasp, lift and release of the box, at 15,
// 30 and 60 Hz visual rates, the tick's unilateral contacts against the bilateral baseline: energy
// into the device, force after the release, force error against the world stepped every tick,
// penetration, tick cost (offline mode, closed loop).
void add_touch_suite(CLI::App& app);
}  // namespace hapticd::bench
