#pragma once
// What the haptic tick needs prepared from a model before it arrives: its stiffness made passive for
// the device's coupling (passive_stiffness), the factors of its tick solver (prepare_tick_solver, for
// glove-sized models) and the longest lookahead its contact rows hold at.
// The haptic side owns the device links and the haptic period these depend on; the visual step
// calls it on each model it builds, off the haptic thread.
#include <vector>

#include "server/haptic/device_link.hpp"

namespace hapticd::haptic {

class TickSolverPreparer {
 public:
  TickSolverPreparer(std::vector<DeviceLink> links, double haptic_dt_s)
      : links_(std::move(links)), haptic_dt_s_(haptic_dt_s) {}
  // Prepares `model`'s tick solver for the first link that drives hand h with as many handles;
  // false (model.solver.prepared cleared) when none does or the model is too small to need it (its
  // contact rows' lookahead bound is still set then: prepare_contact_lookahead).
  bool prepare(int h, HapticModel& model) const;
  // The models whose stiffness passive_stiffness changed, and the largest (generalized) eigenvalue it
  // removed, against the coupling's stiffness: hapticd's report (visual.stiffness_made_passive).
  long stiffness_made_passive() const { return made_passive_; }
  double stiffness_removed_max() const { return removed_max_; }

 private:
  std::vector<DeviceLink> links_;
  double haptic_dt_s_;
  // Written by prepare (the visual thread only), read once the loops have stopped.
  mutable long made_passive_ = 0;
  mutable double removed_max_ = 0;
};

}  // namespace hapticd::haptic
