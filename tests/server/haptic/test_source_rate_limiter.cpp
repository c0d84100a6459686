// The haptic loop's per-source token bucket on a synthetic clock: bursts, the steady allowance,
// sources apart, a table overrun by many sources, and no allocation.
#include <arpa/inet.h>
#include <gtest/gtest.h>
#include <netinet/in.h>

#include <cstring>

#include "allocation_counter.hpp"
#include "server/haptic/source_rate_limiter.hpp"

namespace hapticd::haptic {
namespace {

sockaddr_storage v4(const char* address, std::uint16_t port) {
  sockaddr_in a{};
  a.sin_family = AF_INET;
  a.sin_port = htons(port);
  inet_pton(AF_INET, address, &a.sin_addr);
  sockaddr_storage s{};
  std::memcpy(&s, &a, sizeof a);
  return s;
}

sockaddr_storage v6(const char* address, std::uint16_t port) {
  sockaddr_in6 a{};
  a.sin6_family = AF_INET6;
  a.sin6_port = htons(port);
  inet_pton(AF_INET6, address, &a.sin6_addr);
  sockaddr_storage s{};
  std::memcpy(&s, &a, sizeof a);
  return s;
}

constexpr socklen_t kV4 = sizeof(sockaddr_in), kV6 = sizeof(sockaddr_in6);
constexpr std::uint64_t kMs = 1'000'000;

int allowed(SourceRateLimiter& limiter, const sockaddr_storage& from, socklen_t len, int n, std::uint64_t t) {
  int ok = 0;
  for (int i = 0; i < n; ++i) ok += limiter.allow(from, len, t);
  return ok;
}

TEST(SourceRateLimiter, ABurstThenTheSteadyAllowance) {
  SourceRateLimiter limiter(4000, 200);
  const sockaddr_storage a = v4("10.0.0.1", 5000);
  const std::uint64_t t0 = 1'000'000'000;
  EXPECT_EQ(allowed(limiter, a, kV4, 1000, t0), 200);                 // the burst, then nothing at the same instant
  EXPECT_NEAR(allowed(limiter, a, kV4, 1000, t0 + 10 * kMs), 40, 1);  // 4000/s x 10 ms (to rounding)
  // A source sending just under its allowance (one per 0.26 ms, 3846/s) is never refused.
  int refused = 0;
  for (int k = 1; k <= 4000; ++k) refused += !limiter.allow(a, kV4, t0 + 10 * kMs + k * 260'000ull);
  EXPECT_EQ(refused, 0);
  // Idle for a second: the bucket is full again, not fuller.
  EXPECT_EQ(allowed(limiter, a, kV4, 1000, t0 + 2000 * kMs), 200);
}

TEST(SourceRateLimiter, SourcesDifferingByPortOrAddressHaveTheirOwnBuckets) {
  SourceRateLimiter limiter(1000, 10);
  const std::uint64_t t = 5 * kMs;
  EXPECT_EQ(allowed(limiter, v4("127.0.0.1", 4000), kV4, 50, t), 10);
  EXPECT_EQ(allowed(limiter, v4("127.0.0.1", 4001), kV4, 50, t), 10);
  EXPECT_EQ(allowed(limiter, v4("127.0.0.2", 4000), kV4, 50, t), 10);
  EXPECT_EQ(allowed(limiter, v6("::1", 4000), kV6, 50, t), 10);
  EXPECT_EQ(allowed(limiter, v6("fe80::1", 4000), kV6, 50, t), 10);
  EXPECT_EQ(allowed(limiter, v4("127.0.0.1", 4000), kV4, 50, t), 0);
  EXPECT_EQ(limiter.evictions(), 0u);
}

TEST(SourceRateLimiter, ManySourcesEvictEachOtherButNeverLeaveOneBelowItsAllowance) {
  SourceRateLimiter limiter(1000, 10);
  const sockaddr_storage good = v4("10.0.0.9", 7000);
  std::uint64_t t = kMs;
  // The good source sends at its allowance (1 per ms) while 4x the table's slots of other sources
  // arrive with it, each sending its whole burst.
  int good_refused = 0;
  for (int k = 0; k < 4 * SourceRateLimiter::kSlots; ++k) {
    t += kMs;
    good_refused += !limiter.allow(good, kV4, t);
    EXPECT_EQ(allowed(limiter, v4("10.1.0.1", static_cast<std::uint16_t>(20000 + k)), kV4, 20, t), 10);
  }
  EXPECT_EQ(good_refused, 0);
  EXPECT_GT(limiter.evictions(), 2u * SourceRateLimiter::kSlots);
}

TEST(SourceRateLimiter, AllowNeverAllocates) {
  SourceRateLimiter limiter(1000, 10);
  const long n = testing_util::allocations_in([&] {
    for (int k = 0; k < 10000; ++k)
      limiter.allow(v4("10.2.0.1", static_cast<std::uint16_t>(k)), kV4, static_cast<std::uint64_t>(k) * kMs);
  });
  EXPECT_EQ(n, 0);
}

}  // namespace
}  // namespace hapticd::haptic
