#pragma once
// Lock-free single-writer / single-reader handoff of the latest value
// (DESIGN.md section 1): the writer fills its back slot and swaps it with the
// middle one; the reader swaps the middle slot in when it holds something new.
// Neither side waits, locks or allocates; the reader always sees a whole value.
#include <atomic>
#include <cstdint>

namespace hapticd::haptic {

template <typename T>
class TripleBuffer {
 public:
  TripleBuffer() = default;
  explicit TripleBuffer(const T& initial) : slots_{initial, initial, initial} {}
  TripleBuffer(const TripleBuffer&) = delete;
  TripleBuffer& operator=(const TripleBuffer&) = delete;

  // Writer side: the slot to fill, then publish().
  T& back() { return slots_[back_]; }
  void publish() {
    const std::uint8_t previous = middle_.exchange(static_cast<std::uint8_t>(back_ | kFresh), std::memory_order_acq_rel);
    back_ = previous & kIndex;
  }

  // Reader side: swaps in the newest published value if there is one; true if it did.
  bool update() {
    if (!(middle_.load(std::memory_order_relaxed) & kFresh)) return false;
    const std::uint8_t previous = middle_.exchange(front_, std::memory_order_acq_rel);
    front_ = previous & kIndex;
    return true;
  }
  const T& front() const { return slots_[front_]; }
  T& front() { return slots_[front_]; }

 private:
  static constexpr std::uint8_t kIndex = 0x3, kFresh = 0x4;
  T slots_[3]{};
  std::uint8_t back_ = 0, front_ = 1;  // each owned by one side
  std::atomic<std::uint8_t> middle_{2};
};

}  // namespace hapticd::haptic
