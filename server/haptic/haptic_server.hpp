#pragma once
// The haptic loop of hapticd (DESIGN.md sections 1, 4, 5): one dedicated thread
// that owns the UDP socket, the sessions and their proxies. It waits on the
// socket until the next tick's absolute deadline: a pose sample is answered at
// once from the current proxy (the device does not wait for a tick); at each
// tick every proxy is integrated under its hand's latest linearized model and
// the proxy poses are handed to the visual loop. Both handoffs are triple
// buffers: no lock, no allocation, no logging on this thread (counted instead).
#include <atomic>
#include <boost/asio/ip/udp.hpp>
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "protocol/codec.hpp"
#include "protocol/sequence_window.hpp"
#include "server/haptic/loop_stats.hpp"
#include "server/haptic/triple_buffer.hpp"
#include "server/haptic/device_link.hpp"
#include "server/haptic/virtual_coupling.hpp"

namespace hapticd {

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
  bool driven[kMaxHands]{};
  // Counts the driving session's re-syncs (a first pose, a pose after a gap): the
  // proxies jumped onto the device, and the hand is moved there rigidly rather
  // than dragged through space in one step.
  std::uint32_t resyncs[kMaxHands]{};
  HapticPose pose[kMaxHands][kMaxHapticHandles];
  Eigen::Vector3d v_W[kMaxHands][kMaxHapticHandles], w_W[kMaxHands][kMaxHapticHandles];
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
};

struct ServerStats {
  std::uint64_t packets_in = 0, packets_out = 0, packets_dropped = 0;
  std::uint64_t rejected[protocol::kRejectReasonCount]{};
  std::uint64_t unknown_session = 0, wrong_peer = 0, duplicates = 0, stale = 0, gaps = 0;
  std::uint64_t clamps = 0, resets = 0, resyncs = 0, overruns = 0, ticks = 0, replies = 0;
  std::uint64_t sessions_opened = 0, sessions_closed = 0, sessions_timed_out = 0, send_errors = 0;
  MicrosecondHistogram tick_compute_us, tick_jitter_us, reply_compute_us;
  double elapsed_s = 0;
  bool realtime = false;
};

class HapticServer {
 public:
  // Binds the socket (throws std::runtime_error with the address on failure).
  HapticServer(std::vector<DeviceLink> links, const ServerOptions& options, TripleBuffer<HapticSnapshot>& snapshots,
               TripleBuffer<ProxyTargets>& targets);
  ~HapticServer();
  HapticServer(const HapticServer&) = delete;
  HapticServer& operator=(const HapticServer&) = delete;

  std::uint16_t port() const;
  std::string address() const;

  // The haptic thread's body: returns when `stop` becomes true (sessions are sent nothing more).
  void run(const std::atomic<bool>& stop);

  // Readable after run() returned.
  const ServerStats& stats() const { return *stats_; }
  // The visual loop's achieved rate and step time, for the Stats message (set by the visual thread).
  std::atomic<double> visual_rate_hz{0}, visual_step_ms{0};

 private:
  struct Session;
  void tick(std::uint64_t now_ns);
  void handle(std::size_t bytes, std::uint64_t now_ns);
  void on_hello(const protocol::Hello& hello);
  void on_pose(const protocol::PoseSample& pose, std::uint64_t now_ns);
  void send(const protocol::EncodeResult& encoded);
  void send_error(protocol::ErrorCode code, const char* message);
  Session* find_session(std::uint64_t id);
  void fill_stats(protocol::Stats& out) const;

  std::vector<DeviceLink> links_;
  ServerOptions options_;
  TripleBuffer<HapticSnapshot>& snapshots_;
  TripleBuffer<ProxyTargets>& targets_;
  struct Io;
  std::unique_ptr<Io> io_;
  std::unique_ptr<Session[]> sessions_;
  std::unique_ptr<ServerStats> stats_;
  std::unique_ptr<protocol::ReceiveBuffer> rx_;
  std::unique_ptr<protocol::Message> message_;
  std::unique_ptr<protocol::Message> reply_;
  protocol::Encoder encoder_;
  std::uint64_t next_session_id_ = 0;
  std::uint32_t hand_resyncs_[kMaxHands]{};
  HapticModel no_model_;  // handles = 0: the proxy feels only its device
  std::uint64_t start_ns_ = 0;
};

}  // namespace hapticd
