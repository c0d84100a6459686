#pragma once
// What every haptic-bench suite prints and stores: the machine, percentiles.
#include <filesystem>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "protocol/messages.hpp"
#include "protocol/percentile.hpp"

namespace hapticd::bench {

struct Machine {
  std::string cpu;    // model name from /proc/cpuinfo
  int cores = 0;      // online logical cores
  std::string blas;   // BLAS library mapped into this process
  std::string git_revision;
};
Machine describe_machine();
nlohmann::json to_json(const Machine& m);

// Percentiles by the one definition (protocol/percentile.hpp: linear interpolation between order
// statistics); NaN for an empty sample.
using stats::median;
using stats::percentile;

// Writes `doc` to `path` (pretty-printed); throws std::runtime_error on failure.
void write_json(const std::string& path, const nlohmann::json& doc);

// The directory of the running executable (haptic-bench finds hapticd and haptic-echo there).
std::filesystem::path own_directory();

// The Hello of a simulated stylus: one 6-DoF frame, id 0, named "stylus".
protocol::Hello stylus_hello(const std::string& client_name, unsigned rate_hz);

}  // namespace hapticd::bench
