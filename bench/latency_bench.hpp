#pragma once
#include <CLI/CLI.hpp>

namespace hapticd::bench {
// `haptic-bench latency`: device round trips against haptic-echo (the raw UDP baseline) and
// against hapticd, same paced servo loop, same run; the server's figures as ratios to the echo's.
void add_latency_suite(CLI::App& app);
}  // namespace hapticd::bench
