#include "server/haptic/source_rate_limiter.hpp"

#include <netinet/in.h>

#include <algorithm>
#include <cstring>
#include <random>

namespace hapticd::haptic {
namespace {

// splitmix64's finalizer: every input bit reaches every output bit.
std::uint64_t mix(std::uint64_t x) {
  x ^= x >> 30;
  x *= 0xbf58476d1ce4e5b9ull;
  x ^= x >> 27;
  x *= 0x94d049bb133111ebull;
  return x ^ (x >> 31);
}

}  // namespace

SourceRateLimiter::SourceRateLimiter(double rate_hz, double burst) : rate_hz_(rate_hz), burst_(std::max(burst, 1.0)) {
  // Slot positions are not predictable from outside (no chosen ports crowding one probe run).
  std::random_device rd;
  seed_ = (static_cast<std::uint64_t>(rd()) << 32) ^ rd();
}

SourceRateLimiter::Key SourceRateLimiter::key_of(const sockaddr_storage& from, socklen_t len) {
  Key k;
  if (from.ss_family == AF_INET && len >= static_cast<socklen_t>(sizeof(sockaddr_in))) {
    sockaddr_in a;
    std::memcpy(&a, &from, sizeof a);
    k.family_port = (static_cast<std::uint64_t>(AF_INET) << 16) | a.sin_port;
    k.address_lo = a.sin_addr.s_addr;
  } else if (from.ss_family == AF_INET6 && len >= static_cast<socklen_t>(sizeof(sockaddr_in6))) {
    sockaddr_in6 a;
    std::memcpy(&a, &from, sizeof a);
    k.family_port = (static_cast<std::uint64_t>(AF_INET6) << 16) | a.sin6_port;
    std::memcpy(&k.address_hi, a.sin6_addr.s6_addr, 8);
    std::memcpy(&k.address_lo, a.sin6_addr.s6_addr + 8, 8);
  } else {
    k.family_port = from.ss_family;  // no port to tell sources apart: one bucket per family
  }
  return k;
}

std::uint64_t SourceRateLimiter::hash(const Key& k) const {
  return mix(mix(mix(k.family_port ^ seed_) ^ k.address_hi) ^ k.address_lo);
}

bool SourceRateLimiter::allow(const sockaddr_storage& from, socklen_t from_len, std::uint64_t now) {
  const Key key = key_of(from, from_len);
  const std::uint64_t start = hash(key);
  Slot* slot = nullptr;
  Slot* victim = nullptr;
  for (int i = 0; i < kProbe && !slot; ++i) {
    Slot& s = slots_[(start + static_cast<std::uint64_t>(i)) & (kSlots - 1)];
    if (s.used && s.key == key) {
      slot = &s;
    } else if (!victim || (victim->used && (!s.used || s.last_ns < victim->last_ns))) {
      victim = &s;
    }
  }
  if (!slot) {
    evictions_ += victim->used;
    *victim = Slot{key, true, now, burst_};
    slot = victim;
  }
  // Refill for the time since this source was last seen (a clock that steps back refills nothing).
  const double elapsed_s = now > slot->last_ns ? 1e-9 * static_cast<double>(now - slot->last_ns) : 0.0;
  slot->tokens = std::min(burst_, slot->tokens + rate_hz_ * elapsed_s);
  slot->last_ns = now;
  if (slot->tokens < 1.0) return false;
  slot->tokens -= 1.0;
  return true;
}

}  // namespace hapticd::haptic
