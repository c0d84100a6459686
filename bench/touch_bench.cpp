// `haptic-bench touch [--size tiny|default] [--json FILE] [--tick-sweeps N]`
//
// Contacts that make and break (issue 17), closed loop through the lockstep runner (hapticd's haptic
// tick and visual step, the passivity controller on as in hapticd), each interaction scripted as its
// tests script it (server/offline/touch.hpp):
//   press_hold_lift  the simulated stylus presses 2 cm (device) into the movable bunny of
//                    stylus_bunny.json at 2 cm/s, holds 0.5 s, lifts at 5 cm/s to 1 cm above its start;
//   grasp_release    the simulated 16-frame glove lowers its palm over the box of glove_grasp.json,
//                    closes in a tripod grasp, lifts it 5 cm, opens.
// Each at visual rates of 15, 30 and 60 Hz with the linearized model (the tick's unilateral contact
// rows) and the bilateral baseline (the last step's pushing contacts held both ways), and once with
// the world stepped at every haptic tick (the reference).
//
// JSON (--json FILE): {"suite": "touch", "size", "tick_contact_sweeps", "haptic_hz": 1000, "method", "rows": [...],
// "wall_s", "threads": 1, "machine": {...}}. One row per (interaction, visual rate, model):
//   interaction         string  "press_hold_lift" | "grasp_release"
//   visual_hz           number  nominal visual rate (15, 30, 60; 1000 = every tick, the reference)
//   visual_every_ticks  number  the world steps every this many 1 ms ticks
//   model               string  "linearized" | "bilateral"
//   energy_j            number  work of the rendered forces on the device over the run (> 0: the
//                               rendering put energy in; the glove's: palm and joints)
//   release_n           number  the largest force after the release: the stylus's toward the bunny once
//                               its commanded tip is back above the height where it first touched, the
//                               glove's largest frame force once the hand is open; both after one haptic
//                               and one visual period, N
//   after_n             number  the largest force from one second after the lift / the opening, N
//   rms_force_error_n   number  RMS over ticks of sqrt(sum over frames |f_D - f_D,ref|^2) against the
//                               reference run (closed loop both: the same commanded motion), N
//   max_force_error_n   number  its largest value, N
//   penetration_max_mm  number  the deepest skin point inside anything after any visual step, mm
//   tick_us_p99         number  99th percentile of one haptic tick's wall time, us
//   contact_solves      number  ticks that solved the model's contact rows (ProxyHand::contact_solves)
//   contact_unexact     number  share of them that ended at the sweep limit without an exact answer
//   contact_sweeps_mean number  Gauss-Seidel sweeps per contact solve, mean (at most 8): the tick's
//                               contact work counted, reproducible where tick_us_p99 carries the
//                               machine's noise
//   visual_ms_median    number  median wall time of one visual step, ms
//   resets              number  proxy and world resets
//   lift_mm             number  grasp_release only: how high the box rose, mm (else 0)
//   reference           bool    true on the reference row (its errors are 0 by definition)
#include "touch_bench.hpp"

#include <spdlog/spdlog.h>

#include <chrono>
#include <cmath>
#include <cstdio>
#include <memory>
#include <string>
#include <vector>

#include "bench_common.hpp"
#include "server/offline/multirate.hpp"
#include "server/offline/touch.hpp"
#include "server/world/scene_loader.hpp"
#include "touch_runs.hpp"

namespace hapticd::bench {
namespace {

constexpr double kHapticPeriodS = 1e-3;


// default (a few minutes on a 2-core EPYC): both interactions at 15, 30 and 60 Hz with the scenes'
// hands; tiny (a smoke run of ~10 s): the press at 30 Hz with a ~400-tet hand (the glove's reference
// alone would take ~40 s).
struct Size {
  std::vector<int> visual_ticks;
  int hand_tets;  // 0: the scene's
  bool grasp;
};
Size size_of(const std::string& name) {
  if (name == "tiny") return {{33}, 400, false};
  return {{67, 33, 17}, 0, true};
}

struct Row : TouchOutcome {
  std::string interaction;
  int every = 1;
  haptic::HandleModelKind model = haptic::HandleModelKind::linearized;
  offline::ForceError error;
  bool reference = false;
};

world::SceneDesc with_hand_tets(world::SceneDesc scene, int tets) {
  if (tets > 0)
    for (world::HandDesc& h : scene.hands) h.resolution_tets = tets;
  return scene;
}

offline::OfflineOptions options_for(int every, haptic::HandleModelKind model, int tick_sweeps) {
  offline::OfflineOptions o;
  o.tick_contact_sweeps = tick_sweeps;
  o.haptic_period_s = kHapticPeriodS;
  o.visual_every_ticks = every;
  o.model = model;
  return o;
}

Row press_row(const world::SceneDesc& scene, int every, haptic::HandleModelKind model, int tick_sweeps) {
  Row r;
  static_cast<TouchOutcome&>(r) = bench_press(scene, options_for(every, model, tick_sweeps));
  r.interaction = "press_hold_lift";
  r.every = every;
  r.model = model;
  return r;
}

Row grasp_row(const world::SceneDesc& scene, int every, haptic::HandleModelKind model, int tick_sweeps) {
  Row r;
  static_cast<TouchOutcome&>(r) = bench_grasp(scene, options_for(every, model, tick_sweeps));
  r.interaction = "grasp_release";
  r.every = every;
  r.model = model;
  return r;
}

// 15, 30, 60 Hz for 67, 33, 17 ticks (as multirate names them), 1000 for every tick.
int nominal_hz(int every) { return every == 17 ? 60 : static_cast<int>(std::lround(1.0 / (every * kHapticPeriodS))); }

double unexact_share(const offline::OfflineContactSolves& s) {
  return s.solves > 0 ? static_cast<double>(s.unconverged) / static_cast<double>(s.solves) : 0.0;
}
double sweeps_mean(const offline::OfflineContactSolves& s) {
  return s.solves > 0 ? static_cast<double>(s.sweeps) / static_cast<double>(s.solves) : 0.0;
}

nlohmann::json row_json(const Row& r) {
  return {{"interaction", r.interaction},
          {"visual_hz", nominal_hz(r.every)},
          {"visual_every_ticks", r.every},
          {"model", haptic::to_string(r.model)},
          {"energy_j", r.run.energy_j},
          {"release_n", r.release_n},
          {"after_n", r.after_n},
          {"rms_force_error_n", r.error.rms_n},
          {"max_force_error_n", r.error.max_n},
          {"penetration_max_mm", 1e3 * r.run.penetration_max_m},
          {"tick_us_p99", r.run.trace.timings.haptic_us_p99},
          {"contact_solves", r.run.trace.contact_solves.solves},
          {"contact_unexact", unexact_share(r.run.trace.contact_solves)},
          {"contact_sweeps_mean", sweeps_mean(r.run.trace.contact_solves)},
          {"visual_ms_median", r.run.trace.timings.visual_ms_median},
          {"resets", r.run.trace.resets},
          {"lift_mm", 1e3 * r.lift_m},
          {"reference", r.reference}};
}

void run_touch_bench(const TouchSuiteArgs& a) {
  const Size size = size_of(a.size);
  const Machine machine = describe_machine();
  const auto t0 = std::chrono::steady_clock::now();
  const world::SceneDesc press_scene = with_hand_tets(offline::press_scene("movable_bunny"), size.hand_tets);
  const world::SceneDesc grasp_scene = with_hand_tets(
      offline::grasp_scene(world::load_scene(std::string(HAPTICD_SCENES_DIR) + "/glove_grasp.json")), size.hand_tets);
  std::vector<Row> rows;
  for (const char* interaction : {"press_hold_lift", "grasp_release"}) {
    const bool press = std::string(interaction) == "press_hold_lift";
    if (!press && !size.grasp) continue;
    auto run = [&](int every, haptic::HandleModelKind model) {
      spdlog::info("touch: {} at {} ticks, {}", interaction, every, haptic::to_string(model));
      return press ? press_row(press_scene, every, model, a.tick_sweeps)
                   : grasp_row(grasp_scene, every, model, a.tick_sweeps);
    };
    Row reference = run(1, haptic::HandleModelKind::linearized);
    reference.reference = true;
    for (int every : size.visual_ticks)
      for (haptic::HandleModelKind model : {haptic::HandleModelKind::linearized, haptic::HandleModelKind::bilateral}) {
        Row r = run(every, model);
        r.error = offline::force_error(r.run.trace, reference.run.trace);
        rows.push_back(std::move(r));
      }
    rows.push_back(std::move(reference));
  }
  const double wall_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();

  std::printf(
      "Contacts that make and break, closed loop at 1 kHz, passivity controller on: press_hold_lift = the stylus 2 cm "
      "into the movable bunny and lifted; grasp_release = the 16-frame glove lifting the box and opening. Error "
      "against the world stepped every tick (the reference, closed loop). release: force toward the object after "
      "the lift (stylus) / largest frame force after the opening (glove).\n");
  std::printf("%-16s %7s %-11s %10s %9s %9s %10s %10s %8s %8s %8s %7s %8s %6s %7s\n", "interaction", "visual", "model",
              "energy_J", "release_N", "after_N", "rms_err_N", "max_err_N", "pen_mm", "tick_p99", "unexact", "sweeps",
              "vis_ms", "resets", "lift_mm");
  nlohmann::json json_rows = nlohmann::json::array();
  for (const Row& r : rows) {
    char visual[32];
    std::snprintf(visual, sizeof visual, "%d Hz", nominal_hz(r.every));
    std::printf("%-16s %7s %-11s %+10.4f %9.3f %9.4f %10.4f %10.4f %8.2f %8.1f %8.2f %7.2f %8.2f %6ld %7.1f%s\n",
                r.interaction.c_str(), visual, haptic::to_string(r.model), r.run.energy_j, r.release_n, r.after_n,
                r.error.rms_n, r.error.max_n, 1e3 * r.run.penetration_max_m, r.run.trace.timings.haptic_us_p99,
                unexact_share(r.run.trace.contact_solves), sweeps_mean(r.run.trace.contact_solves),
                r.run.trace.timings.visual_ms_median, r.run.trace.resets, 1e3 * r.lift_m,
                r.reference ? "  (reference)" : "");
    json_rows.push_back(row_json(r));
  }
  std::printf(
      "%.1f s wall (all runs); machine: %s, %d cores, BLAS %s, revision %s (one thread); tick contact sweeps "
      "at most %d\n",
      wall_s, machine.cpu.c_str(), machine.cores, machine.blas.c_str(), machine.git_revision.c_str(), a.tick_sweeps);
  if (!a.json.empty())
    write_json(a.json,
               {{"suite", "touch"},
                {"size", a.size},
                {"tick_contact_sweeps", a.tick_sweeps},
                {"haptic_hz", 1000},
                {"method",
                 "closed loop through the lockstep runner, passivity controller on; press_hold_lift: "
                 "the stylus 2 cm (device) into the movable bunny at 2 cm/s, held 0.5 s, lifted at 5 cm/s; "
                 "grasp_release: the 16-frame glove lowers its palm over the box, closes in a tripod grasp, "
                 "lifts it 5 cm, opens (server/offline/touch.hpp); reference = the linearized model with the "
                 "world stepped at every haptic tick; force error per tick = sqrt(sum over frames |f_D - "
                 "f_D,ref|^2)"},
                {"hand_tets_target", size.hand_tets > 0 ? size.hand_tets : press_scene.hands[0].resolution_tets},
                {"rows", json_rows},
                {"wall_s", wall_s},
                {"threads", 1},
                {"machine", to_json(machine)}});
}

}  // namespace

void add_touch_suite(CLI::App& app) {
  add_touch_suite_command(app, "touch", "press-hold-lift and grasp-release at 15/30/60 Hz: energy, force after release, error, tick cost", run_touch_bench);
}

}  // namespace hapticd::bench
