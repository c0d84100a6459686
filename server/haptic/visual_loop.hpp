#pragma once
// The visual loop of hapticd (DESIGN.md section 1): a thread stepping the world
// at the visual rate on absolute deadlines (or as fast as it can, counted),
// pulling each driven hand's handles toward the haptic proxies and publishing
// each hand's handle-space model for the haptic loop.
#include <atomic>

#include "server/haptic/haptic_server.hpp"
#include "server/haptic/loop_stats.hpp"
#include "server/world/world.hpp"

namespace hapticd {

struct VisualStats {
  long steps = 0, late_steps = 0, resets = 0;
  MicrosecondHistogram step_us;
  double elapsed_s = 0;
};

// Fills `out` (hand h's model) from the world's last step; in_contact from its contacts.
void fill_haptic_model(const World& world, int h, HapticModel& out);

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
};

}  // namespace hapticd
