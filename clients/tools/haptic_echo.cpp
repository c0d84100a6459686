// haptic-echo: the raw UDP baseline for the latency bench. It answers like a server that computes
// nothing: a Hello with a Welcome, each PoseSample with a zero ForceSample of the same frames
// (echoed sequence and client timestamp), a StatsRequest with its counters, a Heartbeat with an
// echo. Same socket set-up as hapticd (one UDP socket, default SO_RCVBUF/SO_SNDBUF, blocking
// recvfrom on a dedicated thread), so a device's round trip against it is the network and the
// codec (~0.2 us, protocol/README.md) and nothing else: hapticd's round trip divided by this one is
// what the server costs.

#include <signal.h>
#include <sys/socket.h>
#include <unistd.h>

#include <CLI/CLI.hpp>
#include <atomic>
#include <boost/asio/io_context.hpp>
#include <boost/asio/ip/udp.hpp>
#include <cerrno>
#include <cstdio>
#include <cstring>
#include <string>
#include <spdlog/sinks/stdout_sinks.h>
#include <spdlog/spdlog.h>
#include <thread>

#include "protocol/clock.hpp"
#include "protocol/codec.hpp"

namespace {

using namespace hapticd::protocol;

struct EchoCounters {
  std::atomic<std::uint64_t> packets_in{0};
  std::atomic<std::uint64_t> packets_out{0};
  std::atomic<std::uint64_t> dropped{0};
};

// The receive thread: everything it touches after start is preallocated.
void serve(int fd, const std::atomic<bool>& stopping, EchoCounters& counters) {
  Encoder encoder;
  ReceiveBuffer rx;
  Message in;
  ForceSample force;
  Welcome welcome;
  Stats stats;
  std::uint64_t next_session = 1;
  for (;;) {
    sockaddr_storage from{};
    socklen_t from_length = sizeof from;
    const ssize_t n =
        ::recvfrom(fd, rx.bytes.data(), rx.bytes.size(), 0, reinterpret_cast<sockaddr*>(&from), &from_length);
    const std::uint64_t received_ns = now_ns();
    if (stopping.load(std::memory_order_relaxed)) return;
    if (n < 0) {
      if (errno == EINTR) continue;
      spdlog::error("recvfrom: {}", std::strerror(errno));  // the receive loop ends: not on its hot path
      return;
    }
    counters.packets_in.fetch_add(1, std::memory_order_relaxed);
    const DecodeResult r = decode({rx.bytes.data(), static_cast<std::size_t>(n)}, in);
    EncodeResult out;
    if (!r.ok()) {
      if (error_reply_allowed(r)) {
        Error e;
        e.code = error_code_for(r.reason);
        e.message.assign(to_string(r.reason));
        out = encoder.encode(e);
      }
    } else if (r.type == MessageType::kPoseSample) {
      force.session_id = in.pose_sample.session_id;
      force.sequence = in.pose_sample.sequence;
      force.client_timestamp_ns = in.pose_sample.client_timestamp_ns;
      force.server_receive_ns = received_ns;
      force.wrenches.resize(in.pose_sample.poses.size());
      for (std::size_t i = 0; i < force.wrenches.size(); ++i)
        force.wrenches[i] = {in.pose_sample.poses[i].frame, 0, {}};
      force.server_send_ns = now_ns();
      out = encoder.encode(force);
    } else if (r.type == MessageType::kHello) {
      welcome.session_id = next_session++;
      welcome.rate_hz = in.hello.requested_rate_hz;
      welcome.force_limit_n = 10.0f;
      welcome.torque_limit_nm = 0.0f;
      welcome.max_force_rate_n_per_s = 1000.0f;
      welcome.frame_map.clear();
      for (const TrackedFrame& f : in.hello.frames) welcome.frame_map.push_back({f.id, kNoHandle});
      out = encoder.encode(welcome);
    } else if (r.type == MessageType::kHeartbeat) {
      Heartbeat h;
      h.session_id = in.heartbeat.session_id;
      h.timestamp_ns = now_ns();
      h.echo_timestamp_ns = in.heartbeat.timestamp_ns;
      out = encoder.encode(h);
    } else if (r.type == MessageType::kStatsRequest) {
      stats.session_id = in.stats_request.session_id;
      stats.packets_in = counters.packets_in.load(std::memory_order_relaxed);
      stats.packets_out = counters.packets_out.load(std::memory_order_relaxed);
      stats.packets_dropped = counters.dropped.load(std::memory_order_relaxed);
      stats.sessions_active = static_cast<std::uint32_t>(next_session - 1);
      out = encoder.encode(stats);
    } else if (r.type == MessageType::kBye) {
      continue;  // nothing to answer, nothing to forget: the echo keeps no sessions
    }
    if (out.bytes.empty()) {
      counters.dropped.fetch_add(1, std::memory_order_relaxed);
      continue;
    }
    if (::sendto(fd, out.bytes.data(), out.bytes.size(), 0, reinterpret_cast<const sockaddr*>(&from), from_length) >= 0)
      counters.packets_out.fetch_add(1, std::memory_order_relaxed);
  }
}

}  // namespace

int main(int argc, char** argv) {
  // Diagnostics through spdlog to stderr as "haptic-echo: <text>"; stdout keeps what scripts read.
  spdlog::set_default_logger(spdlog::stderr_logger_mt("haptic-echo"));
  spdlog::set_pattern("%n: %v");
  CLI::App app{"haptic-echo: raw UDP echo baseline for hapticd's latency (answers poses with zero forces)"};
  std::string bind_address = "127.0.0.1";
  int port = 0;
  double duration_s = 0.0;
  app.add_option("--bind", bind_address, "local address to bind (numeric IPv4 or IPv6)")->capture_default_str();
  app.add_option("--port", port, "UDP port; 0 picks a free one (printed)")
      ->check(CLI::Range(0, 65535))
      ->capture_default_str();
  app.add_option("--duration", duration_s, "exit after this many seconds; 0: run until SIGINT/SIGTERM")
      ->check(CLI::Range(0.0, 1e7))
      ->capture_default_str();
  CLI11_PARSE(app, argc, argv);

  namespace asio = boost::asio;
  asio::io_context io;
  boost::system::error_code ec;
  const asio::ip::address address = asio::ip::make_address(bind_address, ec);
  if (ec) {
    spdlog::error("--bind '{}' is not a numeric IPv4 or IPv6 address", bind_address);
    return 2;
  }
  asio::ip::udp::socket socket(io);
  const asio::ip::udp::endpoint endpoint(address, static_cast<unsigned short>(port));
  socket.open(endpoint.protocol(), ec);
  if (!ec) socket.bind(endpoint, ec);
  if (ec) {
    spdlog::error("cannot bind {} port {}: {}", bind_address, port, ec.message());
    return 1;
  }
  const unsigned short bound_port = socket.local_endpoint().port();
  const int fd = socket.release();

  // Signals are taken by sigtimedwait below, in this thread only: block them before the receive
  // thread starts so it inherits the mask.
  sigset_t signals;
  sigemptyset(&signals);
  sigaddset(&signals, SIGINT);
  sigaddset(&signals, SIGTERM);
  pthread_sigmask(SIG_BLOCK, &signals, nullptr);

  std::atomic<bool> stopping{false};
  EchoCounters counters;
  std::thread receiver(serve, fd, std::cref(stopping), std::ref(counters));

  const std::string shown = address.is_v6() ? "[" + bind_address + "]" : bind_address;
  std::printf("haptic-echo listening on %s:%u\n", shown.c_str(), static_cast<unsigned>(bound_port));
  std::fflush(stdout);

  if (duration_s > 0.0) {
    const auto whole = static_cast<time_t>(duration_s);
    const timespec limit{whole, static_cast<long>((duration_s - static_cast<double>(whole)) * 1e9)};
    while (sigtimedwait(&signals, nullptr, &limit) < 0 && errno == EINTR) {
    }
  } else {
    int signal_number = 0;
    sigwait(&signals, &signal_number);
  }
  stopping.store(true);
  // On Linux, shutdown() wakes a recvfrom() blocked on a UDP socket (it returns 0).
  ::shutdown(fd, SHUT_RDWR);
  receiver.join();
  ::close(fd);
  spdlog::info("{} datagrams in, {} out, {} dropped", counters.packets_in.load(), counters.packets_out.load(),
               counters.dropped.load());
  return 0;
}
