// hapticd's authentication flags as a user meets them: --generate-key writes a private key once and
// says its fingerprint, --key-file refuses a bad file with its fault, a non-loopback --bind without a
// key is refused before anything is loaded, and a keyed hapticd says it authenticates.
#include <gtest/gtest.h>
#include <sys/stat.h>
#include <unistd.h>

#include <chrono>
#include <filesystem>
#include <fstream>
#include <string>

#include "clients/sim/child_process.hpp"

namespace hapticd::haptic {
namespace {

using namespace std::chrono_literals;

const std::string kHapticd = std::string(HAPTICD_BIN_DIR) + "/hapticd";

std::string scratch(const std::string& name) {
  return ::testing::TempDir() + "hapticd_cli_" + std::to_string(::getpid()) + "_" + name;
}

// Runs hapticd to its end: exit status and output.
std::pair<int, std::string> run(const std::vector<std::string>& args) {
  sim::ChildProcess p(kHapticd, args);
  const auto status = p.wait(60s);
  EXPECT_TRUE(status.has_value());
  return {status.value_or(-1), p.output()};
}

TEST(HapticdCli, GenerateKeyWritesAPrivateKeyOnceAndNamesItsFingerprint) {
  const std::string key = scratch("key");
  std::filesystem::remove(key);
  const auto [status, out] = run({"--generate-key", key});
  EXPECT_EQ(status, 0) << out;
  EXPECT_NE(out.find("wrote a new key to " + key + " (fingerprint "), std::string::npos) << out;
  struct stat st {};
  ASSERT_EQ(::stat(key.c_str(), &st), 0);
  EXPECT_EQ(st.st_mode & 0777, 0600u);
  const auto [again, refused] = run({"--generate-key", key});
  EXPECT_EQ(again, 1);
  EXPECT_NE(refused.find("exists; not overwritten"), std::string::npos) << refused;
  // Served with it: the log names the same fingerprint. On the boxes scene, which builds in a second
  // under the sanitizers (the default bunny's distance grid takes 48 s there).
  const std::string fingerprint = out.substr(out.find("(fingerprint ") + 13, 8);
  sim::ChildProcess server(kHapticd, {"--key-file", key, "--port", "0", "--duration", "30", "--scene",
                                      std::string(HAPTICD_SCENES_DIR) + "/blocks.json"});
  server.wait_for_line(sim::listening_line_pattern(), 60s);
  server.wait_for_line(std::regex("sessions authenticated with the key of .*\\(fingerprint " + fingerprint + "\\)"),
                       10s);
  EXPECT_EQ(server.stop(), 0);
  std::filesystem::remove(key);
}

TEST(HapticdCli, BadKeyFilesAndAnUnprotectedBindAreRefusedWithTheReason) {
  const std::string open_key = scratch("open_key");
  std::ofstream(open_key) << std::string(64, 'a') << "\n";
  ::chmod(open_key.c_str(), 0644);
  const std::string short_key = scratch("short_key");
  std::ofstream(short_key) << "abcd\n";
  ::chmod(short_key.c_str(), 0600);
  const struct {
    std::vector<std::string> args;
    std::string expected;
  } cases[] = {
      {{"--key-file", scratch("missing")}, "cannot open the key file (No such file or directory)"},
      {{"--key-file", open_key}, "permissions 0644 let other users read or change the key; run chmod 600"},
      {{"--key-file", short_key}, "4 hexadecimal digits, expected 64"},
      {{"--bind", "0.0.0.0"}, "refusing to listen on 0.0.0.0 without a key"},
      {{"--bind", "192.0.2.1", "--insecure-bind"}, "cannot bind 192.0.2.1"},
  };
  for (const auto& c : cases) {
    const auto [status, out] = run(c.args);
    EXPECT_EQ(status, 1) << c.args.back();
    EXPECT_NE(out.find(c.expected), std::string::npos) << c.args.back() << ":\n" << out;
  }
  std::filesystem::remove(open_key);
  std::filesystem::remove(short_key);
}

TEST(HapticdCli, ATickContactSweepsOutOfItsRangeIsRefused) {
  for (const char* value : {"0", "10001", "eight"}) {
    const auto [status, out] = run({"--tick-contact-sweeps", value});
    EXPECT_NE(status, 0) << value;
    EXPECT_NE(out.find("--tick-contact-sweeps"), std::string::npos) << value << ":\n" << out;
  }
}

}  // namespace
}  // namespace hapticd::haptic
