#pragma once
// The real-time runner of the visual step (DESIGN.md section 1): the visual thread, stepping a
// VisualStep (visual_step.hpp) on the wall clock at the visual rate on absolute deadlines (or as
// fast as it can, counted), choosing each step's length from the loop's measured latency. A throw
// out of a step is a fault: counted, handed to `on_fault` (hapticd logs it), the hands reset, and
// nothing is published for that step, so the haptic side's watchdog fades to the safe model as for
// a stalled loop if the faults go on; the loop keeps running.
#include <atomic>
#include <cstdint>
#include <functional>
#include <string>

#include "server/haptic/loop_stats.hpp"
#include "server/haptic/visual_step.hpp"

namespace hapticd::haptic {

// The visual loop's step-length rule (visual_loop.cpp).
namespace detail {

// The longest step the visual loop takes after a stall or on a loaded machine, s (beyond, the world
// falls behind the clock). At 0.1 s, hapticd with four CPU-bound competitors (visual loop 7.9-8.7
// Hz) put +1.7e-4 to +3.0e-4 J into the stylus in 3 of 8 runs; at 0.15 s (6.7-7.0 Hz, the world
// keeping up with the clock) it took energy out in 8 of 8, at 0.2 s in 10 of 10
// (tests/e2e/stylus_loopback.sh, README); with six competitors at 0.15 s (5.5-5.7 Hz, the world
// behind the clock) in 4 of 4. The deep press into the deformable bunny, which glued the stylus at
// 200 ms steps while a hand met deformable objects only within 2 mm, passes at 100 and 200 ms
// (SlowTouch/PressHoldLiftForces); 0.15 s stays, as nothing measured asks for longer steps. A
// stall's jumps at 150 and 200 ms steps are StalledServer.LongerSteps; every press-hold-lift runs at
// 150 ms too.
constexpr double kMaxStep_s = 0.15;
// A visual step spans at least this many times the loop's latency (its model
// then reaches the haptic loop before the step it describes is half over).
constexpr double kLatencyMargin = 2.0;
// Each iteration's latency estimate is the slower of its own and this fraction of the last.
constexpr double kLatencyMemory = 0.8;
// The shortest step, as a fraction of the period (a world ahead of the clock catches up no faster).
constexpr double kMinStepFraction = 0.25;

// The visual loop's timing on the times it is given (VisualLoop::run; tested on made-up times): how
// far ahead an iteration publishes (its latency estimate), how long each step is, and when the loop
// reads the proxies again. The loop publishes every `pace` (the period, or twice its latency when
// that is longer, at most kMaxStep_s) and each step is the pace plus half the lag of simulated
// time behind the clock, so a world that fell behind (a stall) catches up geometrically: with the
// step as the pace too, a 300 ms stall kept the steps at kMaxStep_s for the rest of the session.
// The step right after a stall spans the time lost, up to kMaxStep_s: taken as the last model's
// step, it replayed the stall's motion of the proxies in one visual period and put energy into the
// device (a 300 ms stall with one step in it, in the lockstep runner: up to +5 mJ).
// The latency estimate follows a slower machine within a few iterations (at most doubling, plus a
// period, per iteration) and decays by kLatencyMemory: a single descheduled iteration (300 ms) set
// it, and the loop then published 0.2-0.3 s ahead of its reads for a second and a half.
// The world's step to a publication `behind_s` after its simulated time, when its last model was
// built for `step_s`: that step, or, when the world is more than a period further behind (a stall),
// the time to the publication, at most kMaxStep_s. StepClock's rule, and the lockstep runner's after
// its stall windows.
double world_step_for(double behind_s, double step_s, double period_s);

class StepClock {
 public:
  StepClock(double period_s, std::uint64_t start_ns);
  // When an iteration that reads the proxies at t0 publishes: one latency later.
  std::uint64_t publish_ns(std::uint64_t t0_ns) const;
  // The step the world takes to a publication at `publish_ns` (world_step_for).
  double world_step_s(std::uint64_t publish_ns);
  // The world took world_step_s(): the coming step's length, for a model published at `publish_ns`.
  double plan(std::uint64_t publish_ns);
  // The latency asks for a step longer than the period (a late step, counted).
  bool late() const { return kLatencyMargin * latency_s_ > period_s_; }
  // An iteration that published took this long from its read: the next latency estimate.
  void measured(double iteration_s);
  // A faulted iteration published nothing: the world restarts from the proxies at the clock.
  void restart(std::uint64_t now_ns);
  // When to read the proxies again, for an iteration that published (or would have) at `publish_ns`.
  std::uint64_t next_read_ns(std::uint64_t publish_ns) const;
  double latency_s() const { return latency_s_; }
  double lag_s() const { return lag_s_; }

 private:
  double period_s_;
  std::uint64_t start_ns_;
  double latency_s_ = 0, step_s_, pace_s_, taken_s_, world_time_s_ = 0, lag_s_ = 0;
};

}  // namespace detail

struct VisualStats {
  long steps = 0, late_steps = 0, resets = 0, body_resets = 0;  // resets: the world's hands and deformables
  long faults = 0;  // steps that threw (VisualStep::recover ran; nothing was published)
  MicrosecondHistogram step_us;   // the whole iteration: world step and model
  MicrosecondHistogram world_us;  // of which the world step
  MicrosecondHistogram model_us;  // of which the next step's handle-space model
  MicrosecondHistogram prepare_us;  // of which the haptic tick's prepared solver (prepare_tick_solver), all hands
  double elapsed_s = 0;
};

class VisualLoop {
 public:
  // `report`: where the achieved rate and step time go for the Stats message (may be null);
  // `on_fault`: told what a faulted step threw (called on the visual thread; may be empty).
  VisualLoop(VisualStep& step, double rate_hz, VisualReport* report = nullptr,
             std::function<void(const std::string&)> on_fault = {});
  void run(const std::atomic<bool>& stop);
  // Readable after run() returned.
  const VisualStats& stats() const { return stats_; }

 private:
  VisualStep& step_;
  double rate_hz_;
  VisualReport* report_;
  std::function<void(const std::string&)> on_fault_;
  VisualStats stats_;
};

}  // namespace hapticd::haptic
