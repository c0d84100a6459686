#include "server/haptic/visual_loop.hpp"

#include <time.h>

#include <algorithm>

#include "hand_models/rigid_handle.hpp"
#include "protocol/clock.hpp"

namespace hapticd {

void fill_contact_flags(const World& world, int h, HapticModel& out) {
  const WorldSnapshot& snap = world.snapshot();
  const WorldHand& hand = world.hand(h);
  out.in_contact = false;
  std::fill(std::begin(out.handle_in_contact), std::end(out.handle_in_contact), false);
  for (const ContactRecord& c : snap.contacts) {
    if (c.hand != h || c.depth_m <= 0) continue;
    out.in_contact = true;
    // A contact without a skin point of this hand (another hand's skin inside its flesh) marks no handle.
    if (c.point < 0 || c.point >= static_cast<int>(hand.skin_handle.size())) continue;
    const int j = hand.skin_handle[c.point];
    if (j < kMaxHapticHandles) out.handle_in_contact[j] = true;
  }
}

void fill_haptic_model(World& world, int h, HandleLinearization& lin, HapticModel& out) {
  out.handles = 0;
  out.solver.prepared = false;
  WorldHand& hand = world.hand(h);
  fill_contact_flags(world, h, out);
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

bool prepare_for_links(std::span<const DeviceLink> links, int h, double haptic_dt_s, HapticModel& model) {
  model.solver.prepared = false;
  for (const DeviceLink& link : links)
    if (link.hand == h && link.handles == model.handles)
      return prepare_tick_solver(model, link.handles, link.mass_kg, link.inertia_B, link.gains, haptic_dt_s);
  return false;
}

HandleTarget proxy_target(const ProxyTargets& targets, int h, int j, std::uint64_t until_ns) {
  const double ahead = std::clamp(1e-9 * (static_cast<double>(until_ns) - static_cast<double>(targets.t_ns)), -0.1, 0.1);
  const HapticPose& p = targets.pose[h][j];
  const Eigen::Vector3d &v = targets.v_W[h][j], &w = targets.w_W[h][j];
  return {p.p_W + ahead * v, rotate_by(p.q_W, ahead * w), v, w};
}

VisualLoop::VisualLoop(World& world, double rate_hz, TripleBuffer<HapticSnapshot>& snapshots,
                       TripleBuffer<ProxyTargets>& targets, HapticServer* report_to)
    : world_(world), rate_hz_(rate_hz), snapshots_(snapshots), targets_(targets), report_to_(report_to) {}

void VisualLoop::run(const std::atomic<bool>& stop) {
  ensure_ode_for_this_thread();
  single_threaded_cholmod();
  const double period = 1.0 / rate_hz_;
  const std::uint64_t start = protocol::now_ns();
  double latency_s = 0;      // how long an iteration takes from reading the proxies to publishing
  double dt = period;        // the coming step: its model was built for this length, so the world takes it
  double world_time_s = 0;   // simulated time, kept on the wall clock
  while (!stop.load(std::memory_order_relaxed)) {
    const std::uint64_t t0 = protocol::now_ns();
    // The world simulates up to the moment it will publish: the proxies are
    // extrapolated from the time they are of (the end of the haptic tick that
    // wrote them, up to a period ahead of now) to then, and the step spans the time to that
    // publication. The model it then publishes starts at its own publication, so
    // the haptic loop gets it on time; a world behind the clock would replay the
    // proxies' motion faster than it happened and a late model would lag the
    // flesh: both feed energy back to the device.
    const std::uint64_t publish = t0 + static_cast<std::uint64_t>(1e9 * latency_s);
    targets_.update();
    const ProxyTargets& targets = targets_.front();
    for (int h = 0; h < std::min(world_.num_hands(), kMaxHands); ++h) {
      if (!targets.driven[h]) continue;
      WorldHand& hand = world_.hand(h);
      if (targets.resyncs[h] != resyncs_seen_[h]) {
        resyncs_seen_[h] = targets.resyncs[h];
        place_hand(*hand.model, hand.state, targets.pose[h][0].p_W, targets.pose[h][0].q_W, 0);
      }
      for (int j = 0; j < std::min(hand.model->num_handles(), kMaxHapticHandles); ++j)
        set_target(hand.state, j, proxy_target(targets, h, j, publish));
    }
    world_.step(dt);
    world_time_s += dt;
    const std::uint64_t t_world = protocol::now_ns();
    // The coming step: at least the period and twice the loop's latency (its model
    // must reach the haptic loop before the step is half over; a slower machine
    // gets a lower visual rate, counted, never a late model), plus half of any
    // lag of simulated time behind the wall clock. The model is built for exactly
    // this length and the world then takes it, reusing the model's factorization.
    const double lag_s = 1e-9 * static_cast<double>(publish - start) - world_time_s;
    dt = std::clamp(std::max(period, kLatencyMargin * latency_s) + 0.5 * lag_s, 0.25 * period, kMaxStep_s);
    if (kLatencyMargin * latency_s > period) ++stats_.late_steps;
    HapticSnapshot& out = snapshots_.back();
    out.hands = std::min(world_.num_hands(), kMaxHands);
    std::uint64_t prepare_ns = 0;
    for (int h = 0; h < out.hands; ++h) {
      world_.hand(h).state.dt_s = dt;
      fill_haptic_model(world_, h, scratch_, out.model[h]);
      out.model[h].t_end_ns = publish + static_cast<std::uint64_t>(1e9 * dt);
      out.model[h].resyncs = resyncs_seen_[h];
      if (report_to_ && out.model[h].handles >= kMinPreparedHandles) {
        const std::uint64_t p0 = protocol::now_ns();
        prepare_for_links(report_to_->links(), h, report_to_->haptic_period_s(), out.model[h]);
        prepare_ns += protocol::now_ns() - p0;
      }
    }
    const std::uint64_t t1 = protocol::now_ns();
    // The next iteration's latency: the slower of this one and a decaying memory of the last.
    latency_s = std::max(1e-9 * static_cast<double>(t1 - t0), 0.8 * latency_s);
    snapshots_.publish();
    ++stats_.steps;
    stats_.step_us.add(1e-3 * static_cast<double>(t1 - t0));
    stats_.world_us.add(1e-3 * static_cast<double>(t_world - t0));
    stats_.model_us.add(1e-3 * static_cast<double>(t1 - t_world));
    stats_.prepare_us.add(1e-3 * static_cast<double>(prepare_ns));
    stats_.resets = world_.snapshot().resets;
    stats_.body_resets = world_.snapshot().body_resets;
    stats_.elapsed_s = 1e-9 * static_cast<double>(t1 - start);
    if (report_to_) {
      report_to_->visual_step_ms.store(1e-3 * stats_.step_us.percentile(50), std::memory_order_relaxed);
      report_to_->visual_rate_hz.store(static_cast<double>(stats_.steps) / std::max(stats_.elapsed_s, 1e-9),
                                       std::memory_order_relaxed);
    }
    // Read the proxies again one latency before the coming step's publication.
    const std::uint64_t deadline = publish + static_cast<std::uint64_t>(1e9 * dt) -
                                   std::min(static_cast<std::uint64_t>(1e9 * latency_s), static_cast<std::uint64_t>(1e9 * dt));
    if (protocol::now_ns() >= deadline) continue;
    timespec ts{static_cast<time_t>(deadline / 1000000000ull), static_cast<long>(deadline % 1000000000ull)};
    clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &ts, nullptr);
  }
}

}  // namespace hapticd
