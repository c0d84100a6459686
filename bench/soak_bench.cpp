#include "soak_bench.hpp"

#include <sys/stat.h>
#include <unistd.h>

#include <atomic>
#include <barrier>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <memory>
#include <mutex>
#include <optional>
#include <spdlog/spdlog.h>
#include <stdexcept>
#include <string>
#include <thread>
#include <vector>

#include "bench_common.hpp"
#include "clients/chaos/chaos_relay.hpp"
#include "clients/cpp/client.hpp"
#include "clients/sim/child_process.hpp"
#include "clients/sim/servo_loop.hpp"
#include "clients/sim/servo_report.hpp"
#include "clients/sim/trajectory.hpp"
#include "protocol/key_file.hpp"

namespace hapticd::bench {
namespace {

using namespace std::chrono_literals;

struct SoakBenchArgs {
  double minutes = 10.0;
  int devices = 4;
  double window_s = 10.0;
  unsigned rate_hz = 1000;
  std::string trajectory = "press-stroke";
  // The relay's faults (issue 7: the soak runs with the chaos relay in the path). Milder than the
  // e2e fault test's, a network that is poor but usable, for as long as the soak lasts.
  chaos::ChaosConfig chaos{.loss = 0.02, .duplicate = 0.005, .reorder = 0.01, .corrupt = 0.001,
                           .delay_ms = 0.0, .jitter_ms = 0.2, .reorder_hold_ms = 20.0, .seed = 1};
  std::string hapticd;  // default: next to haptic-bench
  std::vector<std::string> server_args;
  std::string json;
  double rss_growth_limit_mib = 4.0;  // what --check calls flat
  bool check = false;
};

// One window of the soak: what every device saw, what hapticd's memory and counters were at its end.
struct Window {
  double t_end_s = 0.0;
  double rss_mib = std::nan("");
  std::vector<double> rtt_us;
  std::uint64_t sent = 0, replies = 0, late = 0, lost = 0, missed = 0, reconnects = 0;
  double force_max_n = 0.0;
  double force_rate_max_n_per_s = 0.0;
  std::optional<protocol::Stats> server;  // none when every stats request was lost
};

// Resident set of process `pid` in MiB (VmRSS of /proc/PID/status); NaN when it cannot be read.
double resident_mib(pid_t pid) {
  std::ifstream status("/proc/" + std::to_string(pid) + "/status");
  for (std::string line; std::getline(status, line);)
    if (line.rfind("VmRSS:", 0) == 0) return std::stod(line.substr(6)) / 1024.0;  // kB
  return std::nan("");
}

std::uint64_t rejected_total(const protocol::Stats& s) {
  std::uint64_t n = 0;
  for (std::uint64_t r : s.rejected_by_reason) n += r;
  return n;
}

// Least-squares slope of y over x; NaN with fewer than two points.
double slope(const std::vector<double>& x, const std::vector<double>& y) {
  const std::size_t n = x.size();
  if (n < 2) return std::nan("");
  double mx = 0, my = 0;
  for (std::size_t i = 0; i < n; ++i) mx += x[i] / n, my += y[i] / n;
  double sxy = 0, sxx = 0;
  for (std::size_t i = 0; i < n; ++i) sxy += (x[i] - mx) * (y[i] - my), sxx += (x[i] - mx) * (x[i] - mx);
  return sxx > 0 ? sxy / sxx : std::nan("");
}

// Server counters of window i minus those of the window before (the server's are since its start).
struct Delta {
  long long overruns = -1, resets = -1, rejected = -1, dropped = -1, clamps = -1;
};
Delta delta(const std::vector<Window>& w, std::size_t i) {
  Delta d;
  if (!w[i].server) return d;
  const protocol::Stats* before = nullptr;
  for (std::size_t j = i; j-- > 0;)
    if (w[j].server) {
      before = &*w[j].server;
      break;
    }
  const protocol::Stats zero{};
  const protocol::Stats& b = before ? *before : zero;
  const protocol::Stats& s = *w[i].server;
  d.overruns = static_cast<long long>(s.overruns - b.overruns);
  d.resets = static_cast<long long>(s.resets - b.resets);
  d.rejected = static_cast<long long>(rejected_total(s) - rejected_total(b));
  d.dropped = static_cast<long long>(s.packets_dropped - b.packets_dropped);
  d.clamps = static_cast<long long>(s.clamps - b.clamps);
  return d;
}

void print_window(const Window& w, const Delta& d) {
  const sim::RttSummary r = sim::summarize_rtt(w.rtt_us);
  const double loss = w.sent ? 100.0 * static_cast<double>(w.lost) / static_cast<double>(w.sent) : 0.0;
  const double late = w.sent ? 100.0 * static_cast<double>(w.late) / static_cast<double>(w.sent) : 0.0;
  std::printf("%7.0f %8.2f %8llu %6.2f %6.2f %8.1f %8.1f %8.1f %6.2f %8lld %6lld %8lld %7lld %4llu\n", w.t_end_s,
              w.rss_mib, static_cast<unsigned long long>(w.sent), loss, late, r.p50_us, r.p99_us, r.max_us,
              w.force_max_n, d.overruns, d.resets, d.rejected, d.dropped,
              static_cast<unsigned long long>(w.reconnects));
  std::fflush(stdout);
}

nlohmann::json to_json(const Window& w, const Delta& d) {
  return {{"t_end_s", w.t_end_s},
          {"rss_mib", w.rss_mib},
          {"rtt_us", sim::to_json(sim::summarize_rtt(w.rtt_us))},
          {"samples_sent", w.sent},
          {"replies", w.replies},
          {"late", w.late},
          {"lost", w.lost},
          {"missed_ticks", w.missed},
          {"reconnects", w.reconnects},
          {"force_max_n", w.force_max_n},
          {"force_rate_max_n_per_s", w.force_rate_max_n_per_s},
          {"server_stats", w.server ? sim::to_json(*w.server) : nlohmann::json(nullptr)},
          {"server_delta",
           {{"overruns", d.overruns},
            {"resets", d.resets},
            {"rejected", d.rejected},
            {"dropped", d.dropped},
            {"clamps", d.clamps}}}};
}

void run_soak_bench(const SoakBenchArgs& a) {
  chaos::validate(a.chaos);
  const sim::Trajectory trajectory = sim::Trajectory::parse(a.trajectory);
  const std::string server_binary = a.hapticd.empty() ? (own_directory() / "hapticd").string() : a.hapticd;
  if (::access(server_binary.c_str(), X_OK) != 0)
    throw std::runtime_error(server_binary + " not found or not executable (build its target, or pass --hapticd)");
  const std::size_t windows = std::max<std::size_t>(1, static_cast<std::size_t>(std::llround(a.minutes * 60.0 / a.window_s)));
  const double total_s = static_cast<double>(windows) * a.window_s;

  // A fresh key in a private directory: the soak runs authenticated, as a deployment would.
  char dir_template[] = "/tmp/haptic-bench-soak-XXXXXX";
  if (::mkdtemp(dir_template) == nullptr) throw std::runtime_error("cannot create a temporary directory");
  const std::filesystem::path work = dir_template;
  struct RemoveWork {
    std::filesystem::path p;
    ~RemoveWork() {
      std::error_code ec;
      std::filesystem::remove_all(p, ec);
    }
  } remove_work{work};
  const protocol::Key key = protocol::generate_key_file((work / "key").string());
  const std::string stats_path = (work / "server.json").string();

  spdlog::info("soak: {} stylus device(s) x {:.1f} min in {} windows of {:.0f} s at {} Hz through the chaos relay "
               "(loss {:.3g}, duplicate {:.3g}, reorder {:.3g}, corrupt {:.3g}, jitter {:.3g} ms, seed {}), "
               "authenticated",
               a.devices, total_s / 60.0, windows, a.window_s, a.rate_hz, a.chaos.loss, a.chaos.duplicate,
               a.chaos.reorder, a.chaos.corrupt, a.chaos.jitter_ms, a.chaos.seed);
  std::vector<std::string> args{"--port",     "0", "--key-file", (work / "key").string(), "--duration",
                                std::to_string(static_cast<long long>(total_s) + 120), "--stats", stats_path};
  args.insert(args.end(), a.server_args.begin(), a.server_args.end());
  sim::ChildProcess server(server_binary, args, "  [hapticd] ");
  const sim::ListenAddress address =
      sim::parse_listening_line(server.wait_for_line(sim::listening_line_pattern(), 120s));
  chaos::ChaosRelay relay(a.chaos, address.host, address.port);
  relay.start();

  std::vector<Window> table(windows);
  std::mutex table_mutex;
  std::vector<std::string> errors(static_cast<std::size_t>(a.devices));
  std::atomic<bool> failed{false};
  const auto t0 = std::chrono::steady_clock::now();
  // At the end of each window device 0 asks hapticd for its counters and reads its memory, the
  // others wait, so the windows of every device line up.
  std::barrier window_end(a.devices);

  std::printf("%7s %8s %8s %6s %6s %8s %8s %8s %6s %8s %6s %8s %7s %4s\n", "t_s", "rss_MiB", "sent", "loss%",
              "late%", "p50_us", "p99_us", "max_us", "F_max", "overruns", "resets", "rejected", "dropped", "reco");
  std::vector<std::thread> threads;
  for (int i = 0; i < a.devices; ++i)
    threads.emplace_back([&, i] {
      client::Client client;
      client.set_key(key);
      protocol::Hello hello = stylus_hello("haptic-bench-soak-" + std::to_string(i), a.rate_hz);
      auto connect = [&] { client.connect("127.0.0.1", relay.port(), hello, 5s); };
      bool connected = false;
      try {
        connect();
        connected = true;
      } catch (const std::exception& e) {
        errors[static_cast<std::size_t>(i)] = e.what();
        failed.store(true);
      }
      for (std::size_t w = 0; w < windows; ++w) {
        sim::ServoResult r;
        std::uint64_t reconnects = 0;
        if (connected && !failed.load()) {
          sim::ServoConfig config;
          config.rate_hz = a.rate_hz;
          config.duration_s = a.window_s;
          r = sim::run_servo_loop(client, trajectory, config);
          // A session the server no longer answers (timed out through a long run of losses) is opened
          // again; counted, since a soak should see none.
          if (r.replies == 0) {
            try {
              connect();
              ++reconnects;
            } catch (const std::exception& e) {
              errors[static_cast<std::size_t>(i)] = std::string("reconnect: ") + e.what();
              failed.store(true);
            }
          }
        }
        std::optional<protocol::Stats> stats;
        if (i == 0 && connected)
          for (int attempt = 0; attempt < 5 && !stats; ++attempt) try {
              stats = client.request_stats(300ms);
            } catch (const client::ClientError&) {  // lost in the relay: ask again
            }
        {
          std::lock_guard lock(table_mutex);
          Window& row = table[w];
          row.rtt_us.insert(row.rtt_us.end(), r.rtt_us.begin(), r.rtt_us.end());
          row.sent += r.samples_sent;
          row.replies += r.replies;
          row.late += r.late;
          row.lost += r.lost;
          row.missed += r.missed_ticks;
          row.reconnects += reconnects;
          row.force_max_n = std::max(row.force_max_n, r.force_max_n);
          row.force_rate_max_n_per_s = std::max(row.force_rate_max_n_per_s, r.force_rate_max_n_per_s);
          if (i == 0) {
            row.server = stats;
            row.rss_mib = resident_mib(server.pid());
            row.t_end_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
          }
        }
        window_end.arrive_and_wait();
        if (i == 0) print_window(table[w], delta(table, w));
      }
      if (connected) client.bye();
    });
  for (std::thread& t : threads) t.join();
  relay.stop();
  const int exit_status = server.stop(10s);
  nlohmann::json server_report = nullptr;
  if (std::ifstream in(stats_path); in) server_report = nlohmann::json::parse(in, nullptr, false);

  // Memory: from the end of the first window (scene loaded, sessions open, buffers warm) to the end.
  std::vector<double> t, rss;
  for (const Window& w : table)
    if (std::isfinite(w.rss_mib)) t.push_back(w.t_end_s / 60.0), rss.push_back(w.rss_mib);
  const double rss_first = rss.empty() ? std::nan("") : rss.front();
  const double rss_last = rss.empty() ? std::nan("") : rss.back();
  const double rss_max = rss.empty() ? std::nan("") : *std::max_element(rss.begin(), rss.end());
  const double growth = rss_last - rss_first;
  const double growth_per_min = slope(t, rss);
  std::uint64_t sent = 0, lost = 0, late = 0, reconnects = 0;
  std::vector<double> all_rtt;
  for (const Window& w : table) {
    sent += w.sent, lost += w.lost, late += w.late, reconnects += w.reconnects;
    all_rtt.insert(all_rtt.end(), w.rtt_us.begin(), w.rtt_us.end());
  }
  const sim::RttSummary rtt = sim::summarize_rtt(all_rtt);
  const chaos::ChaosCounts counts = relay.counts();
  auto counter = [&](const char* section, const char* name) -> long long {
    if (!server_report.is_object() || !server_report.contains(section)) return -1;
    const nlohmann::json& s = server_report[section];
    return s.contains(name) ? s[name].get<long long>() : -1;
  };
  const long long proxy_resets = server_report.is_object() ? server_report.value("proxy_resets", -1LL) : -1;
  const long long hand_resets = counter("visual", "hand_resets");
  const long long body_resets = counter("visual", "body_resets");
  const long long overruns = counter("haptic", "overruns");
  const long long lookahead_fallbacks = counter("haptic", "lookahead_fallbacks");
  const long long contact_holds = counter("haptic", "contact_holds");
  std::printf(
      "soak: %.1f min, %d devices: hapticd RSS %.2f MiB after the first window, %.2f at the end (growth %+.2f MiB, "
      "slope %+.3f MiB/min, max %.2f); %llu samples sent, loss %.2f %%, late %.3f %%, RTT p50 %.1f p99 %.1f max "
      "%.1f us; overruns %lld, resets: proxy %lld, hand %lld, body %lld; contact solves without the lookahead "
      "%lld, proxy holds %lld; reconnects %llu; relay lost %llu / "
      "corrupted %llu / duplicated %llu / reordered %llu of %llu to hapticd; hapticd exit %d\n",
      total_s / 60.0, a.devices, rss_first, rss_last, growth, growth_per_min, rss_max,
      static_cast<unsigned long long>(sent), sent ? 100.0 * lost / sent : 0.0, sent ? 100.0 * late / sent : 0.0,
      rtt.p50_us, rtt.p99_us, rtt.max_us, overruns, proxy_resets, hand_resets, body_resets, lookahead_fallbacks,
      contact_holds,
      static_cast<unsigned long long>(reconnects), static_cast<unsigned long long>(counts.to_server.lost),
      static_cast<unsigned long long>(counts.to_server.corrupted),
      static_cast<unsigned long long>(counts.to_server.duplicated),
      static_cast<unsigned long long>(counts.to_server.reordered),
      static_cast<unsigned long long>(counts.to_server.received), exit_status);
  const Machine machine = describe_machine();
  std::printf("machine: %s, %d cores, revision %s\n", machine.cpu.c_str(), machine.cores,
              machine.git_revision.c_str());

  const bool flat = std::isfinite(growth) && growth <= a.rss_growth_limit_mib;
  const bool no_resets = proxy_resets == 0 && hand_resets == 0 && body_resets == 0;
  if (!a.json.empty()) {
    nlohmann::json rows = nlohmann::json::array();
    for (std::size_t i = 0; i < table.size(); ++i) rows.push_back(to_json(table[i], delta(table, i)));
    nlohmann::json device_errors = nlohmann::json::array();
    for (const std::string& e : errors) device_errors.push_back(e);
    write_json(a.json, {{"suite", "soak"},
                        {"minutes", total_s / 60.0},
                        {"devices", a.devices},
                        {"window_s", a.window_s},
                        {"rate_hz", a.rate_hz},
                        {"trajectory", a.trajectory},
                        {"rss_mib", {{"first_window", rss_first}, {"last", rss_last}, {"max", rss_max},
                                     {"growth", growth}, {"slope_per_min", growth_per_min},
                                     {"growth_limit", a.rss_growth_limit_mib}, {"flat", flat}}},
                        {"rtt_us", sim::to_json(rtt)},
                        {"samples_sent", sent},
                        {"lost", lost},
                        {"late", late},
                        {"reconnects", reconnects},
                        {"resets", {{"proxy", proxy_resets}, {"hand", hand_resets}, {"body", body_resets}}},
                        {"overruns", overruns},
                        {"chaos", chaos::to_json(counts, a.chaos)},
                        {"server", server_report},
                        {"server_exit_status", exit_status},
                        {"device_errors", device_errors},
                        {"windows", rows},
                        {"machine", to_json(machine)}});
  }
  for (std::size_t i = 0; i < errors.size(); ++i)
    if (!errors[i].empty()) throw std::runtime_error("device " + std::to_string(i) + ": " + errors[i]);
  if (exit_status != 0)
    throw std::runtime_error("hapticd exited with status " + std::to_string(exit_status) +
                             " instead of 0 after SIGTERM: it failed during the soak");
  if (a.check && !(flat && no_resets && reconnects == 0))
    throw std::runtime_error("--check: " + std::string(flat ? "" : "RSS grew beyond the limit; ") +
                             (no_resets ? "" : "resets; ") + (reconnects == 0 ? "" : "sessions reopened"));
}

}  // namespace

void add_soak_suite(CLI::App& app) {
  auto args = std::make_shared<SoakBenchArgs>();
  CLI::App* sub = app.add_subcommand(
      "soak", "hapticd for minutes with N simulated styluses through the chaos relay, authenticated: memory, "
              "overruns, resets, dropped and rejected packets and round trips per window");
  sub->add_option("--minutes", args->minutes, "length of the run (rounded to whole windows)")
      ->check(CLI::Range(0.01, 24.0 * 60.0))
      ->capture_default_str();
  sub->add_option("--devices", args->devices, "simulated styluses, each on its own thread and session")
      ->check(CLI::Range(1, 16))
      ->capture_default_str();
  sub->add_option("--window", args->window_s, "seconds per report row")
      ->check(CLI::Range(1.0, 3600.0))
      ->capture_default_str();
  sub->add_option("--rate", args->rate_hz, "servo rate of every device, Hz")
      ->check(CLI::Range(10u, 10000u))
      ->capture_default_str();
  sub->add_option("--trajectory", args->trajectory, "press | stroke | press-stroke | tap | circle | CSV file")
      ->capture_default_str();
  sub->add_option("--loss", args->chaos.loss, "relay: probability a datagram is lost")->capture_default_str();
  sub->add_option("--duplicate", args->chaos.duplicate, "relay: probability of a second copy")->capture_default_str();
  sub->add_option("--reorder", args->chaos.reorder, "relay: probability of being overtaken")->capture_default_str();
  sub->add_option("--corrupt", args->chaos.corrupt, "relay: probability of one byte changed")->capture_default_str();
  sub->add_option("--delay-ms", args->chaos.delay_ms, "relay: fixed one-way delay")->capture_default_str();
  sub->add_option("--jitter-ms", args->chaos.jitter_ms, "relay: uniform extra delay up to this")->capture_default_str();
  sub->add_option("--seed", args->chaos.seed, "relay: seed of its decisions")->capture_default_str();
  sub->add_option("--rss-growth-limit", args->rss_growth_limit_mib,
                  "MiB of RSS growth after the first window that --check still calls flat")
      ->capture_default_str();
  sub->add_flag("--check", args->check,
                "exit 1 unless RSS stayed flat, nothing was reset and no session had to be reopened");
  sub->add_option("--hapticd", args->hapticd, "hapticd binary (default: next to haptic-bench)");
  sub->add_option("--json", args->json, "write the report as JSON to this file");
  sub->add_option("server_args", args->server_args, "extra hapticd arguments, after -- (e.g. -- --scene FILE)");
  sub->callback([args] { run_soak_bench(*args); });
}

}  // namespace hapticd::bench
