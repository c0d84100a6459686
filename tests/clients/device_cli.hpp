#pragma once
// Shared by the haptic-device end-to-end tests: scratch file paths and the
// check that bad command lines are refused, each with its reason.
#include <gtest/gtest.h>
#include <unistd.h>

#include <chrono>
#include <string>
#include <vector>

#include "clients/sim/child_process.hpp"

namespace hapticd::sim::testing_util {

// A scratch file name unique to this test process.
inline std::string temp_path(const std::string& prefix, const std::string& name) {
  return ::testing::TempDir() + prefix + std::to_string(::getpid()) + "_" + name;
}

struct RefusedCase {
  std::vector<std::string> args;
  std::string expected;  // in the output
};

// Runs `binary` with each case's arguments: it must exit non-zero and say `expected`.
inline void expect_refused(const char* binary, const std::vector<RefusedCase>& cases) {
  using namespace std::chrono_literals;
  for (const RefusedCase& c : cases) {
    ChildProcess process(binary, c.args);
    const std::optional<int> status = process.wait(10s);
    ASSERT_TRUE(status.has_value());
    EXPECT_NE(*status, 0) << c.args.back();
    EXPECT_NE(process.output().find(c.expected), std::string::npos) << c.args.back() << ":\n" << process.output();
  }
}

}  // namespace hapticd::sim::testing_util
