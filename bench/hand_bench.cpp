#include "hand_bench.hpp"

#include <cstdio>
#include <memory>
#include <string>
#include <vector>

#include "bench_common.hpp"
#include "hand_models/coupled_solver.hpp"
#include "hand_models/press_scenario.hpp"

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

double relative_error(const Eigen::VectorXd& h, const Eigen::VectorXd& t, const Eigen::VectorXd& h_ref,
                      const Eigen::VectorXd& t_ref) {
  return std::sqrt((h - h_ref).squaredNorm() + (t - t_ref).squaredNorm()) /
         std::sqrt(h_ref.squaredNorm() + t_ref.squaredNorm());
}

void run_hand_bench(const HandBenchArgs& a) {
  PressScenarioOptions options;
  options.target_tets = a.tets;
  options.handles = a.handles;
  PressScenario scene = make_press_scenario(options);
  const HandModel& model = *scene.model;
  SolverOptions solver_options;
  solver_options.cg_tolerance = a.cg_tolerance;
  solver_options.lagged_tolerance = a.lagged_tolerance;
  solver_options.ordering = parse_ordering(a.ordering);
  solver_options.supernodal = !a.simplicial;
  const SolverKind kind = parse_solver_kind(a.solver);
  auto solver = make_solver(kind, solver_options);
  auto reference = make_solver(SolverKind::monolithic);
  const Machine machine = describe_machine();
  std::fprintf(stderr, "hand: %d tets, %d nodes, %d handle(s) (%zu coupled nodes in the first), solver %s, %d steps\n",
               model.fem().num_tets(), model.num_nodes(), model.num_handles(), model.handles()[0].nodes.size(),
               a.solver.c_str(), a.steps);

  std::vector<double> total, assembly, factor, schur, solve, errors;
  std::vector<double> iterations;
  int factorizations = 0;
  int contacts_max = 0;
  const double dt = model.config().dt_s;
  for (int k = 0; k < a.warmup + a.steps; ++k) {
    scene.drive((k + 1) * dt);
    step(model, scene.state, *solver);
    if (k < a.warmup) continue;
    const StepTimings& t = scene.state.timings;
    total.push_back(t.total_ms);
    assembly.push_back(t.assembly_ms);
    factor.push_back(t.factor_ms);
    schur.push_back(t.schur_ms);
    solve.push_back(t.solve_ms);
    iterations.push_back(static_cast<double>(t.iterations));
    factorizations += t.factor_ms > 0 && kind != SolverKind::schur_cg;
    contacts_max = std::max(contacts_max, scene.state.floor_contacts);
    const int i = k - a.warmup;
    if (kind != SolverKind::monolithic && a.error_every > 0 && i % a.error_every == 0) {
      // Same system, solved by the reference: the solver's own error this step.
      Eigen::VectorXd v_h, v_t;
      SolveReport r;
      if (reference->solve(scene.state.system, v_h, v_t, r))
        errors.push_back(relative_error(scene.state.v_h_next, scene.state.v_t_next, v_h, v_t));
    }
    if (i > 0 && i % 50 == 0) std::fprintf(stderr, "  step %d/%d, median %.2f ms\n", i, a.steps, median(total));
  }
  const double max_error = errors.empty() ? 0.0 : *std::max_element(errors.begin(), errors.end());
  nlohmann::json doc = {
      {"suite", "hand"},
      {"tets", model.fem().num_tets()},
      {"nodes", model.num_nodes()},
      {"dofs", 3 * model.num_nodes() + 6 * model.num_handles()},
      {"handles", model.num_handles()},
      {"coupled_nodes_first_handle", model.handles()[0].nodes.size()},
      {"solver", a.solver},
      {"ordering", a.ordering},
      {"supernodal", !a.simplicial},
      {"cg_tolerance", a.cg_tolerance},
      {"dt_s", dt},
      {"steps", a.steps},
      {"step_ms_median", median(total)},
      {"step_ms_p99", percentile(total, 99)},
      {"assembly_ms", median(assembly)},
      {"factor_ms", median(factor)},
      {"schur_ms", median(schur)},
      {"solve_ms", median(solve)},
      {"rel_error_vs_monolithic", max_error},
      {"rel_error_median", errors.empty() ? 0.0 : median(errors)},
      {"error_samples", errors.size()},
      {"iterations_median", median(iterations)},
      {"iterations_max", percentile(iterations, 100)},
      {"factorizations", factorizations},
      {"resets_total", scene.state.resets},
      {"floor_contacts_max", contacts_max},
      {"threads", 1},
      {"cpu", machine.cpu},
      {"machine", to_json(machine)},
  };
  std::printf("%-6s %-10s %6s %7s %4s %9s %9s %9s %9s %9s %9s %10s\n", "suite", "solver", "tets", "nodes", "hdl",
              "step_med", "step_p99", "assembly", "factor", "schur", "solve", "rel_err");
  std::printf("%-6s %-10s %6d %7d %4d %9.3f %9.3f %9.3f %9.3f %9.3f %9.3f %10.2e\n", "hand", a.solver.c_str(),
              model.fem().num_tets(), model.num_nodes(), model.num_handles(), median(total), percentile(total, 99),
              median(assembly), median(factor), median(schur), median(solve), max_error);
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
