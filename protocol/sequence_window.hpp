#pragma once

// Sequence-number bookkeeping for one stream (a session's PoseSamples, a client's ForceSamples).
// What to do with each class is the caller's policy; the server drops duplicates and stale
// samples (an old pose is never worth a force) and re-syncs after a gap.

#include <cstdint>
#include <string_view>

namespace hapticd::protocol {

enum class SequenceClass : std::uint8_t {
  kFresh,      // the first one, or newest + 1
  kGap,        // newer than newest + 1: newer, but skipped_by_last_gap() went missing (or are late)
  kDuplicate,  // already seen: a replay or a network duplicate
  kStale,      // older than the newest and not seen yet (reordered, late), or too old to tell
};

std::string_view to_string(SequenceClass c) noexcept;

// Remembers the newest sequence and which of the kWindow before it were seen, like the IPsec
// anti-replay window, so that "seen twice" and "arrived late" are told apart.
class SequenceWindow {
 public:
  static constexpr std::uint64_t kWindow = 64;

  // Classifies `sequence` and records it as seen (kFresh and kGap also make it the newest).
  SequenceClass observe(std::uint64_t sequence) noexcept;
  // The class observe() would return, without recording.
  [[nodiscard]] SequenceClass classify(std::uint64_t sequence) const noexcept;

  [[nodiscard]] bool started() const noexcept { return started_; }
  [[nodiscard]] std::uint64_t newest() const noexcept { return newest_; }
  // Sequences between the previous newest and the one that opened the last gap.
  [[nodiscard]] std::uint64_t skipped_by_last_gap() const noexcept { return skipped_; }
  void reset() noexcept { *this = SequenceWindow{}; }

 private:
  std::uint64_t newest_ = 0;
  std::uint64_t seen_ = 0;  // bit i: newest_ - i was seen (bit 0 is the newest itself)
  std::uint64_t skipped_ = 0;
  bool started_ = false;
};

}  // namespace hapticd::protocol
