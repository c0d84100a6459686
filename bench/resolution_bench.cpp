// `haptic-bench resolution`: what the hand's mesh resolution costs per step and what it changes
// in the force the haptic side feels. The procedural hand at several tet counts runs the same
// scripted press (the hand suite's scene, hand_press_run.hpp: the palm handle's target goes 1 cm
// into the floor over 0.5 s, then strokes sideways, 2 cm amplitude, 2 s period), the same number
// of steps from rest; the finest hand of the list is the reference.
//
// JSON (--json FILE):
//   suite: "resolution"; size: "tiny" | "default"; solver: the coupled solver every run uses;
//   springs: how the floor and coupling springs scale with the mesh (scaled_config below);
//   steps: steps of the press (all measured, from rest); dt_s: the step, s;
//   error_definition: the text below; threads: 1; machine: describe_machine();
//   rows[]: one per hand, coarsest first:
//     tets: the --tets entry (target); elements: the hand's actual tet count; nodes;
//     step_ms_median, step_ms_p99: whole-step wall time, ms;
//     rms_force_n: RMS over the press of |F(t)|, N, for scale;
//     rms_force_error_n, max_force_error_n: RMS and max over the press of |F(t) - F_ref(t)|, N,
//       F(t) the coupling force the flesh puts on the handle at the end of step t (seed 004
//       eq. 5, summed over handles: what the haptic side is rendered), F_ref that of the
//       reference hand at the same step; 0 for the reference;
//     reference: true for the finest hand (the reference), false otherwise;
//     resets: steps that failed or diverged and reset the hand; floor_contacts_max.
#include "resolution_bench.hpp"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <memory>
#include <spdlog/spdlog.h>
#include <string>
#include <vector>

#include "bench_common.hpp"
#include "hand_models/procedural_hand.hpp"
#include "hand_press_run.hpp"

namespace hapticd::bench {
namespace {

struct ResolutionArgs {
  std::string size = "default";
  std::vector<int> tets;  // empty: the size's
  int steps = 0;          // 0: the size's
  std::string solver = "cholmod";
  bool per_node_springs = false;  // the hand suite's springs as they are, per node
  std::string json;
};

// The hand's floor contact and handle coupling are springs per node (HandConfig), so a finer mesh
// has a stiffer floor (more nodes touch it) and a stiffer handle (more nodes in its sphere): the
// force then does not converge with resolution (measured: RMS force 12, 19, 23, 16, 8.8, 11.5 N
// from 350 to 20k tets). By default this suite keeps them per area and per volume, so every hand
// is the same material on the same floor: floor stiffness and damping per node times
// (h / h_1700)^2, coupling times (h / h_1700)^3, h the grid spacing, h_1700 that of the 1700-tet
// hand (where the defaults are used). --per-node-springs runs the hand suite's springs as they are.
hand::HandConfig scaled_config(int target_tets) {
  hand::HandConfig c;
  const double s = hand::hand_spacing_for_tets(target_tets) / hand::hand_spacing_for_tets(1700);
  c.floor.stiffness_n_m *= s * s;
  c.floor.damping_ns_m *= s * s;
  c.coupling.stiffness_n_m *= s * s * s;
  c.coupling.damping_ns_m *= s * s * s;
  return c;
}

// default: ~30 s on a 2-core EPYC (the 20k-tet hand dominates); tiny: a smoke run under a second.
struct Size {
  std::vector<int> tets;
  int steps;
};
Size size_of(const std::string& name) {
  // tiny: the press itself (0.5 s at 60 Hz); default: the press and 1.5 s of the stroke.
  if (name == "tiny") return {{350, 1000}, 30};
  return {{350, 1000, 1700, 5000, 10000, 20000}, 120};
}

constexpr const char* kErrorDefinition =
    "F(t): the coupling force the flesh puts on the handles at the end of step t (seed 004 eq. 5, summed over "
    "handles), N; per step e(t) = |F(t) - F_ref(t)|, F_ref from the finest hand at the same step; "
    "rms_force_error_n = sqrt(mean of e^2), max_force_error_n = max of e, over every step of the press";

void run_resolution_bench(const ResolutionArgs& a) {
  const Machine machine = describe_machine();
  const Size size = size_of(a.size);
  std::vector<int> sizes = a.tets.empty() ? size.tets : a.tets;
  std::sort(sizes.begin(), sizes.end());
  sizes.erase(std::unique(sizes.begin(), sizes.end()), sizes.end());
  const int steps = a.steps > 0 ? a.steps : size.steps;

  std::vector<HandPressRun> runs;
  for (int target : sizes) {
    HandPressOptions o;
    o.tets = target;
    o.solver = hand::parse_solver_kind(a.solver);
    if (!a.per_node_springs) o.config = scaled_config(target);
    o.steps = steps;
    o.warmup = 0;  // the press from rest, every step recorded
    o.error_every = 0;
    o.record_force = true;
    o.progress = false;
    spdlog::info("resolution: {} tets target, {} steps", target, steps);
    runs.push_back(run_hand_press(o));
  }
  const HandPressRun& reference = runs.back();

  nlohmann::json rows = nlohmann::json::array();
  std::printf("Hand pressed into a floor by its palm handle, %d steps of %.1f ms from rest; force error: "
              "|F - F_ref| of the handle coupling force per step against the finest hand (%d tets).\n",
              steps, 1e3 * reference.dt_s, reference.tets);
  std::printf("%6s %8s %6s %9s %9s %10s %12s %12s %6s\n", "tets", "elements", "nodes", "step_med", "step_p99",
              "rms_F_N", "rms_err_N", "max_err_N", "resets");
  for (size_t r = 0; r < runs.size(); ++r) {
    const HandPressRun& run = runs[r];
    double sum_e2 = 0, max_e = 0, sum_f2 = 0;
    for (int k = 0; k < steps; ++k) {
      const double e = (run.f_H_N[k] - reference.f_H_N[k]).norm();
      sum_e2 += e * e;
      max_e = std::max(max_e, e);
      sum_f2 += run.f_H_N[k].squaredNorm();
    }
    const double rms_e = std::sqrt(sum_e2 / steps), rms_f = std::sqrt(sum_f2 / steps);
    const bool is_reference = r + 1 == runs.size();
    rows.push_back({{"tets", sizes[r]},
                    {"elements", run.tets},
                    {"nodes", run.nodes},
                    {"step_ms_median", median(run.total)},
                    {"step_ms_p99", percentile(run.total, 99)},
                    {"rms_force_n", rms_f},
                    {"rms_force_error_n", rms_e},
                    {"max_force_error_n", max_e},
                    {"reference", is_reference},
                    {"resets", run.resets},
                    {"floor_contacts_max", run.floor_contacts_max}});
    std::printf("%6d %8d %6d %9.3f %9.3f %10.3f %12.4f %12.4f %6ld%s\n", sizes[r], run.tets, run.nodes,
                median(run.total), percentile(run.total, 99), rms_f, rms_e, max_e, run.resets,
                is_reference ? "  reference" : "");
  }
  std::printf("machine: %s, %d cores, BLAS %s, revision %s (times in ms, one thread, solver %s)\n",
              machine.cpu.c_str(), machine.cores, machine.blas.c_str(), machine.git_revision.c_str(),
              a.solver.c_str());
  if (!a.json.empty())
    write_json(a.json, {{"suite", "resolution"},
                        {"size", a.size},
                        {"solver", a.solver},
                        {"springs", a.per_node_springs ? "per node" : "per area (floor) and per volume (coupling)"},
                        {"steps", steps},
                        {"dt_s", reference.dt_s},
                        {"error_definition", kErrorDefinition},
                        {"rows", rows},
                        {"threads", 1},
                        {"machine", to_json(machine)}});
}

}  // namespace

void add_resolution_suite(CLI::App& app) {
  auto args = std::make_shared<ResolutionArgs>();
  CLI::App* sub = app.add_subcommand(
      "resolution", "hand mesh resolution: step time vs handle force error against the finest hand, same press");
  sub->add_option("--size", args->size, "tiny (350 vs 1000 tets, 30 steps: a smoke run) | default (350 .. 20000 tets, 120 steps)")
      ->check(CLI::IsMember({"tiny", "default"}));
  sub->add_option("--tets", args->tets, "hand sizes, target tet counts; the finest is the reference (e.g. 350,1700,5000,20000)")
      ->delimiter(',')
      ->check(CLI::Range(50, 200000));
  sub->add_option("--steps", args->steps, "steps of the press from rest (default: the size's)")
      ->check(CLI::Range(1, 1000000));
  sub->add_option("--solver", args->solver, "monolithic | cg | cholmod | lagged (default cholmod, the world's)")
      ->check(CLI::IsMember({"monolithic", "cg", "cholmod", "lagged"}));
  sub->add_flag("--per-node-springs", args->per_node_springs,
                "the hand suite's floor and coupling springs per node, unscaled (by default they are scaled by area "
                "and volume, h^2 and h^3 over the 1700-tet hand's, so every hand is the same material)");
  sub->add_option("--json", args->json, "write the results as JSON to this file");
  sub->callback([args] { run_resolution_bench(*args); });
}

}  // namespace hapticd::bench
