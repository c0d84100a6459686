#include "server/offline/offline_run.hpp"

#include <algorithm>
#include <boost/asio/ip/address_v4.hpp>
#include <chrono>
#include <cmath>
#include <stdexcept>
#include <utility>

#include "protocol/percentile.hpp"
#include "server/haptic/visual_loop.hpp"

namespace hapticd::offline {
namespace {

using Clock = std::chrono::steady_clock;

double elapsed_us(Clock::time_point from, Clock::time_point to) {
  return std::chrono::duration<double, std::micro>(to - from).count();
}

// The p-th percentile (0..100) by the one definition (protocol/percentile.hpp); 0 for an empty sample
// (no step timed), as OfflineTimings' defaults say.
double timing_percentile(const std::vector<double>& v, double p) { return v.empty() ? 0.0 : stats::percentile(v, p); }

Eigen::Vector3d to_eigen(sim::Vec3d v) { return {v.x, v.y, v.z}; }
sim::Vec3d to_sim(const Eigen::Vector3d& v) { return {v.x(), v.y(), v.z()}; }

}  // namespace

// The device's end of the wire: the core's replies land here, stamped with simulated time.
struct OfflineLoops::Wire final : haptic::Transport {
  bool send(std::span<const std::uint8_t> datagram, const haptic::Endpoint&) override {
    if (datagram.size() > sizeof(reply.bytes)) return false;
    std::copy(datagram.begin(), datagram.end(), reply.bytes.begin());
    reply_bytes = datagram.size();
    return true;
  }
  std::uint64_t send_time_ns() override { return now_ns; }
  protocol::ReceiveBuffer reply;
  std::size_t reply_bytes = 0;
  std::uint64_t now_ns = 0;
  protocol::ReceiveBuffer request;  // what the device sends, aligned as a socket's buffer
  const haptic::Endpoint device{boost::asio::ip::make_address_v4("127.0.0.1"), 40000};
};

OfflineLoops::OfflineLoops(world::SceneDesc scene, const OfflineOptions& options)
    : options_(options),
      snapshots_(std::make_unique<haptic::TripleBuffer<haptic::HapticSnapshot>>()),
      targets_(std::make_unique<haptic::TripleBuffer<haptic::ProxyTargets>>()),
      wire_(std::make_unique<Wire>()),
      pose_(std::make_unique<protocol::Message>()),
      received_(std::make_unique<protocol::Message>()),
      late_draws_(options.late_model_seed) {
  if (options_.visual_every_ticks < 1 || options_.model_delay_ticks < 0 ||
      options_.model_delay_ticks >= options_.visual_every_ticks || options_.late_model_max_ticks < 0 ||
      options_.model_delay_ticks + options_.late_model_max_ticks > options_.visual_every_ticks ||
      !(options_.haptic_period_s > 0))
    throw std::invalid_argument(
        "offline run: visual_every_ticks >= 1, 0 <= model_delay_ticks < visual_every_ticks, late_model_max_ticks >= 0 "
        "with model_delay_ticks + late_model_max_ticks <= visual_every_ticks, haptic_period_s > 0");
  for (const auto* windows : {&options_.withheld_samples_s, &options_.visual_stalls_s, &options_.haptic_stalls_s})
    for (const auto& [from, to] : *windows)
      if (!(std::isfinite(from) && std::isfinite(to) && from < to))
        throw std::invalid_argument(
            "offline run: a withheld-samples, visual-stall or haptic-stall window needs finite from < to");
  if (options_.device < 0 || options_.device >= static_cast<int>(scene.devices.size()))
    throw std::runtime_error(scene.name + ": no device " + std::to_string(options_.device) + " to serve");
  period_ns_ = static_cast<std::uint64_t>(std::llround(1e9 * options_.haptic_period_s));
  // As hapticd: the scene's step is the visual period.
  const double dt = options_.visual_every_ticks * options_.haptic_period_s;
  scene.dt_s = dt;
  scene.visual_rate_hz = 1.0 / dt;
  world::WorldOptions world_options = haptic::served_world_options();
  world_options.contact = options_.contact;
  if (options_.palm_hand_mass_scale) world_options.palm_hand_mass_scale = *options_.palm_hand_mass_scale;
  // CHOLMOD's OpenMP regions: one thread, as the visual thread runs it.
  hand::single_threaded_cholmod();
  world_ = std::make_unique<world::World>(scene, world_options);
  if (world::RigidWorld* rigid = world_->rigid())
    for (long i = 0; i < std::lround(options_.settle_s / options_.haptic_period_s); ++i)
      rigid->step(options_.haptic_period_s);
  link_ = haptic::make_device_link(*world_, scene.devices[options_.device], 1.0 / options_.haptic_period_s);
  haptic::ServerOptions server;  // hapticd's defaults at this haptic rate
  server.haptic_rate_hz = 1.0 / options_.haptic_period_s;
  server.passivity_control = options_.passivity_control;
  server.tick_contact_sweeps = options_.tick_contact_sweeps;
  core_ = std::make_unique<haptic::HapticCore>(std::vector<haptic::DeviceLink>{link_}, server, *snapshots_, *targets_,
                                               *wire_);
  preparer_ =
      std::make_unique<haptic::TickSolverPreparer>(std::vector<haptic::DeviceLink>{link_}, options_.haptic_period_s);
  visual_ = std::make_unique<haptic::VisualStep>(*world_, *snapshots_, *targets_, preparer_.get(), options_.model);
  const std::uint64_t t0 = now_ns();
  core_->start(t0);
  // The session, opened as a device opens it.
  protocol::Hello hello;
  hello.client_name.assign("lockstep");
  hello.device_kind = link_.kind;
  for (int j = 0; j < link_.handles; ++j) {
    protocol::TrackedFrame f;
    f.id = static_cast<std::uint16_t>(j);
    f.name.assign("frame" + std::to_string(j));
    hello.frames.push_back(f);
  }
  hello.requested_rate_hz = static_cast<std::uint32_t>(std::lround(server.haptic_rate_hz));
  wire_->now_ns = t0;
  send(encoder_.encode(hello));
  if (!protocol::decode({wire_->reply.bytes.data(), wire_->reply_bytes}, *received_).ok() ||
      received_->type != protocol::MessageType::kWelcome)
    throw std::runtime_error(scene.name + ": the haptic core refused the device's session" +
                             (received_->type == protocol::MessageType::kError
                                  ? " (" + std::string(received_->error.message.view()) + ")"
                                  : std::string()));
  session_ = received_->welcome.session_id;
  pose_->pose_sample.session_id = session_;
  const long expected_steps = 1024;
  haptic_us_.reserve(static_cast<std::size_t>(expected_steps * options_.visual_every_ticks));
  visual_ms_.reserve(static_cast<std::size_t>(expected_steps));
}

OfflineLoops::~OfflineLoops() = default;

// Simulated time starts at 1 s, so no time of the run is the core's "never" (0).
std::uint64_t OfflineLoops::now_ns() const { return tick_ns(ticks_); }
std::uint64_t OfflineLoops::tick_ns(long tick) const {
  return 1'000'000'000ull + static_cast<std::uint64_t>(tick) * period_ns_;
}

void OfflineLoops::send(const protocol::EncodeResult& encoded) {
  if (!encoded.ok())
    throw std::runtime_error("offline run: the device's message does not encode (" +
                             std::string(protocol::to_string(encoded.reason)) + ")");
  std::copy(encoded.bytes.begin(), encoded.bytes.end(), wire_->request.bytes.begin());
  wire_->reply_bytes = 0;
  core_->handle({wire_->request.bytes.data(), encoded.bytes.size()}, wire_->device, wire_->now_ns);
}

void OfflineLoops::frame_pose_at_handle(int j, Eigen::Vector3d& p_D, Eigen::Quaterniond& q_D) const {
  const hand::HandleState& h = world_->hand(link_.hand).handles()[static_cast<std::size_t>(j)];
  link_.map.to_device(j, {h.p_WH, h.q_WH}, p_D, q_D);
}

const haptic::ProxyHand& OfflineLoops::proxy() const { return *core_->proxy_of(session_); }

long OfflineLoops::resets() const { return proxy().resets() + world_->snapshot().resets; }

OfflineTimings OfflineLoops::timings() const {
  return {timing_percentile(haptic_us_, 50), timing_percentile(haptic_us_, 99), timing_percentile(visual_ms_, 50),
          timing_percentile(visual_ms_, 99), static_cast<long>(visual_ms_.size())};
}

void OfflineLoops::tick(const DeviceFrames& sample, DeviceReply& reply) {
  const std::uint64_t now = now_ns();
  const Clock::time_point c0 = Clock::now();
  const double t_s = time_s();
  const auto within = [t_s](const std::vector<std::pair<double, double>>& windows) {
    return std::any_of(windows.begin(), windows.end(),
                       [t_s](const auto& w) { return t_s >= w.first && t_s < w.second; });
  };
  const bool stalled = within(options_.visual_stalls_s);
  // The model of the last visual step reaches the haptic side `model_delay_ticks` after its step.
  if (pending_ && ticks_ >= publish_at_ && !stalled) visual_->publish(), pending_ = false;
  reply = DeviceReply{};
  const bool sent = ticks_ == 0 || !within(options_.withheld_samples_s);
  if (ticks_ > 0 && within(options_.haptic_stalls_s)) {
    // The haptic thread does not run: the sample waits in the socket, unanswered.
    if (sent) queued_.emplace_back(sample, ticks_);
  } else {
    // After a stall, as HapticServer::run: the samples that waited are read at once (a microsecond
    // apart) and each answered in turn before the late tick; the device applies the answer to its newest.
    for (std::size_t i = 0; i < queued_.size(); ++i)
      answer(queued_[i].first, queued_[i].second, now - 1000 * (queued_.size() - i), reply);
    queued_.clear();
    if (sent) answer(sample, ticks_, now, reply);
    // The haptic tick: the proxies integrated over [now, now + T] under the newest model.
    core_->tick(now);
    haptic_us_.push_back(elapsed_us(c0, Clock::now()));
  }
  if (ticks_ >= next_visual_tick_ && !stalled) {
    visual_step();
    next_visual_tick_ = ticks_ + options_.visual_every_ticks;
  }
  ++ticks_;
}

void OfflineLoops::answer(const DeviceFrames& sample, long tick, std::uint64_t read_ns, DeviceReply& reply) {
  // The device's sample, answered at once from the proxies (HapticCore::handle).
  protocol::PoseSample& p = pose_->pose_sample;
  p.sequence = static_cast<std::uint64_t>(tick) + 1;
  p.client_timestamp_ns = tick_ns(tick);
  p.poses.clear();
  for (int j = 0; j < sample.frames; ++j) {
    protocol::FramePose f;
    f.frame = static_cast<std::uint16_t>(j);
    const Eigen::Vector3d& x = sample.p_D[j];
    const Eigen::Quaterniond& q = sample.q_D[j];
    f.position_m = {static_cast<float>(x.x()), static_cast<float>(x.y()), static_cast<float>(x.z())};
    f.orientation = {static_cast<float>(q.w()), static_cast<float>(q.x()), static_cast<float>(q.y()),
                     static_cast<float>(q.z())};
    p.poses.push_back(f);
  }
  wire_->now_ns = read_ns;
  send(encoder_.encode(p));
  if (wire_->reply_bytes > 0 && protocol::decode({wire_->reply.bytes.data(), wire_->reply_bytes}, *received_).ok() &&
      received_->type == protocol::MessageType::kForceSample) {
    const protocol::ForceSample& f = received_->force_sample;
    reply.frames = static_cast<int>(f.wrenches.size());
    for (int j = 0; j < reply.frames; ++j) {
      const protocol::Wrench& w = f.wrenches[j].wrench;
      reply.wrench[j].f_D = {w.force_n.x, w.force_n.y, w.force_n.z};
      reply.wrench[j].tau_D = {w.torque_nm.x, w.torque_nm.y, w.torque_nm.z};
      reply.wrench[j].clamped = f.wrenches[j].flags & protocol::ForceFlags::kClamped;
      reply.in_contact[j] = f.wrenches[j].flags & protocol::ForceFlags::kInContact;
    }
  }
}

void OfflineLoops::visual_step() {
  const Clock::time_point c0 = Clock::now();
  // VisualLoop::run with a latency of model_delay_ticks: the world simulates up to the model's
  // publication, from proxies of the end of this tick (ProxyTargets::t_ns), and the model covers the
  // coming k T from then.
  const std::uint64_t latency_ns = static_cast<std::uint64_t>(options_.model_delay_ticks) * period_ns_;
  const std::uint64_t publish = now_ns() + period_ns_ + latency_ns;
  const double dt = options_.visual_every_ticks * options_.haptic_period_s;
  // After a stall (visual_stalls_s) the world's step spans the time since the last step, as
  // VisualLoop's does.
  const long since = ticks_ - next_visual_tick_ + options_.visual_every_ticks;
  visual_->advance_world(publish,
                         haptic::detail::world_step_for(static_cast<double>(since) * options_.haptic_period_s, dt, dt));
  visual_->build_models(options_.targets_one_tick_stale ? publish - period_ns_ : publish, dt);
  if (options_.model_stiffness_scale != 1.0)
    for (haptic::HapticModel& model : snapshots_->back().model) model.K *= options_.model_stiffness_scale;
  visual_->prepare_tick_solvers();
  pending_ = true;
  publish_at_ = ticks_ + options_.model_delay_ticks;
  if (options_.late_model_max_ticks > 0) {
    late_draws_ = late_draws_ * 6364136223846793005ull + 1442695040888963407ull;
    publish_at_ += static_cast<long>((late_draws_ >> 33) % static_cast<std::uint64_t>(options_.late_model_max_ticks));
  }
  visual_ms_.push_back(1e-3 * elapsed_us(c0, Clock::now()));
}

// --- Devices -------------------------------------------------------------------------------------

SimulatedStylus::SimulatedStylus(const Eigen::Vector3d& start_D, Command command, double period_s,
                                 const sim::DeviceParams& params)
    : start_D_(start_D), command_(std::move(command)), period_s_(period_s), params_(params) {
  state_.p_DT_m = to_sim(start_D_ + command_(0.0));
}

void SimulatedStylus::advance(long tick, double t_s, DeviceFrames& out) {
  t_ns_ = static_cast<std::uint64_t>(std::llround(1e9 * t_s));
  if (tick > 0) {
    constexpr double h = 1e-6;  // as sim::Trajectory::velocity
    const Eigen::Vector3d v_C = (command_(t_s + h) - command_(t_s - h)) / (2 * h);
    const Eigen::Vector3d f_D = watchdog_.scale(t_ns_) * f_D_;  // as sim::run_servo_loop
    energy_j_ += sim::step(params_, state_, to_sim(start_D_ + command_(t_s)), to_sim(v_C), to_sim(f_D), period_s_);
  }
  out.frames = 1;
  out.p_D[0] = to_eigen(state_.p_DT_m);
  out.q_D[0].setIdentity();
}

void SimulatedStylus::receive(const DeviceReply& reply) {
  if (reply.frames == 0) return;  // no reply: the DAC holds its command
  f_D_ = reply.wrench[0].f_D;
  watchdog_.on_reply(t_ns_);
}

SimulatedGlove::SimulatedGlove(sim::GloveTrajectory trajectory, int frames, bool left, double period_s,
                               const sim::GloveParams& params)
    : sim_(std::move(trajectory), params, frames, left, period_s) {}

void SimulatedGlove::advance(long tick, double t_s, DeviceFrames& out) {
  t_ns_ = static_cast<std::uint64_t>(std::llround(1e9 * t_s));
  if (tick > 0) {
    sim_.set_output_scale(watchdog_.scale(t_ns_));  // as sim::GloveServo
    sim_.advance();
  }
  const auto poses = sim_.frame_poses();
  out.frames = sim_.frames();
  for (int j = 0; j < out.frames; ++j) out.p_D[j] = poses[j].p_m, out.q_D[j] = poses[j].q;
}

void SimulatedGlove::receive(const DeviceReply& reply) {
  if (reply.frames > 0) watchdog_.on_reply(t_ns_);
  for (int j = 0; j < reply.frames; ++j)
    sim_.set_wrench(j, to_sim(reply.wrench[j].f_D), to_sim(reply.wrench[j].tau_D), reply.in_contact[j]);
  sim_.record_tick();
}

void RecordedDevice::advance(long tick, double, DeviceFrames& out) {
  out = poses_[static_cast<std::size_t>(std::clamp<long>(tick, 0, static_cast<long>(poses_.size()) - 1))];
}

// --- Whole runs ----------------------------------------------------------------------------------

OfflineTrace run_offline(OfflineLoops& loops, OfflineDevice& device, long ticks) {
  return run_offline(loops, device, ticks, [](long) {});
}

OfflineTrace run_offline(OfflineLoops& loops, OfflineDevice& device, long ticks,
                         const std::function<void(long tick)>& after_tick) {
  if (device.frames() != loops.link().handles)
    throw std::invalid_argument("offline run: the device has " + std::to_string(device.frames()) +
                                " frames, its hand " + std::to_string(loops.link().handles) + " handles");
  OfflineTrace trace;
  trace.poses.resize(static_cast<std::size_t>(ticks));
  trace.replies.resize(static_cast<std::size_t>(ticks));
  for (long k = 0; k < ticks; ++k) {
    const long tick = loops.ticks();
    DeviceFrames& pose = trace.poses[static_cast<std::size_t>(k)];
    DeviceReply& reply = trace.replies[static_cast<std::size_t>(k)];
    device.advance(tick, loops.time_s(), pose);
    loops.tick(pose, reply);
    device.receive(reply);
    after_tick(tick);
  }
  trace.timings = loops.timings();
  trace.resets = loops.resets();
  const haptic::ProxyHand& proxy = loops.proxy();
  trace.contact_solves = {proxy.contact_solves(), proxy.contact_unconverged(), proxy.contact_sweeps_total()};
  return trace;
}

}  // namespace hapticd::offline
