#pragma once

// A child process whose stdout and stderr are read line by line on a thread of their own, so the
// child never blocks on a full pipe. haptic-bench starts haptic-echo and hapticd with it; the
// tests start haptic-echo and haptic-device.

#include <sys/types.h>

#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <deque>
#include <mutex>
#include <optional>
#include <regex>
#include <string>
#include <thread>
#include <vector>

namespace hapticd::sim {

class ChildProcess {
 public:
  // Starts `path` with `args` as argv[1..]. Lines it prints are kept (the last kMaxLines) and, with
  // a non-empty `echo_prefix`, copied to this process's stderr behind that prefix. Throws
  // std::runtime_error when it cannot start.
  ChildProcess(const std::string& path, const std::vector<std::string>& args, std::string echo_prefix = {});
  ~ChildProcess();  // stop() if still running
  ChildProcess(const ChildProcess&) = delete;
  ChildProcess& operator=(const ChildProcess&) = delete;

  // The first output line matching `pattern` (regex_search), waiting at most `timeout`. Throws
  // std::runtime_error with the output so far when the child ends first or time runs out.
  std::string wait_for_line(const std::regex& pattern, std::chrono::milliseconds timeout);
  // Exit status once the child ended within `timeout` (128 + signal when a signal ended it).
  std::optional<int> wait(std::chrono::milliseconds timeout);
  // SIGTERM, then SIGKILL after `grace`; the exit status.
  int stop(std::chrono::milliseconds grace = std::chrono::seconds(5));
  // Every line kept so far, joined by '\n'; complete once the child ended.
  [[nodiscard]] std::string output() const;
  [[nodiscard]] pid_t pid() const noexcept { return pid_; }

  static constexpr std::size_t kMaxLines = 2000;

 private:
  void read_output(int fd);

  std::string name_;
  std::string echo_prefix_;
  pid_t pid_ = -1;
  std::optional<int> status_;
  mutable std::mutex mutex_;
  std::condition_variable changed_;
  std::deque<std::string> lines_;
  std::size_t lines_dropped_ = 0;
  bool output_closed_ = false;
  std::thread reader_;
};

// Host and port of a "... listening on HOST:PORT" line (HOST may be a bracketed IPv6 address).
struct ListenAddress {
  std::string host;
  std::uint16_t port = 0;
};
// The pattern wait_for_line() needs to find such a line.
const std::regex& listening_line_pattern();
// Throws std::invalid_argument when `line` holds no such address.
ListenAddress parse_listening_line(const std::string& line);

}  // namespace hapticd::sim
