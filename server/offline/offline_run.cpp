#include "server/offline/offline_run.hpp"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <stdexcept>
#include <utility>

#include "hand_models/handle_linearization.hpp"
#include "hand_models/rigid_handle.hpp"

namespace hapticd {
namespace {

using Clock = std::chrono::steady_clock;

double elapsed_us(Clock::time_point from, Clock::time_point to) {
  return std::chrono::duration<double, std::micro>(to - from).count();
}

// p-th percentile (0..100) by linear interpolation; 0 for an empty sample.
double percentile(std::vector<double> v, double p) {
  if (v.empty()) return 0;
  std::sort(v.begin(), v.end());
  const double rank = p / 100.0 * static_cast<double>(v.size() - 1);
  const auto lo = static_cast<std::size_t>(rank);
  const std::size_t hi = std::min(lo + 1, v.size() - 1);
  return v[lo] + (rank - static_cast<double>(lo)) * (v[hi] - v[lo]);
}

Eigen::Vector3d to_eigen(sim::Vec3d v) { return {v.x, v.y, v.z}; }
sim::Vec3d to_sim(const Eigen::Vector3d& v) { return {v.x(), v.y(), v.z()}; }

// hapticd's defaults (ServerOptions): a first pose re-syncs; the session's force ramps up over 0.1 s.
const ServerOptions kServer{};

}  // namespace

const char* to_string(HandleModelKind kind) {
  switch (kind) {
    case HandleModelKind::linearized:
      return "linearized";
    case HandleModelKind::zoh:
      return "zoh";
    case HandleModelKind::zoh_coupling:
      return "zoh_coupling";
  }
  return "?";
}

OfflineLoops::OfflineLoops(SceneDesc scene, const OfflineOptions& options) : options_(options) {
  if (options_.visual_every_ticks < 1 || options_.model_delay_ticks < 0 || !(options_.haptic_period_s > 0))
    throw std::invalid_argument("offline run: visual_every_ticks >= 1, model_delay_ticks >= 0, haptic_period_s > 0");
  if (options_.device < 0 || options_.device >= static_cast<int>(scene.devices.size()))
    throw std::runtime_error(scene.name + ": no device " + std::to_string(options_.device) + " to serve");
  // As hapticd: the scene's step is the visual period, hands are weightless, their
  // handles follow the proxies, and the visual loop builds the coming step's model itself.
  const double dt = options_.visual_every_ticks * options_.haptic_period_s;
  scene.dt_s = dt;
  scene.visual_rate_hz = 1.0 / dt;
  const DeviceDesc& device = scene.devices[options_.device];
  const CouplingGains gains =
      coupling_gains_for(device.stiffness_n_m, device.workspace.scale, options_.haptic_period_s);
  WorldOptions world_options;
  world_options.hand_gravity = false;
  // hapticd's handles follow the proxies almost kinematically; the naive server's
  // are pulled to the device by the virtual coupling itself.
  world_options.drive = options_.model != HandleModelKind::zoh_coupling
                            ? kProxyDrive
                            : DriveParams{gains.k_n_m, gains.b_ns_m, gains.k_nm_rad, gains.b_nms_rad};
  world_options.linearize = false;
  world_options.contact = options_.contact;
  // CHOLMOD's OpenMP regions: one thread, as the visual thread runs it.
  single_threaded_cholmod();
  world_ = std::make_unique<World>(scene, world_options);
  if (RigidWorld* rigid = world_->rigid())
    for (long i = 0; i < std::lround(options_.settle_s / options_.haptic_period_s); ++i)
      rigid->step(options_.haptic_period_s);
  link_ = make_device_link(*world_, scene.devices[options_.device], 1.0 / options_.haptic_period_s);
  proxy_.configure(link_.handles, link_.mass_kg, link_.inertia_B, link_.gains, link_.limits, link_.map);
  for (int j = 0; j < kMaxHapticHandles; ++j) {
    device_v_W_[j].setZero(), device_w_W_[j].setZero(), held_f_W_[j].setZero(), held_tau_W_[j].setZero();
    last_f_D_[j].setZero(), last_tau_D_[j].setZero();
  }
  const long expected_steps = 1024;
  haptic_us_.reserve(static_cast<std::size_t>(expected_steps * options_.visual_every_ticks));
  visual_ms_.reserve(static_cast<std::size_t>(expected_steps));
}

void OfflineLoops::frame_pose_at_handle(int j, Eigen::Vector3d& p_D, Eigen::Quaterniond& q_D) const {
  const HandleState& h = world_->hand(link_.hand).state.handles[j];
  link_.map.to_device(j, {h.p_WH, h.q_WH}, p_D, q_D);
}

long OfflineLoops::resets() const { return proxy_.resets() + world_->snapshot().resets; }

OfflineTimings OfflineLoops::timings() const {
  return {percentile(haptic_us_, 50), percentile(haptic_us_, 99), percentile(visual_ms_, 50),
          percentile(visual_ms_, 99), static_cast<long>(visual_ms_.size())};
}

void OfflineLoops::tick(const DeviceFrames& sample, DeviceReply& reply) {
  const double T = options_.haptic_period_s, t = time_s();
  const Clock::time_point c0 = Clock::now();
  if (options_.model == HandleModelKind::zoh_coupling) {
    // The naive server: the sample moves the coupling's device end; the reply is the held force.
    for (int j = 0; j < link_.handles; ++j) {
      const HapticPose pose = link_.map.to_world(j, sample.p_D[j], sample.q_D[j]);
      if (have_device_) {
        device_v_W_[j] = (pose.p_W - device_W_[j].p_W) / T;
        device_w_W_[j] = rotation_difference(pose.q_W, device_W_[j].q_W) / T;
      }
      device_W_[j] = pose;
    }
    if (!have_device_) have_device_ = true, ++resyncs_;
    if (pending_ && ticks_ >= publish_at_) current_ = next_, pending_ = false;
    reply_held(reply);
  } else {
    // HapticServer::handle: the sample, then the reply from the current proxies.
    for (int j = 0; j < link_.handles; ++j) proxy_.set_device_pose(j, sample.p_D[j], sample.q_D[j]);
    if (proxy_.commit_sample(t, kServer.resync_gap_s)) ++resyncs_;
    reply.frames = link_.handles;
    for (int j = 0; j < link_.handles; ++j) {
      const bool gated = link_.contact_gated && !(current_.handles == link_.handles && current_.handle_in_contact[j]);
      reply.wrench[j] = proxy_.reply(j, gated ? 0.0 : output_scale_, T);
    }
    if (link_.output == ForceOutput::finger_lines) {
      HapticPose device_W[kMaxHapticHandles];
      for (int j = 0; j < link_.handles; ++j) device_W[j] = proxy_.device(j);
      project_onto_finger_lines(link_, device_W, reply.wrench);
    }
    for (int j = 0; j < link_.handles; ++j)
      reply.in_contact[j] = link_.contact_gated ? current_.handle_in_contact[j] : current_.in_contact;
    // HapticServer::tick: the newest published model (none until one computed
    // after the last re-sync), the proxies' step.
    if (pending_ && ticks_ >= publish_at_) current_ = next_, t_end_s_ = next_t_end_s_, pending_ = false;
    const HapticModel& model = current_.resyncs == resyncs_ ? current_ : none_;
    proxy_.integrate(model, T, model.handles ? std::clamp(t_end_s_ - t, -0.1, 0.1) : 0.0);
  }
  // The session's output ramp (HapticServer::tick).
  output_scale_ = std::min(1.0, output_scale_ + T / std::max(kServer.ramp_s, T));
  haptic_us_.push_back(elapsed_us(c0, Clock::now()));
  if (ticks_ % options_.visual_every_ticks == 0) visual_step(t);
  ++ticks_;
}

void OfflineLoops::reply_held(DeviceReply& reply) {
  // As ProxyHand::reply, with the held coupling wrench for the proxy's: reversed,
  // in device space about the frame's origin, clamped and slew-limited.
  const double T = options_.haptic_period_s;
  const HapticModel& held = current_.resyncs == resyncs_ ? current_ : none_;
  const DeviceMap& map = link_.map;
  const DeviceLimits& lim = link_.limits;
  const Eigen::Matrix3d R_DW = map.R_WD.toRotationMatrix().transpose();
  reply.frames = link_.handles;
  for (int j = 0; j < link_.handles; ++j) {
    ReplyWrench& r = reply.wrench[j];
    r = ReplyWrench{};
    const bool gated = link_.contact_gated && !held.handle_in_contact[j];
    const double scale = held.handles == link_.handles && !gated ? output_scale_ : 0.0;
    const Eigen::Vector3d f_W = scale > 0 ? Eigen::Vector3d(held.F0.segment<3>(6 * j)) : Eigen::Vector3d::Zero();
    const Eigen::Vector3d tau_W = scale > 0 ? Eigen::Vector3d(held.F0.segment<3>(6 * j + 3)) : Eigen::Vector3d::Zero();
    const Eigen::Vector3d r_W = device_W_[j].q_W * (map.handle_q_F[j].conjugate() * map.handle_p_F[j]);
    Eigen::Vector3d f = -scale * map.scale * (R_DW * f_W);
    Eigen::Vector3d tau = -scale * (R_DW * (tau_W + r_W.cross(f_W)));
    auto clamp_norm = [](Eigen::Vector3d& v, double limit) {
      const double n = v.norm();
      if (n <= limit) return false;
      v *= limit / n;
      return true;
    };
    r.clamped = clamp_norm(f, lim.max_force_n);
    r.clamped = clamp_norm(tau, lim.max_torque_nm) || r.clamped;
    Eigen::Vector3d df = f - last_f_D_[j], dtau = tau - last_tau_D_[j];
    r.clamped = clamp_norm(df, lim.max_force_rate_n_s * T) || r.clamped;
    r.clamped = clamp_norm(dtau, lim.max_force_rate_n_s * lim.max_torque_nm / lim.max_force_n * T) || r.clamped;
    r.f_D = last_f_D_[j] += df;
    r.tau_D = last_tau_D_[j] += dtau;
  }
  if (link_.output == ForceOutput::finger_lines) project_onto_finger_lines(link_, device_W_, reply.wrench);
  for (int j = 0; j < link_.handles; ++j)
    reply.in_contact[j] = link_.contact_gated ? held.handle_in_contact[j] : held.in_contact;
}

void OfflineLoops::visual_step(double t) {
  const Clock::time_point c0 = Clock::now();
  const double T = options_.haptic_period_s;
  const double latency = options_.model_delay_ticks * T, dt = options_.visual_every_ticks * T;
  // The proxies are as of the end of this tick (the model of zoh_coupling has no time).
  const double t_read = options_.targets_one_tick_stale ? t : t + T;
  WorldHand& hand = world_->hand(link_.hand);
  const bool coupled = options_.model == HandleModelKind::zoh_coupling;
  // VisualLoop::run: the world simulates up to the model's publication, its
  // handles driven to the proxies (zoh_coupling: the device) extrapolated to then; a
  // re-synced proxy takes the hand along rigidly.
  if (coupled ? have_device_ : proxy_.has_device_pose()) {
    if (resyncs_ != resyncs_seen_) {
      resyncs_seen_ = resyncs_;
      const HapticPose& p = coupled ? device_W_[0] : proxy_.proxy(0);
      place_hand(*hand.model, hand.state, p.p_W, p.q_W, 0);
    }
    for (int j = 0; j < std::min(hand.model->num_handles(), kMaxHapticHandles); ++j) {
      const HapticPose& p = coupled ? device_W_[j] : proxy_.proxy(j);
      const Eigen::Vector3d& v = coupled ? device_v_W_[j] : proxy_.proxy_velocity(j);
      const Eigen::Vector3d& w = coupled ? device_w_W_[j] : proxy_.proxy_angular_velocity(j);
      set_target(hand.state, j, {p.p_W + latency * v, rotate_by(p.q_W, latency * w), v, w});
    }
  }
  world_->step(dt);
  // The coming step has the same length; its model is built for it and published `latency` later.
  for (int h = 0; h < world_->num_hands(); ++h) world_->hand(h).state.dt_s = dt;
  build_model(next_);
  // As VisualLoop::run: the haptic tick's solver of the model, prepared here (a glove's).
  if (!coupled && next_.handles >= kMinPreparedHandles) prepare_for_links({&link_, 1}, link_.hand, T, next_);
  next_.resyncs = resyncs_seen_;
  next_t_end_s_ = t_read + latency + dt;
  pending_ = true;
  publish_at_ = ticks_ + options_.model_delay_ticks;
  visual_ms_.push_back(1e-3 * elapsed_us(c0, Clock::now()));
}

void OfflineLoops::build_model(HapticModel& out) {
  if (options_.model == HandleModelKind::linearized) {
    fill_haptic_model(*world_, link_.hand, scratch_, out);
    return;
  }
  out.handles = 0;
  out.solver.prepared = false;
  fill_contact_flags(*world_, link_.hand, out);
  const HandState& s = world_->hand(link_.hand).state;
  const int m = link_.handles;
  if (options_.model == HandleModelKind::zoh) {
    // The flesh's wrench on the handles as the step left them (seed 004 eq. 4-5), held: K = D = 0.
    const Eigen::VectorXd F = coupling_wrench(*world_->hand(link_.hand).model, s.x, s.v, s.handles);
    if (F.size() != 6 * m) return;
    out.F0 = F;
    out.K.setZero(6 * m, 6 * m);
    out.D.setZero(6 * m, 6 * m);
    for (int j = 0; j < m; ++j) {
      out.x0[j] = {s.handles[j].p_WH, s.handles[j].q_WH};
      out.v0[j] = s.handles[j].v_WH;
      out.w0[j] = s.handles[j].w_WH;
    }
  } else {
    // zoh_coupling: the virtual coupling's wrench on each handle as the step
    // ended (the world's drive, implicit: at the end-of-step state), for the replies.
    const CouplingGains& g = link_.gains;
    out.F0.resize(6 * m);
    for (int j = 0; j < m; ++j) {
      const HandleState& h = s.handles[j];
      const HandleTarget& tg = s.targets[j];
      out.F0.segment<3>(6 * j) = -g.k_n_m * (h.p_WH - tg.p_W) - g.b_ns_m * (h.v_WH - tg.v_W);
      out.F0.segment<3>(6 * j + 3) =
          -g.k_nm_rad * rotation_difference(h.q_WH, tg.q_W) - g.b_nms_rad * (h.w_WH - tg.w_W);
    }
  }
  if (out.F0.allFinite()) out.handles = m;
}

// --- Devices -------------------------------------------------------------------------------------

SimulatedStylus::SimulatedStylus(const Eigen::Vector3d& start_D, Command command, double period_s,
                                 const sim::DeviceParams& params)
    : start_D_(start_D), command_(std::move(command)), period_s_(period_s), params_(params) {
  state_.p_DT_m = to_sim(start_D_ + command_(0.0));
}

void SimulatedStylus::advance(long tick, double t_s, DeviceFrames& out) {
  if (tick > 0) {
    constexpr double h = 1e-6;  // as sim::Trajectory::velocity
    const Eigen::Vector3d v_C = (command_(t_s + h) - command_(t_s - h)) / (2 * h);
    energy_j_ += sim::step(params_, state_, to_sim(start_D_ + command_(t_s)), to_sim(v_C), to_sim(f_D_), period_s_);
  }
  out.frames = 1;
  out.p_D[0] = to_eigen(state_.p_DT_m);
  out.q_D[0].setIdentity();
}

void SimulatedStylus::receive(const DeviceReply& reply) { f_D_ = reply.wrench[0].f_D; }

SimulatedGlove::SimulatedGlove(sim::GloveTrajectory trajectory, int frames, bool left, double period_s,
                               const sim::GloveParams& params)
    : sim_(std::move(trajectory), params, frames, left, period_s) {}

void SimulatedGlove::advance(long tick, double, DeviceFrames& out) {
  if (tick > 0) sim_.advance();
  const auto poses = sim_.frame_poses();
  out.frames = sim_.frames();
  for (int j = 0; j < out.frames; ++j) out.p_D[j] = poses[j].p_m, out.q_D[j] = poses[j].q;
}

void SimulatedGlove::receive(const DeviceReply& reply) {
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
  return trace;
}

}  // namespace hapticd
