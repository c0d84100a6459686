#include "server/haptic/haptic_core.hpp"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <limits>
#include <random>
#include <stdexcept>

#include "clients/cpp/reply_watchdog.hpp"

namespace hapticd::haptic {

using protocol::MessageType;

namespace {

// How far a session's least sample wait may rise a sample, ns: 1 us, what two clocks 100 ppm apart
// drift over a 100 Hz glove's 10 ms, ten times that over a 1 kHz device's 1 ms.
constexpr std::int64_t kWaitFloorRise_ns = 1000;

// How a device fades a held reply when the server goes silent: the client library's default
// (client::ReplyWatchdog, used by haptic-device's servo loop).
constexpr client::ReplyWatchdogOptions kDeviceWatchdog{};

// A session's proxy counters, summed into the server's (when it closes, and at the end of a run).
void add_proxy_counts(ServerStats& st, const ProxyHand& p) {
  st.clamps += static_cast<std::uint64_t>(p.clamps());
  st.resets += static_cast<std::uint64_t>(p.resets());
  st.solver_fallbacks += static_cast<std::uint64_t>(p.solver_fallbacks());
  st.solver_refinements += static_cast<std::uint64_t>(p.solver_refinements());
  st.lookahead_fallbacks += static_cast<std::uint64_t>(p.lookahead_fallbacks());
  st.contact_holds += static_cast<std::uint64_t>(p.contact_holds());
  st.contact_unconverged += static_cast<std::uint64_t>(p.contact_unconverged());
  st.contact_solves += static_cast<std::uint64_t>(p.contact_solves());
  st.contact_sweeps += static_cast<std::uint64_t>(p.contact_sweeps_total());
  st.overdue_device_ticks += static_cast<std::uint64_t>(p.overdue_device_ticks());
  st.bridged_gaps += static_cast<std::uint64_t>(p.bridged_gaps());
}

}  // namespace

struct HapticCore::Session {
  bool active = false;
  bool follower = false;  // shares a device's hand with an earlier session: feels it, does not drive it
  std::uint64_t id = 0;
  Endpoint peer;
  int link = 0;
  int frames = 0;
  std::uint16_t frame_id[kMaxHapticHandles]{};
  bool lost[kMaxHapticHandles]{};  // left out of the last pose sample: tracking lost, force ramped to zero
  ProxyHand proxy;
  protocol::SequenceWindow sequence;
  std::uint64_t last_seen_ns = 0, last_reply_ns = 0;
  // The last reply to a sample that did not wait long to be read: the device holds replies from then.
  std::uint64_t held_reply_ns = 0;
  std::uint64_t last_client_ns = 0;  // the last sample's client_timestamp_ns
  // The least wait of its samples: read time less client timestamp (the clocks' offset and the
  // link's latency), rising by at most kWaitFloorRise_ns a sample to follow the clocks' drift.
  std::int64_t quickest_wait_ns = 0;
  // When the proxies' integration has reached (the end of the last period integrated; 0: none yet),
  // and when the last sample was taken, on the server's clock (its read time, or for a sample that
  // waited in the socket while the loop was stalled, the one before it plus the device's interval).
  std::uint64_t integrated_to_ns = 0, sample_ns = 0;
  // The last silence of the server longer than the device's watchdog holds a reply
  // (client::ReplyWatchdog): samples taken in (from, to] were taken while it faded the reply out.
  std::uint64_t unheld_from_ns = 0, unheld_to_ns = 0;
  double output_scale = 0;  // ramps 0 -> 1 when poses flow, -> 0 when the session goes silent
  bool resynced = false;    // the next reply carries the resynced flag
  // With a key: no authenticated datagram from the client yet. A pending session drives and
  // replaces nothing, so a replayed Hello cannot take over its peer's live session.
  bool pending = false;
  protocol::SessionKeys keys;
  protocol::SequenceWindow counters_in;  // client -> server trailer counters seen
  std::uint64_t counter_out = 0;         // last server -> client trailer counter sent
};

// With a key, what a closed session leaves behind: enough to tell a late copy of one of its
// datagrams (a network duplicate of its Bye, a retransmitted pose) from anything else naming a
// session that is gone.
struct HapticCore::ClosedSession {
  std::uint64_t id = 0;
  Endpoint peer;
  protocol::SessionKeys keys;
  protocol::SequenceWindow counters_in;
};

HapticCore::HapticCore(std::vector<DeviceLink> links, const ServerOptions& options,
                       TripleBuffer<HapticSnapshot>& snapshots, TripleBuffer<ProxyTargets>& targets,
                       Transport& transport, const VisualReport* visual)
    : links_(std::move(links)),
      options_(options),
      snapshots_(snapshots),
      targets_(targets),
      transport_(transport),
      visual_(visual),
      sessions_(std::make_unique<Session[]>(kMaxSessions)),
      closed_(std::make_unique<ClosedSession[]>(kClosedRemembered)),
      stats_(std::make_unique<ServerStats>()),
      message_(std::make_unique<protocol::Message>()),
      reply_(std::make_unique<protocol::Message>()) {
  if (!(options_.haptic_rate_hz >= 100 && options_.haptic_rate_hz <= 10000))
    throw std::invalid_argument("--haptic-rate: must be in [100, 10000] Hz");
  period_ns_ = static_cast<std::uint64_t>(std::llround(1e9 / options_.haptic_rate_hz));
  if (!(options_.model_stale_after_s > 0) || !(options_.model_fade_s >= 0) || !(options_.model_contacts_hold_s >= 0))
    throw std::invalid_argument("model watchdog: stale_after must be > 0, fade and contacts_hold >= 0");
  if (options_.key) {
    auth_ = std::make_unique<protocol::AuthKeys>(*options_.key);
    sealer_ = std::make_unique<protocol::Sealer>();
    hello_nonces_ = std::make_unique<protocol::NonceCache>();
  }
  // Session ids are not guessable from outside (a spoofed pose must name a live session).
  std::random_device rd;
  next_session_id_ = (static_cast<std::uint64_t>(rd()) << 32) ^ rd();
}

HapticCore::~HapticCore() = default;

std::size_t HapticCore::session_bytes() { return sizeof(Session); }

std::size_t HapticCore::memory_bytes() const {
  return sizeof(*this) + kMaxSessions * sizeof(Session) + sizeof(ServerStats) + 2 * sizeof(protocol::Message) +
         (auth_ ? sizeof(protocol::AuthKeys) + sizeof(protocol::Sealer) + sizeof(protocol::NonceCache) : 0);
}

void HapticCore::start(std::uint64_t now) { start_ns_ = snapshot_arrival_ns_ = last_watch_ns_ = last_tick_ns_ = now; }

void HapticCore::finish() {
  for (int i = 0; i < kMaxSessions; ++i) add_proxy_counts(*stats_, sessions_[i].proxy);
}

const ProxyHand* HapticCore::proxy_of(std::uint64_t id) const {
  for (int i = 0; i < kMaxSessions; ++i)
    if (sessions_[i].active && sessions_[i].id == id) return &sessions_[i].proxy;
  return nullptr;
}

HapticCore::Session* HapticCore::find_session(std::uint64_t id) {
  for (int i = 0; i < kMaxSessions; ++i)
    if (sessions_[i].active && sessions_[i].id == id) return &sessions_[i];
  return nullptr;
}

void HapticCore::watch_models(std::uint64_t now) {
  ServerStats& st = *stats_;
  const HapticSnapshot& snap = snapshots_.front();
  // On the clock, not per tick: late ticks (an overloaded machine) must not stretch the fade.
  const double elapsed_s = now > last_watch_ns_ ? 1e-9 * static_cast<double>(now - last_watch_ns_) : 0.0;
  last_watch_ns_ = now;
  const double step = options_.model_fade_s > 0 ? elapsed_s / options_.model_fade_s : 1.0;
  bool fading = false;
  for (int h = 0; h < kMaxHands; ++h) {
    // Due: the later of its arrival and the end of its step (a slow visual step's model serves
    // until then); overdue past that by model_stale_after_s, the visual loop has stopped for it.
    const std::uint64_t due = std::max(snapshot_arrival_ns_, snap.model[h].t_end_ns);
    const double overdue_s = now > due ? 1e-9 * static_cast<double>(now - due) : 0.0;
    const bool overdue = overdue_s > options_.model_stale_after_s;
    if (h < snap.hands) {
      st.stale_models += overdue && !model_overdue_[h];
      if (overdue) st.model_overdue_max_s = std::max(st.model_overdue_max_s, overdue_s);
    }
    model_overdue_[h] = overdue;
    model_fade_[h] = std::clamp(model_fade_[h] + (overdue ? step : -step), 0.0, 1.0);
    const bool surfaces_overdue = overdue_s > options_.model_stale_after_s + options_.model_contacts_hold_s;
    output_fade_[h] = std::clamp(output_fade_[h] + (surfaces_overdue ? step : -step), 0.0, 1.0);
    fading = fading || (h < snap.hands && model_fade_[h] > 0);
  }
  st.stale_model_ticks += fading;
}

namespace {
// smoothstep: the weight leaves 1 and reaches 0 with zero slope, so the force changes without a kink
// at either end (a kink rings the proxy on its coupling spring).
double smooth_weight(double u) { return 1.0 - u * u * (3.0 - 2.0 * u); }
}  // namespace

double HapticCore::model_weight(int h) const { return smooth_weight(model_fade_[h]); }
double HapticCore::output_weight(int h) const { return smooth_weight(output_fade_[h]); }

const HapticModel& HapticCore::served_model(const Session& s) const {
  const int hand = links_[s.link].hand;
  const HapticModel& model = snapshots_.front().model[hand];
  return model.resyncs == hand_resyncs_[hand] ? model : no_model_;
}

void HapticCore::integrate_period(Session& s, std::uint64_t t) {
  const HapticModel& model = served_model(s);
  const double lookahead = 1e-9 * (static_cast<double>(model.t_end_ns) - static_cast<double>(t));
  const double lookahead_s = model.t_end_ns ? std::clamp(lookahead, -kMaxModelLookahead_s, kMaxModelLookahead_s) : 0.0;
  s.proxy.predict_device(1e-9 * static_cast<double>(t - start_ns_));
  s.proxy.integrate(model, 1e-9 * static_cast<double>(period_ns_), lookahead_s, model_weight(links_[s.link].hand));
  s.integrated_to_ns = t + period_ns_;
}

// A loop that was descheduled for a while (a busy machine) comes back to a device that moved on: held
// where the loop stopped, the proxies were a stall's motion behind it, and the device was jerked back
// by the coupling stiffness times that distance (1.17 N after 10 ms as a stylus lifted at 8 cm/s;
// Touch/SampleGaps/ServerStall). The periods missed are integrated as their ticks would have been:
// before each sample that waited through the stall is answered, up to when it was taken, under the
// device as the samples before it put it (HapticServer::run reads them before the late tick); then by
// the late tick up to its own time, the device carried along its velocity if its samples stopped too.
void HapticCore::catch_up(Session& s, std::uint64_t t) {
  if (s.integrated_to_ns == 0) return;
  const auto most = static_cast<long>(options_.resync_gap_s * 1e9 / static_cast<double>(period_ns_) + 0.5);
  for (long n = 0; n < most && s.integrated_to_ns < t; ++n) {
    integrate_period(s, s.integrated_to_ns);
    ++stats_->catch_up_ticks;
  }
}

void HapticCore::tick(std::uint64_t now) {
  ServerStats& st = *stats_;
  ++st.ticks;
  if (snapshots_.update()) snapshot_arrival_ns_ = now;
  watch_models(now);
  last_tick_ns_ = now;
  ProxyTargets& out = targets_.back();
  out.t_ns = now + period_ns_;  // each proxy is integrated over [now, now + T]
  for (bool& d : out.driven) d = false;
  for (int h = 0; h < kMaxHands; ++h) out.resyncs[h] = hand_resyncs_[h];
  for (int i = 0; i < kMaxSessions; ++i) {
    Session& s = sessions_[i];
    if (!s.active) continue;
    // (A datagram read after `now` was taken is not silence.)
    const double silent_s = now > s.last_seen_ns ? 1e-9 * static_cast<double>(now - s.last_seen_ns) : 0.0;
    if (s.pending) {
      if (silent_s > std::min(options_.pending_timeout_s, options_.session_timeout_s)) {
        close(s);
        ++st.pending_expired;
      }
      continue;
    }
    if (silent_s > options_.session_timeout_s) {
      close(s);
      ++st.sessions_timed_out;
      continue;
    }
    // Silence: the force fades out over ramp_s; poses bring it back at the same rate.
    const double dt = 1.0 / options_.haptic_rate_hz;
    const double step = dt / std::max(options_.ramp_s, dt);
    s.output_scale =
        silent_s > options_.silence_s ? std::max(0.0, s.output_scale - step) : std::min(1.0, s.output_scale + step);
    const DeviceLink& link = links_[s.link];
    catch_up(s, now - period_ns_);  // a tick more than a period late: the ticks missed
    integrate_period(s, now);
    if (s.follower || !s.proxy.has_device_pose()) continue;
    out.driven[link.hand] = true;
    for (int j = 0; j < link.handles; ++j) {
      out.pose[link.hand][j] = s.proxy.proxy(j);
      out.v_W[link.hand][j] = s.proxy.proxy_velocity(j);
      out.w_W[link.hand][j] = s.proxy.proxy_angular_velocity(j);
      out.v_device_W[link.hand][j] = s.proxy.device_velocity(j);
      out.w_device_W[link.hand][j] = s.proxy.device_angular_velocity(j);
    }
  }
  targets_.publish();
}

void HapticCore::send(const protocol::EncodeResult& encoded, Session* session) {
  if (!encoded.ok()) {
    ++stats_->send_errors;
    return;
  }
  std::span<const std::uint8_t> bytes = encoded.bytes;
  if (auth_ && session) {
    bytes = sealer_->seal(bytes, {protocol::TrailerKind::kServerToClient, session->id, ++session->counter_out},
                          session->keys.server_to_client);
  } else if (auth_ && handshake_key_) {
    bytes = sealer_->seal(bytes, {protocol::TrailerKind::kHandshakeReply, handshake_session_, 0}, *handshake_key_);
  }
  if (!bytes.empty() && transport_.send(bytes, *peer_)) {
    ++stats_->packets_out;
  } else {
    ++stats_->send_errors;
  }
}

void HapticCore::send_error(protocol::ErrorCode code, const char* message) {
  reply_->type = MessageType::kError;
  reply_->error.code = code;
  reply_->error.message.assign(message);
  send(encoder_.encode(reply_->error));
}

void HapticCore::reject(protocol::RejectReason reason) {
  ++stats_->packets_dropped;
  ++stats_->rejected[static_cast<std::size_t>(reason)];
}

void HapticCore::handle(std::span<const std::uint8_t> datagram, const Endpoint& peer, std::uint64_t now) {
  ++stats_->packets_in;
  peer_ = &peer;
  if (auth_) {
    handle_authenticated(datagram, now);
  } else {
    handle_plain(datagram, now);
  }
  peer_ = nullptr;
}

void HapticCore::handle_plain(std::span<const std::uint8_t> datagram, std::uint64_t now) {
  ServerStats& st = *stats_;
  const protocol::DecodeResult r = protocol::decode(datagram, *message_);
  if (!r.ok()) {
    ++st.packets_dropped;
    ++st.rejected[static_cast<std::size_t>(r.reason)];
    if (r.type == MessageType::kPoseSample && r.session_id != protocol::kNoSession) {
      // A malformed pose (NaN, absurd) from a live session's own peer: its force goes to zero now.
      if (Session* s = find_session(r.session_id); s && s->peer == *peer_) {
        s->proxy.resync();
        s->output_scale = 0;
      }
    }
    if (protocol::error_reply_allowed(r)) send_error(protocol::error_code_for(r.reason), to_string(r.reason).data());
    return;
  }
  dispatch(now);
}

// protocol/auth.hpp: the trailer is split and its tag checked before the FlatBuffer is even
// verified, so an unauthenticated datagram costs one MAC and reaches nothing else.
void HapticCore::handle_authenticated(std::span<const std::uint8_t> datagram, std::uint64_t now) {
  using protocol::RejectReason;
  ServerStats& st = *stats_;
  std::span<const std::uint8_t> body;
  protocol::Trailer trailer;
  const auto is_hello = [this](std::span<const std::uint8_t> bytes) {
    return protocol::decode(bytes, *message_).ok() && message_->type == MessageType::kHello;
  };
  if (const RejectReason r = protocol::split_trailer(datagram, body, trailer); r != RejectReason::kNone) {
    reject(r);
    // A client without the key asking for a session is told why, in plain (it could check no MAC).
    if (r == RejectReason::kMissingMac && is_hello(datagram))
      send_error(protocol::ErrorCode::kUnauthorized, "missing_mac: this server authenticates sessions (key file)");
    return;
  }
  if (trailer.kind == protocol::TrailerKind::kHello) {
    if (!protocol::verify_mac(datagram, auth_->hello_key())) {
      reject(RejectReason::kBadMac);
      if (is_hello(body)) send_error(protocol::ErrorCode::kUnauthorized, "bad_mac: the key files differ");
      return;
    }
    const protocol::DecodeResult r = protocol::decode(body, *message_);
    if (!r.ok()) {
      reject(r.reason);
      if (protocol::error_reply_allowed(r)) send_error(protocol::error_code_for(r.reason), to_string(r.reason).data());
      return;
    }
    if (message_->type != MessageType::kHello || trailer.session_id != protocol::kNoSession) {
      reject(RejectReason::kBadMac);  // a trailer kind that does not fit the message
      return;
    }
    const protocol::Hello& hello = message_->hello;
    if (hello.credentials.size() != protocol::kNonceBytes) {
      reject(RejectReason::kBadNonce);
      send_error(protocol::ErrorCode::kMalformedHello, "bad_nonce");
      return;
    }
    protocol::Nonce client_nonce;
    std::copy_n(hello.credentials.span().begin(), client_nonce.size(), client_nonce.begin());
    if (!hello_nonces_->insert(client_nonce)) {
      reject(RejectReason::kReplayed);
      return;
    }
    handshake_key_storage_ = auth_->reply_key(client_nonce);
    handshake_key_ = &handshake_key_storage_;
    on_hello(hello, &client_nonce, now);
    handshake_key_ = nullptr;
    handshake_session_ = protocol::kNoSession;
    return;
  }
  if (trailer.kind != protocol::TrailerKind::kClientToServer) {
    reject(RejectReason::kBadMac);  // a server's trailer sent to the server
    return;
  }
  Session* s = find_session(trailer.session_id);
  if (!s) {
    // An authentic datagram of a session closed lately whose counter was seen: a late copy, such as
    // the network's duplicate of the Bye that closed it, counted as the replay it is.
    for (int i = 0; i < kClosedRemembered; ++i) {
      ClosedSession& c = closed_[i];
      if (c.id != trailer.session_id || c.id == protocol::kNoSession || c.peer != *peer_ ||
          !protocol::verify_mac(datagram, c.keys.client_to_server))
        continue;
      if (protocol::accept_counter(c.counters_in, trailer.counter) == RejectReason::kReplayed) {
        reject(RejectReason::kReplayed);
        return;
      }
      break;
    }
    ++st.unknown_session;
    reject(RejectReason::kUnknownSession);
    return;
  }
  if (s->peer != *peer_) {
    ++st.wrong_peer;
    reject(RejectReason::kWrongPeer);
    return;
  }
  if (!protocol::verify_mac(datagram, s->keys.client_to_server)) {
    reject(RejectReason::kBadMac);
    return;
  }
  if (const RejectReason r = protocol::accept_counter(s->counters_in, trailer.counter); r != RejectReason::kNone) {
    reject(r);
    return;
  }
  const protocol::DecodeResult r = protocol::decode(body, *message_);
  if (r.ok() && r.session_id != trailer.session_id) {
    reject(RejectReason::kBadSession);
    return;
  }
  if (!r.ok()) {
    reject(r.reason);
    // An authentic malformed pose (NaN, absurd): its session's force goes to zero now.
    if (r.type == MessageType::kPoseSample && r.session_id == trailer.session_id) {
      s->proxy.resync();
      s->output_scale = 0;
    }
    return;
  }
  if (message_->type == MessageType::kHello) {
    reject(RejectReason::kBadMac);  // a Hello under a session key: a trailer kind that does not fit
    return;
  }
  if (s->pending) confirm(*s);
  dispatch(now);
}

void HapticCore::dispatch(std::uint64_t now) {
  ServerStats& st = *stats_;
  // A datagram naming no live session, or a live one from another address.
  const auto drop_foreign = [this, &st](const Session* s) {
    if (s) {
      ++st.wrong_peer;
      reject(protocol::RejectReason::kWrongPeer);
    } else {
      ++st.unknown_session;
      reject(protocol::RejectReason::kUnknownSession);
    }
  };
  switch (message_->type) {
    case MessageType::kHello:
      on_hello(message_->hello, nullptr, now);
      return;
    case MessageType::kPoseSample:
      on_pose(message_->pose_sample, now);
      return;
    case MessageType::kHeartbeat: {
      Session* s = find_session(message_->heartbeat.session_id);
      if (!s || s->peer != *peer_) return drop_foreign(s);
      s->last_seen_ns = now;
      reply_->heartbeat = {s->id, now, message_->heartbeat.timestamp_ns};
      send(encoder_.encode(reply_->heartbeat), s);
      return;
    }
    case MessageType::kStatsRequest: {
      Session* s = find_session(message_->stats_request.session_id);
      if (!s || s->peer != *peer_) return drop_foreign(s);
      fill_stats(reply_->stats, now);
      reply_->stats.session_id = s->id;
      for (int j = 0; j < s->proxy.handles(); ++j) {
        reply_->stats.passivity_energy_j += static_cast<float>(s->proxy.energy_in(j));
        reply_->stats.passivity_damped_j += static_cast<float>(s->proxy.passivity_damped_j(j));
      }
      reply_->stats.passivity_actions = static_cast<std::uint64_t>(s->proxy.passivity_actions());
      send(encoder_.encode(reply_->stats), s);
      return;
    }
    case MessageType::kBye: {
      Session* s = find_session(message_->bye.session_id);
      if (!s || s->peer != *peer_) return drop_foreign(s);
      close(*s);
      ++st.sessions_closed;
      return;
    }
    default:
      // Server-to-client messages sent to the server.
      ++st.packets_dropped;
      return;
  }
}

void HapticCore::on_hello(const protocol::Hello& hello, const protocol::Nonce* client_nonce, std::uint64_t now) {
  // A device of the requested kind whose hand has one handle per tracked frame; a free one first,
  // else share the least used one as a follower. The peer's own sessions (which the new one
  // replaces) and pending ones (which may never be confirmed) use nothing.
  int best = -1, best_users = kMaxSessions + 1;
  for (size_t l = 0; l < links_.size(); ++l) {
    if (links_[l].kind != hello.device_kind || links_[l].handles != static_cast<int>(hello.frames.size())) continue;
    // A glove that names its hand binds to a device on a hand of that side only.
    if (hello.hand != protocol::Hand::kUnspecified && links_[l].left != (hello.hand == protocol::Hand::kLeft)) continue;
    int users = 0;
    for (int i = 0; i < kMaxSessions; ++i) {
      const Session& o = sessions_[i];
      users += o.active && !o.pending && o.link == static_cast<int>(l) && o.peer != *peer_;
    }
    if (users < best_users) best = static_cast<int>(l), best_users = users;
  }
  if (best < 0) {
    send_error(protocol::ErrorCode::kUnsupportedDevice,
               hello.hand == protocol::Hand::kUnspecified
                   ? "the scene has no device of this kind with one handle per tracked frame"
               : hello.hand == protocol::Hand::kLeft
                   ? "the scene has no device of this kind on a left hand with one handle per tracked frame"
                   : "the scene has no device of this kind on a right hand with one handle per tracked frame");
    return;
  }
  // Without a key the same peer saying hello again replaces its session at once (in its slot).
  // With one the new session waits, pending, in a free slot (or the oldest pending one's) until
  // the client proves it holds the session key; only then is the old one replaced.
  Session* slot = nullptr;
  for (int i = 0; i < kMaxSessions && !slot && !auth_; ++i)
    if (sessions_[i].active && sessions_[i].peer == *peer_) slot = &sessions_[i];
  for (int i = 0; i < kMaxSessions && !slot; ++i)
    if (!sessions_[i].active) slot = &sessions_[i];
  for (int i = 0; i < kMaxSessions && auth_; ++i) {
    Session& o = sessions_[i];
    if (o.active && o.pending && (!slot || (slot->active && o.last_seen_ns < slot->last_seen_ns))) slot = &o;
  }
  if (!slot) {
    send_error(protocol::ErrorCode::kServerFull, "every session slot is taken");
    return;
  }
  if (slot->active) {
    if (!slot->pending) ++stats_->sessions_replaced;
    if (slot->pending) ++stats_->pending_expired;
    close(*slot);
  }
  const DeviceLink& link = links_[best];
  Session& s = *slot;
  s = Session{};
  s.active = true;
  s.pending = auth_ != nullptr;
  do s.id = ++next_session_id_;
  while (s.id == protocol::kNoSession || (find_session(s.id) != &s && find_session(s.id)));
  s.peer = *peer_;
  s.link = best;
  s.frames = static_cast<int>(hello.frames.size());
  for (int j = 0; j < s.frames; ++j) s.frame_id[j] = hello.frames[j].id;
  s.proxy.configure(link.handles, link.mass_kg, link.inertia_B, link.gains, link.limits, link.map);
  s.proxy.set_passivity_control(options_.passivity_control);
  s.proxy.set_contact_sweeps(options_.tick_contact_sweeps);
  s.proxy.set_fingers_grounded_on_palm(link.kind == protocol::DeviceKind::kGlove && link.handles > 1);
  s.last_seen_ns = now;
  ++stats_->sessions_opened;
  protocol::Welcome& w = reply_->welcome;
  fill_welcome(link, s.id, static_cast<std::uint32_t>(options_.haptic_rate_hz),
               {s.frame_id, static_cast<std::size_t>(s.frames)}, w);
  if (auth_ && client_nonce) {
    const protocol::Nonce server_nonce = protocol::random_nonce();
    w.server_nonce.assign(std::span<const std::uint8_t>(server_nonce));
    s.keys = auth_->session_keys(*client_nonce, server_nonce, s.id);
  }
  if (!s.pending) confirm(s);
  handshake_session_ = s.id;
  send(encoder_.encode(w));
  handshake_session_ = protocol::kNoSession;
}

void HapticCore::confirm(Session& s) {
  s.pending = false;
  s.follower = false;
  for (int i = 0; i < kMaxSessions; ++i) {
    Session& o = sessions_[i];
    if (!o.active || &o == &s) continue;
    if (o.peer == s.peer) {
      close(o);
      ++stats_->sessions_replaced;
    } else if (!o.pending && o.link == s.link) {
      s.follower = true;  // the device's hand is driven already: feel it, do not drive it
    }
  }
}

void HapticCore::close(Session& s) {
  add_proxy_counts(*stats_, s.proxy);
  if (auth_ && s.active) {
    ClosedSession& c = closed_[closed_next_++ % kClosedRemembered];
    c.id = s.id;
    c.peer = s.peer;
    c.keys = s.keys;
    c.counters_in = s.counters_in;
  }
  s = Session{};
}

void HapticCore::on_pose(const protocol::PoseSample& pose, std::uint64_t now) {
  ServerStats& st = *stats_;
  Session* s = find_session(pose.session_id);
  if (!s || s->peer != *peer_) {
    ++(s ? st.wrong_peer : st.unknown_session);
    reject(s ? protocol::RejectReason::kWrongPeer : protocol::RejectReason::kUnknownSession);
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
  // A sample names the tracked frames it has, in the handshake's order. A frame it leaves out has
  // lost tracking (a glove sensor that reads NaN): its device pose is held and its force ramps to
  // zero, while the others keep working. The first sample must have them all (nothing to hold).
  int tracked = 0;
  for (int j = 0; j < s->frames && tracked < static_cast<int>(pose.poses.size()); ++j)
    tracked += pose.poses[tracked].frame == s->frame_id[j];
  if (tracked != static_cast<int>(pose.poses.size())) {  // an id the handshake did not declare
    ++st.rejected[static_cast<std::size_t>(protocol::RejectReason::kFrameIdsNotIncreasing)];
    ++st.packets_dropped;
    return;
  }
  if (tracked != s->frames && !s->proxy.has_device_pose()) {
    ++st.rejected[static_cast<std::size_t>(protocol::RejectReason::kBadCount)];
    ++st.packets_dropped;
    return;
  }
  for (int j = 0, k = 0; j < s->frames; ++j) {
    s->lost[j] = !(k < tracked && pose.poses[k].frame == s->frame_id[j]);
    if (s->lost[j]) {
      ++st.frames_lost;
      continue;
    }
    const protocol::FramePose& f = pose.poses[k++];
    s->proxy.set_device_pose(j, Eigen::Vector3d(f.position_m.x, f.position_m.y, f.position_m.z),
                             Eigen::Quaterniond(f.orientation.w, f.orientation.x, f.orientation.y, f.orientation.z));
  }
  const std::uint64_t silent_ns = now - s->last_seen_ns;
  s->last_seen_ns = now;
  // The device's own interval since its last sample (its time stamps, if they went forward): its
  // velocity is taken over that, not over how far apart the samples were read, and a gap in its
  // samples is one in its time stamps, however soon after the last sample it is read
  // (ProxyHand::commit_sample). Found by read times alone, a gap was hidden by a sample that waited
  // in the link before it and was read late, just before the first after it: the force the device
  // had faded out of came back in full at the depth it sank to (+2.2e-3 to +1.75e-2 J: ServerStalls,
  // a stopped machine). At most the re-sync gap long, it is the device's pace.
  const bool stamps_forward = s->last_client_ns != 0 && pose.client_timestamp_ns > s->last_client_ns;
  const std::uint64_t max_interval_ns = static_cast<std::uint64_t>(1e9 * options_.resync_gap_s);
  const std::uint64_t interval_ns = pose.client_timestamp_ns - s->last_client_ns;
  const double interval_s =
      stamps_forward ? 1e-9 * static_cast<double>(interval_ns) : std::numeric_limits<double>::quiet_NaN();
  const bool has_interval = stamps_forward && interval_ns <= max_interval_ns;
  // How much longer than its quickest samples this one waited to be read: one from a queue waited
  // (ProxyHand::commit_sample), however its reading was broken up.
  double waited_s = std::numeric_limits<double>::quiet_NaN();
  const auto wait_ns = static_cast<std::int64_t>(now - pose.client_timestamp_ns);
  if (has_interval) {
    s->quickest_wait_ns = std::min(wait_ns, s->quickest_wait_ns + kWaitFloorRise_ns);
    waited_s = 1e-9 * static_cast<double>(wait_ns - s->quickest_wait_ns);
  } else {  // a first sample, or after a gap or a jump of the client's clock
    s->quickest_wait_ns = wait_ns;
  }
  s->last_client_ns = pose.client_timestamp_ns;
  // A loop that missed ticks (more than a period since the last) reads the samples that waited in the
  // socket meanwhile: each was taken its device's interval after the one before, and the proxies
  // are integrated up to then before it is answered (catch_up), however long the loop was stopped
  // (a sample its device took at its pace is no gap to re-sync on). Read at the loop's pace, a sample
  // was taken when it is read. It is committed at when it was taken: committed at its read time,
  // the last sample before a stopped machine's gap, read late, counted as fresh, the catch-up to the
  // first sample after the gap held the proxies under it instead of carrying the device along its
  // velocity (ProxyHand::predict_device), and that sample was then a stop's motion away: 0.56 N
  // departures lifting in free space after 10 ms (Touch/SampleGaps/MachineStall).
  const bool stalled = now > last_tick_ns_ + 2 * period_ns_;
  s->sample_ns = stalled && has_interval && s->sample_ns ? std::min(now, s->sample_ns + interval_ns) : now;
  if (stalled && (has_interval || silent_ns <= max_interval_ns)) catch_up(*s, s->sample_ns);
  if (s->proxy.commit_sample(1e-9 * static_cast<double>(s->sample_ns - start_ns_), options_.resync_gap_s, interval_s,
                             waited_s)) {
    s->resynced = true;
    ++st.resyncs;
    if (!s->follower) ++hand_resyncs_[links_[s->link].hand];
  }
  const double since_reply = s->last_reply_ns ? 1e-9 * static_cast<double>(now - s->last_reply_ns) : 1e-3;
  // A device holds each reply until the next, and fades it out once none has come for its watchdog's
  // hold, over its ramp (client::ReplyWatchdog, DESIGN section 5). Silent longer than the hold (a
  // descheduled server, a stopped machine), the device pressed on holding the reply from before,
  // then less: the stretch it built meanwhile, none of which it felt, is unfelt (ProxyHand::reply's
  // `unfelt_share`), not given back as it lifts. A deeper press is felt from there, backing out of
  // it neither pulls nor pushes, and the stretch it felt before comes back as the device's watchdog
  // and the session's ramp bring the force back (a device held still through a short stall feels its
  // press again). Given in full, the proxies caught up on the bunny's surface pushed the stylus that
  // had sunk 8 mm out with +1.3e-2 to +2.0e-2 J (hapticd stopped 100-200 ms; ServerStalls), and the
  // observer, booking replies to the queue that the device never felt, let them. After a bridged gap
  // in the device's own samples, that share of all it felt is unfelt (ProxyHand::reply).
  const auto hold_ns = static_cast<std::uint64_t>(kDeviceWatchdog.hold.count());
  // A reply to a sample that waited to be read (a queue read after a stall, a link that held it)
  // reaches the device no sooner than the replies to the samples after it: it ends no silence of the
  // device for them (the last sample before a stopped machine's gap, answered just before the first
  // after it). Waited: half the watchdog's hold longer than the quickest samples, so that a step in
  // the link's latency, which the quickest wait follows only slowly, is not taken for a silence.
  const bool waited = has_interval && waited_s > 0.5e-9 * static_cast<double>(hold_ns);
  if (s->held_reply_ns && now > s->held_reply_ns + hold_ns)
    s->unheld_from_ns = s->held_reply_ns + hold_ns, s->unheld_to_ns = now;
  double unfelt_share = 0;  // of the held reply, when the device took this sample
  if (s->sample_ns > s->unheld_from_ns && s->sample_ns <= s->unheld_to_ns)
    unfelt_share = std::min(1.0, static_cast<double>(s->sample_ns - s->unheld_from_ns) /
                                     static_cast<double>(std::max<std::int64_t>(kDeviceWatchdog.ramp.count(), 1)));
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
  // A model overdue past its contacts' hold fades out of what the device feels: the proxy stays on the
  // model's surfaces (ProxyHand::integrate) while the device stops feeling them.
  const double scale = s->output_scale * (model.handles == s->frames ? output_weight(link.hand) : 1.0);
  ReplyWrench replies[kMaxHapticHandles];
  for (int j = 0; j < s->frames; ++j) {
    const bool gated = link.contact_gated && !(model.handles == s->frames && model.handle_in_contact[j]);
    replies[j] = s->proxy.reply(j, gated || s->lost[j] ? 0.0 : scale, since_reply, gated, unfelt_share);
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
  if (model.handles == 0 || model_fade_[link.hand] > 0) out.flags |= protocol::ForceFlags::kStale;
  s->last_reply_ns = now;
  if (!waited) s->held_reply_ns = now;
  out.server_send_ns = transport_.send_time_ns();
  const protocol::EncodeResult encoded = encoder_.encode(out);
  // Compute per sample: from the datagram read to the reply encoded (the send syscall is I/O).
  st.reply_compute_us.add(1e-3 * static_cast<double>(transport_.send_time_ns() - now));
  send(encoded, s);
  ++st.replies;
}

void HapticCore::fill_stats(protocol::Stats& out, std::uint64_t now) const {
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
    active += !sessions_[i].pending;
    clamps += static_cast<std::uint64_t>(sessions_[i].proxy.clamps());
    resets += static_cast<std::uint64_t>(sessions_[i].proxy.resets());
  }
  out.clamps = clamps;
  out.resets = resets;
  out.overruns = st.overruns;
  out.tick_compute_p50_us = static_cast<float>(st.tick_compute_us.percentile(50));
  out.tick_compute_p99_us = static_cast<float>(st.tick_compute_us.percentile(99));
  out.tick_jitter_p99_us = static_cast<float>(st.tick_jitter_us.percentile(99));
  out.visual_step_median_ms = visual_ ? static_cast<float>(visual_->step_ms.load(std::memory_order_relaxed)) : 0.0f;
  const double elapsed = 1e-9 * static_cast<double>(now - start_ns_);
  out.haptic_rate_hz = elapsed > 0 ? static_cast<float>(static_cast<double>(st.ticks) / elapsed) : 0.0f;
  out.visual_rate_hz = visual_ ? static_cast<float>(visual_->rate_hz.load(std::memory_order_relaxed)) : 0.0f;
  out.sessions_active = active;
}

}  // namespace hapticd::haptic
