// `haptic-bench contact [--size tiny|default] [--scene FILE] [--json FILE]`
//
// Constraint contact (PGS on the step's Delassus operator) against penalty contact (implicit
// springs), the world's two hand contact models (WorldOptions::contact), on the same scripted
// stylus press into a static box (bench/wall_press.hpp), offline mode at 1 kHz. The reference
// is constraint contact with the world stepped at every haptic tick, closed loop; every other
// run replays the reference's device poses (open loop, as `haptic-bench multirate`), so its
// force error is the contact model's and the visual rate's alone.
//
// JSON (--json FILE): {"suite": "contact", "size", "haptic_hz": 1000, "method", "press": {...},
// "hand_tets_target", "wall_gap_m", "reference_rms_force_n", "rows": [...], "threads": 1,
// "machine": {...}}. One row per (contact model, visual rate), the reference among them:
//   contact             string  "constraint" | "penalty"
//   visual_hz           number  nominal visual rate (30, 60, 1000 = every haptic tick)
//   visual_every_ticks  number  the world steps every this many 1 ms ticks
//   visual_ms_per_step  number  median wall time of one visual step (world step + model), ms
//   visual_ms_per_step_p99 number
//   penetration_max_mm  number  deepest skin point inside the box after any visual step, mm
//   penetration_rms_mm  number  RMS of that depth over the visual steps ending while the
//                               press is down or held, mm
//   rms_force_error_n   number  RMS over ticks of |f_D - f_D,ref| (device force), N
//   max_force_error_n   number  its largest value, N
//   resets              number  proxy and world resets in the run
//   reference           bool    true on the reference row (its errors are 0 by definition)
#include "contact_bench.hpp"

#include <chrono>
#include <cmath>
#include <cstdio>
#include <memory>
#include <string>
#include <utility>
#include <vector>

#include "bench_common.hpp"
#include "server/offline/multirate.hpp"
#include "wall_press.hpp"

namespace hapticd::bench {
namespace {

struct ContactArgs {
  std::string size = "default";
  std::string scene = std::string(HAPTICD_SCENES_DIR) + "/stylus_bunny.json";
  std::string json;
};

// default (~2 min on a busy 2-core EPYC): the project's 4 s press with the scene's hand (1700 tets);
// tiny (a few seconds): the 0.8 s short press with a ~400-tet hand.
struct Size {
  PressProfile press;
  int hand_tets;  // 0: the scene's
};
Size size_of(const std::string& name) {
  if (name == "tiny") return {tiny_press(), 400};
  return {default_press(), 0};
}

constexpr double kHapticPeriodS = 1e-3;
// The box's top 3 mm (world) under the hand's lowest flesh: contact after 1.5 mm of device travel.
constexpr double kWallGapM = 0.003;
// Visual periods in 1 ms ticks: 30 and 60 Hz rounded to whole ticks (as multirate), and every tick.
const std::vector<int> kVisualTicks = {33, 17, 1};
const std::vector<double> kNominalHz = {30, 60, 1000};

struct Row {
  world::ContactModel contact = world::ContactModel::constraint;
  double nominal_hz = 0;
  int every = 1;
  PressRun run;
  offline::ForceError error;
  bool reference = false;
};

nlohmann::json row_json(const Row& r) {
  return {{"contact", std::string(to_string(r.contact))},
          {"visual_hz", static_cast<int>(std::lround(r.nominal_hz))},
          {"visual_every_ticks", r.every},
          {"visual_ms_per_step", r.run.trace.timings.visual_ms_median},
          {"visual_ms_per_step_p99", r.run.trace.timings.visual_ms_p99},
          {"penetration_max_mm", 1e3 * r.run.penetration_max_m},
          {"penetration_rms_mm", 1e3 * r.run.penetration_rms_m},
          {"rms_force_error_n", r.error.rms_n},
          {"max_force_error_n", r.error.max_n},
          {"resets", r.run.trace.resets},
          {"reference", r.reference}};
}

void run_contact_bench(const ContactArgs& a) {
  const Size size = size_of(a.size);
  const Machine machine = describe_machine();
  const world::SceneDesc scene = wall_scene(a.scene, size.hand_tets, kWallGapM);
  const long ticks = std::lround(size.press.total_s() / kHapticPeriodS);
  const auto t0 = std::chrono::steady_clock::now();
  offline::OfflineOptions options;
  options.haptic_period_s = kHapticPeriodS;
  options.visual_every_ticks = 1;
  options.contact = world::ContactModel::constraint;
  Row reference;
  reference.nominal_hz = 1000;
  reference.reference = true;
  {
    offline::OfflineLoops loops(scene, options);
    offline::SimulatedStylus stylus = press_stylus(loops, size.press, sim::DeviceParams{});
    reference.run = run_press(loops, stylus, ticks, size.press);
  }
  const offline::OfflineTrace& ref = reference.run.trace;
  std::vector<Row> rows;
  for (world::ContactModel contact : {world::ContactModel::constraint, world::ContactModel::penalty})
    for (std::size_t i = 0; i < kVisualTicks.size(); ++i) {
      if (contact == world::ContactModel::constraint && kVisualTicks[i] == 1) {
        rows.push_back(reference);
        continue;
      }
      Row row;
      row.contact = contact;
      row.nominal_hz = kNominalHz[i];
      row.every = kVisualTicks[i];
      options.contact = contact;
      options.visual_every_ticks = row.every;
      offline::OfflineLoops loops(scene, options);
      offline::RecordedDevice replay(ref.poses);
      row.run = run_press(loops, replay, ticks, size.press);
      row.error = offline::force_error(row.run.trace, ref);
      rows.push_back(std::move(row));
    }
  const double wall_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();

  std::printf(
      "Stylus press into a static box (top %.0f mm under the hand), %.1f s, haptic loop 1 kHz. Reference: constraint "
      "contact, world stepped every tick, closed loop; the other runs replay its device poses (open loop). "
      "Penetration: deepest skin point after each visual step; RMS over the steps while pressed.\n",
      1e3 * kWallGapM, size.press.total_s());
  std::printf("%-11s %8s %6s %10s %10s %9s %9s %10s %10s %7s\n", "contact", "visual", "ticks", "visual_ms", "vis_p99",
              "pen_max", "pen_rms", "rms_err_N", "max_err_N", "resets");
  nlohmann::json json_rows = nlohmann::json::array();
  for (const Row& r : rows) {
    char visual[32];
    std::snprintf(visual, sizeof visual, "%.0f Hz", r.nominal_hz);
    std::printf("%-11s %8s %6d %10.2f %10.2f %6.2f mm %6.2f mm %10.4f %10.4f %7ld%s\n",
                std::string(to_string(r.contact)).c_str(), visual, r.every, r.run.trace.timings.visual_ms_median,
                r.run.trace.timings.visual_ms_p99, 1e3 * r.run.penetration_max_m, 1e3 * r.run.penetration_rms_m,
                r.error.rms_n, r.error.max_n, r.run.trace.resets, r.reference ? "  (reference)" : "");
    json_rows.push_back(row_json(r));
  }
  const int hand_tets = scene.hands[0].resolution_tets;
  std::printf("reference: RMS force %.3f N; hand %d tets target; %.1f s wall (all runs)\n", offline::rms_force(ref),
              hand_tets, wall_s);
  std::printf("machine: %s, %d cores, BLAS %s, revision %s (one thread; times are medians)\n", machine.cpu.c_str(),
              machine.cores, machine.blas.c_str(), machine.git_revision.c_str());
  if (!a.json.empty())
    write_json(a.json, {{"suite", "contact"},
                        {"size", a.size},
                        {"haptic_hz", 1000},
                        {"method",
                         "stylus press into a static box; reference = constraint contact, world stepped at every "
                         "haptic tick, closed loop; the other runs replay the reference's device poses (open loop); "
                         "force error per tick = |f_D - f_D,ref|; penetration = World snapshot max_penetration_m "
                         "after each visual step, RMS over the steps that end while the press is down or held"},
                        {"press",
                         {{"settle_s", size.press.settle_s},
                          {"ramp_s", size.press.ramp_s},
                          {"hold_s", size.press.hold_s},
                          {"rest_s", size.press.rest_s},
                          {"depth_device_m", size.press.depth_m}}},
                        {"hand_tets_target", hand_tets},
                        {"wall_gap_m", kWallGapM},
                        {"reference_rms_force_n", offline::rms_force(ref)},
                        {"rows", json_rows},
                        {"wall_s", wall_s},
                        {"threads", 1},
                        {"machine", to_json(machine)}});
}

}  // namespace

void add_contact_suite(CLI::App& app) {
  auto args = std::make_shared<ContactArgs>();
  CLI::App* sub = app.add_subcommand(
      "contact", "constraint vs penalty contact: visual step time, skin penetration, force error vs 1 kHz constraint");
  sub->add_option("--size", args->size, "tiny (a smoke run of a few seconds) | default")
      ->check(CLI::IsMember({"tiny", "default"}));
  sub->add_option("--scene", args->scene, "stylus scene (its objects are replaced by the box)")
      ->check(CLI::ExistingFile);
  sub->add_option("--json", args->json, "write the results as JSON to this file");
  sub->callback([args] { run_contact_bench(*args); });
}

}  // namespace hapticd::bench
