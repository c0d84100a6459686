#include "server/haptic/haptic_server.hpp"

#include <poll.h>
#include <pthread.h>
#include <sched.h>
#include <sys/socket.h>

#include <algorithm>
#include <boost/asio/io_context.hpp>
#include <boost/asio/ip/address.hpp>
#include <cmath>
#include <random>
#include <stdexcept>

#include "protocol/clock.hpp"

namespace hapticd {

namespace asio = boost::asio;
using protocol::MessageType;

struct HapticServer::Session {
  bool active = false;
  bool follower = false;  // shares a device's hand with an earlier session: feels it, does not drive it
  std::uint64_t id = 0;
  asio::ip::udp::endpoint peer;
  int link = 0;
  int frames = 0;
  std::uint16_t frame_id[kMaxHapticHandles]{};
  ProxyHand proxy;
  protocol::SequenceWindow sequence;
  std::uint64_t last_seen_ns = 0, last_reply_ns = 0;
  double output_scale = 0;  // ramps 0 -> 1 when poses flow, -> 0 when the session goes silent
  bool resynced = false;    // the next reply carries the resynced flag
};

struct HapticServer::Io {
  asio::io_context context;
  asio::ip::udp::socket socket{context};
  asio::ip::udp::endpoint peer;  // sender of the datagram being handled
};

HapticServer::HapticServer(std::vector<DeviceLink> links, const ServerOptions& options,
                           TripleBuffer<HapticSnapshot>& snapshots, TripleBuffer<ProxyTargets>& targets)
    : links_(std::move(links)),
      options_(options),
      snapshots_(snapshots),
      targets_(targets),
      io_(std::make_unique<Io>()),
      sessions_(std::make_unique<Session[]>(kMaxSessions)),
      stats_(std::make_unique<ServerStats>()),
      rx_(std::make_unique<protocol::ReceiveBuffer>()),
      message_(std::make_unique<protocol::Message>()),
      reply_(std::make_unique<protocol::Message>()) {
  if (!(options_.haptic_rate_hz >= 100 && options_.haptic_rate_hz <= 10000))
    throw std::invalid_argument("--haptic-rate: must be in [100, 10000] Hz");
  boost::system::error_code ec;
  const auto address = asio::ip::make_address(options_.bind, ec);
  if (ec) throw std::runtime_error("--bind " + options_.bind + ": not an IP address (" + ec.message() + ")");
  const asio::ip::udp::endpoint endpoint(address, options_.port);
  io_->socket.open(endpoint.protocol(), ec);
  if (!ec) io_->socket.bind(endpoint, ec);
  if (ec) throw std::runtime_error("cannot bind " + options_.bind + ":" + std::to_string(options_.port) + ": " + ec.message());
  io_->socket.non_blocking(true, ec);
  // Session ids are not guessable from outside (a spoofed pose must name a live session).
  std::random_device rd;
  next_session_id_ = (static_cast<std::uint64_t>(rd()) << 32) ^ rd();
}

HapticServer::~HapticServer() = default;

std::uint16_t HapticServer::port() const { return io_->socket.local_endpoint().port(); }
std::string HapticServer::address() const { return io_->socket.local_endpoint().address().to_string(); }

HapticServer::Session* HapticServer::find_session(std::uint64_t id) {
  for (int i = 0; i < kMaxSessions; ++i)
    if (sessions_[i].active && sessions_[i].id == id) return &sessions_[i];
  return nullptr;
}

void HapticServer::run(const std::atomic<bool>& stop) {
  ServerStats& st = *stats_;
  // Spinning at real-time priority would starve every other thread of its core.
  if (options_.realtime && !options_.busy_poll) {
    sched_param param{};
    param.sched_priority = 80;
    st.realtime = pthread_setschedparam(pthread_self(), SCHED_FIFO, &param) == 0;
  }
  const auto period_ns = static_cast<std::uint64_t>(1e9 / options_.haptic_rate_hz);
  const int fd = io_->socket.native_handle();
  start_ns_ = protocol::now_ns();
  std::uint64_t deadline = start_ns_ + period_ns;
  while (!stop.load(std::memory_order_relaxed)) {
    std::uint64_t now = protocol::now_ns();
    if (now >= deadline) {
      st.tick_jitter_us.add(1e-3 * static_cast<double>(now - deadline));
      tick(now);
      st.tick_compute_us.add(1e-3 * static_cast<double>(protocol::now_ns() - now));
      deadline += period_ns;
      if (protocol::now_ns() >= deadline) {
        // Missed a whole period: count it and re-anchor instead of bursting ticks.
        ++st.overruns;
        deadline = protocol::now_ns() + period_ns;
      }
      continue;
    }
    if (!options_.busy_poll) {
      const std::uint64_t wait = deadline - now;
      timespec timeout{static_cast<time_t>(wait / 1000000000ull), static_cast<long>(wait % 1000000000ull)};
      pollfd p{fd, POLLIN, 0};
      if (ppoll(&p, 1, &timeout, nullptr) <= 0) continue;
    }
    // Drain what arrived; each datagram is answered before the next is read.
    for (int burst = 0; burst < 64; ++burst) {
      socklen_t len = sizeof(sockaddr_storage);
      sockaddr_storage from{};
      const ssize_t n = ::recvfrom(fd, rx_->bytes.data(), rx_->bytes.size(), MSG_DONTWAIT,
                                   reinterpret_cast<sockaddr*>(&from), &len);
      if (n < 0) break;
      io_->peer.resize(len);
      std::copy_n(reinterpret_cast<const char*>(&from), len, reinterpret_cast<char*>(io_->peer.data()));
      handle(static_cast<std::size_t>(n), protocol::now_ns());
      if (protocol::now_ns() >= deadline) break;
    }
  }
  st.elapsed_s = 1e-9 * static_cast<double>(protocol::now_ns() - start_ns_);
  for (int i = 0; i < kMaxSessions; ++i) {
    st.clamps += static_cast<std::uint64_t>(sessions_[i].proxy.clamps());
    st.resets += static_cast<std::uint64_t>(sessions_[i].proxy.resets());
  }
}

void HapticServer::tick(std::uint64_t now) {
  ServerStats& st = *stats_;
  ++st.ticks;
  snapshots_.update();
  const HapticSnapshot& snap = snapshots_.front();
  const double dt = 1.0 / options_.haptic_rate_hz;
  ProxyTargets& out = targets_.back();
  for (bool& d : out.driven) d = false;
  for (int h = 0; h < kMaxHands; ++h) out.resyncs[h] = hand_resyncs_[h];
  for (int i = 0; i < kMaxSessions; ++i) {
    Session& s = sessions_[i];
    if (!s.active) continue;
    const double silent_s = 1e-9 * static_cast<double>(now - s.last_seen_ns);
    if (silent_s > options_.session_timeout_s) {
      st.clamps += static_cast<std::uint64_t>(s.proxy.clamps());
      st.resets += static_cast<std::uint64_t>(s.proxy.resets());
      s = Session{};
      ++st.sessions_timed_out;
      continue;
    }
    // Silence: the force fades out over ramp_s; poses bring it back at the same rate.
    const double step = dt / std::max(options_.ramp_s, dt);
    s.output_scale = silent_s > options_.silence_s ? std::max(0.0, s.output_scale - step)
                                                   : std::min(1.0, s.output_scale + step);
    const DeviceLink& link = links_[s.link];
    // Until the visual loop has moved the hand to a re-synced proxy, its model
    // would pull the proxy back to where the hand was: the proxy feels the device only.
    const HapticModel& model =
        snap.model[link.hand].resyncs == hand_resyncs_[link.hand] ? snap.model[link.hand] : no_model_;
    const double lookahead = 1e-9 * (static_cast<double>(model.t_end_ns) - static_cast<double>(now));
    s.proxy.integrate(model, dt, model.t_end_ns ? std::clamp(lookahead, -0.1, 0.1) : 0.0);
    if (s.follower || !s.proxy.has_device_pose()) continue;
    out.driven[link.hand] = true;
    for (int j = 0; j < link.handles; ++j) {
      out.pose[link.hand][j] = s.proxy.proxy(j);
      out.v_W[link.hand][j] = s.proxy.proxy_velocity(j);
      out.w_W[link.hand][j] = s.proxy.proxy_angular_velocity(j);
    }
  }
  targets_.publish();
}

void HapticServer::send(const protocol::EncodeResult& encoded) {
  if (!encoded.ok()) {
    ++stats_->send_errors;
    return;
  }
  const ssize_t n = ::sendto(io_->socket.native_handle(), encoded.bytes.data(), encoded.bytes.size(), MSG_DONTWAIT,
                             io_->peer.data(), static_cast<socklen_t>(io_->peer.size()));
  if (n == static_cast<ssize_t>(encoded.bytes.size())) {
    ++stats_->packets_out;
  } else {
    ++stats_->send_errors;
  }
}

void HapticServer::send_error(protocol::ErrorCode code, const char* message) {
  reply_->type = MessageType::kError;
  reply_->error.code = code;
  reply_->error.message.assign(message);
  send(encoder_.encode(reply_->error));
}

void HapticServer::handle(std::size_t bytes, std::uint64_t now) {
  ServerStats& st = *stats_;
  ++st.packets_in;
  const protocol::DecodeResult r = protocol::decode({rx_->bytes.data(), bytes}, *message_);
  if (!r.ok()) {
    ++st.packets_dropped;
    ++st.rejected[static_cast<std::size_t>(r.reason)];
    if (r.type == MessageType::kPoseSample && r.session_id != protocol::kNoSession) {
      // A malformed pose (NaN, absurd) from a live session's own peer: its force goes to zero now.
      if (Session* s = find_session(r.session_id); s && s->peer == io_->peer) {
        s->proxy.resync();
        s->output_scale = 0;
      }
    }
    if (protocol::error_reply_allowed(r)) send_error(protocol::error_code_for(r.reason), to_string(r.reason).data());
    return;
  }
  switch (message_->type) {
    case MessageType::kHello:
      on_hello(message_->hello);
      return;
    case MessageType::kPoseSample:
      on_pose(message_->pose_sample, now);
      return;
    case MessageType::kHeartbeat: {
      Session* s = find_session(message_->heartbeat.session_id);
      if (!s || s->peer != io_->peer) {
        ++st.unknown_session, ++st.packets_dropped;
        return;
      }
      s->last_seen_ns = now;
      reply_->heartbeat = {s->id, now, message_->heartbeat.timestamp_ns};
      send(encoder_.encode(reply_->heartbeat));
      return;
    }
    case MessageType::kStatsRequest: {
      Session* s = find_session(message_->stats_request.session_id);
      if (!s || s->peer != io_->peer) {
        ++st.unknown_session, ++st.packets_dropped;
        return;
      }
      fill_stats(reply_->stats);
      reply_->stats.session_id = s->id;
      send(encoder_.encode(reply_->stats));
      return;
    }
    case MessageType::kBye: {
      Session* s = find_session(message_->bye.session_id);
      if (!s || s->peer != io_->peer) {
        ++st.unknown_session, ++st.packets_dropped;
        return;
      }
      st.clamps += static_cast<std::uint64_t>(s->proxy.clamps());
      st.resets += static_cast<std::uint64_t>(s->proxy.resets());
      *s = Session{};
      ++st.sessions_closed;
      return;
    }
    default:
      // Server-to-client messages sent to the server.
      ++st.packets_dropped;
      return;
  }
}

void HapticServer::on_hello(const protocol::Hello& hello) {
  // A device of the requested kind whose hand has one handle per tracked frame;
  // a free one first, else share the least used one as a follower.
  int best = -1, best_users = kMaxSessions + 1;
  for (size_t l = 0; l < links_.size(); ++l) {
    if (links_[l].kind != hello.device_kind || links_[l].handles != static_cast<int>(hello.frames.size())) continue;
    int users = 0;
    for (int i = 0; i < kMaxSessions; ++i) users += sessions_[i].active && sessions_[i].link == static_cast<int>(l);
    if (users < best_users) best = static_cast<int>(l), best_users = users;
  }
  if (best < 0) {
    send_error(protocol::ErrorCode::kUnsupportedDevice,
               "the scene has no device of this kind with one handle per tracked frame");
    return;
  }
  // The same peer saying hello again replaces its session.
  Session* slot = nullptr;
  for (int i = 0; i < kMaxSessions && !slot; ++i)
    if (sessions_[i].active && sessions_[i].peer == io_->peer) slot = &sessions_[i];
  for (int i = 0; i < kMaxSessions && !slot; ++i)
    if (!sessions_[i].active) slot = &sessions_[i];
  if (!slot) {
    send_error(protocol::ErrorCode::kServerFull, "every session slot is taken");
    return;
  }
  const DeviceLink& link = links_[best];
  Session& s = *slot;
  s = Session{};
  s.active = true;
  s.follower = best_users > 0;
  do s.id = ++next_session_id_;
  while (s.id == protocol::kNoSession || (find_session(s.id) != &s && find_session(s.id)));
  s.peer = io_->peer;
  s.link = best;
  s.frames = static_cast<int>(hello.frames.size());
  for (int j = 0; j < s.frames; ++j) s.frame_id[j] = hello.frames[j].id;
  s.proxy.configure(link.handles, link.mass_kg, link.inertia_B, link.gains, link.limits, link.map);
  s.last_seen_ns = protocol::now_ns();
  ++stats_->sessions_opened;
  protocol::Welcome& w = reply_->welcome;
  w = protocol::Welcome{};
  w.session_id = s.id;
  w.rate_hz = static_cast<std::uint32_t>(options_.haptic_rate_hz);
  w.force_limit_n = static_cast<float>(link.limits.max_force_n);
  w.torque_limit_nm = static_cast<float>(link.limits.max_torque_nm);
  w.max_force_rate_n_per_s = static_cast<float>(link.limits.max_force_rate_n_s);
  for (int j = 0; j < s.frames; ++j) w.frame_map.push_back({s.frame_id[j], static_cast<std::uint16_t>(j)});
  send(encoder_.encode(w));
}

void HapticServer::on_pose(const protocol::PoseSample& pose, std::uint64_t now) {
  ServerStats& st = *stats_;
  Session* s = find_session(pose.session_id);
  if (!s || s->peer != io_->peer) {
    ++(s ? st.wrong_peer : st.unknown_session);
    ++st.packets_dropped;
    return;
  }
  switch (s->sequence.observe(pose.sequence)) {
    case protocol::SequenceClass::kDuplicate:
      ++st.duplicates, ++st.packets_dropped;
      return;
    case protocol::SequenceClass::kStale:
      ++st.stale, ++st.packets_dropped;
      return;
    case protocol::SequenceClass::kGap:
      ++st.gaps;
      break;
    case protocol::SequenceClass::kFresh:
      break;
  }
  // Every tracked frame must be in the sample, in the handshake's order.
  if (static_cast<int>(pose.poses.size()) != s->frames) {
    ++st.rejected[static_cast<std::size_t>(protocol::RejectReason::kBadCount)];
    ++st.packets_dropped;
    return;
  }
  for (int j = 0; j < s->frames; ++j) {
    const protocol::FramePose& f = pose.poses[j];
    if (f.frame != s->frame_id[j]) {
      ++st.rejected[static_cast<std::size_t>(protocol::RejectReason::kFrameIdsNotIncreasing)];
      ++st.packets_dropped;
      return;
    }
    s->proxy.set_device_pose(j, Eigen::Vector3d(f.position_m.x, f.position_m.y, f.position_m.z),
                             Eigen::Quaterniond(f.orientation.w, f.orientation.x, f.orientation.y, f.orientation.z));
  }
  s->last_seen_ns = now;
  if (s->proxy.commit_sample(1e-9 * static_cast<double>(now - start_ns_), options_.resync_gap_s)) {
    s->resynced = true;
    ++st.resyncs;
    if (!s->follower) ++hand_resyncs_[links_[s->link].hand];
  }
  const double since_reply = s->last_reply_ns ? 1e-9 * static_cast<double>(now - s->last_reply_ns) : 1e-3;
  protocol::ForceSample& out = reply_->force_sample;
  out.session_id = s->id;
  out.sequence = pose.sequence;
  out.client_timestamp_ns = pose.client_timestamp_ns;
  out.server_receive_ns = now;
  out.flags = 0;
  out.wrenches.clear();
  const DeviceLink& link = links_[s->link];
  const HapticModel& model = snapshots_.front().model[link.hand];
  // A gated frame whose part touches nothing is driven to zero through the slew limit (no step).
  ReplyWrench replies[kMaxHapticHandles];
  for (int j = 0; j < s->frames; ++j) {
    const bool gated = link.contact_gated && !(model.handles == s->frames && model.handle_in_contact[j]);
    replies[j] = s->proxy.reply(j, gated ? 0.0 : s->output_scale, since_reply);
  }
  if (link.output == ForceOutput::finger_lines) {
    HapticPose device_W[kMaxHapticHandles];
    for (int j = 0; j < s->frames; ++j) device_W[j] = s->proxy.device(j);
    project_onto_finger_lines(link, device_W, replies);
  }
  for (int j = 0; j < s->frames; ++j) {
    const ReplyWrench& w = replies[j];
    const bool contact = link.contact_gated ? model.handle_in_contact[j] : model.in_contact;
    protocol::FrameWrench fw;
    fw.frame = s->frame_id[j];
    fw.flags = static_cast<std::uint16_t>((contact ? protocol::ForceFlags::kInContact : 0) |
                                          (w.clamped ? protocol::ForceFlags::kClamped : 0));
    fw.wrench.force_n = {static_cast<float>(w.f_D.x()), static_cast<float>(w.f_D.y()), static_cast<float>(w.f_D.z())};
    fw.wrench.torque_nm = {static_cast<float>(w.tau_D.x()), static_cast<float>(w.tau_D.y()),
                           static_cast<float>(w.tau_D.z())};
    out.flags |= fw.flags;
    out.wrenches.push_back(fw);
  }
  if (s->resynced) out.flags |= protocol::ForceFlags::kResynced, s->resynced = false;
  if (model.handles == 0) out.flags |= protocol::ForceFlags::kStale;
  s->last_reply_ns = now;
  out.server_send_ns = protocol::now_ns();
  const protocol::EncodeResult encoded = encoder_.encode(out);
  // Compute per sample: from the datagram read to the reply encoded (the send syscall is I/O).
  st.reply_compute_us.add(1e-3 * static_cast<double>(protocol::now_ns() - now));
  send(encoded);
  ++st.replies;
}

void HapticServer::fill_stats(protocol::Stats& out) const {
  const ServerStats& st = *stats_;
  out = protocol::Stats{};
  out.packets_in = st.packets_in;
  out.packets_out = st.packets_out;
  out.packets_dropped = st.packets_dropped;
  for (std::size_t i = 0; i < protocol::kRejectReasonCount; ++i) out.rejected_by_reason[i] = st.rejected[i];
  std::uint64_t clamps = st.clamps, resets = st.resets;
  std::uint32_t active = 0;
  for (int i = 0; i < kMaxSessions; ++i) {
    if (!sessions_[i].active) continue;
    ++active;
    clamps += static_cast<std::uint64_t>(sessions_[i].proxy.clamps());
    resets += static_cast<std::uint64_t>(sessions_[i].proxy.resets());
  }
  out.clamps = clamps;
  out.resets = resets;
  out.overruns = st.overruns;
  out.tick_compute_p50_us = static_cast<float>(st.tick_compute_us.percentile(50));
  out.tick_compute_p99_us = static_cast<float>(st.tick_compute_us.percentile(99));
  out.tick_jitter_p99_us = static_cast<float>(st.tick_jitter_us.percentile(99));
  out.visual_step_median_ms = static_cast<float>(visual_step_ms.load(std::memory_order_relaxed));
  const double elapsed = 1e-9 * static_cast<double>(protocol::now_ns() - start_ns_);
  out.haptic_rate_hz = elapsed > 0 ? static_cast<float>(static_cast<double>(st.ticks) / elapsed) : 0.0f;
  out.visual_rate_hz = static_cast<float>(visual_rate_hz.load(std::memory_order_relaxed));
  out.sessions_active = active;
}

}  // namespace hapticd
