#pragma once
#include <CLI/CLI.hpp>

namespace hapticd::bench {
// `haptic-bench soak`: hapticd driven for minutes by N simulated styluses through the chaos relay,
// authenticated; per window its memory, overruns, resets, dropped and rejected packets and the
// round-trip percentiles (issue 7, "Soak").
void add_soak_suite(CLI::App& app);
}  // namespace hapticd::bench
