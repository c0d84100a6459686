#pragma once
#include <CLI/CLI.hpp>

namespace hapticd::bench {
// `haptic-bench hands`: every hand model (seed 004's FEM hand, seed 002's spring hand, seed 001's
// contact-point hand) on the same scripted interactions, closed loop through the lockstep runner:
// step and tick cost, penetration, energy into the device, the force after the release, the box's
// lift, and the force error against the same model's world stepped at every haptic tick (issue 18).
void add_hands_suite(CLI::App& app);
}  // namespace hapticd::bench
