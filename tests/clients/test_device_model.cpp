#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <complex>
#include <fstream>
#include <numbers>
#include <string>

#include "clients/sim/device_model.hpp"
#include "clients/sim/device_simulation.hpp"

namespace hapticd::sim {
namespace {

const DeviceParams kParams;  // the documented defaults: 0.1 kg, 200 N/m, 5 N s/m, 0.2 N s/m

// Free tip (f = 0) driven along x by p_C = A cos(w t); returns the complex gain of the tip's
// steady-state response measured by projection onto e^{-jwt} over whole periods.
std::complex<double> measured_gain(double frequency_hz, double dt_s) {
  const double w = 2.0 * std::numbers::pi * frequency_hz, amplitude = 0.01;
  DeviceState s;
  s.p_DT_m = {amplitude, 0.0, 0.0};
  const int per_period = static_cast<int>(std::lround(1.0 / (frequency_hz * dt_s)));
  const int settle = 20 * per_period, measure = 4 * per_period;  // 20 periods: transient < 1e-20
  std::complex<double> sum = 0.0;
  for (int n = 1; n <= settle + measure; ++n) {
    const double t = n * dt_s;
    step(kParams, s, {amplitude * std::cos(w * t), 0, 0}, {-amplitude * w * std::sin(w * t), 0, 0}, {}, dt_s);
    if (n > settle) sum += s.p_DT_m.x * std::exp(std::complex<double>(0.0, -w * t));
  }
  return 2.0 * sum / (static_cast<double>(measure) * amplitude);
}

// Continuous-time transfer function from p_C to p of m a = k (p_C - p) + b_a (v_C - v) - b_d v.
std::complex<double> closed_form_gain(double frequency_hz) {
  const double w = 2.0 * std::numbers::pi * frequency_hz;
  const double m = kParams.mass_kg, k = kParams.arm_stiffness_n_per_m, ba = kParams.arm_damping_n_s_per_m,
               bd = kParams.device_damping_n_s_per_m;
  const std::complex<double> jw(0.0, w);
  return (k + ba * jw) / (k - m * w * w + (ba + bd) * jw);
}

TEST(DeviceModel, FreeTipFollowsARampWithTheClosedFormLag) {
  // Steady state of m a = k (p_C - p) + b_a (v_C - v) - b_d v on a ramp v_C: a = 0, v = v_C, so
  // the lag is b_d v_C / k. Implicit Euler has the same fixed point, so it is met to round-off.
  const double v = 0.05, dt = 1e-3;
  DeviceState s;
  for (int n = 1; n <= 3000; ++n) step(kParams, s, {v * n * dt, 0, 0}, {v, 0, 0}, {}, dt);
  const double lag = v * 3.0 - s.p_DT_m.x;
  const double expected = kParams.device_damping_n_s_per_m * v / kParams.arm_stiffness_n_per_m;
  EXPECT_NEAR(lag, expected, 1e-9 * v) << "lag " << lag << " m, closed form " << expected << " m";
  EXPECT_NEAR(s.v_DT_m_s.x, v, 1e-9 * v);
  EXPECT_EQ(s.p_DT_m.y, 0.0);
  EXPECT_EQ(s.p_DT_m.z, 0.0);
}

TEST(DeviceModel, FreeTipFollowsASinusoidWithTheArmsFrequencyResponseAtFirstOrder) {
  // At 2 Hz the arm (7.1 Hz natural frequency, damping ratio 0.58) amplifies and delays the
  // motion visibly; implicit Euler approaches the closed form at first order in dt.
  const std::complex<double> exact = closed_form_gain(2.0);
  const double e1 = std::abs(measured_gain(2.0, 1e-3) - exact);
  const double e2 = std::abs(measured_gain(2.0, 0.5e-3) - exact);
  EXPECT_GT(std::abs(exact), 1.05) << "the test must look at a frequency where the arm shapes the motion";
  EXPECT_LT(e1, 0.02 * std::abs(exact)) << "2 % at the 1 kHz servo rate";
  EXPECT_NEAR(e1 / e2, 2.0, 0.1) << "first order: halving dt halves the error (" << e1 << ", " << e2 << ")";
}

TEST(DeviceModel, ConstantForceDisplacesTheTipByForceOverArmStiffness) {
  const Vec3d f{0.5, -1.0, -2.0};
  DeviceState s;
  for (int n = 0; n < 2000; ++n) step(kParams, s, {}, {}, f, 1e-3);
  const Vec3d expected = f / kParams.arm_stiffness_n_per_m;
  // The brief's 1 %; the fixed point is in fact exact (rest: k (0 - p) + f = 0).
  EXPECT_NEAR(s.p_DT_m.x, expected.x, 0.01 * std::abs(expected.x));
  EXPECT_NEAR(s.p_DT_m.y, expected.y, 0.01 * std::abs(expected.y));
  EXPECT_NEAR(s.p_DT_m.z, expected.z, 0.01 * std::abs(expected.z));
  EXPECT_NEAR(norm(s.p_DT_m - expected), 0.0, 1e-12);
  EXPECT_NEAR(norm(s.v_DT_m_s), 0.0, 1e-12);
}

TEST(DeviceModel, ImplicitArmStaysStableForAStiffArmAtALowRate) {
  // k dt^2 / m = 1e5 * 0.01^2 / 0.1 = 100: explicit Euler would explode; implicit settles.
  DeviceParams stiff = kParams;
  stiff.arm_stiffness_n_per_m = 1e5;
  DeviceState s;
  s.p_DT_m = {0.05, 0, 0};
  for (int n = 0; n < 200; ++n) step(stiff, s, {}, {}, {}, 0.01);
  EXPECT_LT(std::abs(s.p_DT_m.x), 1e-6);
}

TEST(DeviceModel, StepReturnsTheWorkOfTheForce) {
  DeviceState s;
  const Vec3d f{0.0, 0.0, 3.0};
  const Vec3d before = s.p_DT_m;
  const double work = step(kParams, s, {}, {}, f, 1e-3);
  EXPECT_DOUBLE_EQ(work, dot(f, s.p_DT_m - before));
  EXPECT_GT(work, 0.0) << "a force on a tip at rest moves it along the force";
}

// Passivity bookkeeping over a run: the tip moves around a circle (the arm drives it) while a
// velocity-dependent force acts on it.
double energy_with_force_gain(double c_n_s_per_m, double* independent = nullptr) {
  DeviceSimulation sim(Trajectory::circle(), kParams, 1e-3);
  double sum = 0.0;
  for (int n = 0; n < 4000; ++n) {
    const Vec3d f = c_n_s_per_m * sim.state().v_DT_m_s;
    sim.set_force(f, false);
    const Vec3d before = sim.state().p_DT_m;
    sim.advance();
    sum += dot(f, sim.state().p_DT_m - before);
  }
  if (independent != nullptr) *independent = sum;
  return sim.passivity_energy_j();
}

TEST(DevicePassivity, ADampingForceOnlyTakesEnergyOut) {
  double independent = 0.0;
  const double energy = energy_with_force_gain(-2.0, &independent);
  EXPECT_LT(energy, 0.0);
  EXPECT_NEAR(energy, independent, 1e-15) << "the sum of f . dp over the steps";
  // Order of magnitude: c |v|^2 T with |v| = 2 pi 0.5 Hz 2 cm ~ 0.063 m/s, T = 4 s: ~ -0.03 J.
  EXPECT_GT(energy, -0.05);
  EXPECT_LT(energy, -0.01);
}

TEST(DevicePassivity, AForceAlongTheVelocityPutsEnergyIn) {
  const double energy = energy_with_force_gain(+2.0);
  EXPECT_GT(energy, 0.01);
}

TEST(DevicePassivity, NoForceNoEnergy) { EXPECT_EQ(energy_with_force_gain(0.0), 0.0); }

TEST(DeviceSimulation, PenetrationIsTheCommandToTipDistanceWhileInContact) {
  // The hand holds the tip at 1 cm while the server pushes up with 2 N and reports contact: the
  // tip rests F / k = 10 mm above where the hand wants it, and that is the penetration.
  const std::string path = ::testing::TempDir() + "hold_device_model.csv";
  std::ofstream(path) << "0,0,0,0.01\n";
  DeviceSimulation sim(Trajectory::from_csv(path), kParams, 1e-3);
  for (int n = 0; n < 1000; ++n) {  // free: no contact recorded
    sim.advance();
    sim.record_tick();
  }
  EXPECT_EQ(sim.penetration_max_m(), 0.0);
  sim.set_force({0.0, 0.0, 2.0}, true);
  double largest = 0.0;
  for (int n = 0; n < 3000; ++n) {
    sim.advance();
    sim.record_tick();
    largest = std::max(largest, norm(sim.commanded() - sim.state().p_DT_m));
  }
  EXPECT_EQ(sim.penetration_max_m(), largest);
  EXPECT_NEAR(norm(sim.commanded() - sim.state().p_DT_m), 2.0 / kParams.arm_stiffness_n_per_m, 1e-9)
      << "at rest: F / k";
  // A force step on the arm (damping ratio 0.58) overshoots by exp(-pi z / sqrt(1 - z^2)) = 10.7 %.
  const double z = (kParams.arm_damping_n_s_per_m + kParams.device_damping_n_s_per_m) /
                   (2.0 * std::sqrt(kParams.arm_stiffness_n_per_m * kParams.mass_kg));
  const double overshoot = std::exp(-std::numbers::pi * z / std::sqrt(1.0 - z * z));
  EXPECT_NEAR(largest / 0.01 - 1.0, overshoot, 0.01) << "1 % of F / k: implicit Euler at 1 ms damps a little more";
  EXPECT_EQ(sim.recorded_ticks(), 4000u);
  EXPECT_EQ(sim.contact_ticks(), 3000u);
  EXPECT_DOUBLE_EQ(sim.force_max_n(), 2.0);
  EXPECT_NEAR(sim.force_rms_n(), 2.0 * std::sqrt(3000.0 / 4000.0), 1e-12);
}

}  // namespace
}  // namespace hapticd::sim
