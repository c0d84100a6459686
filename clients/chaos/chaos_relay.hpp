#pragma once

// A UDP relay for tests and benches that sits between clients and a server on loopback and damages
// the traffic in both directions at configured rates: loss, duplication, reordering, fixed and
// jittered delay, corruption. Deterministic decisions for a seed (one generator, consulted in the
// order datagrams arrive). `haptic-chaos` (clients/tools/haptic_chaos.cpp) is the tool around it;
// tests run it in-process on a thread of their own.
//
// Per datagram, in this order: lost with probability `loss`; else corrupted (one byte at a random
// offset XORed with a random non-zero value) with probability `corrupt`; duplicated (a second, intact
// copy sent right after the first) with probability `duplicate`; held back so that the next
// datagram of the same direction overtakes it with probability `reorder` (released right after that
// one, or after `reorder_hold_ms` if none comes); delayed by `delay_ms` plus a uniform draw in
// [0, jitter_ms] (jitter alone may reorder too; that is not counted as reordered).
//
// Each client address gets its own upstream socket, so the server sees as many peers as there are
// clients. Not for the hot path: it allocates freely.

#include <atomic>
#include <cstdint>
#include <memory>
#include <nlohmann/json.hpp>
#include <string>

namespace hapticd::chaos {

struct ChaosConfig {
  double loss = 0.0;              // probability per datagram, in [0, 1]
  double duplicate = 0.0;         // in [0, 1]
  double reorder = 0.0;           // in [0, 1]
  double corrupt = 0.0;           // in [0, 1]
  double delay_ms = 0.0;          // fixed one-way delay, >= 0
  double jitter_ms = 0.0;         // uniform extra delay in [0, jitter_ms], >= 0
  double reorder_hold_ms = 20.0;  // the longest a held-back datagram waits for one to overtake it
  std::uint64_t seed = 1;
};

// Throws std::invalid_argument naming the field when a rate is outside [0, 1] or a delay negative.
void validate(const ChaosConfig& config);

struct DirectionCounts {
  std::uint64_t received = 0;    // datagrams read from the sender
  std::uint64_t sent = 0;        // datagrams written to the receiver (duplicates included)
  std::uint64_t lost = 0;        // dropped on purpose
  std::uint64_t duplicated = 0;  // extra copies sent
  std::uint64_t reordered = 0;   // held back until another overtook it
  std::uint64_t corrupted = 0;   // sent with one byte changed
  std::uint64_t send_errors = 0;
  std::uint64_t overflow = 0;  // dropped because the delay queue was full
};

struct ChaosCounts {
  DirectionCounts to_server;  // client -> server
  DirectionCounts to_client;  // server -> client
  std::uint64_t clients = 0;  // distinct client addresses seen
};

class ChaosRelay {
 public:
  // Binds `listen_address`:`listen_port` (0 picks a free port) for clients and forwards to
  // `forward_host`:`forward_port` (resolved once, IPv4 first). Throws std::runtime_error.
  ChaosRelay(const ChaosConfig& config, const std::string& forward_host, std::uint16_t forward_port,
             const std::string& listen_address = "127.0.0.1", std::uint16_t listen_port = 0);
  ~ChaosRelay();
  ChaosRelay(const ChaosRelay&) = delete;
  ChaosRelay& operator=(const ChaosRelay&) = delete;

  [[nodiscard]] std::uint16_t port() const;
  [[nodiscard]] std::string address() const;

  // Relays on the calling thread until `stop` becomes true; what is still queued then is dropped
  // (not counted as sent).
  void run(const std::atomic<bool>& stop);
  // The same on a thread of its own, until stop() (or the destructor).
  void start();
  void stop();

  // Safe to read at any time (a consistent copy).
  [[nodiscard]] ChaosCounts counts() const;
  [[nodiscard]] const ChaosConfig& config() const;

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

// {"config": {...}, "to_server": {...}, "to_client": {...}, "clients": n}
nlohmann::json to_json(const ChaosCounts& counts, const ChaosConfig& config);

}  // namespace hapticd::chaos
