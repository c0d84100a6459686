#pragma once
// The scripted touches the `touch` and `hands` suites run (server/offline/touch.hpp), with what both
// report of them.
#include <CLI/CLI.hpp>
#include <functional>
#include <string>

#include "server/offline/touch.hpp"

namespace hapticd::bench {

// Both suites' options: --size tiny (a smoke run) | default, --json FILE.
struct TouchSuiteArgs {
  std::string size = "default";
  std::string json;
  int tick_sweeps = haptic::kDefaultTickContactSweeps;  // the tick contact solve's sweeps at most
};
// Registers suite `name` (`help`) with those options; `run` runs it.
void add_touch_suite_command(CLI::App& app, const char* name, const char* help,
                             std::function<void(const TouchSuiteArgs&)> run);

struct TouchOutcome {
  offline::TouchRun run;
  double release_n = 0;    // the force after the release (AfterLift::pull, GraspRun::release_n), N
  double after_n = 0;      // the largest force from one second after the release, N
  double lift_m = 0;       // grasps: how high the box rose
  double hold_slip_m = 0;  // grasps: how far the box moved in the palm's frame while held up
  double squeeze_world_n = 0, squeeze_felt_n = 0;  // grasps: GraspRun's
};

// The benches' press: 2 cm (device) at 2 cm/s, held 0.5 s, lifted at 5 cm/s; the scene settles 0.5 s
// first (the bunny on the table, at every rate alike).
TouchOutcome bench_press(const world::SceneDesc& scene, offline::OfflineOptions options);
// The glove's grasp, lift and release (offline::run_grasp_release; the box's tripod unless told).
TouchOutcome bench_grasp(const world::SceneDesc& scene, const offline::OfflineOptions& options,
                         offline::GraspKind kind = offline::GraspKind::tripod_box);

}  // namespace hapticd::bench
