#pragma once
// The real-time runner of the haptic tick (DESIGN.md sections 1, 4, 5): one dedicated thread that
// owns the UDP socket and drives a HapticCore (haptic_core.hpp: the sessions, their proxies, the
// replies) on the wall clock. It waits on the socket until the next tick's absolute deadline: a pose
// sample is answered at once from the current proxy (the device does not wait for a tick); at each
// deadline the core ticks. Per-source rate limits and the socket's batching live here; no lock, no
// allocation, no logging on this thread (counted instead).
#include <atomic>
#include <boost/asio/ip/udp.hpp>
#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "server/haptic/haptic_core.hpp"
#include "server/haptic/source_rate_limiter.hpp"

namespace hapticd::haptic {

class HapticServer {
 public:
  // Throws std::runtime_error when options.bind is not an IP address, is not loopback while there
  // is no key and no insecure_bind, or cannot be bound with options.port (an address this host does
  // not have, a port in use). The constructor checks the same; hapticd calls it before loading the scene.
  static void check_bind(const ServerOptions& options);
  // Binds the socket (throws std::runtime_error with the address on failure). `visual`: the visual
  // runner's report for the Stats message (none: zeros).
  HapticServer(std::vector<DeviceLink> links, const ServerOptions& options, TripleBuffer<HapticSnapshot>& snapshots,
               TripleBuffer<ProxyTargets>& targets, const VisualReport* visual = nullptr);
  ~HapticServer();
  HapticServer(const HapticServer&) = delete;
  HapticServer& operator=(const HapticServer&) = delete;

  std::uint16_t port() const;
  std::string address() const;
  const std::vector<DeviceLink>& links() const { return core_.links(); }
  double haptic_period_s() const { return core_.haptic_period_s(); }

  // The haptic thread's body: returns when `stop` becomes true (sessions are sent nothing more).
  void run(const std::atomic<bool>& stop);

  // Readable after run() returned.
  const ServerStats& stats() const { return core_.stats(); }
  // Memory, all of it allocated by the constructor (nothing after): one session slot, and the
  // whole server (kMaxSessions slots, buffers, codec, rate limiter), bytes.
  static std::size_t session_bytes() { return HapticCore::session_bytes(); }
  std::size_t memory_bytes() const;

 private:
  struct Io;
  struct Socket;
  struct RxBatch;
  ServerOptions options_;
  std::unique_ptr<Io> io_;
  std::unique_ptr<Socket> socket_;
  HapticCore core_;
  // Datagrams are read kRxBatch per system call, at most kRxRounds calls before the tick deadline is checked.
  static constexpr int kRxBatch = 32, kRxRounds = 8;
  // While a source is over its allowance, the loop drains the socket this often instead of waking
  // for every datagram (a bound on what a flood adds to the others' round trips), ns; not while a
  // batch comes back full (then it reads on).
  static constexpr std::uint64_t kFloodCoalesce_ns = 50'000;
  // The socket's receive buffer asked for (the kernel counts its own overhead in it), bytes.
  static constexpr int kReceiveBufferBytes = 4 << 20;
  // SCHED_FIFO priority of the haptic thread (above the kernel's default threaded IRQs at 50).
  static constexpr int kRealtimePriority = 80;
  std::unique_ptr<RxBatch> rx_batch_;
  std::unique_ptr<SourceRateLimiter> limiter_;
  struct Drained {
    bool flooded = false;  // a source was over its allowance
    bool backlog = false;  // the last call filled its batch: more may be waiting
  };
  // Reads what has arrived and hands each datagram to the core, a batch per system call, up to
  // kRxRounds calls, and stops early once `deadline` has passed.
  Drained drain(std::uint64_t deadline);
};

}  // namespace hapticd::haptic
