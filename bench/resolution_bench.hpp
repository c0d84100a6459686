#pragma once
#include <CLI/CLI.hpp>

namespace hapticd::bench {
// `haptic-bench resolution`: step time vs handle force error against the finest hand, same scripted press.
void add_resolution_suite(CLI::App& app);
}  // namespace hapticd::bench
