#include "hand_bench.hpp"

#include <algorithm>
#include <cstdio>
#include <memory>
#include <string>
#include <vector>

#include "bench_common.hpp"
#include "hand_press_run.hpp"

namespace hapticd::bench {
namespace {

struct HandBenchArgs {
  int tets = 1700;
  int handles = 1;
  std::string solver = "cholmod";
  std::string ordering = "auto";
  bool simplicial = false;
  double cg_tolerance = 1e-10;
  double lagged_tolerance = 1e-12;
  int steps = 200;
  int warmup = 10;
  int error_every = 1;
  std::string json;
};

void run_hand_bench(const HandBenchArgs& a) {
  HandPressOptions o;
  o.tets = a.tets;
  o.handles = a.handles;
  o.solver = hand::parse_solver_kind(a.solver);
  o.solver_options.cg_tolerance = a.cg_tolerance;
  o.solver_options.lagged_tolerance = a.lagged_tolerance;
  o.solver_options.ordering = hand::parse_ordering(a.ordering);
  o.solver_options.supernodal = !a.simplicial;
  o.steps = a.steps;
  o.warmup = a.warmup;
  o.error_every = a.error_every;
  const Machine machine = describe_machine();
  const HandPressRun run = run_hand_press(o);
  const std::vector<double>& errors = run.errors;
  const std::vector<double>& total = run.total;
  const double max_error = errors.empty() ? 0.0 : *std::max_element(errors.begin(), errors.end());
  nlohmann::json doc = {
      {"suite", "hand"},
      {"tets", run.tets},
      {"nodes", run.nodes},
      {"dofs", 3 * run.nodes + 6 * run.handles},
      {"handles", run.handles},
      {"coupled_nodes_first_handle", run.coupled_nodes_first_handle},
      {"solver", a.solver},
      {"ordering", a.ordering},
      {"supernodal", !a.simplicial},
      {"cg_tolerance", a.cg_tolerance},
      {"dt_s", run.dt_s},
      {"steps", a.steps},
      {"step_ms_median", median(total)},
      {"step_ms_p99", percentile(total, 99)},
      {"assembly_ms", median(run.assembly)},
      {"factor_ms", median(run.factor)},
      {"schur_ms", median(run.schur)},
      {"solve_ms", median(run.solve)},
      {"rel_error_vs_monolithic", max_error},
      {"rel_error_median", errors.empty() ? 0.0 : median(errors)},
      {"error_samples", errors.size()},
      {"iterations_median", median(run.iterations)},
      {"iterations_max", percentile(run.iterations, 100)},
      {"factorizations", run.factorizations},
      {"resets_total", run.resets},
      {"floor_contacts_max", run.floor_contacts_max},
      {"threads", 1},
      {"cpu", machine.cpu},
      {"machine", to_json(machine)},
  };
  std::printf("%-6s %-10s %6s %7s %4s %9s %9s %9s %9s %9s %9s %10s\n", "suite", "solver", "tets", "nodes", "hdl",
              "step_med", "step_p99", "assembly", "factor", "schur", "solve", "rel_err");
  std::printf("%-6s %-10s %6d %7d %4d %9.3f %9.3f %9.3f %9.3f %9.3f %9.3f %10.2e\n", "hand", a.solver.c_str(),
              run.tets, run.nodes, run.handles, median(total), percentile(total, 99),
              median(run.assembly), median(run.factor), median(run.schur), median(run.solve), max_error);
  std::printf("machine: %s, %d cores, BLAS %s, revision %s (times in ms, one thread)\n", machine.cpu.c_str(),
              machine.cores, machine.blas.c_str(), machine.git_revision.c_str());
  if (!a.json.empty()) write_json(a.json, doc);
}

}  // namespace

void add_hand_suite(CLI::App& app) {
  auto args = std::make_shared<HandBenchArgs>();
  CLI::App* sub = app.add_subcommand("hand", "procedural hand pressed into a floor by its handle(s): step time per phase and solver error");
  sub->add_option("--tets", args->tets, "target tet count of the procedural hand")->check(CLI::Range(50, 200000));
  sub->add_option("--handles", args->handles, "handles: 1 palm, 6 palm + fingertips, 16 palm + phalanges")
      ->check(CLI::Range(1, 16));
  sub->add_option("--solver", args->solver, "monolithic | cg | cholmod | lagged")
      ->check(CLI::IsMember({"monolithic", "cg", "cholmod", "lagged"}));
  sub->add_option("--ordering", args->ordering, "CHOLMOD ordering: auto | amd | metis | nesdis | natural")
      ->check(CLI::IsMember({"auto", "amd", "metis", "nesdis", "natural"}));
  sub->add_flag("--simplicial", args->simplicial, "CHOLMOD simplicial instead of supernodal factorization");
  sub->add_option("--lagged-tol", args->lagged_tolerance, "relative residual of eq. 7 for the lagged solver")
      ->check(CLI::Range(1e-16, 1.0));
  sub->add_option("--cg-tol", args->cg_tolerance, "relative residual of each CG solve")->check(CLI::Range(1e-16, 1.0));
  sub->add_option("--steps", args->steps, "measured steps")->check(CLI::Range(1, 1000000));
  sub->add_option("--warmup", args->warmup, "unmeasured steps first")->check(CLI::Range(0, 100000));
  sub->add_option("--error-every", args->error_every, "compare with the monolithic solve every K steps (0: never)")
      ->check(CLI::Range(0, 1000000));
  sub->add_option("--json", args->json, "write the results as JSON to this file");
  sub->callback([args] { run_hand_bench(*args); });
}

}  // namespace hapticd::bench
