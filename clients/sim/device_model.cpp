#include "clients/sim/device_model.hpp"

namespace hapticd::sim {

double step(const DeviceParams& params, DeviceState& state, Vec3d p_DC_m, Vec3d v_DC_m_s, Vec3d f_DT_N,
            double dt_s) noexcept {
  const double m = params.mass_kg, k = params.arm_stiffness_n_per_m, b_arm = params.arm_damping_n_s_per_m;
  const double b = b_arm + params.device_damping_n_s_per_m;
  // m (v1 - v0) = dt [k (p_C - p0 - dt v1) + b_arm (v_C - v1) - b_dev v1 + f], solved for v1.
  const Vec3d rhs = m * state.v_DT_m_s + dt_s * (k * (p_DC_m - state.p_DT_m) + b_arm * v_DC_m_s + f_DT_N);
  state.v_DT_m_s = rhs / (m + dt_s * b + dt_s * dt_s * k);
  const Vec3d dp = dt_s * state.v_DT_m_s;
  state.p_DT_m += dp;
  return dot(f_DT_N, dp);
}

}  // namespace hapticd::sim
