// haptic-bench: the project's whole-scenario benchmarks (see README, Performance).
#include <spdlog/sinks/stdout_sinks.h>
#include <spdlog/spdlog.h>

#include <CLI/CLI.hpp>
#include <cstdio>
#include <exception>

#include "contact_bench.hpp"
#include "hand_bench.hpp"
#include "hands_bench.hpp"
#include "haptic_rate_bench.hpp"
#include "latency_bench.hpp"
#include "multirate_bench.hpp"
#include "resolution_bench.hpp"
#include "server/process_heap.hpp"
#include "soak_bench.hpp"
#include "solvers_bench.hpp"
#include "touch_bench.hpp"
#include "world_bench.hpp"

int main(int argc, char** argv) {
  // As hapticd does: the benches measure the visual step the server runs.
  // Diagnostics through spdlog to stderr, each naming its suite ("latency: ..."); stdout keeps the tables.
  spdlog::set_default_logger(spdlog::stderr_logger_mt("haptic-bench"));
  spdlog::set_pattern("%v");
  if (!hapticd::process::keep_large_allocations_on_heap()) spdlog::warn("haptic-bench: heap settings refused");
  CLI::App app{"haptic-bench: hapticd benchmarks; every figure printed with its machine and baseline"};
  app.require_subcommand(1);
  hapticd::bench::add_hand_suite(app);
  hapticd::bench::add_world_suite(app);
  hapticd::bench::add_latency_suite(app);
  hapticd::bench::add_multirate_suite(app);
  hapticd::bench::add_soak_suite(app);
  hapticd::bench::add_contact_suite(app);
  hapticd::bench::add_touch_suite(app);
  hapticd::bench::add_hands_suite(app);
  hapticd::bench::add_haptic_rate_suite(app);
  hapticd::bench::add_solvers_suite(app);
  hapticd::bench::add_resolution_suite(app);
  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    return app.exit(e);
  } catch (const std::exception& e) {
    spdlog::error("haptic-bench: {}", e.what());
    return 1;
  }
  return 0;
}
