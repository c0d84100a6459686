#pragma once
// A fixture with a fresh temporary folder per test, for tests that write files.
#include <gtest/gtest.h>
#include <unistd.h>

#include <filesystem>
#include <fstream>
#include <string>

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

}  // namespace hapticd::testing_util
