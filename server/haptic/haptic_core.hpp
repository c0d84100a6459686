#pragma once
// The haptic tick of hapticd (DESIGN.md sections 1, 4, 5), without a socket or a clock: a datagram
// from a peer at a given time is decoded, checked and answered through a Transport (decode ->
// session -> reply from the current proxy), and a tick at a given time integrates every session's
// proxies under its hand's newest model and publishes their poses. The real-time runner
// (HapticServer: the UDP socket, pacing, the haptic thread) and the lockstep runner
// (server/offline: simulated time, tests, the multirate suite) drive this same object. Both
// handoffs with the visual step are triple buffers: no lock, no allocation, no logging here.
#include <atomic>
#include <boost/asio/ip/udp.hpp>
#include <cstdint>
#include <memory>
#include <optional>
#include <span>
#include <string>
#include <vector>

#include "protocol/auth.hpp"
#include "protocol/codec.hpp"
#include "protocol/sequence_window.hpp"
#include "server/haptic/device_link.hpp"
#include "server/haptic/loop_stats.hpp"
#include "server/haptic/triple_buffer.hpp"
#include "server/haptic/virtual_coupling.hpp"

namespace hapticd::haptic {

constexpr int kMaxHands = 4;
constexpr int kMaxSessions = 16;

// What the visual loop publishes for the haptic loop.
struct HapticSnapshot {
  int hands = 0;
  HapticModel model[kMaxHands];
};

// What the haptic loop publishes for the visual loop: per hand, where its
// driving session's proxies are (the targets the simulated handles are pulled to).
struct ProxyTargets {
  ProxyTargets() {
    for (int h = 0; h < kMaxHands; ++h)
      for (int j = 0; j < kMaxHapticHandles; ++j)
        v_W[h][j].setZero(), w_W[h][j].setZero(), v_device_W[h][j].setZero(), w_device_W[h][j].setZero();
  }
  bool driven[kMaxHands]{};
  // Counts the driving session's re-syncs (a first pose, a pose after a gap): the
  // proxies jumped onto the device, and the hand is moved there rigidly rather
  // than dragged through space in one step.
  std::uint32_t resyncs[kMaxHands]{};
  HapticPose pose[kMaxHands][kMaxHapticHandles];
  Eigen::Vector3d v_W[kMaxHands][kMaxHapticHandles], w_W[kMaxHands][kMaxHapticHandles];
  // The devices' filtered velocities (HandleTarget::v_device_W).
  Eigen::Vector3d v_device_W[kMaxHands][kMaxHapticHandles], w_device_W[kMaxHands][kMaxHapticHandles];
  // The time the poses are of (CLOCK_MONOTONIC, ns): the end of the haptic tick that integrated
  // them, up to one period after the visual loop reads them.
  std::uint64_t t_ns = 0;
};

struct ServerOptions {
  std::string bind = "127.0.0.1";
  std::uint16_t port = 0;
  double haptic_rate_hz = 1000;
  bool busy_poll = false;         // spin on the socket instead of sleeping (a dedicated core)
  double resync_gap_s = 0.05;     // a pose after a longer gap re-syncs the proxy (no force jump)
  double silence_s = 0.1;         // no pose for this long: the session's force ramps to zero...
  double ramp_s = 0.1;            // ...over this time (and back up when poses resume)
  double session_timeout_s = 5.0; // then the session is dropped
  bool realtime = true;           // try SCHED_FIFO for the haptic thread (not with busy_poll)
  // The pre-shared key: every session is authenticated and every datagram carries a MAC
  // (protocol/auth.hpp). Without one the server binds only to loopback unless insecure_bind.
  std::optional<protocol::Key> key;
  bool insecure_bind = false;
  // With a key, a session stays pending (drives nothing, replaces nothing) until its client's
  // first authenticated datagram; a pending session silent this long is dropped.
  double pending_timeout_s = 2.0;
  // Visual-loop watchdog: a hand's model is overdue from the later of its arrival and the end of the
  // step it describes (HapticModel::t_end_ns). Overdue longer than model_stale_after_s, its
  // influence (F0, K, D) fades smoothly over model_fade_s to the safe model (the replies are flagged
  // stale); when models flow again it comes back over the same time, so neither way has a force
  // jump. The model's contact rows and clearance planes, the surfaces the world last found, hold the
  // proxy throughout, and the device feels them for model_contacts_hold_s more; overdue past both,
  // what the device feels fades out over model_fade_s too (a world that stays stopped: its surfaces'
  // tangent planes would be felt where nothing is). A stall while the device presses an object then
  // leaves the object solid: faded at once, the device sank into it unfelt and was pushed back out when
  // models came again (+9 mJ with the passivity controller off, a 1 N drag on the lift after with it
  // on: VisualStalls).
  // Every session's passivity controller (ProxyHand::set_passivity_control, kPassivityBudget_J).
  bool passivity_control = true;
  // Every session's tick contact solve: at most this many sweeps (ProxyHand::set_contact_sweeps).
  int tick_contact_sweeps = kDefaultTickContactSweeps;
  double model_stale_after_s = 0.1;
  double model_fade_s = 0.1;
  double model_contacts_hold_s = 0.5;
  // Per-source limit (a token bucket per address and port, before anything is decoded): datagrams
  // a second (0: 4x haptic_rate_hz, the rate every session is granted) and the burst allowed.
  double source_rate_hz = 0;
  double source_burst = 200;
};

struct ServerStats {
  std::uint64_t packets_in = 0, packets_out = 0, packets_dropped = 0;
  std::uint64_t rejected[protocol::kRejectReasonCount]{};
  std::uint64_t unknown_session = 0, wrong_peer = 0, duplicates = 0, stale = 0, gaps = 0;
  std::uint64_t frames_lost = 0;  // tracked frames left out of pose samples (lost tracking), summed
  std::uint64_t clamps = 0, resets = 0, resyncs = 0, overruns = 0, ticks = 0, replies = 0;
  // Ticks of a glove-sized model the dense LU solved instead of its prepared solver (ProxyHand::solver_fallbacks).
  std::uint64_t solver_fallbacks = 0;
  // Ticks whose prepared answer the probes sent to the exact residual (ProxyHand::solver_refinements).
  std::uint64_t solver_refinements = 0;
  // Ticks whose contact solve was redone without the lookahead, and ticks at which the proxies held
  // still after it (ProxyHand::lookahead_fallbacks, ProxyHand::contact_holds).
  std::uint64_t lookahead_fallbacks = 0, contact_holds = 0;
  // Ticks whose contact solve stopped at its sweep limit without an exact answer (ProxyHand::contact_unconverged).
  std::uint64_t contact_unconverged = 0;
  // The contact solves run and their sweeps summed (ProxyHand::contact_solves, contact_sweeps_total).
  std::uint64_t contact_solves = 0, contact_sweeps = 0;
  // Ticks at which a session's device was overdue and followed along its velocity (ProxyHand::predict_device).
  std::uint64_t overdue_device_ticks = 0;
  // Gaps in a device's samples bridged by a clutch, not re-synced (ProxyHand::commit_sample).
  std::uint64_t bridged_gaps = 0;
  // Periods integrated for the ticks the loop missed (HapticCore::catch_up), summed over sessions.
  std::uint64_t catch_up_ticks = 0;
  std::uint64_t sessions_opened = 0, sessions_closed = 0, sessions_timed_out = 0, send_errors = 0;
  // Sessions replaced by the same peer's newer one; pending sessions never confirmed (a key only).
  std::uint64_t sessions_replaced = 0, pending_expired = 0;
  // Datagrams over their source's allowance (also in rejected[kRateLimited]); sources that displaced
  // another from the rate limiter's table.
  std::uint64_t rate_limited = 0, rate_sources_evicted = 0;
  // Visual-loop watchdog, per hand: models that went overdue (stale_models), ticks at which a hand's
  // model was faded at all (stale_model_ticks), and the longest time a model was overdue, s.
  std::uint64_t stale_models = 0, stale_model_ticks = 0;
  double model_overdue_max_s = 0;
  MicrosecondHistogram tick_compute_us, tick_jitter_us, reply_compute_us;
  double elapsed_s = 0;
  double cpu_s = 0;  // the haptic thread's CPU time over the run (user and system)
  int receive_buffer_bytes = 0;  // the socket's, as the kernel granted it
  bool realtime = false;
};

// What the visual runner reports of itself for the Stats message (written by the visual thread,
// read by the haptic one; neither holds the other).
struct VisualReport {
  std::atomic<double> rate_hz{0}, step_ms{0};
};

using Endpoint = boost::asio::ip::udp::endpoint;

// Where the core's replies go. The real-time runner sends them on its socket; the lockstep runner
// hands them to its simulated device.
class Transport {
 public:
  // Sends one datagram to `to`; false when it could not (counted as a send error).
  virtual bool send(std::span<const std::uint8_t> datagram, const Endpoint& to) = 0;
  // The time stamped into a reply as it is sent (ForceSample::server_send_ns, the reply's compute
  // time): a measurement for the client, never an input to the simulation.
  virtual std::uint64_t send_time_ns() = 0;

 protected:
  ~Transport() = default;
};

class HapticCore {
 public:
  // Throws std::invalid_argument on options out of range. Allocates everything it will use.
  HapticCore(std::vector<DeviceLink> links, const ServerOptions& options, TripleBuffer<HapticSnapshot>& snapshots,
             TripleBuffer<ProxyTargets>& targets, Transport& transport, const VisualReport* visual = nullptr);
  ~HapticCore();
  HapticCore(const HapticCore&) = delete;
  HapticCore& operator=(const HapticCore&) = delete;

  // The run starts at `now_ns` (session clocks, the watchdog's).
  void start(std::uint64_t now_ns);
  // One datagram from `peer`, received at `now_ns`.
  void handle(std::span<const std::uint8_t> datagram, const Endpoint& peer, std::uint64_t now_ns);
  // One haptic tick at `now_ns`: the newest snapshot, the watchdog, every session's proxies
  // integrated over one haptic period, the proxies published for the visual step.
  void tick(std::uint64_t now_ns);
  // A datagram dropped by the runner before it reached the core (e.g. over its source's rate).
  void reject(protocol::RejectReason reason);
  // At the end of a run: the open sessions' proxy counters added to the stats.
  void finish();

  const std::vector<DeviceLink>& links() const { return links_; }
  const ServerOptions& options() const { return options_; }
  double haptic_period_s() const { return 1.0 / options_.haptic_rate_hz; }
  // A live session's proxies (null for no such session): for the lockstep runner and tests.
  const ProxyHand* proxy_of(std::uint64_t session_id) const;
  ServerStats& stats() { return *stats_; }
  const ServerStats& stats() const { return *stats_; }
  static std::size_t session_bytes();
  std::size_t memory_bytes() const;

 private:
  struct Session;
  struct ClosedSession;
  static constexpr int kClosedRemembered = 16;
  void watch_models(std::uint64_t now_ns);
  // The model session `s`'s proxies are integrated under: its hand's, once the visual loop has moved
  // the hand to the proxies' last re-sync (until then the proxies feel their device only).
  const HapticModel& served_model(const Session& s) const;
  // One period of `s`'s proxies from `t_ns` (a tick's: the device as predict_device takes it then,
  // the served model with its lookahead from then).
  void integrate_period(Session& s, std::uint64_t t_ns);
  // The periods of `s`'s proxies that begin before `t_ns` and were not integrated (a loop that
  // missed ticks: HapticServer::run), each integrated as its tick would have been, at most the
  // re-sync gap's worth; counted (catch_up_ticks).
  void catch_up(Session& s, std::uint64_t t_ns);
  // The smoothstep weights of the watchdog's fades (1: none): the model's F0, K, D on the proxy, and
  // what the device feels.
  double model_weight(int hand) const;
  double output_weight(int hand) const;
  void handle_plain(std::span<const std::uint8_t> datagram, std::uint64_t now_ns);
  void handle_authenticated(std::span<const std::uint8_t> datagram, std::uint64_t now_ns);
  void dispatch(std::uint64_t now_ns);
  void on_hello(const protocol::Hello& hello, const protocol::Nonce* client_nonce, std::uint64_t now_ns);
  void on_pose(const protocol::PoseSample& pose, std::uint64_t now_ns);
  void confirm(Session& s);
  void close(Session& s);
  // Sends to the peer of the datagram being handled: plain without a key; with one, a session's
  // reply sealed with its server -> client key, or a handshake reply sealed with the reply key of
  // the Hello being answered (handshake_key_, or plain when that Hello was not authentic).
  void send(const protocol::EncodeResult& encoded, Session* session = nullptr);
  void send_error(protocol::ErrorCode code, const char* message);
  Session* find_session(std::uint64_t id);
  void fill_stats(protocol::Stats& out, std::uint64_t now_ns) const;

  std::vector<DeviceLink> links_;
  ServerOptions options_;
  TripleBuffer<HapticSnapshot>& snapshots_;
  TripleBuffer<ProxyTargets>& targets_;
  Transport& transport_;
  const VisualReport* visual_;
  const Endpoint* peer_ = nullptr;  // the sender of the datagram being handled
  std::unique_ptr<Session[]> sessions_;
  std::unique_ptr<ClosedSession[]> closed_;  // the last kClosedRemembered sessions closed (with a key)
  unsigned closed_next_ = 0;
  std::unique_ptr<ServerStats> stats_;
  std::unique_ptr<protocol::Message> message_;
  std::unique_ptr<protocol::Message> reply_;
  protocol::Encoder encoder_;
  std::unique_ptr<protocol::AuthKeys> auth_;  // null without a key
  std::unique_ptr<protocol::Sealer> sealer_;
  std::unique_ptr<protocol::NonceCache> hello_nonces_;
  const protocol::Key* handshake_key_ = nullptr;  // the reply key of the Hello being answered
  protocol::Key handshake_key_storage_{};
  std::uint64_t handshake_session_ = 0;
  std::uint64_t next_session_id_ = 0;
  std::uint32_t hand_resyncs_[kMaxHands]{};
  // Visual-loop watchdog: when the newest snapshot arrived, and per hand how far its model has faded
  // (0 fresh .. 1 safe model; its weight is 1 - smoothstep) and whether it is overdue.
  std::uint64_t snapshot_arrival_ns_ = 0, last_watch_ns_ = 0;
  double model_fade_[kMaxHands]{}, output_fade_[kMaxHands]{};
  bool model_overdue_[kMaxHands]{};
  HapticModel no_model_;  // handles = 0: the proxy feels only its device
  std::uint64_t start_ns_ = 0, period_ns_ = 0;
  std::uint64_t last_tick_ns_ = 0;  // the time of the last tick() (start() before the first)
};

}  // namespace hapticd::haptic
