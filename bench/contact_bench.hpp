#pragma once
#include <CLI/CLI.hpp>

namespace hapticd::bench {
// `haptic-bench contact`: constraint vs penalty hand contact on a stylus press into a static box,
// at several visual rates: visual step time, skin penetration, force error against constraint
// contact stepped at every haptic tick (offline mode).
void add_contact_suite(CLI::App& app);
}  // namespace hapticd::bench
