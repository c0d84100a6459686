#pragma once
#include <CLI/CLI.hpp>

namespace hapticd::bench {
// `haptic-bench solvers`: step time vs error against the monolithic solve, every solver, several hand sizes.
void add_solvers_suite(CLI::App& app);
}  // namespace hapticd::bench
