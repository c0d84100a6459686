#pragma once
// Helpers for tests that read and write files: a fresh temporary folder per
// test, and a check of MeshError messages.
#include <gtest/gtest.h>
#include <unistd.h>

#include <filesystem>
#include <fstream>
#include <functional>
#include <string>

#include "hand_models/tet_mesh.hpp"

namespace hapticd::testing_util {

class TempDirTest : public ::testing::Test {
 protected:
  void SetUp() override {
    // The pid keeps concurrent runs of a test binary (ctest -j, two build dirs) apart.
    dir_ = std::filesystem::path(::testing::TempDir()) /
           ("hapticd_" + std::to_string(::getpid()) + "_" +
            ::testing::UnitTest::GetInstance()->current_test_info()->test_suite_name() + "_" +
            ::testing::UnitTest::GetInstance()->current_test_info()->name());
    std::filesystem::create_directories(dir_);
  }
  void TearDown() override {
    std::error_code ec;
    std::filesystem::remove_all(dir_, ec);
  }
  // Writes `text` to a file of that name in the folder and returns its path.
  std::string write(const std::string& name, const std::string& text) {
    const std::string path = (dir_ / name).string();
    std::ofstream(path, std::ios::binary) << text;
    return path;
  }

  std::filesystem::path dir_;
};

// Passes when load throws a MeshError starting "<path>:<line>: " and containing phrase.
inline ::testing::AssertionResult throws_mesh_error(const std::function<void()>& load, const std::string& path,
                                                    long long line, const std::string& phrase) {
  try {
    load();
  } catch (const hand::MeshError& e) {
    const std::string msg = e.what();
    const std::string prefix = path + ":" + std::to_string(line) + ": ";
    if (msg.rfind(prefix, 0) != 0)
      return ::testing::AssertionFailure() << "message '" << msg << "' lacks prefix '" << prefix << "'";
    if (msg.find(phrase) == std::string::npos)
      return ::testing::AssertionFailure() << "message '" << msg << "' lacks '" << phrase << "'";
    return ::testing::AssertionSuccess();
  }
  return ::testing::AssertionFailure() << "no MeshError thrown";
}

}  // namespace hapticd::testing_util
