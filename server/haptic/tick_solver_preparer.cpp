#include "server/haptic/tick_solver_preparer.hpp"

#include <algorithm>

namespace hapticd::haptic {

bool TickSolverPreparer::prepare(int h, HapticModel& model) const {
  model.solver.prepared = false;
  for (const DeviceLink& link : links_) {
    if (link.hand != h || link.handles != model.handles) continue;
    const double removed = passive_stiffness(model.K, link.gains);
    if (removed > 0) ++made_passive_, removed_max_ = std::max(removed_max_, removed);
    if (model.handles >= kMinPreparedHandles)
      return prepare_tick_solver(model, link.handles, link.mass_kg, link.inertia_B, link.gains, haptic_dt_s_);
    prepare_contact_lookahead(model, link.mass_kg, link.inertia_B, link.gains, haptic_dt_s_);
    return false;
  }
  return false;
}

}  // namespace hapticd::haptic
