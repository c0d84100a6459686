#pragma once
#include <CLI/CLI.hpp>

namespace hapticd::bench {
// `haptic-bench haptic_rate`: the haptic loop at 1, 2 and 4 kHz: its tick cost, and the stiffest
// virtual coupling that renders a stylus press into a wall without putting energy into a modelled
// Phantom-class device (offline mode).
void add_haptic_rate_suite(CLI::App& app);
}  // namespace hapticd::bench
