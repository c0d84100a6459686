// haptic-device: a simulated stylus held by a simulated hand, or a simulated glove on a simulated
// hand. It opens a session with hapticd, runs the servo loop (clients/sim/servo_loop.hpp) along a
// trajectory at the session rate, lets the returned forces act on the simulated tip or fingers, and
// reports round trips, late and lost replies, force, the energy the rendering put into the device,
// how far the hand pushed past the surface and, for the glove, the same per finger.

#include <CLI/CLI.hpp>
#include <atomic>
#include <chrono>
#include <cmath>
#include <csignal>
#include <cstdio>
#include <fstream>
#include <nlohmann/json.hpp>
#include <numbers>
#include <optional>
#include <spdlog/sinks/stdout_sinks.h>
#include <spdlog/spdlog.h>
#include <string>
#include <tuple>
#include <vector>

#include "clients/cpp/client.hpp"
#include "clients/sim/glove_servo.hpp"
#include "clients/sim/glove_simulation.hpp"
#include "clients/sim/glove_trajectory.hpp"
#include "clients/sim/servo_loop.hpp"
#include "clients/sim/servo_report.hpp"
#include "clients/sim/trajectory.hpp"
#include "protocol/key_file.hpp"

namespace {

using namespace hapticd;

std::atomic<bool> g_stop{false};

void request_stop(int) { g_stop.store(true); }

struct HostPort {
  std::string host;
  std::uint16_t port = 0;
};

// "HOST:PORT" or "[IPv6]:PORT"; throws CLI::ValidationError with what was expected.
HostPort parse_server(const std::string& text) {
  const auto fail = [&] {
    throw CLI::ValidationError("--server",
                               "expected HOST:PORT with PORT in 1..65535 (e.g. 127.0.0.1:7000), got '" + text + "'");
  };
  const auto colon = text.rfind(':');
  if (colon == std::string::npos || colon == 0 || colon + 1 == text.size()) fail();
  HostPort hp;
  hp.host = text.substr(0, colon);
  if (hp.host.front() == '[') {
    if (hp.host.size() < 3 || hp.host.back() != ']') fail();
    hp.host = hp.host.substr(1, hp.host.size() - 2);
  } else if (hp.host.find(':') != std::string::npos) {
    fail();  // an IPv6 address needs brackets, or the port is ambiguous
  }
  const std::string port = text.substr(colon + 1);
  if (port.size() > 5 || port.find_first_not_of("0123456789") != std::string::npos) fail();
  const unsigned long value = std::stoul(port);
  if (value == 0 || value > 65535) fail();
  hp.port = static_cast<std::uint16_t>(value);
  return hp;
}

std::string quoted_command_line(int argc, char** argv) {
  std::string line;
  for (int i = 0; i < argc; ++i) {
    std::string arg = argv[i];
    if (arg.empty() || arg.find_first_of(" \t\"'\\$") != std::string::npos) {
      std::string q = "'";
      for (char c : arg) q += c == '\'' ? std::string("'\\''") : std::string(1, c);
      arg = q + "'";
    }
    line += (i ? " " : "") + arg;
  }
  return line;
}

void write_stylus_trace(std::ofstream& trace, const std::vector<sim::TraceRow>& rows) {
  trace << "t_s,pc_x_m,pc_y_m,pc_z_m,p_x_m,p_y_m,p_z_m,v_x_m_s,v_y_m_s,v_z_m_s,f_x_n,f_y_n,f_z_n,in_contact,sent\n";
  trace.precision(9);
  for (const sim::TraceRow& t : rows)
    trace << t.t_s << ',' << t.p_DC_m.x << ',' << t.p_DC_m.y << ',' << t.p_DC_m.z << ',' << t.p_DT_m.x << ','
          << t.p_DT_m.y << ',' << t.p_DT_m.z << ',' << t.v_DT_m_s.x << ',' << t.v_DT_m_s.y << ',' << t.v_DT_m_s.z << ','
          << t.f_DT_N.x << ',' << t.f_DT_N.y << ',' << t.f_DT_N.z << ',' << t.in_contact << ',' << t.sent << '\n';
}

// t_s, the 20 commanded angles (qc_<column>_deg), the 20 angles (q_<column>_deg), commanded and actual
// palm position, each frame's force, in_contact, sent.
void write_glove_trace(std::ofstream& trace, const std::vector<sim::GloveTraceRow>& rows, int frames) {
  constexpr double kDegPerRad = 180.0 / std::numbers::pi;
  trace << "t_s";
  for (const char* prefix : {"qc_", "q_"})
    for (int c = 1; c <= hand::kHandJointDofs; ++c) trace << ',' << prefix << sim::glove_csv_column_name(c);
  trace << ",pc_palm_x_m,pc_palm_y_m,pc_palm_z_m,p_palm_x_m,p_palm_y_m,p_palm_z_m";
  for (int id = 0; id < frames; ++id)
    for (const char* axis : {"x", "y", "z"}) trace << ",f_" << sim::glove_frame_name(frames, id) << '_' << axis << "_n";
  trace << ",in_contact,sent\n";
  trace.precision(9);
  for (const sim::GloveTraceRow& t : rows) {
    trace << t.t_s;
    for (int j = 0; j < hand::kHandJointDofs; ++j) trace << ',' << kDegPerRad * t.q_C_rad[j];
    for (int j = 0; j < hand::kHandJointDofs; ++j) trace << ',' << kDegPerRad * t.q_rad[j];
    for (const sim::Vec3d& p : {t.p_palm_C_m, t.p_palm_m}) trace << ',' << p.x << ',' << p.y << ',' << p.z;
    for (int id = 0; id < frames; ++id) {
      const sim::Vec3d& f = t.f_N[static_cast<std::size_t>(id)];
      trace << ',' << f.x << ',' << f.y << ',' << f.z;
    }
    trace << ',' << t.in_contact << ',' << t.sent << '\n';
  }
}

nlohmann::json to_json(const sim::DeviceParams& p) {
  return {{"mass_kg", p.mass_kg},
          {"arm_stiffness_n_per_m", p.arm_stiffness_n_per_m},
          {"arm_damping_n_s_per_m", p.arm_damping_n_s_per_m},
          {"device_damping_n_s_per_m", p.device_damping_n_s_per_m}};
}

nlohmann::json to_json(const sim::GloveParams& p) {
  static constexpr const char* kJoints[4] = {"abduction", "flexion1", "flexion2", "flexion3"};
  nlohmann::json joints = nlohmann::json::object();
  for (int k = 0; k < 4; ++k)
    joints[kJoints[k]] = {{"inertia_kg_m2", p.joint[k].inertia_kg_m2},
                          {"stiffness_n_m_per_rad", p.joint[k].stiffness_n_m_per_rad},
                          {"damping_n_m_s_per_rad", p.joint[k].damping_n_m_s_per_rad}};
  return {{"joints", joints}, {"palm", to_json(p.palm)}};
}

}  // namespace

int main(int argc, char** argv) {
  // Diagnostics through spdlog to stderr as "haptic-device: <text>"; stdout keeps what scripts read.
  spdlog::set_default_logger(spdlog::stderr_logger_mt("haptic-device"));
  spdlog::set_pattern("%n: %v");
  CLI::App app{
      "haptic-device: a simulated stylus (tip mass, damping and the user's arm impedance) or glove (the user's "
      "fingers on the standard hand skeleton, each joint an impedance about the commanded posture) streaming poses "
      "to hapticd and feeling its forces"};
  std::string server_text;
  std::string device = "stylus";
  std::string trajectory_spec;
  int frames = sim::kGloveFramesAll;
  std::string hand = "right";
  unsigned rate_hz = 1000;
  double duration_s = 10.0;
  std::string report_path;
  std::string trace_path;
  std::vector<double> origin{0.0, 0.0, 0.0};
  std::string client_name = "haptic-device";
  std::string frame_name = "stylus";
  double handshake_timeout_s = 2.0;
  std::string key_path;
  sim::DeviceParams params;  // the stylus's tip, or the glove's palm
  const sim::DeviceParams palm_defaults = sim::GloveParams{}.palm;

  app.add_option("--server", server_text, "hapticd address HOST:PORT")->required();
  app.add_option("--device", device, "simulated device")
      ->check(CLI::IsMember({"stylus", "glove"}))
      ->capture_default_str();
  auto* frames_option =
      app.add_option("--frames", frames, "glove: tracked frames, 16 (palm + 15 phalanges) or 6 (palm + fingertips)")
          ->check(CLI::IsMember({sim::kGloveFramesAll, sim::kGloveFramesTips}))
          ->capture_default_str();
  auto* hand_option = app.add_option("--hand", hand, "glove: which hand")
                          ->check(CLI::IsMember({"left", "right"}))
                          ->capture_default_str();
  app.add_option("--trajectory", trajectory_spec,
                 "stylus: press (default) | stroke | press-stroke | tap | circle | CSV file (t_s,x_m,y_m,z_m); glove: "
                 "grasp (default) | pinch | release | fist | spread | tap | CSV file (t_s, 20 joint angles in degrees "
                 "[, palm x,y,z in m])");
  app.add_option("--rate", rate_hz, "servo rate requested, Hz (the server may grant another)")
      ->check(CLI::Range(10u, 10000u))
      ->capture_default_str();
  app.add_option("--duration", duration_s, "run length, s")->check(CLI::Range(0.001, 86400.0))->capture_default_str();
  app.add_option("--report", report_path, "write the run's figures as JSON to this file");
  app.add_option("--trace", trace_path,
                 "write one CSV row per tick: stylus: t_s, commanded x y z, tip x y z, tip velocity, force, contact, "
                 "sent; glove: t_s, commanded and actual joint angles, commanded and actual palm, each frame's force, "
                 "contact, sent");
  app.add_option("--origin", origin, "trajectory origin (stylus tip, glove palm) x,y,z in the device frame, m")
      ->delimiter(',')
      ->expected(3)
      ->check(CLI::Range(-10.0, 10.0));
  app.add_option("--name", client_name, "client name sent in the Hello (1..64 printable bytes)")->capture_default_str();
  auto* frame_name_option = app.add_option("--frame-name", frame_name,
                                           "stylus: name of the tracked frame in the Hello (1..31 printable bytes)")
                                ->capture_default_str();
  app.add_option("--key-file", key_path,
                 "the server's pre-shared key file (hapticd --key-file): authenticate the session");
  app.add_option("--handshake-timeout", handshake_timeout_s, "seconds to wait for the Welcome")
      ->check(CLI::Range(0.01, 60.0))
      ->capture_default_str();
  auto* mass_option = app.add_option("--mass", params.mass_kg,
                                     "effective tip mass (stylus, default 0.1) or palm mass (glove, default 0.4), kg")
                          ->check(CLI::Range(1e-4, 100.0));
  auto* stiffness_option = app.add_option("--arm-stiffness", params.arm_stiffness_n_per_m,
                                          "user's arm stiffness toward the trajectory (tip or palm), N/m (default 200)")
                               ->check(CLI::Range(0.0, 1e5));
  auto* damping_option = app.add_option("--arm-damping", params.arm_damping_n_s_per_m,
                                        "user's arm damping, N s/m (stylus default 5, glove 10)")
                             ->check(CLI::Range(0.0, 1e4));
  auto* device_damping_option = app.add_option("--device-damping", params.device_damping_n_s_per_m,
                                               "device linkage damping, N s/m (stylus default 0.2, glove 0)")
                                    ->check(CLI::Range(0.0, 1e4));
  double watchdog_hold_ms = 20.0, watchdog_ramp_ms = 50.0;
  app.add_option("--silence-hold-ms", watchdog_hold_ms,
                 "no reply for this long and the held force fades out (a stalled or dead server), ms")
      ->check(CLI::Range(1.0, 10000.0))
      ->capture_default_str();
  app.add_option("--silence-ramp-ms", watchdog_ramp_ms,
                 "the fade to zero, and back when replies resume, ms (0: at once)")
      ->check(CLI::Range(0.0, 10000.0))
      ->capture_default_str();
  CLI11_PARSE(app, argc, argv);

  const bool glove = device == "glove";
  HostPort server;
  std::optional<sim::Trajectory> trajectory;
  std::optional<sim::GloveTrajectory> glove_trajectory;
  protocol::Hello hello;
  try {
    server = parse_server(server_text);
    if (glove) {
      if (frame_name_option->count() > 0)
        throw CLI::ValidationError("--frame-name",
                                   "is for --device stylus (a glove's frames are named by the skeleton)");
      // The palm's defaults where the stylus's flags were not given.
      if (mass_option->count() == 0) params.mass_kg = palm_defaults.mass_kg;
      if (stiffness_option->count() == 0) params.arm_stiffness_n_per_m = palm_defaults.arm_stiffness_n_per_m;
      if (damping_option->count() == 0) params.arm_damping_n_s_per_m = palm_defaults.arm_damping_n_s_per_m;
      if (device_damping_option->count() == 0) params.device_damping_n_s_per_m = palm_defaults.device_damping_n_s_per_m;
      try {
        // The Hello names the hand, so hapticd binds the glove to a device on a hand of that side.
        hello = sim::glove_hello(frames, client_name, rate_hz,
                                 hand == "left" ? protocol::Hand::kLeft : protocol::Hand::kRight);
      } catch (const std::invalid_argument& e) {
        throw CLI::ValidationError("--name", e.what());
      }
      if (trajectory_spec.empty()) trajectory_spec = "grasp";
      glove_trajectory = sim::GloveTrajectory::parse(trajectory_spec, {origin[0], origin[1], origin[2]});
    } else {
      for (const auto* option : {frames_option, hand_option})
        if (option->count() > 0) throw CLI::ValidationError(option->get_name(), "is for --device glove");
      if (trajectory_spec.empty()) trajectory_spec = "press";
      trajectory = sim::Trajectory::parse(trajectory_spec, {origin[0], origin[1], origin[2]});
      hello.device_kind = protocol::DeviceKind::kStylus;
      hello.requested_rate_hz = rate_hz;
      protocol::TrackedFrame frame;
      frame.id = 0;
      frame.dof = 6;  // a Phantom-class stylus senses position and orientation; the tip sends identity
      if (!hello.client_name.assign(client_name) || !frame.name.assign(frame_name))
        throw CLI::ValidationError("--name/--frame-name", "too long (client name <= 64, frame name <= 31 bytes)");
      hello.frames.push_back(frame);
      if (const protocol::RejectReason r = protocol::validate(hello); r != protocol::RejectReason::kNone)
        throw CLI::ValidationError("--name/--frame-name",
                                   "the Hello would be refused: " + std::string(protocol::to_string(r)));
    }
  } catch (const CLI::ValidationError& e) {
    spdlog::error(e.what());
    return 2;
  } catch (const std::exception& e) {
    spdlog::error("--trajectory: {}", e.what());
    return 2;
  }
  // Opened now, so a bad path fails before the run rather than after it.
  std::ofstream report, trace;
  for (auto [stream, path, flag] : {std::tuple{&report, &report_path, "--report"}, {&trace, &trace_path, "--trace"}}) {
    if (path->empty()) continue;
    stream->open(*path);
    if (!*stream) {
      spdlog::error("{}: cannot write '{}'", flag, *path);
      return 2;
    }
  }

  client::Client client;
  if (!key_path.empty()) {
    try {
      client.set_key(protocol::load_key_file(key_path));
    } catch (const std::exception& e) {
      spdlog::error("--key-file {}", e.what());
      return 2;
    }
  }
  protocol::Welcome welcome;
  try {
    welcome = client.connect(server.host, server.port, hello,
                             std::chrono::nanoseconds(static_cast<std::int64_t>(handshake_timeout_s * 1e9)));
  } catch (const client::ClientError& e) {
    spdlog::error(e.what());
    return 1;
  }
  if (welcome.rate_hz != rate_hz)
    spdlog::warn("asked for {} Hz, the server granted {} Hz: running at {} Hz", rate_hz, welcome.rate_hz,
                 welcome.rate_hz);

  std::signal(SIGINT, request_stop);
  std::signal(SIGTERM, request_stop);
  sim::ServoConfig config;
  config.rate_hz = welcome.rate_hz;
  config.duration_s = duration_s;
  config.device = params;
  config.frame_id = hello.frames[0].id;
  config.stop = &g_stop;
  config.watchdog.hold = std::chrono::microseconds(std::llround(1e3 * watchdog_hold_ms));
  config.watchdog.ramp = std::chrono::microseconds(std::llround(1e3 * watchdog_ramp_ms));
  std::vector<sim::TraceRow> rows;
  std::vector<sim::GloveTraceRow> glove_rows;
  std::optional<sim::GloveSimulation> glove_sim;
  sim::ServoResult result;
  if (glove) {
    sim::GloveParams glove_params;
    glove_params.palm = params;
    glove_sim.emplace(*glove_trajectory, glove_params, frames, hand == "left", sim::servo_period_s(config.rate_hz));
    sim::GloveServo servo(*glove_sim, trace.is_open() ? &glove_rows : nullptr);
    result = sim::run_servo_loop(client, servo, config);
  } else {
    if (trace.is_open()) config.trace = &rows;
    result = sim::run_servo_loop(client, *trajectory, config);
  }
  const std::string& trajectory_name = glove ? glove_trajectory->name() : trajectory->name();

  nlohmann::json server_stats = nullptr;
  try {
    server_stats = sim::to_json(client.request_stats(std::chrono::milliseconds(200)));
  } catch (const client::ClientError& e) {
    spdlog::warn("no server stats: {}", e.what());
  }
  // Datagrams still on their way (a relay's copy of the Stats reply, a late ForceSample) are read
  // until 50 ms pass quietly, so the client's counters cover everything the server or a relay sent.
  while (client.poll_force(std::chrono::milliseconds(50))) {
  }
  result.counters = client.counters();
  client.bye();

  const sim::RttSummary rtt = sim::summarize_rtt(result.rtt_us);
  const std::string what = glove ? "glove (" + std::to_string(frames) + " frames, " + hand + " hand)" : device;
  std::printf("haptic-device: %s, trajectory %s, %.2f s at %u Hz against %s (session %llu)%s\n", what.c_str(),
              trajectory_name.c_str(), result.elapsed_s, welcome.rate_hz, client.server_address().c_str(),
              static_cast<unsigned long long>(welcome.session_id), g_stop.load() ? ", stopped early" : "");
  std::printf(
      "  sent %llu, replies %llu, late %llu (%.3f %%), lost %llu (%.3f %%), missed ticks %llu, %.1f Hz achieved\n",
      static_cast<unsigned long long>(result.samples_sent), static_cast<unsigned long long>(result.replies),
      static_cast<unsigned long long>(result.late), 100.0 * result.late_fraction(),
      static_cast<unsigned long long>(result.lost), 100.0 * result.loss_fraction(),
      static_cast<unsigned long long>(result.missed_ticks), result.rate_hz_achieved);
  std::printf("  rtt us: p50 %.1f  p90 %.1f  p99 %.1f  p99.9 %.1f  max %.1f\n", rtt.p50_us, rtt.p90_us, rtt.p99_us,
              rtt.p999_us, rtt.max_us);
  std::printf(
      "  force N: max %.3f rms %.3f; contact %.1f %% of ticks; penetration max %.2f mm; passivity energy %.4g J\n",
      result.force_max_n, result.force_rms_n, 100.0 * result.contact_fraction(), 1e3 * result.penetration_max_m,
      result.passivity_energy_j);
  if (glove) {
    for (int g = 0; g <= sim::kPalmGroup; ++g) {
      const sim::GloveGroupFigures f = glove_sim->group_figures(g);
      std::printf("  %-6s force N: max %.3f rms %.3f; contact %.1f %% of ticks",
                  g < hand::kHandFingers ? hand::finger_name(g) : "palm", f.force_max_n, f.force_rms_n,
                  100.0 * f.contact_fraction);
      if (g < hand::kHandFingers)
        std::printf("; joint lag max %.2f deg", f.joint_lag_max_rad * 180.0 / std::numbers::pi);
      std::printf("\n");
    }
  }

  if (trace.is_open()) {
    if (glove) {
      write_glove_trace(trace, glove_rows, frames);
    } else {
      write_stylus_trace(trace, rows);
    }
    if (!trace.flush()) {
      spdlog::error("--trace: failed writing '{}'", trace_path);
      return 1;
    }
    std::printf("  trace: %s (%zu ticks)\n", trace_path.c_str(), glove ? glove_rows.size() : rows.size());
  }
  if (report.is_open()) {
    nlohmann::json doc = sim::to_json(result);
    doc["server"] = client.server_address();
    doc["command_line"] = quoted_command_line(argc, argv);
    doc["device"] = device;
    doc["trajectory"] = trajectory_name;
    doc["origin_m"] = origin;
    doc["rate_hz_requested"] = rate_hz;
    doc["rate_hz"] = welcome.rate_hz;
    doc["duration_s"] = duration_s;
    doc["session_id"] = welcome.session_id;
    doc["authenticated"] = client.authenticating();
    doc["welcome"] = {{"force_limit_n", welcome.force_limit_n},
                      {"torque_limit_nm", welcome.torque_limit_nm},
                      {"max_force_rate_n_per_s", welcome.max_force_rate_n_per_s}};
    if (glove) {
      const nlohmann::json figures = sim::glove_figures_to_json(*glove_sim);
      doc["fingers"] = figures["fingers"];
      doc["palm"] = figures["palm"];
      doc["frames"] = frames;
      doc["hand"] = hand;
      doc["glove_model"] = to_json(glove_sim->params());
    } else {
      doc["device_model"] = to_json(params);
    }
    doc["server_stats"] = server_stats;
    doc["stopped_early"] = g_stop.load();
    report << doc.dump(2) << "\n";
    if (!report.flush()) {
      spdlog::error("--report: failed writing '{}'", report_path);
      return 1;
    }
    std::printf("  report: %s\n", report_path.c_str());
  }
  return 0;
}
