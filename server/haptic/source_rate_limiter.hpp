#pragma once
// Per-source datagram rate limit of the haptic thread (DESIGN.md section 4: every datagram is
// untrusted): a token bucket per source address and port, in a fixed open-addressed table. The
// haptic loop asks it before a datagram is authenticated or decoded, so a flood from one source
// costs one table probe per datagram and reaches nothing else. No allocation, no lock.
//
// A source not in the table takes the free slot of its probe run, else the run's least recently
// seen one, with a full bucket: many sources (spoofed or rotating ports) can only evict each other
// and legitimate clients back to a full bucket, never below their allowance; they escape the
// per-source limit that way, and what bounds their cost then is the drain rate of the loop.
#include <sys/socket.h>

#include <cstdint>

namespace hapticd::haptic {

class SourceRateLimiter {
 public:
  static constexpr int kSlots = 256;  // sources tracked at once (a power of two)
  static constexpr int kProbe = 8;    // slots a source may land in

  // `rate_hz` datagrams a second per source, in bursts of up to `burst` datagrams.
  SourceRateLimiter(double rate_hz, double burst);

  // Whether a datagram from `from` at `now_ns` may be handled; it takes a token if so.
  bool allow(const sockaddr_storage& from, socklen_t from_len, std::uint64_t now_ns);

  double rate_hz() const { return rate_hz_; }
  double burst() const { return burst_; }
  // Sources that displaced another from the table.
  std::uint64_t evictions() const { return evictions_; }

 private:
  struct Key {
    std::uint64_t family_port = 0, address_hi = 0, address_lo = 0;
    bool operator==(const Key&) const = default;
  };
  struct Slot {
    Key key;
    bool used = false;
    std::uint64_t last_ns = 0;
    double tokens = 0;
  };
  static Key key_of(const sockaddr_storage& from, socklen_t from_len);
  std::uint64_t hash(const Key& k) const;

  double rate_hz_, burst_;
  std::uint64_t seed_;
  std::uint64_t evictions_ = 0;
  Slot slots_[kSlots];
};

}  // namespace hapticd::haptic
