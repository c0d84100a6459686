#include "clients/sim/child_process.hpp"

#include <fcntl.h>
#include <signal.h>
#include <spawn.h>
#include <sys/wait.h>
#include <unistd.h>

#include <cerrno>
#include <cstdio>
#include <cstring>
#include <stdexcept>
#include <utility>

extern char** environ;

namespace hapticd::sim {

ChildProcess::ChildProcess(const std::string& path, const std::vector<std::string>& args, std::string echo_prefix)
    : name_(path), echo_prefix_(std::move(echo_prefix)) {
  if (::access(path.c_str(), X_OK) != 0) throw std::runtime_error("cannot run " + path + ": " + std::strerror(errno));
  int fds[2];
  // O_CLOEXEC: only the dup2'ed copies reach the child, so EOF comes when the child ends.
  if (::pipe2(fds, O_CLOEXEC) != 0) throw std::runtime_error(std::string("pipe: ") + std::strerror(errno));
  posix_spawn_file_actions_t actions;
  posix_spawn_file_actions_init(&actions);
  posix_spawn_file_actions_adddup2(&actions, fds[1], STDOUT_FILENO);
  posix_spawn_file_actions_adddup2(&actions, fds[1], STDERR_FILENO);
  std::vector<std::string> argv_storage;
  argv_storage.push_back(path);
  argv_storage.insert(argv_storage.end(), args.begin(), args.end());
  std::vector<char*> argv;
  for (std::string& a : argv_storage) argv.push_back(a.data());
  argv.push_back(nullptr);
  const int err = ::posix_spawn(&pid_, path.c_str(), &actions, nullptr, argv.data(), environ);
  posix_spawn_file_actions_destroy(&actions);
  ::close(fds[1]);
  if (err != 0) {
    ::close(fds[0]);
    throw std::runtime_error("cannot start " + path + ": " + std::strerror(err));
  }
  reader_ = std::thread([this, fd = fds[0]] { read_output(fd); });
}

ChildProcess::~ChildProcess() {
  if (!status_) stop(std::chrono::seconds(2));
  if (reader_.joinable()) reader_.join();
}

void ChildProcess::read_output(int fd) {
  std::string partial;
  char buffer[4096];
  const auto add_line = [this](std::string line) {
    if (!echo_prefix_.empty()) std::fprintf(stderr, "%s%s\n", echo_prefix_.c_str(), line.c_str());
    const std::lock_guard lock(mutex_);
    lines_.push_back(std::move(line));
    if (lines_.size() > kMaxLines) {
      lines_.pop_front();
      ++lines_dropped_;
    }
    changed_.notify_all();
  };
  for (;;) {
    const ssize_t n = ::read(fd, buffer, sizeof buffer);
    if (n < 0 && errno == EINTR) continue;
    if (n <= 0) break;
    partial.append(buffer, static_cast<std::size_t>(n));
    for (std::size_t newline; (newline = partial.find('\n')) != std::string::npos;) {
      add_line(partial.substr(0, newline));
      partial.erase(0, newline + 1);
    }
  }
  if (!partial.empty()) add_line(partial);
  ::close(fd);
  const std::lock_guard lock(mutex_);
  output_closed_ = true;
  changed_.notify_all();
}

std::string ChildProcess::wait_for_line(const std::regex& pattern, std::chrono::milliseconds timeout) {
  const auto deadline = std::chrono::steady_clock::now() + timeout;
  std::unique_lock lock(mutex_);
  std::size_t checked = 0;
  for (;;) {
    for (; checked < lines_.size(); ++checked)
      if (std::regex_search(lines_[checked], pattern)) return lines_[checked];
    if (output_closed_) {
      lock.unlock();
      const std::optional<int> status = wait(std::chrono::seconds(1));
      throw std::runtime_error(name_ + " ended (status " + (status ? std::to_string(*status) : "unknown") +
                               ") before printing the expected line; its output:\n" + output());
    }
    if (changed_.wait_until(lock, deadline) == std::cv_status::timeout) {
      lock.unlock();
      throw std::runtime_error(name_ + " did not print the expected line within " + std::to_string(timeout.count()) +
                               " ms; its output:\n" + output());
    }
  }
}

std::optional<int> ChildProcess::wait(std::chrono::milliseconds timeout) {
  if (status_) return status_;
  const auto deadline = std::chrono::steady_clock::now() + timeout;
  for (;;) {
    int status = 0;
    const pid_t done = ::waitpid(pid_, &status, WNOHANG);
    if (done == pid_ || (done < 0 && errno != EINTR)) {
      status_ = done < 0 ? -1 : WIFEXITED(status) ? WEXITSTATUS(status) : 128 + WTERMSIG(status);
      if (reader_.joinable()) reader_.join();  // the output is complete once the child ended
      return status_;
    }
    if (std::chrono::steady_clock::now() >= deadline) return std::nullopt;
    std::this_thread::sleep_for(std::chrono::milliseconds(5));
  }
}

int ChildProcess::stop(std::chrono::milliseconds grace) {
  if (status_) return *status_;
  ::kill(pid_, SIGTERM);
  if (const std::optional<int> status = wait(grace)) return *status;
  ::kill(pid_, SIGKILL);
  return wait(std::chrono::seconds(10)).value_or(-1);
}

std::string ChildProcess::output() const {
  const std::lock_guard lock(mutex_);
  std::string all;
  if (lines_dropped_ > 0) all = "[" + std::to_string(lines_dropped_) + " earlier lines dropped]\n";
  for (const std::string& line : lines_) all += line + "\n";
  return all;
}

const std::regex& listening_line_pattern() {
  static const std::regex pattern(R"(listening on (\[[0-9A-Fa-f:.%a-z]+\]|[^\s:\[\]]+):(\d+))");
  return pattern;
}

ListenAddress parse_listening_line(const std::string& line) {
  std::smatch m;
  if (!std::regex_search(line, m, listening_line_pattern()))
    throw std::invalid_argument("no 'listening on HOST:PORT' in: " + line);
  ListenAddress a;
  a.host = m[1].str();
  if (a.host.front() == '[') a.host = a.host.substr(1, a.host.size() - 2);
  const unsigned long port = std::stoul(m[2].str());
  if (port == 0 || port > 65535) throw std::invalid_argument("bad port in: " + line);
  a.port = static_cast<std::uint16_t>(port);
  return a;
}

}  // namespace hapticd::sim
