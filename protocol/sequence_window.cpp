#include "protocol/sequence_window.hpp"

namespace hapticd::protocol {

std::string_view to_string(SequenceClass c) noexcept {
  switch (c) {
    case SequenceClass::kFresh:
      return "fresh";
    case SequenceClass::kGap:
      return "gap";
    case SequenceClass::kDuplicate:
      return "duplicate";
    case SequenceClass::kStale:
      return "stale";
  }
  return "unknown";
}

SequenceClass SequenceWindow::classify(std::uint64_t sequence) const noexcept {
  if (!started_) return SequenceClass::kFresh;
  // Written as a difference: newest_ + 1 wraps to 0 at the top of the range.
  if (sequence > newest_) return sequence - newest_ == 1 ? SequenceClass::kFresh : SequenceClass::kGap;
  const std::uint64_t age = newest_ - sequence;
  if (age >= kWindow) return SequenceClass::kStale;  // too old to know whether it was seen
  return (seen_ >> age) & 1u ? SequenceClass::kDuplicate : SequenceClass::kStale;
}

SequenceClass SequenceWindow::observe(std::uint64_t sequence) noexcept {
  const SequenceClass c = classify(sequence);
  switch (c) {
    case SequenceClass::kFresh:
    case SequenceClass::kGap: {
      const std::uint64_t advance = started_ ? sequence - newest_ : kWindow;
      skipped_ = c == SequenceClass::kGap ? advance - 1 : 0;
      // A shift by >= 64 bits is undefined: past the window nothing old is remembered anyway.
      seen_ = (advance >= kWindow ? 0 : seen_ << advance) | 1u;
      newest_ = sequence;
      started_ = true;
      break;
    }
    case SequenceClass::kStale:
      if (newest_ - sequence < kWindow) seen_ |= std::uint64_t{1} << (newest_ - sequence);
      break;
    case SequenceClass::kDuplicate:
      break;
  }
  return c;
}

}  // namespace hapticd::protocol
