// hapticd: the haptic rendering server. Loads a scene, builds its world, and
// runs the visual loop and the haptic loop (UDP) until --duration ends or
// SIGINT / SIGTERM arrives; then writes --stats.
#include <pthread.h>
#include <spdlog/sinks/stdout_sinks.h>
#include <spdlog/spdlog.h>
#include <sys/mman.h>

#include <CLI/CLI.hpp>
#include <atomic>
#include <chrono>
#include <csignal>
#include <cstdio>
#include <fstream>
#include <nlohmann/json.hpp>
#include <thread>

#include "protocol/clock.hpp"
#include "protocol/key_file.hpp"
#include "server/haptic/haptic_server.hpp"
#include "server/haptic/visual_loop.hpp"
#include "server/process_heap.hpp"
#include "server/world/scene_loader.hpp"
#include "server/world/world.hpp"

namespace haptic = hapticd::haptic;
namespace protocol = hapticd::protocol;
namespace world = hapticd::world;

namespace {

std::atomic<bool> g_stop{false};
void on_signal(int) { g_stop.store(true); }

// Diagnostics go to stderr through spdlog's default logger as "hapticd: <text>", filtered by
// --log-level; stdout carries only what scripts read (the listening line, --generate-key's result).
// The haptic thread never logs; the visual loop's fault callback does (the logger is thread-safe).
void init_logger(const std::string& level) {
  auto logger = spdlog::stderr_logger_mt("hapticd");
  logger->set_pattern("%n: %v");
  using spdlog::level::level_enum;
  logger->set_level(level == "error"  ? level_enum::err
                    : level == "warn" ? level_enum::warn
                    : level == "debug" ? level_enum::debug
                                       : level_enum::info);
  logger->flush_on(spdlog::level::debug);
  spdlog::set_default_logger(std::move(logger));
}

nlohmann::json histogram_json(const haptic::MicrosecondHistogram& h) {
  return {{"p50", h.percentile(50)}, {"p99", h.percentile(99)}, {"p999", h.percentile(99.9)},
          {"max", h.max_us()},       {"count", h.count()}};
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"hapticd: real-time haptic rendering server (UDP, FlatBuffers)"};
  std::string scene_path = std::string(HAPTICD_SCENES_DIR) + "/stylus_bunny.json";
  haptic::ServerOptions options;
  double visual_rate = 60, duration = 0;
  std::string stats_path, level = "info", key_path, generate_key_path;
  app.add_option("--scene", scene_path, "scene file (default: the stylus, bunny and blocks scene)")
      ->check(CLI::ExistingFile);
  app.add_option("--bind", options.bind,
                 "address to listen on (default 127.0.0.1); an address other than loopback needs --key-file or "
                 "--insecure-bind");
  app.add_option("--key-file", key_path,
                 "pre-shared key (one line of 64 hex digits, mode 600): every session is authenticated and every "
                 "datagram carries a MAC; clients need the same file");
  app.add_option("--generate-key", generate_key_path, "write a new random key file (mode 600) and exit");
  app.add_flag("--insecure-bind", options.insecure_bind,
               "allow --bind to a non-loopback address without --key-file (anyone who reaches it can drive the "
               "device)");
  app.add_option("--port", options.port, "UDP port; 0 picks a free one and prints it")->check(CLI::Range(0, 65535));
  app.add_option("--haptic-rate", options.haptic_rate_hz, "haptic loop rate, Hz (default 1000)")
      ->check(CLI::Range(100.0, 10000.0));
  app.add_option("--visual-rate", visual_rate, "visual loop rate, Hz (default 60)")->check(CLI::Range(1.0, 1000.0));
  app.add_option("--duration", duration, "seconds to run; 0 runs until SIGINT / SIGTERM")
      ->check(CLI::Range(0.0, 1e7));
  app.add_option("--stats", stats_path, "write the run's statistics as JSON to this file on exit");
  app.add_option("--log-level", level, "error | warn | info | debug")
      ->check(CLI::IsMember({"error", "warn", "info", "debug"}));
  app.add_flag("--no-passivity-control", [&options](std::int64_t) { options.passivity_control = false; },
               "switch off the passivity controller of every device (on by default: it damps a device's frame "
               "once the rendering has given it more than its share of 0.1 mJ a device)");
  app.add_option("--tick-contact-sweeps", options.tick_contact_sweeps,
                 "the haptic tick's contact solve: at most this many Gauss-Seidel sweeps before it keeps its answer "
                 "(default 8; fewer cost less, more rarely change the force)")
      ->check(CLI::Range(1, haptic::kMaxTickContactSweeps));
  app.add_flag("--busy-poll", options.busy_poll, "spin on the socket instead of sleeping (for a dedicated core)");
  app.add_option("--session-timeout", options.session_timeout_s, "drop a silent session after this many seconds")
      ->check(CLI::Range(0.2, 3600.0));
  app.add_option("--model-stale-after", options.model_stale_after_s,
                 "seconds a hand's model may be overdue (the visual loop stalled) before it fades to the safe "
                 "model: the hand's dynamics go, the surfaces it touched stay for --model-contacts-hold (default 0.1)")
      ->check(CLI::Range(0.001, 10.0));
  app.add_option("--model-fade", options.model_fade_s, "seconds that fade takes, and the recovery (default 0.1)")
      ->check(CLI::Range(0.0, 10.0));
  app.add_option("--model-contacts-hold", options.model_contacts_hold_s,
                 "seconds the device still feels a faded model's surfaces (the objects the world last found) "
                 "before they fade out of the force too (default 0.5)")
      ->check(CLI::Range(0.0, 60.0));
  app.add_option("--source-rate", options.source_rate_hz,
                 "datagrams a second allowed per source address and port; 0: 4x the haptic rate (default)")
      ->check(CLI::Range(0.0, 1e7));
  app.add_option("--source-burst", options.source_burst, "datagrams a source may send at once (default 200)")
      ->check(CLI::Range(1.0, 1e6));
  CLI11_PARSE(app, argc, argv);
  init_logger(level);

  if (!generate_key_path.empty()) {
    try {
      const protocol::Key key = protocol::generate_key_file(generate_key_path);
      std::printf("hapticd: wrote a new key to %s (fingerprint %s); give it to hapticd and its clients\n",
                  generate_key_path.c_str(), protocol::key_fingerprint(key).c_str());
      return 0;
    } catch (const std::exception& e) {
      spdlog::error(std::string("--generate-key ") + e.what());
      return 1;
    }
  }
  if (!key_path.empty()) {
    try {
      options.key = protocol::load_key_file(key_path);
    } catch (const std::exception& e) {
      spdlog::error(std::string("--key-file ") + e.what());
      return 1;
    }
  }

  try {
    haptic::HapticServer::check_bind(options);  // before the scene: a refused address fails at once
    world::SceneDesc scene = world::load_scene(scene_path);
    scene.visual_rate_hz = visual_rate;
    scene.dt_s = 1.0 / visual_rate;
    if (scene.devices.empty()) throw std::runtime_error(scene_path + ": devices: the scene names no device to serve");
    world::World world(scene, haptic::served_world_options());
    if (world.num_hands() > haptic::kMaxHands)
      throw std::runtime_error("hands: at most " + std::to_string(haptic::kMaxHands));
    std::vector<haptic::DeviceLink> links;
    for (const world::DeviceDesc& d : scene.devices)
      links.push_back(haptic::make_device_link(world, d, options.haptic_rate_hz));
    if (!hapticd::process::keep_large_allocations_on_heap())
      spdlog::warn("the allocator refused the heap settings (a sanitizer's does): the visual step's large blocks are mapped anew each step");
    // Lock memory so a page fault never stalls the haptic thread (needs CAP_IPC_LOCK).
    if (mlockall(MCL_CURRENT | MCL_FUTURE) != 0)
      spdlog::warn("memory not locked (mlockall not permitted): page faults may delay the haptic loop");

    auto snapshots = std::make_unique<haptic::TripleBuffer<haptic::HapticSnapshot>>();
    auto targets = std::make_unique<haptic::TripleBuffer<haptic::ProxyTargets>>();
    haptic::VisualReport visual_report;
    haptic::HapticServer server(links, options, *snapshots, *targets, &visual_report);
    const haptic::TickSolverPreparer preparer(links, server.haptic_period_s());
    haptic::VisualStep step(world, *snapshots, *targets, &preparer);
    // The first models before the first packet.
    step.build_models(protocol::now_ns(), 1.0 / visual_rate);
    step.prepare_tick_solvers();
    step.publish();
    haptic::VisualLoop visual(step, visual_rate, &visual_report, [](const std::string& what) {
      spdlog::error("visual step failed (" + what + "): hands reset, models held until a step succeeds");
    });
    std::signal(SIGINT, on_signal);
    std::signal(SIGTERM, on_signal);
    std::atomic<bool> stop_loops{false};
    std::thread visual_thread([&] { visual.run(stop_loops); });
    std::thread haptic_thread([&] { server.run(stop_loops); });
    // Named for top -H and for the tests that find a loop's thread (press_hold_lift_busy.sh's stall).
    pthread_setname_np(visual_thread.native_handle(), "hapticd-visual");
    pthread_setname_np(haptic_thread.native_handle(), "hapticd-haptic");
    std::printf("hapticd listening on %s:%u\n", server.address().c_str(), static_cast<unsigned>(server.port()));
    std::fflush(stdout);
    if (options.key) {
      spdlog::info("sessions authenticated with the key of " + key_path + " (fingerprint " +
                           protocol::key_fingerprint(*options.key) + ")");
    } else if (options.insecure_bind && !boost::asio::ip::make_address(server.address()).is_loopback()) {
      spdlog::warn("no --key-file and --insecure-bind: sessions are NOT authenticated on " + server.address() +
                           "; anyone who can reach this port can drive the device");
    } else {
      spdlog::info("no --key-file: sessions are not authenticated; listening on loopback only");
    }
    spdlog::info("scene " + scene.name + ": " + std::to_string(world.num_hands()) + " hand(s), " +
                         std::to_string(links.size()) + " device(s); haptic " +
                         std::to_string(static_cast<int>(options.haptic_rate_hz)) + " Hz, visual " +
                         std::to_string(static_cast<int>(visual_rate)) + " Hz");
    const auto start = std::chrono::steady_clock::now();
    while (!g_stop.load()) {
      std::this_thread::sleep_for(std::chrono::milliseconds(20));
      if (duration > 0 && std::chrono::steady_clock::now() - start >= std::chrono::duration<double>(duration)) break;
    }
    stop_loops.store(true);
    haptic_thread.join();
    visual_thread.join();
    const haptic::ServerStats& st = server.stats();
    const haptic::VisualStats& vs = visual.stats();
    if (!st.realtime && !options.busy_poll)
      spdlog::warn("haptic thread ran without real-time priority (SCHED_FIFO not permitted)");
    nlohmann::json rejected = nlohmann::json::object();
    for (std::size_t i = 0; i < protocol::kRejectReasonCount; ++i)
      if (st.rejected[i]) rejected[std::string(to_string(static_cast<protocol::RejectReason>(i)))] = st.rejected[i];
    nlohmann::json doc = {
        {"scene", scene.name},
        {"elapsed_s", st.elapsed_s},
        {"haptic",
         {{"rate_hz_configured", options.haptic_rate_hz},
          {"rate_hz_achieved", st.elapsed_s > 0 ? static_cast<double>(st.ticks) / st.elapsed_s : 0.0},
          {"ticks", st.ticks},
          {"overruns", st.overruns},
          {"tick_compute_us", histogram_json(st.tick_compute_us)},
          {"tick_jitter_us", histogram_json(st.tick_jitter_us)},
          {"reply_compute_us", histogram_json(st.reply_compute_us)},
          {"realtime", st.realtime},
          {"busy_poll", options.busy_poll},
          {"cpu_s", st.cpu_s},
          {"solver_fallbacks", st.solver_fallbacks},
          {"solver_refinements", st.solver_refinements},
          {"lookahead_fallbacks", st.lookahead_fallbacks},
          {"contact_holds", st.contact_holds},
          {"contact_unconverged", st.contact_unconverged},
          {"contact_solves", st.contact_solves},
          {"contact_sweeps", st.contact_sweeps},
          {"overdue_device_ticks", st.overdue_device_ticks},
          {"bridged_gaps", st.bridged_gaps},
          {"catch_up_ticks", st.catch_up_ticks},
          {"model_watchdog",
           {{"stale_after_s", options.model_stale_after_s},
            {"fade_s", options.model_fade_s},
            {"contacts_hold_s", options.model_contacts_hold_s},
            {"stale_models", st.stale_models},
            {"stale_model_ticks", st.stale_model_ticks},
            {"overdue_max_s", st.model_overdue_max_s}}}}},
        {"visual",
         {{"rate_hz_configured", visual_rate},
          {"rate_hz_achieved", vs.elapsed_s > 0 ? static_cast<double>(vs.steps) / vs.elapsed_s : 0.0},
          {"steps", vs.steps},
          {"late_steps", vs.late_steps},
          {"stiffness_made_passive", preparer.stiffness_made_passive()},
          {"stiffness_removed_max", preparer.stiffness_removed_max()},
          {"step_ms_median", 1e-3 * vs.step_us.percentile(50)},
          {"step_ms_p99", 1e-3 * vs.step_us.percentile(99)},
          {"world_step_ms_median", 1e-3 * vs.world_us.percentile(50)},
          {"model_ms_median", 1e-3 * vs.model_us.percentile(50)},
          {"hand_resets", vs.resets},
          {"faults", vs.faults},
          {"body_resets", vs.body_resets},
          {"ode_messages", world::ode_messages()}}},
        {"packets",
         {{"in", st.packets_in},
          {"out", st.packets_out},
          {"dropped", st.packets_dropped},
          {"rejected", rejected},
          {"unknown_session", st.unknown_session},
          {"wrong_peer", st.wrong_peer},
          {"duplicates", st.duplicates},
          {"stale", st.stale},
          {"gaps", st.gaps},
          {"frames_lost", st.frames_lost},
          {"authenticated", options.key.has_value()},
          {"send_errors", st.send_errors},
          {"rate_limited", st.rate_limited},
          {"rate_sources_evicted", st.rate_sources_evicted},
          {"source_rate_hz", options.source_rate_hz > 0 ? options.source_rate_hz : 4.0 * options.haptic_rate_hz},
          {"source_burst", options.source_burst},
          {"receive_buffer_bytes", st.receive_buffer_bytes}}},
        {"replies", st.replies},
        {"clamps", st.clamps},
        {"proxy_resets", st.resets},
        {"resyncs", st.resyncs},
        {"sessions",
         {{"opened", st.sessions_opened},
          {"closed", st.sessions_closed},
          {"timed_out", st.sessions_timed_out},
          {"replaced", st.sessions_replaced},
          {"pending_expired", st.pending_expired},
          {"max", haptic::kMaxSessions}}},
        {"memory",
         {{"session_bytes", haptic::HapticServer::session_bytes()}, {"server_bytes", server.memory_bytes()}}}};
    if (!stats_path.empty()) {
      std::ofstream out(stats_path);
      if (!out) throw std::runtime_error("--stats " + stats_path + ": cannot write");
      out << doc.dump(2) << "\n";
    }
    spdlog::info("stopped after " + std::to_string(st.elapsed_s) + " s: " + std::to_string(st.replies) +
                         " replies, " + std::to_string(st.overruns) + " overruns, visual " +
                         std::to_string(doc["visual"]["rate_hz_achieved"].get<double>()) + " Hz");
    return 0;
  } catch (const std::exception& e) {
    spdlog::error(e.what());
    return 1;
  }
}
