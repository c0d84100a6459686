#include "hand_press_run.hpp"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <spdlog/spdlog.h>

#include "bench_common.hpp"
#include "hand_models/handle_linearization.hpp"
#include "hand_models/press_scenario.hpp"

namespace hapticd::bench {
namespace {

double relative_error(const Eigen::VectorXd& h, const Eigen::VectorXd& t, const Eigen::VectorXd& h_ref,
                      const Eigen::VectorXd& t_ref) {
  return std::sqrt((h - h_ref).squaredNorm() + (t - t_ref).squaredNorm()) /
         std::sqrt(h_ref.squaredNorm() + t_ref.squaredNorm());
}

}  // namespace

HandPressRun run_hand_press(const HandPressOptions& o) {
  hand::PressScenarioOptions scenario_options;
  scenario_options.target_tets = o.tets;
  scenario_options.handles = o.handles;
  hand::PressScenario scene = make_press_scenario(scenario_options, o.config);
  const hand::HandModel& model = *scene.model;
  auto solver = make_solver(o.solver, o.solver_options);
  auto reference = make_solver(hand::SolverKind::monolithic);
  const bool compare = o.solver != hand::SolverKind::monolithic && o.error_every > 0;

  HandPressRun run;
  run.tets = model.fem().num_tets();
  run.nodes = model.num_nodes();
  run.handles = model.num_handles();
  run.coupled_nodes_first_handle = static_cast<int>(model.handles()[0].nodes.size());
  run.dt_s = model.config().dt_s;
  if (o.progress)
    spdlog::info("hand: {} tets, {} nodes, {} handle(s) ({} coupled nodes in the first), solver {}, {} steps", run.tets,
                 run.nodes, run.handles, run.coupled_nodes_first_handle, to_string(o.solver), o.steps);
  for (auto* v : {&run.total, &run.assembly, &run.factor, &run.schur, &run.solve, &run.iterations})
    v->reserve(o.steps);
  if (o.record_force) run.f_H_N.reserve(o.steps);

  for (int k = 0; k < o.warmup + o.steps; ++k) {
    scene.drive((k + 1) * run.dt_s);
    const hand::StepStatus status = step(model, scene.state, *solver);
    if (k < o.warmup) continue;
    const hand::StepTimings& t = scene.state.timings;
    run.total.push_back(t.total_ms);
    run.assembly.push_back(t.assembly_ms);
    run.factor.push_back(t.factor_ms);
    run.schur.push_back(t.schur_ms);
    run.solve.push_back(t.solve_ms);
    run.iterations.push_back(static_cast<double>(t.iterations));
    run.factorizations += t.factor_ms > 0 && o.solver != hand::SolverKind::schur_cg;
    run.floor_contacts_max = std::max(run.floor_contacts_max, scene.state.floor_contacts);
    if (o.record_force) {
      const Eigen::VectorXd W = coupling_wrench(model, scene.state.x, scene.state.v, scene.state.handles);
      Eigen::Vector3d f = Eigen::Vector3d::Zero();
      for (int j = 0; j < run.handles; ++j) f += W.segment<3>(6 * j);
      run.f_H_N.push_back(f);
    }
    const int i = k - o.warmup;
    if (compare && status == hand::StepStatus::ok && i % o.error_every == 0) {
      // Same system, solved by the reference: the solver's own error this step.
      Eigen::VectorXd v_h, v_t;
      hand::SolveReport r;
      if (reference->solve(scene.state.system, v_h, v_t, r))
        run.errors.push_back(relative_error(scene.state.v_h_next, scene.state.v_t_next, v_h, v_t));
    }
    if (o.progress && i > 0 && i % 50 == 0)
      spdlog::info("  step {}/{}, median {:.2f} ms", i, o.steps, median(run.total));
  }
  run.resets = scene.state.resets;
  return run;
}

}  // namespace hapticd::bench
