#include "server/haptic/visual_loop.hpp"

#include <time.h>

#include <algorithm>
#include <exception>

#include "protocol/clock.hpp"

namespace hapticd::haptic {

VisualLoop::VisualLoop(VisualStep& step, double rate_hz, VisualReport* report,
                       std::function<void(const std::string&)> on_fault)
    : step_(step), rate_hz_(rate_hz), report_(report), on_fault_(std::move(on_fault)) {}

void VisualLoop::run(const std::atomic<bool>& stop) {
  world::ensure_ode_for_this_thread();
  hand::single_threaded_cholmod();
  world::World& world = step_.world();
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
    std::uint64_t t_world = t0, t_model = t0;
    bool faulted = false;
    try {
      step_.advance_world(publish, dt);
      world_time_s += dt;
      t_world = protocol::now_ns();
      // The coming step: at least the period and twice the loop's latency (its model
      // must reach the haptic loop before the step is half over; a slower machine
      // gets a lower visual rate, counted, never a late model), plus half of any
      // lag of simulated time behind the wall clock. The model is built for exactly
      // this length and the world then takes it, reusing the model's factorization.
      const double lag_s = 1e-9 * static_cast<double>(publish - start) - world_time_s;
      dt = std::clamp(std::max(period, detail::kLatencyMargin * latency_s) + 0.5 * lag_s,
                      detail::kMinStepFraction * period, detail::kMaxStep_s);
      if (detail::kLatencyMargin * latency_s > period) ++stats_.late_steps;
      step_.build_models(publish, dt);
      t_model = protocol::now_ns();
      step_.prepare_tick_solvers();
    } catch (const std::exception& e) {
      faulted = true;
      if (on_fault_) on_fault_(e.what());
    } catch (...) {
      faulted = true;
      if (on_fault_) on_fault_("a non-standard exception");
    }
    if (faulted) {
      // Nothing of this step is published; the world restarts from the proxies at the clock.
      step_.recover();
      ++stats_.faults;
      dt = period;
      world_time_s = 1e-9 * static_cast<double>(protocol::now_ns() - start);
    }
    const std::uint64_t t1 = protocol::now_ns();
    if (!faulted) {
      // The next iteration's latency: the slower of this one and a decaying memory of the last.
      latency_s = std::max(1e-9 * static_cast<double>(t1 - t0), detail::kLatencyMemory * latency_s);
      step_.publish();
      ++stats_.steps;
      stats_.step_us.add(1e-3 * static_cast<double>(t1 - t0));
      stats_.world_us.add(1e-3 * static_cast<double>(t_world - t0));
      stats_.model_us.add(1e-3 * static_cast<double>(t_model - t_world));
      stats_.prepare_us.add(1e-3 * static_cast<double>(t1 - t_model));
    }
    stats_.resets = world.snapshot().resets;
    stats_.body_resets = world.snapshot().body_resets;
    stats_.elapsed_s = 1e-9 * static_cast<double>(t1 - start);
    if (report_) {
      report_->step_ms.store(1e-3 * stats_.step_us.percentile(50), std::memory_order_relaxed);
      report_->rate_hz.store(static_cast<double>(stats_.steps) / std::max(stats_.elapsed_s, 1e-9),
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

}  // namespace hapticd::haptic
