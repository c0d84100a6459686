#pragma once

// The simulated stylus and the hand holding it, as one point mass at the tip:
//
//   m a = k_arm (p_C - p) + b_arm (v_C - v) - b_dev v + f
//
// p, v: tip position and velocity in the device base frame D; p_C, v_C: where the user's hand
// wants the tip (the trajectory); f: the force the server returned, held over the tick like a
// device's DAC holds its command. The arm is a spring-damper about the intended motion (the user
// moves along the trajectory and resists deviations from it); the device's own losses are a small
// viscous term against the base.
//
// Parameter choices (DeviceParams defaults):
//   m      0.1 kg     effective tip mass: a Phantom-class linkage's apparent mass (~0.05 kg) plus
//                     the fingers' share
//   k_arm  200 N/m    a relaxed grip; the arm's endpoint stiffness is 100-1000 N/m, the low end
//                     lets a stiff virtual surface push the tip back rather than be overridden
//   b_arm  5 N s/m    with k_arm and m: 7.1 Hz natural frequency, damping ratio 0.58, so a free
//                     tip settles in ~0.1 s without ringing
//   b_dev  0.2 N s/m  linkage friction as viscous loss; small, so free motion is the arm's
// Closed forms used by the tests: with f = 0 a ramp v_C is followed with a lag b_dev v_C / k_arm;
// a constant f displaces the tip at rest by f / k_arm.

#include "clients/sim/vec3.hpp"

namespace hapticd::sim {

struct DeviceParams {
  double mass_kg = 0.1;
  double arm_stiffness_n_per_m = 200.0;
  double arm_damping_n_s_per_m = 5.0;
  double device_damping_n_s_per_m = 0.2;
};

struct DeviceState {
  Vec3d p_DT_m;    // tip position in D
  Vec3d v_DT_m_s;  // tip velocity in D
};

// One step of dt: implicit Euler in the arm and device terms (linear, so solved exactly and stable
// for any stiffness and step), explicit in the held server force f_DT_N. p_DC / v_DC are the
// commanded position and velocity at the end of the step. Returns the work the server force did
// on the device over the step, f . (p_new - p_old) in J: > 0 means it put energy in.
double step(const DeviceParams& params, DeviceState& state, Vec3d p_DC_m, Vec3d v_DC_m_s, Vec3d f_DT_N,
            double dt_s) noexcept;

}  // namespace hapticd::sim
