#include <gtest/gtest.h>

#include <chrono>
#include <cstdint>
#include <thread>

#include "protocol/bounded.hpp"
#include "protocol/clock.hpp"

namespace hapticd::protocol {
namespace {

TEST(Clock, NowNsIsMonotonicAndAgreesWithSteadyClock) {
  // libstdc++'s steady_clock is CLOCK_MONOTONIC: both read the same clock.
  const auto steady_before = std::chrono::steady_clock::now();
  const std::uint64_t before = now_ns();
  std::this_thread::sleep_for(std::chrono::milliseconds(20));
  const std::uint64_t after = now_ns();
  const auto steady_after = std::chrono::steady_clock::now();
  const auto steady_ns = std::chrono::duration_cast<std::chrono::nanoseconds>(steady_after - steady_before).count();
  EXPECT_GE(after - before, 20'000'000u);
  EXPECT_LE(after - before, static_cast<std::uint64_t>(steady_ns));
  const auto steady_epoch_ns =
      std::chrono::duration_cast<std::chrono::nanoseconds>(steady_before.time_since_epoch()).count();
  EXPECT_LE(static_cast<std::uint64_t>(steady_epoch_ns), before);

  std::uint64_t last = now_ns();
  for (int i = 0; i < 100000; ++i) {
    const std::uint64_t t = now_ns();
    ASSERT_GE(t, last);
    last = t;
  }
}

TEST(FixedString, RefusesWhatDoesNotFitInsteadOfTruncating) {
  FixedString<5> s = "abc";
  EXPECT_EQ(s.view(), "abc");
  EXPECT_TRUE(s.assign("abcde"));
  EXPECT_EQ(s.size(), 5u);
  EXPECT_FALSE(s.assign("abcdef"));
  EXPECT_EQ(s.view(), "abcde") << "unchanged";
  EXPECT_TRUE(s.assign(""));
  EXPECT_TRUE(s.empty());
  EXPECT_EQ(FixedString<5>("ab"), FixedString<5>("ab"));
  EXPECT_FALSE(FixedString<5>("ab") == FixedString<5>("abc"));
}

TEST(BoundedArray, HoldsAtMostItsCapacity) {
  BoundedArray<int, 3> a;
  EXPECT_TRUE(a.push_back(1));
  EXPECT_TRUE(a.push_back(2));
  EXPECT_TRUE(a.push_back(3));
  EXPECT_FALSE(a.push_back(4));
  EXPECT_EQ(a.size(), 3u);
  EXPECT_FALSE(a.resize(4));
  EXPECT_TRUE(a.resize(2));
  int sum = 0;
  for (int v : a) sum += v;
  EXPECT_EQ(sum, 3) << "iteration covers the used part only";
  const int four[] = {1, 2, 3, 4};
  EXPECT_FALSE(a.assign(four));
  EXPECT_EQ(a.size(), 2u);
  BoundedArray<int, 3> b;
  b.push_back(1);
  b.push_back(2);
  EXPECT_EQ(a, b);
  b[1] = 5;
  EXPECT_FALSE(a == b);
}

}  // namespace
}  // namespace hapticd::protocol
