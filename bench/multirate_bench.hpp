#pragma once
#include <CLI/CLI.hpp>

namespace hapticd::bench {
// `haptic-bench multirate`: the force error of the linearized handle-space model and of a
// zero-order hold against a visual loop at every haptic tick, across visual rates (offline mode).
void add_multirate_suite(CLI::App& app);
}  // namespace hapticd::bench
