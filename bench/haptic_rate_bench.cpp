// `haptic-bench haptic_rate [--size tiny|default] [--scene FILE] [--json FILE]`
//
// The haptic loop at 1, 2 and 4 kHz, the visual loop at 60 Hz each time (offline mode), on the
// scripted stylus press into a static box (bench/wall_press.hpp) with constraint contact:
//  (a) the cost of a haptic tick (sample, reply, proxy integration), median and p99 over the
//      run with the scene's device stiffness;
//  (b) the stiffest virtual coupling (DeviceDesc::stiffness_n_m, device space: the spring between
//      the device and the proxy, whose damping coupling_gains_for sets to 0.75 k T) at which the
//      rendering puts no energy into a Phantom-class simulated device over the whole press (down,
//      held, up, rest): W = sum over ticks of f_D . dp (SimulatedStylus::energy_j) <= kEnergyTolJ,
//      and no proxy or world reset. Found by bracketing (x4 steps from the scene's stiffness) and
//      bisection on log k; `--size tiny` bisects coarsely. The sweep lifts the force slew limit
//      (kSweepSlewLimit_n_s) and keeps the 8 N clamp.
//
// Theory. Colgate & Schenkel 1997 ("Passivity of a class of sampled-data systems: application to
// haptic interfaces"): a virtual wall K with virtual damper B, zero-order hold and backward-
// difference velocity on a device of physical damping b is passive for every input iff
// b > K T / 2 + |B|; with the coupling's B = 0.75 K T that is K < 0.8 b / T (b = the device's and the
// holding arm's damping), growing as the rate: colgate_passivity_bound_n_per_m. That worst-case
// bound lies far under what the press measures: the coupling's B makes the low-frequency effective
// damping B - K T / 2 = 0.25 K T positive, so a smooth press stays dissipative until the loop
// itself goes unstable, and that limit is set by the tip mass: a damper B on a mass m sampled at T
// needs B T / m below a constant, so K ~ m / T^2 and grows as the rate squared (Gil et al. 2004,
// "Stability analysis of a 1 DOF haptic interface using the Routh-Hurwitz criterion", find the
// virtual damping on the stabilizing side). theory_n_per_m is that stability bound computed for the
// ideal wall (proxy held fixed; ideal_wall_stability_bound). Measured (tiny and default): the
// passive bound is 0.5-0.75 of it at each rate and grows 4x per doubling of the rate, as it does;
// the proxy is not held fixed (it rides on the hand's flesh) and the clamp bends the loop.
//
// JSON (--json FILE): {"suite": "haptic_rate", "size", "visual_hz": 60, "method", "device": {...},
// "energy_tolerance_j", "sweep_slew_limit_n_s", "press": {...}, "hand_tets_target", "rows": [...],
// "threads": 1, "machine": {...}}. One row per haptic rate:
//   haptic_hz                        number  1000 | 2000 | 4000
//   visual_every_ticks               number  the world steps every this many ticks (~60 Hz)
//   visual_hz_exact                  number  haptic_hz / visual_every_ticks
//   tick_us_median, tick_us_p99      number  wall time of one haptic tick, us (at the scene's stiffness)
//   max_passive_stiffness_n_per_m    number  the largest stiffness found passive, N/m (device space)
//   first_active_n_per_m             number  the smallest stiffness found active (the bracket's top;
//                                            0: none up to 4.1 MN/m)
//   energy_at_max_j                  number  W at max_passive_stiffness_n_per_m, J (<= tolerance)
//   theory_n_per_m                   number  the ideal wall's stability bound (above)
//   colgate_passivity_bound_n_per_m  number  0.8 b / T (above)
//   probes                           array   every stiffness tried: {"k_n_per_m", "energy_j", "resets", "passive"}
#include "protocol/limits.hpp"
#include "haptic_rate_bench.hpp"

#include <chrono>
#include <Eigen/Eigenvalues>
#include <cmath>
#include <cstdio>
#include <memory>
#include <string>
#include <vector>

#include "bench_common.hpp"
#include "wall_press.hpp"

namespace hapticd::bench {
namespace {

struct HapticRateArgs {
  std::string size = "default";
  std::string scene = std::string(HAPTICD_SCENES_DIR) + "/stylus_bunny.json";
  std::string json;
};

// default: the project's 4 s press on a ~400-tet hand (the stiffness limit is the device's and the
// coupling's: the 1700-tet hand gave the same three stiffnesses, 166, 664 and 2656 kN/m, in ~7 min instead of ~30 s),
// the bracket bisected to 10%; tiny (~15 s): the 0.8 s short press, the same hand, to 50%.
struct Size {
  PressProfile press;
  int hand_tets;        // 0: the scene's
  double bracket_ratio;  // bisect until first_active / max_passive <= this
};
Size size_of(const std::string& name) {
  if (name == "tiny") return {tiny_press(), 400, 1.5};
  return {default_press(), 400, 1.10};
}

const std::vector<int> kHapticHz = {1000, 2000, 4000};
constexpr double kVisualHz = 60;
constexpr double kWallGapM = 0.003;
// Passive: the rendering's net work on the device over the press at most 1 mJ. The arm stores
// ~35 mJ in the rendered wall at the bottom of the default press (3.7 N over 2 cm) and gets it
// back on the way up; a coupling that rings gives joules within a second.
constexpr double kEnergyTolJ = 1e-3;
// The sweep lifts the device's force slew limit (the scene's 1000 N/s): with it, no stiffness up to
// 4 MN/m put energy in (measured: the limiter, not the spring, then shapes the force), and the
// sweep would find the limiter's bound. The force clamp (8 N, a Phantom Premium 1.5's peak) stays.
constexpr double kSweepSlewLimit_n_s = protocol::kMaxForceRateNPerS;  // the most the wire carries (2500 N a tick at 4 kHz)
// The bracket's ends: below a soft spring nothing is felt; above 4 MN/m is beyond any desktop device.
constexpr double kMinStiffness = 50, kMaxStiffness = 4.1e6;

// A Phantom-class stylus (sim::DeviceParams; clients/sim/device_model.hpp has the model):
//  - apparent mass at the tip 0.1 kg: the PHANToM Premium 1.0/1.5's tip mass (SensAble's
//    specification, under 75 g) plus the share of the fingers holding the stylus, as
//    device_model.hpp argues for its default;
//  - device damping 0.02 N s/m: "little damping", a cable-driven backdrivable linkage whose
//    viscous loss is small against the holding hand's; an assumption of that order, not a measured
//    figure (Colgate & Brown 1994 name the device's physical damping as what bounds the
//    renderable stiffness at a given rate);
//  - the holding arm as device_model.hpp's relaxed grip: 200 N/m, 5 N s/m about the script.
sim::DeviceParams phantom_class() {
  sim::DeviceParams p;
  p.mass_kg = 0.1;
  p.device_damping_n_s_per_m = 0.02;
  p.arm_stiffness_n_per_m = 200.0;
  p.arm_damping_n_s_per_m = 5.0;
  return p;
}

// Theory, the ideal wall: the proxy held fixed, the device (sim::step: implicit Euler in its arm and
// damping, the force held over the tick) under f = -K p - B v_f with B = coupling_gains_for's
// device-space damping max(0.75 K T, 0.5) and v_f ProxyHand's filtered difference velocity
// (v_f += 0.6 ((p_n - p_n-1) / T - v_f)). Per tick (p, v, v_f, f) -> A (p, v, v_f, f); the largest K
// with spectral radius of A < 1, by bisection on log K. The stability bound, not Colgate's.
double ideal_wall_stability_bound(const sim::DeviceParams& d, double T) {
  constexpr double kAlpha = 0.6;  // ProxyHand's kVelocityFilter (server/haptic/virtual_coupling.cpp)
  auto stable = [&](double K) {
    const double B = std::max(0.75 * K * T, 0.5);
    const double den = d.mass_kg + T * (d.arm_damping_n_s_per_m + d.device_damping_n_s_per_m) +
                       T * T * d.arm_stiffness_n_per_m;
    Eigen::Matrix4d A = Eigen::Matrix4d::Zero();
    // v' = (m v + T (-k_arm p + f)) / den
    const Eigen::RowVector4d v1(-T * d.arm_stiffness_n_per_m / den, d.mass_kg / den, 0, T / den);
    const Eigen::RowVector4d p1 = Eigen::RowVector4d(1, 0, 0, 0) + T * v1;
    const Eigen::RowVector4d vf1 = (1 - kAlpha) * Eigen::RowVector4d(0, 0, 1, 0) + kAlpha * v1;
    A.row(0) = p1, A.row(1) = v1, A.row(2) = vf1, A.row(3) = -K * p1 - B * vf1;
    return Eigen::EigenSolver<Eigen::Matrix4d>(A, false).eigenvalues().cwiseAbs().maxCoeff() < 1.0;
  };
  double lo = 1, hi = 1e9;
  if (!stable(lo)) return 0;
  while (hi / lo > 1.001) {
    const double mid = std::sqrt(lo * hi);
    (stable(mid) ? lo : hi) = mid;
  }
  return lo;
}

struct Probe {
  double k = 0, energy_j = 0;
  long resets = 0;
  bool passive = false;
  offline::OfflineTimings timings;
};

struct RateResult {
  int haptic_hz = 0, every = 1;
  offline::OfflineTimings timings;  // at the scene's stiffness
  double max_passive = 0, first_active = 0, energy_at_max = 0, theory = 0, colgate = 0;
  std::vector<Probe> probes;
};

Probe probe(world::SceneDesc scene, const Size& size, int haptic_hz, int every, double k) {
  const double T = 1.0 / haptic_hz;
  scene.devices[0].stiffness_n_m = k;
  scene.devices[0].max_force_rate_n_s = kSweepSlewLimit_n_s;
  offline::OfflineOptions options;
  options.haptic_period_s = T;
  options.visual_every_ticks = every;
  options.contact = world::ContactModel::constraint;
  offline::OfflineLoops loops(scene, options);
  offline::SimulatedStylus stylus = press_stylus(loops, size.press, phantom_class());
  const PressRun run = run_press(loops, stylus, std::lround(size.press.total_s() / T), size.press);
  Probe p;
  p.k = k;
  p.energy_j = stylus.energy_j();
  p.resets = run.trace.resets;
  p.passive = std::isfinite(p.energy_j) && p.energy_j <= kEnergyTolJ && p.resets == 0;
  p.timings = run.trace.timings;
  return p;
}

RateResult sweep(const world::SceneDesc& scene, const Size& size, int haptic_hz) {
  RateResult r;
  r.haptic_hz = haptic_hz;
  r.every = static_cast<int>(std::lround(haptic_hz / kVisualHz));
  const sim::DeviceParams dev = phantom_class();
  r.colgate = 0.8 * (dev.device_damping_n_s_per_m + dev.arm_damping_n_s_per_m) * haptic_hz;
  r.theory = ideal_wall_stability_bound(dev, 1.0 / haptic_hz);
  auto test = [&](double k) {
    r.probes.push_back(probe(scene, size, haptic_hz, r.every, k));
    return r.probes.back();
  };
  const double k0 = scene.devices[0].stiffness_n_m;
  const Probe first = test(k0);
  r.timings = first.timings;
  double lo = 0, hi = 0;
  if (first.passive) {
    lo = k0;
    for (double k = 4 * k0; k <= kMaxStiffness; k *= 4) {
      if (!test(k).passive) {
        hi = k;
        break;
      }
      lo = k;
    }
  } else {
    hi = k0;
    for (double k = k0 / 4; k >= kMinStiffness; k /= 4) {
      if (test(k).passive) {
        lo = k;
        break;
      }
      hi = k;
    }
  }
  if (lo > 0 && hi > 0)
    while (hi / lo > size.bracket_ratio) {
      const double mid = std::sqrt(lo * hi);
      (test(mid).passive ? lo : hi) = mid;
    }
  r.max_passive = lo;
  r.first_active = hi;  // 0: nothing up to kMaxStiffness was active
  for (const Probe& p : r.probes)
    if (p.k == lo) r.energy_at_max = p.energy_j;
  return r;
}

void run_haptic_rate_bench(const HapticRateArgs& a) {
  const Size size = size_of(a.size);
  const Machine machine = describe_machine();
  const world::SceneDesc scene = wall_scene(a.scene, size.hand_tets, kWallGapM);
  const sim::DeviceParams dev = phantom_class();
  const auto t0 = std::chrono::steady_clock::now();
  std::vector<RateResult> results;
  for (int hz : kHapticHz) results.push_back(sweep(scene, size, hz));
  const double wall_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();

  std::printf(
      "Stylus press into a static box (constraint contact), visual loop ~%.0f Hz; Phantom-class device (tip %.2f kg, "
      "damping %.2f N s/m, arm %.0f N/m, %.1f N s/m). Passive: the rendering's work on the device over the %.1f s "
      "press <= %.0f mJ, no reset; slew limit lifted, 8 N clamp kept. Stiffness = device-to-proxy coupling, "
      "device space; tick times at the scene's %.0f N/m.\n",
      kVisualHz, dev.mass_kg, dev.device_damping_n_s_per_m, dev.arm_stiffness_n_per_m, dev.arm_damping_n_s_per_m,
      size.press.total_s(), 1e3 * kEnergyTolJ, scene.devices[0].stiffness_n_m);
  std::printf("%8s %6s %9s %9s %13s %13s %12s %13s %13s %7s\n", "haptic", "ticks", "tick_us", "tick_p99",
              "passive_N/m", "active_N/m", "W_at_max_mJ", "theory_N/m", "colgate_N/m", "probes");
  nlohmann::json rows = nlohmann::json::array();
  for (const RateResult& r : results) {
    char hz[32];
    std::snprintf(hz, sizeof hz, "%d Hz", r.haptic_hz);
    std::printf("%8s %6d %9.2f %9.2f %13.0f %13.0f %12.3f %13.0f %13.0f %7zu\n", hz, r.every,
                r.timings.haptic_us_median, r.timings.haptic_us_p99, r.max_passive, r.first_active,
                1e3 * r.energy_at_max, r.theory, r.colgate, r.probes.size());
    nlohmann::json probes = nlohmann::json::array();
    for (const Probe& p : r.probes)
      probes.push_back({{"k_n_per_m", p.k}, {"energy_j", p.energy_j}, {"resets", p.resets}, {"passive", p.passive}});
    rows.push_back({{"haptic_hz", r.haptic_hz},
                    {"visual_every_ticks", r.every},
                    {"visual_hz_exact", static_cast<double>(r.haptic_hz) / r.every},
                    {"tick_us_median", r.timings.haptic_us_median},
                    {"tick_us_p99", r.timings.haptic_us_p99},
                    {"max_passive_stiffness_n_per_m", r.max_passive},
                    {"first_active_n_per_m", r.first_active},
                    {"energy_at_max_j", r.energy_at_max},
                    {"theory_n_per_m", r.theory},
                    {"colgate_passivity_bound_n_per_m", r.colgate},
                    {"probes", probes}});
  }
  const int hand_tets = scene.hands[0].resolution_tets;
  std::printf("theory: the ideal wall's stability bound (proxy fixed; ~ m / T^2); colgate: Colgate & Schenkel's "
              "worst-case passivity bound b > K T/2 + B with B = 0.75 K T, K < 0.8 b / T, b = %.2f N s/m; hand %d "
              "tets target; %.1f s wall\n",
              dev.device_damping_n_s_per_m + dev.arm_damping_n_s_per_m, hand_tets, wall_s);
  std::printf("machine: %s, %d cores, BLAS %s, revision %s (one thread; times are medians)\n", machine.cpu.c_str(),
              machine.cores, machine.blas.c_str(), machine.git_revision.c_str());
  if (!a.json.empty())
    write_json(a.json, {{"suite", "haptic_rate"},
                        {"size", a.size},
                        {"visual_hz", kVisualHz},
                        {"method",
                         "stylus press into a static box, constraint contact; tick cost at the scene's device "
                         "stiffness; passive stiffness: largest device-to-proxy coupling stiffness with the "
                         "rendering's work on the simulated device over the press <= energy_tolerance_j and no "
                         "reset, by x4 bracketing from the scene's stiffness and bisection on log k"},
                        {"device",
                         {{"mass_kg", dev.mass_kg},
                          {"device_damping_n_s_per_m", dev.device_damping_n_s_per_m},
                          {"arm_stiffness_n_per_m", dev.arm_stiffness_n_per_m},
                          {"arm_damping_n_s_per_m", dev.arm_damping_n_s_per_m},
                          {"max_force_n", scene.devices[0].max_force_n},
                          {"max_force_rate_n_s", scene.devices[0].max_force_rate_n_s}}},
                        {"energy_tolerance_j", kEnergyTolJ},
                        {"sweep_slew_limit_n_s", kSweepSlewLimit_n_s},
                        {"press",
                         {{"settle_s", size.press.settle_s},
                          {"ramp_s", size.press.ramp_s},
                          {"hold_s", size.press.hold_s},
                          {"rest_s", size.press.rest_s},
                          {"depth_device_m", size.press.depth_m}}},
                        {"hand_tets_target", hand_tets},
                        {"rows", rows},
                        {"wall_s", wall_s},
                        {"threads", 1},
                        {"machine", to_json(machine)}});
}

}  // namespace

void add_haptic_rate_suite(CLI::App& app) {
  auto args = std::make_shared<HapticRateArgs>();
  CLI::App* sub = app.add_subcommand(
      "haptic_rate", "haptic loop at 1, 2, 4 kHz: tick cost and the stiffest coupling rendered passively");
  sub->add_option("--size", args->size, "tiny (a smoke run of ~15 s) | default")
      ->check(CLI::IsMember({"tiny", "default"}));
  sub->add_option("--scene", args->scene, "stylus scene (its objects are replaced by the box)")
      ->check(CLI::ExistingFile);
  sub->add_option("--json", args->json, "write the results as JSON to this file");
  sub->callback([args] { run_haptic_rate_bench(*args); });
}

}  // namespace hapticd::bench
