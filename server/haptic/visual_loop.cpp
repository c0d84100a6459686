#include "server/haptic/visual_loop.hpp"

#include <time.h>

#include <algorithm>

#include "protocol/clock.hpp"

namespace hapticd {

void fill_haptic_model(World& world, int h, HandleLinearization& lin, HapticModel& out) {
  const WorldSnapshot& snap = world.snapshot();
  out.step = snap.step;
  out.handles = 0;
  out.in_contact = false;
  for (const ContactRecord& c : snap.contacts) out.in_contact = out.in_contact || (c.hand == h && c.depth_m > 0);
  WorldHand& hand = world.hand(h);
  if (!linearize_next_step(*hand.model, hand.state, *hand.solver, lin)) return;
  const int m = static_cast<int>(lin.x0.size());
  if (m > kMaxHapticHandles || lin.F0.size() != 6 * m) return;
  out.F0 = lin.F0;
  out.K = lin.K;
  out.D = lin.D;
  for (int j = 0; j < m; ++j) {
    out.x0[j] = {lin.x0[j].p_WH, lin.x0[j].q_WH};
    out.v0[j] = lin.x0[j].v_WH;
    out.w0[j] = lin.x0[j].w_WH;
  }
  out.handles = m;
}

VisualLoop::VisualLoop(World& world, double rate_hz, TripleBuffer<HapticSnapshot>& snapshots,
                       TripleBuffer<ProxyTargets>& targets, HapticServer* report_to)
    : world_(world), rate_hz_(rate_hz), snapshots_(snapshots), targets_(targets), report_to_(report_to) {}

void VisualLoop::run(const std::atomic<bool>& stop) {
  ensure_ode_for_this_thread();
  const auto period_ns = static_cast<std::uint64_t>(1e9 / rate_hz_);
  const auto step_ns = static_cast<std::uint64_t>(1e9 * world_.dt());
  const std::uint64_t start = protocol::now_ns();
  std::uint64_t deadline = start;
  while (!stop.load(std::memory_order_relaxed)) {
    const std::uint64_t t0 = protocol::now_ns();
    targets_.update();
    const ProxyTargets& targets = targets_.front();
    for (int h = 0; h < std::min(world_.num_hands(), kMaxHands); ++h) {
      if (!targets.driven[h]) continue;
      WorldHand& hand = world_.hand(h);
      for (int j = 0; j < std::min(hand.model->num_handles(), kMaxHapticHandles); ++j)
        set_target(hand.state, j, {targets.pose[h][j].p_W, targets.pose[h][j].q_W, targets.v_W[h][j], targets.w_W[h][j]});
    }
    world_.step();
    HapticSnapshot& out = snapshots_.back();
    out.hands = std::min(world_.num_hands(), kMaxHands);
    for (int h = 0; h < out.hands; ++h) {
      fill_haptic_model(world_, h, scratch_, out.model[h]);
      // The world now stands where the proxies were at t0; its next step ends one step later.
      out.model[h].t_end_ns = t0 + step_ns;
    }
    out.step = world_.snapshot().step;
    const std::uint64_t t1 = protocol::now_ns();
    out.step_ms = 1e-6 * static_cast<double>(t1 - t0);
    snapshots_.publish();
    ++stats_.steps;
    stats_.step_us.add(1e-3 * static_cast<double>(t1 - t0));
    stats_.resets = world_.snapshot().resets;
    stats_.elapsed_s = 1e-9 * static_cast<double>(t1 - start);
    if (report_to_) {
      report_to_->visual_step_ms.store(1e-3 * stats_.step_us.percentile(50), std::memory_order_relaxed);
      report_to_->visual_rate_hz.store(static_cast<double>(stats_.steps) / std::max(stats_.elapsed_s, 1e-9),
                                       std::memory_order_relaxed);
    }
    deadline += period_ns;
    if (protocol::now_ns() >= deadline) {
      // Slower than the visual rate: run as fast as it can, and count it.
      ++stats_.late_steps;
      deadline = protocol::now_ns();
      continue;
    }
    timespec ts{static_cast<time_t>(deadline / 1000000000ull), static_cast<long>(deadline % 1000000000ull)};
    clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &ts, nullptr);
  }
}

}  // namespace hapticd
