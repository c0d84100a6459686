#pragma once
// The visual loop of hapticd (DESIGN.md section 1): a thread stepping the world
// at the visual rate on absolute deadlines (or as fast as it can, counted),
// pulling each driven hand's handles toward the haptic proxies and publishing
// each hand's handle-space model for the haptic loop.
#include <atomic>
#include <span>

#include "server/haptic/haptic_server.hpp"
#include "server/haptic/loop_stats.hpp"
#include "server/world/world.hpp"

namespace hapticd {

// How the visual loop's handles follow the haptic proxies: almost kinematically
// (GO09: the visual loop's handle is the proxy's), so the handle-space model is
// the flesh's answer to the proxy's own motion.
constexpr DriveParams kProxyDrive{1e6, 1e3, 1e3, 10.0};

// The longest step the visual loop takes after a stall, s (beyond, the world slows down).
constexpr double kMaxStep_s = 0.1;
// A visual step spans at least this many times the loop's latency (its model
// then reaches the haptic loop before the step it describes is half over).
constexpr double kLatencyMargin = 2.0;

struct VisualStats {
  long steps = 0, late_steps = 0, resets = 0, body_resets = 0;  // resets: the world's hands and deformables
  MicrosecondHistogram step_us;   // the whole iteration: world step and model
  MicrosecondHistogram world_us;  // of which the world step
  MicrosecondHistogram model_us;  // of which the next step's handle-space model
  MicrosecondHistogram prepare_us;  // of which the haptic tick's prepared solver (prepare_tick_solver), all hands
  double elapsed_s = 0;
};

// Fills `out` with hand h's model for the coming interval (linearize_next_step:
// the step about to be taken from the world's current state; `lin` is scratch),
// in_contact from the hand's contacts; out.handles = 0 when it cannot.
void fill_haptic_model(World& world, int h, HandleLinearization& lin, HapticModel& out);
// Prepares `model`'s tick solver (prepare_tick_solver) for the first of `links` that drives hand h
// with as many handles, at the haptic period `haptic_dt_s`; false when none does.
bool prepare_for_links(std::span<const DeviceLink> links, int h, double haptic_dt_s, HapticModel& model);
// Only its contact flags (in_contact, handle_in_contact) from the world's last contacts.
void fill_contact_flags(const World& world, int h, HapticModel& out);

// Handle j of hand h's target for a world that simulates up to `until_ns`: the proxy extrapolated
// at its velocity from the time it is of (targets.t_ns) to then, by at most 0.1 s either way (a
// stalled haptic thread leaves old proxies).
HandleTarget proxy_target(const ProxyTargets& targets, int h, int j, std::uint64_t until_ns);

class VisualLoop {
 public:
  VisualLoop(World& world, double rate_hz, TripleBuffer<HapticSnapshot>& snapshots, TripleBuffer<ProxyTargets>& targets,
             HapticServer* report_to = nullptr);
  void run(const std::atomic<bool>& stop);
  const VisualStats& stats() const { return stats_; }

 private:
  World& world_;
  double rate_hz_;
  TripleBuffer<HapticSnapshot>& snapshots_;
  TripleBuffer<ProxyTargets>& targets_;
  HapticServer* report_to_;
  VisualStats stats_;
  HandleLinearization scratch_;
  std::uint32_t resyncs_seen_[kMaxHands]{};
};

}  // namespace hapticd
