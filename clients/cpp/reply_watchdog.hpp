#pragma once

// hapticd::client::ReplyWatchdog: the device's side of DESIGN section 5's silent-session rule. A
// device holds the last wrench it received until the next; if the server stops answering (stopped,
// starved of CPU, crashed, unplugged) it would hold it indefinitely while the user moves, so the
// rendering no longer depends on where the hand is and can push energy into it. The watchdog gives
// the share of the held wrench to render: 1 while replies keep coming, ramping down to 0 once none
// has come for `hold`, and back up at the same rate when they resume (no step either way).
//
//   ReplyWatchdog watchdog;                                  // 20 ms hold, 50 ms ramp
//   if (auto reply = client.poll_force(...)) watchdog.on_reply(reply->received_ns), apply(*reply);
//   render(held_wrench * watchdog.scale(protocol::now_ns()));  // once per servo tick
//
// Allocation-free and noexcept: it sits in a device's servo loop.

#include <algorithm>
#include <chrono>
#include <cstdint>

namespace hapticd::client {

struct ReplyWatchdogOptions {
  // No reply for longer than this and the wrench starts to fade. At 1 kHz, 20 replies in a row; a
  // 10 % random loss drops that many with a probability of 1e-20.
  std::chrono::nanoseconds hold = std::chrono::milliseconds(20);
  // The fade from the full wrench to none, and the way back (0: at once).
  std::chrono::nanoseconds ramp = std::chrono::milliseconds(50);
};

class ReplyWatchdog {
 public:
  explicit ReplyWatchdog(ReplyWatchdogOptions options = {}) noexcept : options_(options) {}

  // A reply was accepted at `received_ns` (the client's clock, as ForceReply::received_ns).
  void on_reply(std::uint64_t received_ns) noexcept {
    if (last_reply_ns_ != 0 && received_ns > last_reply_ns_ + hold_ns()) resumed_ns_ = received_ns;
    last_reply_ns_ = std::max(last_reply_ns_, received_ns);
  }

  // The share of the held wrench to render at `now_ns`, in [0, 1]: it falls by 1 / ramp per
  // second of silence past the hold and rises as fast once replies resume, counted from the last
  // call (or from where the silence's hold ended, or the replies resumed, if later). 1 before the
  // first reply (nothing is held yet); a time before the last call changes nothing.
  double scale(std::uint64_t now_ns) noexcept {
    const bool fresh = last_reply_ns_ == 0 || now_ns <= last_reply_ns_ + hold_ns();
    const std::uint64_t from = std::max(last_scale_ns_, fresh ? resumed_ns_ : last_reply_ns_ + hold_ns());
    const double elapsed = now_ns > from ? static_cast<double>(now_ns - from) : 0.0;
    last_scale_ns_ = std::max(last_scale_ns_, now_ns);
    const auto ramp = static_cast<double>(options_.ramp.count());
    if (ramp <= 0)
      scale_ = fresh ? 1.0 : 0.0;
    else
      scale_ = fresh ? std::min(1.0, scale_ + elapsed / ramp) : std::max(0.0, scale_ - elapsed / ramp);
    if (scale_ < 1.0) ++faded_scales_;
    return scale_;
  }

  // Calls of scale() that gave less than the full wrench (a silence, or the way back from one).
  [[nodiscard]] std::uint64_t faded() const noexcept { return faded_scales_; }

 private:
  ReplyWatchdogOptions options_;
  std::uint64_t hold_ns() const noexcept {
    return static_cast<std::uint64_t>(std::max<std::int64_t>(0, options_.hold.count()));
  }
  std::uint64_t last_reply_ns_ = 0, last_scale_ns_ = 0, resumed_ns_ = 0;
  double scale_ = 1.0;
  std::uint64_t faded_scales_ = 0;
};

}  // namespace hapticd::client
