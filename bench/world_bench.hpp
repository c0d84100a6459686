#pragma once
#include <CLI/CLI.hpp>

namespace hapticd::bench {
// `haptic-bench world`: a scene's world stepped under a scripted press and stroke.
void add_world_suite(CLI::App& app);
}  // namespace hapticd::bench
