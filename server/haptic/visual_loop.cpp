#include "server/haptic/visual_loop.hpp"

#include <time.h>

#include <algorithm>

#include "hand_models/rigid_handle.hpp"
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
  single_threaded_cholmod();
  const auto period_ns = static_cast<std::uint64_t>(1e9 / rate_hz_);
  const std::uint64_t start = protocol::now_ns();
  std::uint64_t deadline = start, previous_publish = 0;
  double latency_s = 0;  // how long an iteration takes from reading the proxies to publishing
  while (!stop.load(std::memory_order_relaxed)) {
    const std::uint64_t t0 = protocol::now_ns();
    // The world simulates up to the moment it will publish: the proxies are
    // extrapolated by the expected latency, and the step spans the wall-clock
    // time between publications (the period when on time). The model it then
    // publishes starts at its own publication, so the haptic loop gets it on
    // time; a world behind the clock would replay the proxies' motion faster
    // than it happened and a late model would lag the flesh: both feed energy
    // back to the device.
    const std::uint64_t publish = t0 + static_cast<std::uint64_t>(1e9 * latency_s);
    const double dt =
        previous_publish ? std::clamp(1e-9 * static_cast<double>(publish - previous_publish), 0.25 / rate_hz_, kMaxStep_s)
                         : 1.0 / rate_hz_;
    previous_publish = publish;
    targets_.update();
    const ProxyTargets& targets = targets_.front();
    for (int h = 0; h < std::min(world_.num_hands(), kMaxHands); ++h) {
      if (!targets.driven[h]) continue;
      WorldHand& hand = world_.hand(h);
      for (int j = 0; j < std::min(hand.model->num_handles(), kMaxHapticHandles); ++j) {
        const HapticPose& p = targets.pose[h][j];
        const Eigen::Vector3d &v = targets.v_W[h][j], &w = targets.w_W[h][j];
        set_target(hand.state, j, {p.p_W + latency_s * v, rotate_by(p.q_W, latency_s * w), v, w});
      }
    }
    world_.step(dt);
    const std::uint64_t t_world = protocol::now_ns();
    HapticSnapshot& out = snapshots_.back();
    out.hands = std::min(world_.num_hands(), kMaxHands);
    for (int h = 0; h < out.hands; ++h) {
      fill_haptic_model(world_, h, scratch_, out.model[h]);
      // Its step ends one step after the publication it was simulated up to.
      out.model[h].t_end_ns = publish + static_cast<std::uint64_t>(1e9 * std::max(dt, 1.0 / rate_hz_));
    }
    out.step = world_.snapshot().step;
    const std::uint64_t t1 = protocol::now_ns();
    out.step_ms = 1e-6 * static_cast<double>(t1 - t0);
    // The next iteration's latency: the slower of this one and a decaying memory of the last.
    latency_s = std::max(1e-9 * static_cast<double>(t1 - t0), 0.8 * latency_s);
    snapshots_.publish();
    ++stats_.steps;
    stats_.step_us.add(1e-3 * static_cast<double>(t1 - t0));
    stats_.world_us.add(1e-3 * static_cast<double>(t_world - t0));
    stats_.model_us.add(1e-3 * static_cast<double>(t1 - t_world));
    stats_.resets = world_.snapshot().resets;
    stats_.elapsed_s = 1e-9 * static_cast<double>(t1 - start);
    if (report_to_) {
      report_to_->visual_step_ms.store(1e-3 * stats_.step_us.percentile(50), std::memory_order_relaxed);
      report_to_->visual_rate_hz.store(static_cast<double>(stats_.steps) / std::max(stats_.elapsed_s, 1e-9),
                                       std::memory_order_relaxed);
    }
    // A step must span well more than its own latency, or its model reaches the
    // haptic loop after the step it describes has ended: slower than the rate
    // when the machine cannot keep up (counted), never flat out.
    const auto min_period_ns = static_cast<std::uint64_t>(1e9 * kLatencyMargin * latency_s);
    if (min_period_ns > period_ns) ++stats_.late_steps;
    deadline = std::max(deadline + period_ns, t0 + min_period_ns);
    if (protocol::now_ns() >= deadline) continue;
    timespec ts{static_cast<time_t>(deadline / 1000000000ull), static_cast<long>(deadline % 1000000000ull)};
    clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &ts, nullptr);
  }
}

}  // namespace hapticd
