#include "latency_bench.hpp"

#include <unistd.h>

#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <functional>
#include <latch>
#include <memory>
#include <optional>
#include <spdlog/spdlog.h>
#include <stdexcept>
#include <string>
#include <thread>
#include <vector>

#include "bench_common.hpp"
#include "clients/cpp/client.hpp"
#include "clients/sim/child_process.hpp"
#include "clients/sim/glove_servo.hpp"
#include "clients/sim/glove_simulation.hpp"
#include "clients/sim/glove_trajectory.hpp"
#include "clients/sim/servo_loop.hpp"
#include "clients/sim/servo_report.hpp"
#include "clients/sim/trajectory.hpp"

namespace hapticd::bench {
namespace {

using namespace std::chrono_literals;

struct LatencyBenchArgs {
  double seconds = 10.0;
  int devices = 1;
  // Per device, "stylus" or "glove" (a 16-frame glove on the grasp trajectory, every other one a
  // left hand); empty: `devices` styluses.
  std::vector<std::string> mix;
  unsigned rate_hz = 1000;
  std::string trajectory = "press-stroke";
  bool busy_poll = false;
  bool echo_only = false;
  std::string hapticd;  // default: next to haptic-bench
  std::string echo;     // default: next to haptic-bench
  std::vector<std::string> server_args;
  std::string json;
};

// One half of the bench: a responder process and K devices driving it.
struct Phase {
  std::string name;
  std::string error;  // why it did not run (empty when it ran)
  std::vector<sim::ServoResult> devices;
  std::vector<std::string> device_errors;
  std::vector<double> rtt_us;  // every device's round trips
  std::uint64_t sent = 0, replies = 0, late = 0, lost = 0, missed = 0;
  nlohmann::json server_stats = nullptr;
  int exit_status = 0;  // of the responder, stopped by SIGTERM after the run: anything but 0 is a crash

  [[nodiscard]] bool ran() const { return error.empty(); }
  [[nodiscard]] double late_fraction() const { return sent ? static_cast<double>(late) / sent : 0.0; }
  [[nodiscard]] double loss_fraction() const { return sent ? static_cast<double>(lost) / sent : 0.0; }
};

bool is_glove(const LatencyBenchArgs& a, std::size_t i) { return i < a.mix.size() && a.mix[i] == "glove"; }



// Starts `binary` with `args`, reads the port it prints, runs the devices, stops it.
Phase run_phase(const std::string& name, const std::string& binary, const std::vector<std::string>& args,
                const LatencyBenchArgs& a) {
  Phase phase;
  phase.name = name;
  if (::access(binary.c_str(), X_OK) != 0) {
    phase.error = binary + " not found or not executable (build its target, or pass its path)";
    return phase;
  }
  spdlog::info("latency: starting {}", binary);
  sim::ChildProcess child(binary, args, "  [" + name + "] ");
  // A server loads its scene before it listens: allow it time.
  const sim::ListenAddress address =
      sim::parse_listening_line(child.wait_for_line(sim::listening_line_pattern(), 120s));
  const sim::Trajectory trajectory = sim::Trajectory::parse(a.trajectory);

  const std::size_t k = a.mix.empty() ? static_cast<std::size_t>(a.devices) : a.mix.size();
  phase.devices.resize(k);
  phase.device_errors.resize(k);
  std::latch connected(static_cast<std::ptrdiff_t>(k));
  std::vector<std::thread> threads;
  for (std::size_t i = 0; i < k; ++i)
    threads.emplace_back([&, i] {
      client::Client client;
      bool ok = false;
      try {
        const std::string client_name = "haptic-bench-latency-" + std::to_string(i);
        const protocol::Welcome w = client.connect(
            address.host, address.port,
            is_glove(a, i) ? sim::glove_hello(sim::kGloveFramesAll, client_name, a.rate_hz,
                                              i % 2 == 1 ? protocol::Hand::kLeft : protocol::Hand::kRight)
                           : stylus_hello(client_name, a.rate_hz),
            2s);
        ok = w.rate_hz == a.rate_hz;
        if (!ok) phase.device_errors[i] = "server granted " + std::to_string(w.rate_hz) + " Hz";
      } catch (const std::exception& e) {
        phase.device_errors[i] = e.what();
      }
      // All devices start their loops together, so K sessions really share the server.
      connected.arrive_and_wait();
      if (!ok) return;
      sim::ServoConfig config;
      config.rate_hz = a.rate_hz;
      config.duration_s = a.seconds;
      if (is_glove(a, i)) {
        // Gloves alternate right and left hands, each closing into a grasp.
        sim::GloveSimulation glove(sim::GloveTrajectory::parse("grasp"), sim::GloveParams{}, sim::kGloveFramesAll,
                                   i % 2 == 1, sim::servo_period_s(config.rate_hz));
        sim::GloveServo servo(glove);
        phase.devices[i] = sim::run_servo_loop(client, servo, config);
      } else {
        phase.devices[i] = sim::run_servo_loop(client, trajectory, config);
      }
      if (i == 0) {
        try {
          phase.server_stats = sim::to_json(client.request_stats(500ms));
        } catch (const client::ClientError& e) {
          spdlog::warn("latency: {}: no stats: {}", name, e.what());
        }
      }
      client.bye();
    });
  for (std::thread& t : threads) t.join();
  phase.exit_status = child.stop(10s);
  if (phase.exit_status != 0)
    spdlog::warn("latency: {} exited with status {}", name, phase.exit_status);

  for (std::size_t i = 0; i < k; ++i) {
    if (!phase.device_errors[i].empty()) {
      phase.error = "device " + std::to_string(i) + ": " + phase.device_errors[i];
      continue;
    }
    const sim::ServoResult& r = phase.devices[i];
    phase.rtt_us.insert(phase.rtt_us.end(), r.rtt_us.begin(), r.rtt_us.end());
    phase.sent += r.samples_sent;
    phase.replies += r.replies;
    phase.late += r.late;
    phase.lost += r.lost;
    phase.missed += r.missed_ticks;
  }
  return phase;
}

// Round trips binned on a log scale (10 bins a decade from 10 us to 100 ms; the last bin takes
// everything above), for the report's histograms.
nlohmann::json rtt_histogram(const std::vector<double>& rtt_us) {
  constexpr int kPerDecade = 10, kBins = 4 * kPerDecade;
  std::vector<double> edges(kBins + 1);
  for (int i = 0; i <= kBins; ++i) edges[static_cast<std::size_t>(i)] = 10.0 * std::pow(10.0, static_cast<double>(i) / kPerDecade);
  std::vector<std::uint64_t> counts(kBins, 0);
  for (double r : rtt_us) {
    const double bin = std::floor(kPerDecade * std::log10(std::max(r, 10.0) / 10.0));
    ++counts[static_cast<std::size_t>(std::clamp(bin, 0.0, static_cast<double>(kBins - 1)))];
  }
  return {{"edges_us", edges}, {"counts", counts}};
}

nlohmann::json to_json(const Phase& p) {
  if (!p.ran()) return {{"error", p.error}};
  nlohmann::json per_device = nlohmann::json::array();
  for (const sim::ServoResult& r : p.devices) per_device.push_back(sim::to_json(r));
  return {{"rtt_us", sim::to_json(sim::summarize_rtt(p.rtt_us))},
          {"rtt_histogram", rtt_histogram(p.rtt_us)},
          {"late_fraction", p.late_fraction()},
          {"loss_fraction", p.loss_fraction()},
          {"samples_sent", p.sent},
          {"replies", p.replies},
          {"late", p.late},
          {"lost", p.lost},
          {"missed_ticks", p.missed},
          {"server_stats", p.server_stats},
          {"exit_status", p.exit_status},
          {"devices", per_device}};
}

void print_row(const Phase& p) {
  if (!p.ran()) {
    std::printf("%-9s not run: %s\n", p.name.c_str(), p.error.c_str());
    return;
  }
  const sim::RttSummary s = sim::summarize_rtt(p.rtt_us);
  std::printf("%-9s %8llu %8llu %7.3f %7.3f %7llu %8.1f %8.1f %8.1f %8.1f %8.1f\n", p.name.c_str(),
              static_cast<unsigned long long>(p.sent), static_cast<unsigned long long>(p.replies),
              100.0 * p.late_fraction(), 100.0 * p.loss_fraction(), static_cast<unsigned long long>(p.missed), s.p50_us,
              s.p90_us, s.p99_us, s.p999_us, s.max_us);
}

void run_latency_bench(const LatencyBenchArgs& a) {
  (void)sim::Trajectory::parse(a.trajectory);  // a bad --trajectory fails before any process starts
  const std::filesystem::path dir = own_directory();
  const std::string echo_binary = a.echo.empty() ? (dir / "haptic-echo").string() : a.echo;
  const std::string server_binary = a.hapticd.empty() ? (dir / "hapticd").string() : a.hapticd;
  // The responders outlive the run by a margin, and exit on their own if the bench dies.
  const std::string lifetime = std::to_string(static_cast<int>(a.seconds) + 60);
  const Machine machine = describe_machine();
  const int devices = a.mix.empty() ? a.devices : static_cast<int>(a.mix.size());
  std::string kinds;
  for (const std::string& m : a.mix) kinds += (kinds.empty() ? "" : ",") + m;
  if (kinds.empty()) kinds = "stylus";
  spdlog::info("latency: {} device(s) ({}) x {:.1f} s at {} Hz, stylus trajectory {}, busy-poll {}", devices, kinds,
               a.seconds, a.rate_hz, a.trajectory, a.busy_poll ? "on" : "off");

  const Phase echo = run_phase("echo", echo_binary, {"--bind", "127.0.0.1", "--port", "0", "--duration", lifetime}, a);
  if (!echo.ran()) throw std::runtime_error("the echo baseline failed: " + echo.error);

  Phase server;
  server.name = "hapticd";
  if (a.echo_only) {
    server.error = "skipped (--echo-only)";
  } else {
    std::vector<std::string> args{"--port", "0", "--duration", lifetime};
    if (a.busy_poll) args.emplace_back("--busy-poll");
    args.insert(args.end(), a.server_args.begin(), a.server_args.end());
    try {
      server = run_phase("hapticd", server_binary, args, a);
    } catch (const std::exception& e) {
      server.error = e.what();
    }
  }

  const sim::RttSummary e = sim::summarize_rtt(echo.rtt_us);
  nlohmann::json ratio = nullptr;
  std::printf("%-9s %8s %8s %7s %7s %7s %8s %8s %8s %8s %8s\n", "responder", "sent", "replies", "late%", "loss%",
              "missed", "p50_us", "p90_us", "p99_us", "p999_us", "max_us");
  print_row(echo);
  print_row(server);
  // A responder that crashed during the run measured nothing worth a ratio.
  if (server.ran() && server.exit_status == 0 && echo.exit_status == 0) {
    const sim::RttSummary s = sim::summarize_rtt(server.rtt_us);
    ratio = {{"p50", s.p50_us / e.p50_us},
             {"p90", s.p90_us / e.p90_us},
             {"p99", s.p99_us / e.p99_us},
             {"p999", s.p999_us / e.p999_us},
             {"max", s.max_us / e.max_us}};
    std::printf("%-9s %8s %8s %7s %7s %7s %7.2fx %7.2fx %7.2fx %7.2fx %7.2fx\n", "ratio", "", "", "", "", "",
                ratio["p50"].get<double>(), ratio["p90"].get<double>(), ratio["p99"].get<double>(),
                ratio["p999"].get<double>(), ratio["max"].get<double>());
  }
  std::printf("machine: %s, %d cores, revision %s; %d device thread(s) (%s) per responder, run one after the other\n",
              machine.cpu.c_str(), machine.cores, machine.git_revision.c_str(), devices, kinds.c_str());

  if (!a.json.empty()) {
    const nlohmann::json doc = {
        {"suite", "latency"},    {"seconds", a.seconds},       {"devices", devices},
        {"device_kinds", kinds},
        {"rate_hz", a.rate_hz},  {"trajectory", a.trajectory}, {"busy_poll", a.busy_poll},
        {"echo", to_json(echo)}, {"server", to_json(server)},  {"ratio_server_over_echo", ratio},
        {"cpu", machine.cpu},    {"machine", to_json(machine)}};
    write_json(a.json, doc);
  }
  for (const Phase& p : std::array<std::reference_wrapper<const Phase>, 2>{echo, server})
    if (p.ran() && p.exit_status != 0)
      throw std::runtime_error(
          p.name + " exited with status " + std::to_string(p.exit_status) +
          " instead of 0 after SIGTERM: it failed during the run, its figures are not a measurement");
  if (!server.ran() && !a.echo_only)
    throw std::runtime_error("the hapticd half did not run: " + server.error +
                             "; the echo baseline above is complete (--echo-only skips the server on purpose)");
}

}  // namespace

void add_latency_suite(CLI::App& app) {
  auto args = std::make_shared<LatencyBenchArgs>();
  CLI::App* sub = app.add_subcommand(
      "latency", "device round trips: raw UDP echo (haptic-echo) vs hapticd, same paced servo loop, same run");
  sub->add_option("--seconds", args->seconds, "seconds each responder is driven")
      ->check(CLI::Range(0.1, 3600.0))
      ->capture_default_str();
  CLI::Option* devices = sub->add_option("--devices", args->devices, "simulated devices, each on its own thread and socket")
      ->check(CLI::Range(1, 16))
      ->capture_default_str();
  sub->add_option("--mix", args->mix,
                  "device kinds, one per device, instead of --devices styluses: stylus | glove (16 frames, grasp "
                  "trajectory, alternately right and left), e.g. --mix glove,glove,stylus")
      ->delimiter(',')
      ->check(CLI::IsMember({"stylus", "glove"}))
      ->excludes(devices);
  sub->add_option("--rate", args->rate_hz, "servo rate of every device, Hz")
      ->check(CLI::Range(10u, 10000u))
      ->capture_default_str();
  sub->add_option("--trajectory", args->trajectory, "press | stroke | press-stroke | tap | circle | CSV file")
      ->capture_default_str();
  sub->add_flag("--busy-poll", args->busy_poll, "pass --busy-poll to hapticd (spins instead of sleeping)");
  sub->add_flag("--echo-only", args->echo_only, "measure the echo baseline only");
  sub->add_option("--hapticd", args->hapticd, "hapticd binary (default: next to haptic-bench)");
  sub->add_option("--echo", args->echo, "haptic-echo binary (default: next to haptic-bench)");
  sub->add_option("--json", args->json, "write the results as JSON to this file");
  sub->add_option("server_args", args->server_args, "extra hapticd arguments, after -- (e.g. -- --scene FILE)");
  sub->callback([args] { run_latency_bench(*args); });
}

}  // namespace hapticd::bench
