// haptic-chaos: a UDP relay between devices and hapticd that loses, duplicates, reorders, delays
// and corrupts datagrams in both directions at configured rates, for tests and benches
// (clients/chaos/chaos_relay.hpp). Prints its listening address, relays until SIGINT / SIGTERM or
// --duration, then prints its counts as JSON (and writes them to --counts FILE).

#include <CLI/CLI.hpp>
#include <atomic>
#include <chrono>
#include <csignal>
#include <cstdio>
#include <fstream>
#include <spdlog/sinks/stdout_sinks.h>
#include <spdlog/spdlog.h>
#include <string>
#include <thread>

#include "clients/chaos/chaos_relay.hpp"

namespace {

std::atomic<bool> g_stop{false};
void request_stop(int) { g_stop.store(true); }

}  // namespace

int main(int argc, char** argv) {
  // Diagnostics through spdlog to stderr as "haptic-chaos: <text>"; stdout keeps what scripts read.
  spdlog::set_default_logger(spdlog::stderr_logger_mt("haptic-chaos"));
  spdlog::set_pattern("%n: %v");
  using namespace hapticd;
  CLI::App app{"haptic-chaos: a UDP relay that damages traffic between devices and hapticd (both directions)"};
  chaos::ChaosConfig config;
  unsigned listen_port = 0;
  std::string bind = "127.0.0.1", forward, counts_path;
  double duration_s = 0;
  app.add_option("--listen", listen_port, "UDP port the devices send to; 0 picks one and prints it")
      ->check(CLI::Range(0u, 65535u))
      ->capture_default_str();
  app.add_option("--bind", bind, "address to listen on")->capture_default_str();
  app.add_option("--forward", forward, "hapticd's address HOST:PORT")->required();
  app.add_option("--loss", config.loss, "probability a datagram is dropped")->check(CLI::Range(0.0, 1.0));
  app.add_option("--duplicate", config.duplicate, "probability a datagram is sent twice")->check(CLI::Range(0.0, 1.0));
  app.add_option("--reorder", config.reorder, "probability a datagram is overtaken by the next one")
      ->check(CLI::Range(0.0, 1.0));
  app.add_option("--corrupt", config.corrupt, "probability one byte of a datagram is changed")
      ->check(CLI::Range(0.0, 1.0));
  app.add_option("--delay-ms", config.delay_ms, "fixed one-way delay, ms")->check(CLI::Range(0.0, 60000.0));
  app.add_option("--jitter-ms", config.jitter_ms, "extra delay drawn uniformly in [0, J] per datagram, ms")
      ->check(CLI::Range(0.0, 60000.0));
  app.add_option("--reorder-hold-ms", config.reorder_hold_ms,
                 "longest a held-back datagram waits for another to overtake it, ms")
      ->check(CLI::Range(0.0, 60000.0))
      ->capture_default_str();
  app.add_option("--seed", config.seed, "seed of the decisions")->capture_default_str();
  app.add_option("--duration", duration_s, "seconds to run; 0 runs until SIGINT / SIGTERM")
      ->check(CLI::Range(0.0, 1e7));
  app.add_option("--counts", counts_path, "also write the counts JSON to this file on exit");
  CLI11_PARSE(app, argc, argv);

  const auto colon = forward.rfind(':');
  std::string host = colon == std::string::npos ? "" : forward.substr(0, colon);
  const std::string port_text = colon == std::string::npos ? "" : forward.substr(colon + 1);
  if (host.size() > 2 && host.front() == '[' && host.back() == ']') host = host.substr(1, host.size() - 2);
  if (host.empty() || port_text.empty() || port_text.size() > 5 ||
      port_text.find_first_not_of("0123456789") != std::string::npos || std::stoul(port_text) == 0 ||
      std::stoul(port_text) > 65535) {
    spdlog::error("--forward: expected HOST:PORT with PORT in 1..65535, got '{}'", forward);
    return 2;
  }
  try {
    chaos::ChaosRelay relay(config, host, static_cast<std::uint16_t>(std::stoul(port_text)), bind,
                            static_cast<std::uint16_t>(listen_port));
    std::signal(SIGINT, request_stop);
    std::signal(SIGTERM, request_stop);
    std::printf("haptic-chaos listening on %s\n", relay.address().c_str());
    std::fflush(stdout);
    relay.start();
    const auto start = std::chrono::steady_clock::now();
    while (!g_stop.load()) {
      std::this_thread::sleep_for(std::chrono::milliseconds(20));
      if (duration_s > 0 && std::chrono::steady_clock::now() - start >= std::chrono::duration<double>(duration_s))
        break;
    }
    relay.stop();
    const std::string doc = chaos::to_json(relay.counts(), relay.config()).dump(2);
    std::printf("%s\n", doc.c_str());
    if (!counts_path.empty()) {
      std::ofstream out(counts_path);
      out << doc << "\n";
      if (!out.flush()) {
        spdlog::error("--counts: cannot write '{}'", counts_path);
        return 1;
      }
    }
    return 0;
  } catch (const std::exception& e) {
    spdlog::error(e.what());
    return 1;
  }
}
