#pragma once
#include <CLI/CLI.hpp>

namespace hapticd::bench {
// `haptic-bench hand`: the hand pressed into a floor, one solver, timed per phase.
void add_hand_suite(CLI::App& app);
}  // namespace hapticd::bench
