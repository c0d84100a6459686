#include "clients/sim/device_simulation.hpp"

#include <algorithm>
#include <cmath>
#include <utility>

namespace hapticd::sim {

DeviceSimulation::DeviceSimulation(Trajectory trajectory, const DeviceParams& params, double dt_s)
    : trajectory_(std::move(trajectory)), params_(params), dt_s_(dt_s) {
  state_.p_DT_m = trajectory_.position(0.0);
}

void DeviceSimulation::advance() noexcept {
  ++steps_;
  const double t = time_s();
  const Vec3d f_DT_N = force();
  force_.add(norm(f_DT_N));
  energy_j_ += step(params_, state_, trajectory_.position(t), trajectory_.velocity(t), f_DT_N, dt_s_);
}

void DeviceSimulation::set_force(Vec3d f_DT_N, bool in_contact) noexcept {
  f_DT_N_ = f_DT_N;
  in_contact_ = in_contact;
}

void DeviceSimulation::record_tick() noexcept {
  ++recorded_ticks_;
  if (!in_contact_) return;
  ++contact_ticks_;
  penetration_max_m_ = std::max(penetration_max_m_, norm(commanded() - state_.p_DT_m));
}

double DeviceSimulation::force_rms_n() const noexcept {
  return force_.rms_n(steps_);
}

}  // namespace hapticd::sim
