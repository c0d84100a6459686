// The handoff between the loops (triple_buffer.hpp) under real concurrency: a writer and a reader on
// two threads, every value the reader sees whole (its checksum, computed by the writer over the rest
// of the value, matches) and never older than one it saw before.
#include <gtest/gtest.h>

#include <array>
#include <atomic>
#include <cstdint>
#include <thread>

#include "server/haptic/triple_buffer.hpp"

namespace hapticd::haptic {
namespace {

// Large enough that a torn copy (a read while the slot is being written) would mix two writes.
struct Stamped {
  std::uint64_t sequence = 0;
  std::array<std::uint64_t, 512> payload{};
  std::uint64_t checksum = 0;
};

std::uint64_t checksum_of(const Stamped& v) {
  // FNV-1a over the sequence and payload: any mixture of two writes changes it.
  std::uint64_t h = 1469598103934665603ull;
  auto mix = [&h](std::uint64_t x) {
    for (int b = 0; b < 8; ++b) h = (h ^ ((x >> (8 * b)) & 0xff)) * 1099511628211ull;
  };
  mix(v.sequence);
  for (std::uint64_t x : v.payload) mix(x);
  return h;
}

TEST(TripleBuffer, AWriterAndAReaderOnTwoThreadsNeverTearAValueNorGoBackInTime) {
  TripleBuffer<Stamped> buffer;
  constexpr std::uint64_t kWrites = 200'000;
  std::atomic<bool> done{false};
  std::thread writer([&] {
    for (std::uint64_t s = 1; s <= kWrites; ++s) {
      Stamped& v = buffer.back();
      v.sequence = s;
      for (std::size_t i = 0; i < v.payload.size(); ++i) v.payload[i] = s * 2654435761ull + i;
      v.checksum = checksum_of(v);
      buffer.publish();
    }
    done = true;
  });
  std::uint64_t seen = 0, updates = 0, torn = 0, backwards = 0;
  for (;;) {
    const bool finished = done.load();  // read before looking: a publish before it is seen below
    if (!buffer.update()) {
      if (finished) break;
      continue;
    }
    ++updates;
    const Stamped& v = buffer.front();
    torn += checksum_of(v) != v.checksum || v.payload[7] != v.sequence * 2654435761ull + 7;
    backwards += v.sequence <= seen;
    seen = v.sequence;
  }
  writer.join();
  EXPECT_EQ(torn, 0u);
  EXPECT_EQ(backwards, 0u);
  EXPECT_EQ(seen, kWrites) << "the last value published was not the last one read";
  EXPECT_GT(updates, 100u) << "the reader saw too few values for the test to mean anything";
}

TEST(TripleBuffer, AReaderWithNothingNewKeepsItsValue) {
  TripleBuffer<int> buffer(7);
  EXPECT_FALSE(buffer.update());
  EXPECT_EQ(buffer.front(), 7);
  buffer.back() = 8;
  buffer.publish();
  buffer.back() = 9;
  buffer.publish();  // the reader skips 8: only the newest is handed over
  EXPECT_TRUE(buffer.update());
  EXPECT_EQ(buffer.front(), 9);
  EXPECT_FALSE(buffer.update());
  EXPECT_EQ(buffer.front(), 9);
}

}  // namespace
}  // namespace hapticd::haptic
