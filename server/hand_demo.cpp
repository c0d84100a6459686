// The hand demo `make demo` runs until the network server exists: a procedural
// 1.7k-tet hand pushed by its palm handle into a static floor and stroked along
// it, printing per-step time and the solver error against the monolithic solve.
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <exception>

#include "hand_models/coupled_solver.hpp"
#include "hand_models/press_scenario.hpp"

namespace hand = hapticd::hand;

int main(int argc, char** argv) {
  try {
    hand::PressScenarioOptions options;
    options.target_tets = argc > 1 ? std::atoi(argv[1]) : 1700;
    if (options.target_tets < 50 || options.target_tets > 200000) {
      std::fprintf(stderr, "usage: hand-demo [target tets, 50..200000]\n");
      return 2;
    }
    hand::PressScenario scene = make_press_scenario(options);
    const hand::HandModel& model = *scene.model;
    auto solver = make_solver(hand::SolverKind::schur_cholmod);
    auto reference = make_solver(hand::SolverKind::monolithic);
    std::printf("hand: %d tets, %d nodes, palm handle with %zu coupled nodes, dt %.1f ms; floor at z = %.3f m\n",
                model.fem().num_tets(), model.num_nodes(), model.handles()[0].nodes.size(), 1e3 * model.config().dt_s,
                model.config().floor.height_m);
    std::printf("%5s %7s %9s %9s %10s %10s %9s %11s\n", "step", "t_s", "step_ms", "factor_ms", "rel_err", "residual",
                "contacts", "palm_z_mm");
    const int steps = 180;
    double worst = 0, total_ms = 0;
    for (int k = 0; k < steps; ++k) {
      const double t = (k + 1) * model.config().dt_s;
      scene.drive(t);
      step(model, scene.state, *solver);
      Eigen::VectorXd v_h, v_t;
      hand::SolveReport r;
      reference->solve(scene.state.system, v_h, v_t, r);
      const double err = std::sqrt((v_h - scene.state.v_h_next).squaredNorm() + (v_t - scene.state.v_t_next).squaredNorm()) /
                         std::sqrt(v_h.squaredNorm() + v_t.squaredNorm());
      const double residual = relative_residual(scene.state.system, scene.state.v_h_next, scene.state.v_t_next);
      worst = std::max(worst, err);
      total_ms += scene.state.timings.total_ms;
      if (k % 10 == 0 || k == steps - 1)
        std::printf("%5d %7.3f %9.3f %9.3f %10.2e %10.2e %9d %11.2f\n", k, t, scene.state.timings.total_ms,
                    scene.state.timings.factor_ms, err, residual, scene.state.floor_contacts,
                    1e3 * (scene.state.handles[0].p_WH.z() - model.config().floor.height_m));
    }
    std::printf("done: %d steps, mean step %.2f ms (Schur + CHOLMOD), worst relative error vs monolithic %.1e, resets %ld\n",
                steps, total_ms / steps, worst, scene.state.resets);
  } catch (const std::exception& e) {
    std::fprintf(stderr, "hand-demo: %s\n", e.what());
    return 1;
  }
  return 0;
}
