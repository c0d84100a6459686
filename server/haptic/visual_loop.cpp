#include "server/haptic/visual_loop.hpp"

#include <time.h>

#include <algorithm>
#include <exception>

#include "protocol/clock.hpp"

namespace hapticd::haptic {

VisualLoop::VisualLoop(VisualStep& step, double rate_hz, VisualReport* report,
                       std::function<void(const std::string&)> on_fault)
    : step_(step), rate_hz_(rate_hz), report_(report), on_fault_(std::move(on_fault)) {}

namespace detail {

namespace {
std::uint64_t to_ns(double s) { return static_cast<std::uint64_t>(1e9 * s); }
}  // namespace

// The first step brings the world to the first publication: simulated time starts a step early.
// (From 0, the world started a period ahead of the clock and, never catching up from ahead, took
// steps shorter than the period: hapticd's stylus scene at 60 Hz on a quiet machine ran at 68 Hz.)
StepClock::StepClock(double period_s, std::uint64_t start_ns)
    : period_s_(period_s),
      start_ns_(start_ns),
      step_s_(period_s),
      pace_s_(period_s),
      taken_s_(period_s),
      world_time_s_(-period_s) {}

std::uint64_t StepClock::publish_ns(std::uint64_t t0_ns) const { return t0_ns + to_ns(latency_s_); }

double world_step_for(double behind_s, double step_s, double period_s) {
  return behind_s > step_s + period_s ? std::min(behind_s, std::max(kMaxStep_s, step_s)) : step_s;
}

double StepClock::world_step_s(std::uint64_t publish_ns) {
  taken_s_ = world_step_for(1e-9 * static_cast<double>(publish_ns - start_ns_) - world_time_s_, step_s_, period_s_);
  return taken_s_;
}

double StepClock::plan(std::uint64_t publish_ns) {
  world_time_s_ += taken_s_;
  // At least the period and twice the loop's latency (its model must reach the haptic loop before the
  // step is half over; a slower machine gets a lower visual rate, counted, never a late model), plus
  // half of any lag of simulated time behind the wall clock. The model is built for exactly this
  // length and the world then takes it, reusing the model's factorization.
  lag_s_ = 1e-9 * static_cast<double>(publish_ns - start_ns_) - world_time_s_;
  const double pace = std::min(std::max(period_s_, kLatencyMargin * latency_s_), kMaxStep_s);
  step_s_ = std::clamp(pace + 0.5 * lag_s_, kMinStepFraction * period_s_, kMaxStep_s);
  // A world ahead of the clock (a shorter step) publishes again at its step's end: the model then
  // never ends before the next one arrives.
  pace_s_ = std::min(step_s_, pace);
  return step_s_;
}

void StepClock::measured(double iteration_s) {
  latency_s_ = std::max(std::min(iteration_s, 2.0 * latency_s_ + period_s_), kLatencyMemory * latency_s_);
}

void StepClock::restart(std::uint64_t now_ns) {
  step_s_ = pace_s_ = taken_s_ = period_s_;
  world_time_s_ = 1e-9 * static_cast<double>(now_ns - start_ns_);
}

std::uint64_t StepClock::next_read_ns(std::uint64_t publish_ns) const {
  // One latency before the coming publication.
  return publish_ns + to_ns(pace_s_) - std::min(to_ns(latency_s_), to_ns(pace_s_));
}

}  // namespace detail

void VisualLoop::run(const std::atomic<bool>& stop) {
  world::ensure_ode_for_this_thread();
  hand::single_threaded_cholmod();
  world::World& world = step_.world();
  const std::uint64_t start = protocol::now_ns();
  detail::StepClock clock(1.0 / rate_hz_, start);
  while (!stop.load(std::memory_order_relaxed)) {
    const std::uint64_t t0 = protocol::now_ns();
    // The world simulates up to the moment it will publish: the proxies are
    // extrapolated from the time they are of (the end of the haptic tick that
    // wrote them, up to a period ahead of now) to then, and the step spans the time to that
    // publication. The model it then publishes starts at its own publication, so
    // the haptic loop gets it on time; a world behind the clock would replay the
    // proxies' motion faster than it happened and a late model would lag the
    // flesh: both feed energy back to the device.
    const std::uint64_t publish = clock.publish_ns(t0);
    std::uint64_t t_world = t0, t_model = t0;
    bool faulted = false;
    try {
      step_.advance_world(publish, clock.world_step_s(publish));
      t_world = protocol::now_ns();
      const double dt = clock.plan(publish);
      if (clock.late()) ++stats_.late_steps;
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
      clock.restart(protocol::now_ns());
    }
    const std::uint64_t t1 = protocol::now_ns();
    if (!faulted) {
      clock.measured(1e-9 * static_cast<double>(t1 - t0));
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
    const std::uint64_t deadline = clock.next_read_ns(publish);
    if (protocol::now_ns() >= deadline) continue;
    timespec ts{static_cast<time_t>(deadline / 1000000000ull), static_cast<long>(deadline % 1000000000ull)};
    clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &ts, nullptr);
  }
}

}  // namespace hapticd::haptic
