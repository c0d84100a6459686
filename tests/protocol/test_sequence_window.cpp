#include <gtest/gtest.h>

#include <cstdint>
#include <limits>

#include "protocol/sequence_window.hpp"

namespace hapticd::protocol {
namespace {

TEST(SequenceWindow, InOrderStreamIsFresh) {
  SequenceWindow w;
  EXPECT_FALSE(w.started());
  EXPECT_EQ(w.observe(1000), SequenceClass::kFresh) << "the first one, whatever its number";
  for (std::uint64_t s = 1001; s < 1100; ++s) ASSERT_EQ(w.observe(s), SequenceClass::kFresh) << s;
  EXPECT_TRUE(w.started());
  EXPECT_EQ(w.newest(), 1099u);
  EXPECT_EQ(w.skipped_by_last_gap(), 0u);
}

TEST(SequenceWindow, ReplayOfTheNewestOrAnOlderSeenOneIsDuplicate) {
  SequenceWindow w;
  for (std::uint64_t s = 1; s <= 10; ++s) w.observe(s);
  EXPECT_EQ(w.observe(10), SequenceClass::kDuplicate);
  EXPECT_EQ(w.observe(3), SequenceClass::kDuplicate);
  EXPECT_EQ(w.observe(1), SequenceClass::kDuplicate);
  EXPECT_EQ(w.newest(), 10u) << "a duplicate never moves the window";
}

TEST(SequenceWindow, GapCountsTheSkippedAndLateOnesAreStaleOnceThenDuplicate) {
  SequenceWindow w;
  w.observe(1);
  w.observe(2);
  EXPECT_EQ(w.observe(7), SequenceClass::kGap);
  EXPECT_EQ(w.skipped_by_last_gap(), 4u);  // 3, 4, 5, 6
  EXPECT_EQ(w.newest(), 7u);
  EXPECT_EQ(w.observe(5), SequenceClass::kStale) << "older than the newest, never seen: late";
  EXPECT_EQ(w.observe(5), SequenceClass::kDuplicate) << "the same late one again is a replay";
  EXPECT_EQ(w.observe(6), SequenceClass::kStale);
  EXPECT_EQ(w.observe(8), SequenceClass::kFresh);
  EXPECT_EQ(w.skipped_by_last_gap(), 0u);
}

TEST(SequenceWindow, OlderThanTheWindowIsStaleBecauseItCannotBeTold) {
  SequenceWindow w;
  for (std::uint64_t s = 1; s <= 200; ++s) w.observe(s);
  EXPECT_EQ(w.classify(200 - SequenceWindow::kWindow + 1), SequenceClass::kDuplicate) << "last slot of the window";
  EXPECT_EQ(w.classify(200 - SequenceWindow::kWindow), SequenceClass::kStale) << "first one past it";
  EXPECT_EQ(w.observe(5), SequenceClass::kStale);
}

TEST(SequenceWindow, AJumpPastTheWindowForgetsTheOldBits) {
  SequenceWindow w;
  for (std::uint64_t s = 1; s <= 10; ++s) w.observe(s);
  EXPECT_EQ(w.observe(10 + 1000), SequenceClass::kGap);
  EXPECT_EQ(w.skipped_by_last_gap(), 999u);
  EXPECT_EQ(w.observe(1009), SequenceClass::kStale) << "not seen, even though bit patterns could alias";
  EXPECT_EQ(w.observe(1010), SequenceClass::kDuplicate);
}

TEST(SequenceWindow, ClassifyDoesNotRecord) {
  SequenceWindow w;
  w.observe(1);
  EXPECT_EQ(w.classify(2), SequenceClass::kFresh);
  EXPECT_EQ(w.classify(2), SequenceClass::kFresh);
  EXPECT_EQ(w.newest(), 1u);
}

TEST(SequenceWindow, ExtremeNumbersAndReset) {
  SequenceWindow w;
  const std::uint64_t max = std::numeric_limits<std::uint64_t>::max();
  EXPECT_EQ(w.observe(0), SequenceClass::kFresh);
  EXPECT_EQ(w.observe(max), SequenceClass::kGap);
  EXPECT_EQ(w.skipped_by_last_gap(), max - 1);
  EXPECT_EQ(w.observe(0), SequenceClass::kStale);
  EXPECT_EQ(w.observe(max), SequenceClass::kDuplicate);
  w.reset();
  EXPECT_FALSE(w.started());
  EXPECT_EQ(w.observe(3), SequenceClass::kFresh) << "a re-synced stream starts over";
  EXPECT_EQ(to_string(SequenceClass::kStale), "stale");
}

}  // namespace
}  // namespace hapticd::protocol
