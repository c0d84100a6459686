// The authenticated server and a simulated stylus pressing its wall through the chaos relay
// (clients/chaos): with loss, reordering, duplication and jitter the session stays alive, no force
// passes the Welcome's limit or its rate limit, the work on the device stays within 1 % of the energy
// stored (see below for why not <= 0), and every duplicate is refused as a replay; with corrupted
// bytes every corrupted datagram is refused by its MAC, and the work on the device is <= 0 up to
// what float32 on the wire accounts for.
//
// One 4 s press cycle each here: the wall is a fixed linear model (a spring on both sides of z = 0,
// at rest at z = 0), so the press starts and ends at rest at z = 0, a closed path on which a passive
// rendering does no net work on the device; 4000 samples at 1 kHz exercise every fault hundreds of
// times. The wall is lossless, so the only dissipation is the coupling's damping, and it is thin on
// a slow press: -1.4e-5 J over the cycle without faults, against 6.7 mJ stored at the bottom.
// float32 on the wire accounts for < 1e-7 J of work (float32_work_j: 9.8e-8 J here).
// With 1 % corrupted datagrams (each refused, so ~2 % of the replies missing) the work stays
// negative: -1.26e-5 to -1.31e-5 J in 10 runs on a quiet machine, -1.3e-5 to -3.3e-5 J in 4 with
// both cores saturated by busy loops; a coupling without damping puts +6e-6 J in, which fails it.
// With 10 % loss both ways, reordering, duplication and 1 ms jitter the strict bound does not hold,
// with the passivity controller on (the default for every device):
//  - loss and jitter hold each force longer than the 1 ms the coupling's damping was sized for,
//    which eats its margin: +2.1e-5 to +2.7e-5 J in 15 runs, quiet or with one or both cores busy
//    (0.31-0.40 % of the energy stored; as much at 220deb1);
//  - the passivity controller does not take that back: it damps only past kPassivityBudget_J
//    (1e-4 J, 1.5 % of the energy stored here) of deficit, and its observer sums the work of the
//    replies the server sent, not of those the device applied (10 % of them lost, others held
//    longer): in those runs it read +3.3e-6 to +7.8e-6 J and never acted.
// A stopped process (this test's server, relay and device are one: a paused virtual machine, a
// busy host) left the device pressing on while its reply faded, and the force it had felt came back
// where it had sunk to: +2.6e-4 J (3.9 %) on CI at b2c1d3d. scripts/chaos-process-stops stops it
// four times: 80 ms (a gap in the device's samples, then hidden by its last sample before the gap,
// read late), up to +8.7e-2 J then, -6.7e-3 to -1.3e-2 J now; 30 ms, up to +5.6e-4 J then,
// -2.5e-4 to -1.7e-3 J now (the stopped machine of ServerStalls holds both).
// So that test bounds the work by 1 % of the energy stored (f^2 / 2k at the bottom), and that bound
// is weak: a coupling without damping (+3.9e-5 J, 0.58 %) or with negative damping -k T / 2
// (+6.1e-5 J, 0.91 %) passes it. The 20 s run, with its bound (<= 0), is
// tests/e2e/chaos_loopback.sh, against the real world (whose flesh and contacts dissipate).
#include <gtest/gtest.h>
#include <unistd.h>

#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <numbers>

#include "clients/chaos/chaos_relay.hpp"
#include "clients/cpp/client.hpp"
#include "clients/sim/servo_loop.hpp"
#include "clients/sim/trajectory.hpp"
#include "haptic_server_test_util.hpp"

namespace hapticd::haptic {
namespace {

using protocol::RejectReason;

constexpr double kSeconds = 4.0;
constexpr double kPressDepth_m = 0.02;

protocol::Key test_key() {
  protocol::Key k;
  for (std::size_t i = 0; i < k.size(); ++i) k[i] = static_cast<std::uint8_t>(0xA5 ^ (7 * i));
  return k;
}

// The press cycle from z = 0 (where the wall model exerts nothing) 2 cm into it and back, with
// half-cosine ramps: 0.5 s rest, 1 s down, 1 s held, 1 s up, 0.5 s rest.
sim::Trajectory closed_press() {
  const std::string path =
      (std::filesystem::temp_directory_path() / ("hapticd_chaos_press_" + std::to_string(::getpid()) + ".csv"))
          .string();
  {
    std::ofstream csv(path);
    csv << "t_s,x_m,y_m,z_m\n";
    for (int i = 0; i <= 400; ++i) {
      const double t = 0.01 * i;
      const auto ramp = [](double u) { return 0.5 - 0.5 * std::cos(std::numbers::pi * std::clamp(u, 0.0, 1.0)); };
      const double depth = kPressDepth_m * (t < 2.5 ? ramp(t - 0.5) : 1.0 - ramp(t - 2.5));
      csv << t << ",0,0," << -depth << "\n";
    }
  }
  sim::Trajectory trajectory = sim::Trajectory::from_csv(path);
  std::filesystem::remove(path);
  return trajectory;
}

struct ChaosRun {
  sim::ServoResult result;
  protocol::Welcome welcome;
  protocol::Stats server_stats;
  chaos::ChaosCounts relay;
  ServerStats server;
  client::ClientCounters client;
};

// A keyed server, the relay in front of it, and the stylus along closed_press() through the relay
// for kSeconds.
ChaosRun run_through(const chaos::ChaosConfig& config) {
  ServerOptions options;
  options.key = test_key();
  test::RunningServer s(options);
  chaos::ChaosRelay relay(config, "127.0.0.1", s.server.port());
  relay.start();
  client::Client c;
  c.set_key(test_key());
  protocol::Hello hello;
  hello.client_name.assign("chaos-test");
  hello.device_kind = protocol::DeviceKind::kStylus;
  protocol::TrackedFrame frame;
  frame.id = 7;
  frame.name.assign("tip");
  hello.frames.push_back(frame);
  ChaosRun run;
  run.welcome = c.connect("127.0.0.1", relay.port(), hello, std::chrono::seconds(5), std::chrono::milliseconds(200));
  sim::ServoConfig servo;
  servo.rate_hz = run.welcome.rate_hz;
  servo.duration_s = kSeconds;
  servo.frame_id = 7;
  run.result = sim::run_servo_loop(c, closed_press(), servo);
  // Alive at the end: the server still answers (through the relay, so asked until it does).
  for (int attempt = 0; attempt < 20; ++attempt) {
    try {
      run.server_stats = c.request_stats(std::chrono::milliseconds(100));
      break;
    } catch (const client::ClientError&) {
    }
  }
  // What is still on its way (the relay's copy of the Stats reply) is read before counting.
  while (c.poll_force(std::chrono::milliseconds(50))) {
  }
  run.client = c.counters();
  c.bye();
  std::this_thread::sleep_for(std::chrono::milliseconds(50));
  relay.stop();
  s.halt();
  run.relay = relay.counts();
  run.server = s.server.stats();
  const nlohmann::json counts = chaos::to_json(run.relay, config);
  std::printf("relay to server: %s\nrelay to client: %s\n", counts["to_server"].dump().c_str(),
              counts["to_client"].dump().c_str());
  std::printf(
      "device: %llu sent, %llu replies (loss %.1f %%), force max %.3f N (limit %.1f), rate max %.0f N/s "
      "(limit %.0f), passivity %.3g J, contact %.0f %%; client unauthenticated %llu\n",
      static_cast<unsigned long long>(run.result.samples_sent), static_cast<unsigned long long>(run.result.replies),
      100 * run.result.loss_fraction(), run.result.force_max_n, run.welcome.force_limit_n,
      run.result.force_rate_max_n_per_s, run.welcome.max_force_rate_n_per_s, run.result.passivity_energy_j,
      100 * run.result.contact_fraction(), static_cast<unsigned long long>(run.client.datagrams_unauthenticated));
  std::printf("server: rejected");
  for (std::size_t i = 0; i < protocol::kRejectReasonCount; ++i)
    if (run.server.rejected[i])
      std::printf(" %s %llu", to_string(static_cast<RejectReason>(i)).data(),
                  static_cast<unsigned long long>(run.server.rejected[i]));
  std::printf(
      "; stale %llu, gaps %llu, resyncs %llu, bridged gaps %llu, timed out %llu; the device missed %llu "
      "ticks, faded %llu\n",
      static_cast<unsigned long long>(run.server.stale), static_cast<unsigned long long>(run.server.gaps),
      static_cast<unsigned long long>(run.server.resyncs), static_cast<unsigned long long>(run.server.bridged_gaps),
      static_cast<unsigned long long>(run.server.sessions_timed_out),
      static_cast<unsigned long long>(run.result.missed_ticks),
      static_cast<unsigned long long>(run.result.faded_ticks));
  return run;
}

std::uint64_t rejected(const ChaosRun& r, RejectReason reason) { return r.server.rejected[static_cast<int>(reason)]; }

// Net work on the device over the closed path, within 1 % of the energy the press stored at its
// bottom (f^2 / 2k, k = 750 N/m: the coupling's 1000 N/m in series with the wall's 3000 N/m).
void expect_about_passive(const ChaosRun& r) {
  const double stored_j = r.result.force_max_n * r.result.force_max_n / (2 * 750.0);
  std::printf("work on the device over the cycle %.3g J, %.2f %% of the %.3g J stored; the server's observer %.3g J, "
              "its controller acted %llu times (%.3g J damped)\n",
              r.result.passivity_energy_j, 100 * r.result.passivity_energy_j / stored_j, stored_j,
              r.server_stats.passivity_energy_j, static_cast<unsigned long long>(r.server_stats.passivity_actions),
              r.server_stats.passivity_damped_j);
  EXPECT_LE(r.result.passivity_energy_j, 0.01 * stored_j);
}

// What float32 on the wire can add to the work over the path, J: the force's rounding, and the pose's
// through the coupling's spring and its damper (on velocities from pose differences: twice the
// rounding over a period), each at most half an ulp of the largest value, over the path's length
// (down and up the press, at most twice its depth).
double float32_work_j(const ChaosRun& r) {
  const auto half_ulp = [](double x) {
    const float f = static_cast<float>(x);
    return 0.5 * static_cast<double>(std::nextafter(f, HUGE_VALF) - f);
  };
  const haptic::CouplingGains g = test::stylus_link().gains;
  const double dp = half_ulp(kPressDepth_m), df = half_ulp(r.result.force_max_n);
  return 2 * kPressDepth_m * (df + g.k_n_m * dp + g.b_ns_m * 2 * dp * r.welcome.rate_hz);
}

// Net work on the device over the closed path: none but what float32 on the wire accounts for.
void expect_passive(const ChaosRun& r) {
  std::printf("work on the device over the cycle %.3g J; float32 on the wire accounts for %.3g J; the server's "
              "observer %.3g J, its controller acted %llu times\n",
              r.result.passivity_energy_j, float32_work_j(r), r.server_stats.passivity_energy_j,
              static_cast<unsigned long long>(r.server_stats.passivity_actions));
  EXPECT_LE(r.result.passivity_energy_j, float32_work_j(r));
}

void expect_safe_and_alive(const ChaosRun& r) {
  EXPECT_LE(r.result.force_max_n, r.welcome.force_limit_n + 1e-4);
  // float32 forces over >= 0.1 ms: 1e-6 relative rounding of a few newtons is < 0.1 N/s.
  EXPECT_LE(r.result.force_rate_max_n_per_s, r.welcome.max_force_rate_n_per_s + 1.0);
  EXPECT_EQ(r.server_stats.sessions_active, 1u) << "the session is alive at the end";
  EXPECT_EQ(r.server.sessions_timed_out, 0u);
  EXPECT_EQ(r.server.sessions_opened, 1u);
  EXPECT_GT(r.result.force_max_n, 3.0) << "the stylus pressed the wall (the arm, 200 N/m, against 750 N/m: 3.2 N)";
}

TEST(HapticServerChaos, LossReorderDuplicationAndJitterKeepTheSessionAliveAndTheForceSafe) {
  chaos::ChaosConfig config;
  config.loss = 0.10;
  config.reorder = 0.05;
  config.duplicate = 0.01;
  config.jitter_ms = 1.0;
  config.seed = 20240611;
  const ChaosRun r = run_through(config);
  expect_safe_and_alive(r);
  expect_about_passive(r);
  // Both directions lose ~10 %, and a pose or reply overtaken by the next one is dropped as stale
  // (~5 % each way): ~28 % of the poses get no reply the device applies.
  EXPECT_GT(r.result.loss_fraction(), 0.15);
  EXPECT_LT(r.result.loss_fraction(), 0.4);
  // Every duplicate that reached the server was refused as a replay, and nothing else was refused.
  EXPECT_EQ(rejected(r, RejectReason::kReplayed), r.relay.to_server.duplicated);
  EXPECT_EQ(r.server.packets_dropped, rejected(r, RejectReason::kReplayed) + r.server.stale);
  EXPECT_EQ(r.server.packets_in, r.relay.to_server.sent);
  // The client refused every duplicate of the server's replies the same way, and nothing else
  // (run_through reads until the link is quiet, so the copy of the closing Stats reply is counted).
  EXPECT_EQ(r.client.datagrams_unauthenticated, r.relay.to_client.duplicated);
  EXPECT_GT(r.relay.to_server.reordered, 0u);
  EXPECT_GT(r.relay.to_server.duplicated, 0u);
}

TEST(HapticServerChaos, EveryCorruptedDatagramIsRefusedByItsMacAndTheServerCarriesOn) {
  chaos::ChaosConfig config;
  config.corrupt = 0.01;
  config.seed = 99;
  const ChaosRun r = run_through(config);
  expect_safe_and_alive(r);
  expect_passive(r);
  ASSERT_GT(r.relay.to_server.corrupted, 10u);
  // One changed byte anywhere: the trailer's magic (missing_mac), its session id (unknown_session) or
  // anything else (bad_mac). Every one refused, nothing else refused.
  const std::uint64_t refused = rejected(r, RejectReason::kMissingMac) + rejected(r, RejectReason::kBadMac) +
                                rejected(r, RejectReason::kUnknownSession);
  EXPECT_EQ(refused, r.relay.to_server.corrupted);
  EXPECT_EQ(r.server.packets_dropped, refused + r.server.stale);
  EXPECT_EQ(r.server.packets_in, r.relay.to_server.sent);
  // The client refuses the server's corrupted ones (a corrupted Hello may also have drawn a plain
  // Error, which it refuses too: at most a few more).
  EXPECT_GE(r.client.datagrams_unauthenticated + r.client.datagrams_rejected, r.relay.to_client.corrupted);
  EXPECT_LE(r.client.datagrams_unauthenticated + r.client.datagrams_rejected, r.relay.to_client.corrupted + 3);
  // Every pose whose datagram and reply both came through intact was answered and applied.
  EXPECT_NEAR(static_cast<double>(r.result.replies),
              static_cast<double>(r.result.samples_sent - r.relay.to_server.corrupted - r.relay.to_client.corrupted),
              3.0);
}

}  // namespace
}  // namespace hapticd::haptic
