#include "touch_runs.hpp"

#include <memory>
#include <utility>

namespace hapticd::bench {

void add_touch_suite_command(CLI::App& app, const char* name, const char* help,
                             std::function<void(const TouchSuiteArgs&)> run) {
  auto args = std::make_shared<TouchSuiteArgs>();
  CLI::App* sub = app.add_subcommand(name, help);
  sub->add_option("--size", args->size, "tiny (a smoke run) | default")->check(CLI::IsMember({"tiny", "default"}));
  sub->add_option("--json", args->json, "write the results as JSON to this file");
  sub->add_option("--tick-sweeps", args->tick_sweeps,
                  "the haptic tick's contact solve: at most this many Gauss-Seidel sweeps (hapticd: 8)")
      ->check(CLI::Range(1, haptic::kMaxTickContactSweeps));
  sub->callback([args, run = std::move(run)] { run(*args); });
}

TouchOutcome bench_press(const world::SceneDesc& scene, offline::OfflineOptions options) {
  const offline::PressSchedule schedule(offline::Press{0.02, 0.02, 0.05});
  options.settle_s = 0.5;
  TouchOutcome out;
  out.run = offline::run_press_hold_lift(scene, schedule, options);
  const offline::AfterLift a = offline::after_lift(out.run.trace, schedule, options);
  out.release_n = a.pull;
  out.after_n = a.after;
  return out;
}

TouchOutcome bench_grasp(const world::SceneDesc& scene, const offline::OfflineOptions& options,
                         offline::GraspKind kind) {
  const offline::GraspRun g = offline::run_grasp_release(scene, options, kind);
  TouchOutcome out;
  out.run = g;
  out.release_n = g.release_n;
  out.after_n = g.after_n;
  out.lift_m = g.object_top - g.object_z0;
  out.hold_slip_m = g.hold_slip_m;
  out.squeeze_world_n = g.squeeze_world_n;
  out.squeeze_felt_n = g.squeeze_felt_n;
  return out;
}

}  // namespace hapticd::bench
