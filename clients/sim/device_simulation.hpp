#pragma once

// The simulated device over a run: the trajectory, the tip model, the force last received, and
// the figures a report needs (force, energy, contact, penetration). Network-free, so the physics
// and the bookkeeping are tested without a server; the servo loop drives it tick by tick.

#include <cstdint>

#include "clients/sim/device_model.hpp"
#include "clients/sim/force_figures.hpp"
#include "clients/sim/trajectory.hpp"

namespace hapticd::sim {

class DeviceSimulation {
 public:
  // The tip starts at rest at the trajectory's position at t = 0.
  DeviceSimulation(Trajectory trajectory, const DeviceParams& params, double dt_s);

  // One tick: t += dt and one step() toward the trajectory under the held force; accumulates the
  // force's work and magnitude.
  void advance() noexcept;
  // The newest force from the server and whether it reported contact; held until the next.
  void set_force(Vec3d f_DT_N, bool in_contact) noexcept;
  // The share of the held force the device renders from the next advance() on (client::ReplyWatchdog).
  void set_output_scale(double scale) noexcept { output_scale_ = scale; }
  // End of a tick: contact and penetration bookkeeping for the current state.
  void record_tick() noexcept;

  [[nodiscard]] double time_s() const noexcept { return static_cast<double>(steps_) * dt_s_; }
  [[nodiscard]] const DeviceState& state() const noexcept { return state_; }
  [[nodiscard]] Vec3d commanded() const noexcept { return trajectory_.position(time_s()); }
  // The force rendered: the held force times the output scale.
  [[nodiscard]] Vec3d force() const noexcept { return output_scale_ * f_DT_N_; }
  [[nodiscard]] bool in_contact() const noexcept { return in_contact_; }

  // Sum over steps of f . dp (J): the energy the rendered force put into the device. A passive
  // rendering keeps it <= 0 (up to what it stores elastically at the end); > 0 means it generated
  // energy.
  [[nodiscard]] double passivity_energy_j() const noexcept { return energy_j_; }
  [[nodiscard]] double force_max_n() const noexcept { return force_.max_n; }
  // RMS over steps of |f| (time-weighted: one sample per tick), N.
  [[nodiscard]] double force_rms_n() const noexcept;
  // Largest |p_C - p| over recorded ticks with contact: how far the hand wanted the tip beyond
  // where the rendered surface held it. The client does not know the contact normal, so this is
  // the full distance, not its normal component.
  [[nodiscard]] double penetration_max_m() const noexcept { return penetration_max_m_; }
  [[nodiscard]] std::uint64_t steps() const noexcept { return steps_; }
  [[nodiscard]] std::uint64_t recorded_ticks() const noexcept { return recorded_ticks_; }
  [[nodiscard]] std::uint64_t contact_ticks() const noexcept { return contact_ticks_; }

 private:
  Trajectory trajectory_;
  DeviceParams params_;
  double dt_s_;
  DeviceState state_;
  Vec3d f_DT_N_;
  double output_scale_ = 1.0;
  bool in_contact_ = false;
  std::uint64_t steps_ = 0;
  std::uint64_t recorded_ticks_ = 0;
  std::uint64_t contact_ticks_ = 0;
  double energy_j_ = 0.0;
  ForceFigures force_;
  double penetration_max_m_ = 0.0;
};

}  // namespace hapticd::sim
