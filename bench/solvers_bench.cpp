// `haptic-bench solvers`: step time against solver error for every coupled solver on the hand
// pressed into a floor (the hand suite's scene, hand_press_run.hpp), at several hand sizes, all
// in one run so the monolithic baseline is measured next to the others.
//
// JSON (--json FILE):
//   suite: "solvers"; size: "tiny" | "default"; dt_s: the step, s; warmup: unmeasured steps per run;
//   lagged_tolerance: relative residual of eq. 7 the lagged solver converges to;
//   error_definition: the text below; threads: 1; machine: describe_machine();
//   rows[]: one per (hand size, solver), in the order printed:
//     tets: actual tet count; target_tets: the --tets entry; nodes;
//     solver: "monolithic" | "cg" | "cholmod" | "lagged";
//     tolerance: the relative residual of each CG solve, null for the other solvers;
//     steps: measured steps; step_ms_median, step_ms_p90, step_ms_p99: whole-step wall time, ms;
//     error_rel: max over the compared steps of the step's relative error against the monolithic
//       solve, e = sqrt(|v_h - v_h,mono|^2 + |v_t - v_t,mono|^2) / sqrt(|v_h,mono|^2 + |v_t,mono|^2),
//       (v_h, v_t) the step's solution of eq. 7 (handle and node velocities at the end of the step)
//       and (v_h,mono, v_t,mono) the monolithic sparse LU's solution of the same system; every
//       measured step is compared (a step that failed and reset is not); 0 for the monolithic
//       solve by definition;
//     error_rel_median: the median of e over the compared steps; error_samples: how many;
//     speedup_vs_monolithic: the monolithic solve's step_ms_median at that size over this one's;
//     iterations_median: CG or GMRES iterations per step (summed over solves);
//     resets: steps that failed (solver) or diverged and reset the hand, warm-up included.
#include "solvers_bench.hpp"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <limits>
#include <memory>
#include <string>
#include <vector>

#include "bench_common.hpp"
#include "hand_press_run.hpp"

namespace hapticd::bench {
namespace {

struct SolversArgs {
  std::string size = "default";
  std::vector<int> tets;  // empty: the size's
  int steps = 0;          // 0: by hand size
  int warmup = 5;
  std::string json;
};

// default: ~2-3 min on a 2-core EPYC, dominated by Schur + CG at 5000 tets; tiny: a smoke run of seconds.
std::vector<int> sizes_of(const std::string& size) {
  if (size == "tiny") return {350};
  return {350, 1700, 5000};
}

// Fewer measured steps where a step takes long (Schur + CG at 1e-12 takes ~0.3 s at 5000 tets, ~2 s at 20000).
int steps_for(const std::string& size, int tets) {
  if (size == "tiny") return 10;
  if (tets <= 500) return 60;
  if (tets <= 2000) return 30;
  if (tets <= 6000) return 15;
  return 6;
}

struct Variant {
  hand::SolverKind kind;
  double cg_tolerance;  // NaN: not CG
};

std::vector<Variant> variants() {
  constexpr double none = std::numeric_limits<double>::quiet_NaN();
  std::vector<Variant> v = {{hand::SolverKind::monolithic, none}};  // first: the baseline of the rows after it
  for (double tol : {1e-2, 1e-4, 1e-6, 1e-8, 1e-10, 1e-12}) v.push_back({hand::SolverKind::schur_cg, tol});
  v.push_back({hand::SolverKind::schur_cholmod, none});
  v.push_back({hand::SolverKind::schur_lagged, none});
  return v;
}

constexpr const char* kErrorDefinition =
    "per compared step e = sqrt(|v_h - v_h,mono|^2 + |v_t - v_t,mono|^2) / sqrt(|v_h,mono|^2 + |v_t,mono|^2): "
    "the step's solution of eq. 7 (handle and node velocities) against the monolithic sparse LU's solution of the "
    "same system; error_rel = max of e over the measured steps (failed steps excepted), 0 for monolithic";

void run_solvers_bench(const SolversArgs& a) {
  const Machine machine = describe_machine();
  const std::vector<int> sizes = a.tets.empty() ? sizes_of(a.size) : a.tets;
  const hand::SolverOptions defaults;
  nlohmann::json rows = nlohmann::json::array();
  double dt_s = 0;
  std::printf("Hand pressed into a floor by its palm handle; error: max over steps of the step's relative error "
              "against the monolithic solve of the same system (velocities of eq. 7).\n");
  std::printf("%6s %6s %-10s %8s %6s %9s %9s %9s %10s %8s %6s\n", "tets", "nodes", "solver", "cg_tol", "steps",
              "step_med", "step_p90", "x_mono", "rel_err", "iters", "resets");
  for (int target : sizes) {
    double monolithic_ms = std::numeric_limits<double>::quiet_NaN();
    for (const Variant& v : variants()) {
      HandPressOptions o;
      o.tets = target;
      o.solver = v.kind;
      if (v.kind == hand::SolverKind::schur_cg) o.solver_options.cg_tolerance = v.cg_tolerance;
      o.steps = a.steps > 0 ? a.steps : steps_for(a.size, target);
      o.warmup = a.warmup;
      o.error_every = 1;
      o.progress = false;
      const HandPressRun run = run_hand_press(o);
      dt_s = run.dt_s;
      const double step_ms = median(run.total);
      if (v.kind == hand::SolverKind::monolithic) monolithic_ms = step_ms;
      const double error = v.kind == hand::SolverKind::monolithic ? 0.0
                           : run.errors.empty()              ? std::numeric_limits<double>::quiet_NaN()
                                                             : *std::max_element(run.errors.begin(), run.errors.end());
      const double error_median = v.kind == hand::SolverKind::monolithic ? 0.0 : median(run.errors);
      const double speedup = monolithic_ms / step_ms;
      const bool cg = v.kind == hand::SolverKind::schur_cg;
      // JSON has no NaN: a run with no successful compared step stores null.
      auto number = [](double x) { return std::isfinite(x) ? nlohmann::json(x) : nlohmann::json(nullptr); };
      rows.push_back({{"tets", run.tets},
                      {"target_tets", target},
                      {"nodes", run.nodes},
                      {"solver", to_string(v.kind)},
                      {"tolerance", cg ? nlohmann::json(v.cg_tolerance) : nlohmann::json(nullptr)},
                      {"steps", o.steps},
                      {"step_ms_median", step_ms},
                      {"step_ms_p90", percentile(run.total, 90)},
                      {"step_ms_p99", percentile(run.total, 99)},
                      {"error_rel", number(error)},
                      {"error_rel_median", number(error_median)},
                      {"error_samples", run.errors.size()},
                      {"speedup_vs_monolithic", number(speedup)},
                      {"iterations_median", median(run.iterations)},
                      {"resets", run.resets}});
      char tol[16] = "";
      if (cg) std::snprintf(tol, sizeof tol, "%.0e", v.cg_tolerance);
      std::printf("%6d %6d %-10s %8s %6d %9.3f %9.3f %8.2fx %10.2e %8.0f %6ld\n", run.tets, run.nodes,
                  to_string(v.kind), tol, o.steps, step_ms, percentile(run.total, 90), speedup, error,
                  median(run.iterations), run.resets);
      std::fflush(stdout);
    }
  }
  std::printf("machine: %s, %d cores, BLAS %s, revision %s (times in ms, one thread; x_mono: speed-up over the "
              "monolithic solve at the same size, this run)\n",
              machine.cpu.c_str(), machine.cores, machine.blas.c_str(), machine.git_revision.c_str());
  if (!a.json.empty())
    write_json(a.json, {{"suite", "solvers"},
                        {"size", a.size},
                        {"dt_s", dt_s},
                        {"warmup", a.warmup},
                        {"lagged_tolerance", defaults.lagged_tolerance},
                        {"error_definition", kErrorDefinition},
                        {"rows", rows},
                        {"threads", 1},
                        {"machine", to_json(machine)}});
}

}  // namespace

void add_solvers_suite(CLI::App& app) {
  auto args = std::make_shared<SolversArgs>();
  CLI::App* sub = app.add_subcommand(
      "solvers", "step time vs error against the monolithic solve: Schur + CG at 1e-2 .. 1e-12, CHOLMOD, lagged");
  sub->add_option("--size", args->size, "tiny (350 tets, 10 steps: a smoke run) | default (350, 1700, 5000 tets)")
      ->check(CLI::IsMember({"tiny", "default"}));
  sub->add_option("--tets", args->tets, "hand sizes, target tet counts (e.g. 350,1700,5000,20000)")
      ->delimiter(',')
      ->check(CLI::Range(50, 200000));
  sub->add_option("--steps", args->steps, "measured steps per run (default: by size, 60 at 350 tets .. 6 above 6000)")
      ->check(CLI::Range(1, 1000000));
  sub->add_option("--warmup", args->warmup, "unmeasured steps first")->check(CLI::Range(0, 100000));
  sub->add_option("--json", args->json, "write the results as JSON to this file");
  sub->callback([args] { run_solvers_bench(*args); });
}

}  // namespace hapticd::bench
