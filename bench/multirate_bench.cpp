#include "multirate_bench.hpp"

#include <chrono>
#include <cmath>
#include <cstdio>
#include <map>
#include <memory>
#include <string>
#include <vector>

#include "bench_common.hpp"
#include "server/offline/multirate.hpp"
#include "server/world/scene_loader.hpp"

namespace hapticd::bench {
namespace {

struct MultirateArgs {
  std::string size = "default";
  std::string stylus_scene = std::string(HAPTICD_SCENES_DIR) + "/stylus_bunny.json";
  std::string glove_scene = std::string(HAPTICD_SCENES_DIR) + "/glove_grasp.json";
  int glove_frames = 0;              // 0: the size's
  double stylus_s = 0, glove_s = 0;  // 0: the size's
  std::vector<std::string> models = {"linearized", "bilateral", "zoh"};
  std::string json;
};

// Run sizes. default (~2 min on one core): the stylus press (settle 0.5 s, 2 cm down over 1 s,
// 1 s held) and the 16-frame glove's grasp (rest 0.5 s, closing over 1 s) at the scenes'
// resolution; tiny (a few seconds): 0.15 s and 0.1 s of them, 6 frames, ~400-tet hands, a smoke run
// (nothing is touched yet).
struct Size {
  double stylus_s, glove_s;
  int glove_frames;
  int hand_tets;  // 0: the scene's
};
Size size_of(const std::string& name) {
  if (name == "tiny") return {0.15, 0.1, 6, 400};
  return {2.5, 1.5, 16, 0};
}

// Visual periods in haptic ticks at 1 kHz: 15, 30, 60, 120, 240 Hz rounded to whole ticks, and every tick.
const std::vector<int> kVisualTicks = {67, 33, 17, 8, 4, 1};
const std::vector<double> kNominalHz = {15, 30, 60, 120, 240, 1000};

nlohmann::json row_json(const offline::MultirateRow& r, double nominal_hz) {
  return {{"interaction", r.interaction},
          {"visual_hz", nominal_hz},
          {"visual_hz_exact", r.visual_hz},
          {"visual_every_ticks", r.visual_ticks},
          {"model", to_string(r.model)},
          {"rms_force_error_n", r.error.rms_n},
          {"max_force_error_n", r.error.max_n},
          {"rms_force_error_near_steps_n", r.error.rms_near_steps_n},
          {"rms_force_error_mid_period_n", r.error.rms_mid_period_n},
          {"haptic_us_per_tick", r.timings.haptic_us_median},
          {"haptic_us_per_tick_p99", r.timings.haptic_us_p99},
          {"visual_ms_per_step", r.timings.visual_ms_median},
          {"visual_ms_per_step_p99", r.timings.visual_ms_p99},
          {"resets", r.resets}};
}

void run_multirate_bench(const MultirateArgs& a) {
  const Size size = size_of(a.size);
  const Machine machine = describe_machine();
  world::SceneDesc stylus_scene = world::load_scene(a.stylus_scene), glove_scene = world::load_scene(a.glove_scene);
  if (size.hand_tets > 0) {
    for (world::HandDesc& h : stylus_scene.hands) h.resolution_tets = size.hand_tets;
    for (world::HandDesc& h : glove_scene.hands) h.resolution_tets = size.hand_tets;
  }
  const int frames = a.glove_frames ? a.glove_frames : size.glove_frames;
  const std::vector<offline::Interaction> interactions = {
      offline::stylus_press(stylus_scene, a.stylus_s > 0 ? a.stylus_s : size.stylus_s),
      offline::stylus_press_fixed(stylus_scene, a.stylus_s > 0 ? a.stylus_s : size.stylus_s),
      offline::glove_grasp(glove_scene, a.glove_s > 0 ? a.glove_s : size.glove_s, frames)};
  std::vector<haptic::HandleModelKind> models;
  for (const std::string& m : a.models)
    models.push_back(m == "linearized"  ? haptic::HandleModelKind::linearized
                     : m == "bilateral" ? haptic::HandleModelKind::bilateral
                                        : haptic::HandleModelKind::zoh);

  nlohmann::json rows = nlohmann::json::array(), meta = nlohmann::json::array(), ratios = nlohmann::json::object();
  std::printf(
      "Open loop: each run replays the device poses of the reference (world stepped every 1 ms, linearized "
      "model, closed loop), all from the same world (rigid bodies settled 1 s first); error per tick = "
      "|f_D - f_D,ref| over all frames, RMS and max over the run. zoh: the proxy under the last visual step's "
      "coupling force, held.\n");
  std::printf("%-18s %8s %6s %-12s %10s %10s %10s %10s %9s %10s %10s %7s\n", "interaction", "visual", "ticks", "model",
              "rms_err_N", "near_steps", "mid_period", "max_err_N", "x_lin", "haptic_us", "visual_ms", "resets");
  for (const offline::Interaction& in : interactions) {
    const auto t0 = std::chrono::steady_clock::now();
    const offline::MultirateRuns runs = offline::run_multirate(in, kVisualTicks, models);
    const double wall_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    const world::HandDesc& hand = in.scene.hands[0];
    meta.push_back({{"interaction", in.name},
                    {"scene", in.scene.name},
                    {"seconds", in.seconds},
                    {"hand_tets_target", hand.resolution_tets},
                    {"handles", std::string(to_string(hand.handles))},
                    {"reference_rms_force_n", offline::rms_force(runs.reference)},
                    {"reference_resets", runs.reference.resets},
                    {"wall_s", wall_s}});
    std::map<int, double> lin_rms;
    for (const offline::MultirateRow& r : runs.rows)
      if (r.model == haptic::HandleModelKind::linearized) lin_rms[r.visual_ticks] = r.error.rms_n;
    for (const offline::MultirateRow& r : runs.rows) {
      double nominal = r.visual_hz;
      for (std::size_t i = 0; i < kVisualTicks.size(); ++i)
        if (kVisualTicks[i] == r.visual_ticks) nominal = kNominalHz[i];
      // The ratio to the linearized model's error at the same rate (not at every tick, where that is zero).
      const bool baseline = r.model != haptic::HandleModelKind::linearized;
      const auto lin = lin_rms.find(r.visual_ticks);
      const double ratio = baseline && lin != lin_rms.end() && lin->second > 1e-9 ? r.error.rms_n / lin->second : NAN;
      if (baseline)
        ratios[in.name][to_string(r.model)][std::to_string(static_cast<int>(nominal))] =
            std::isfinite(ratio) ? nlohmann::json(ratio) : nlohmann::json(nullptr);
      char visual[32], times[32] = "";
      std::snprintf(visual, sizeof visual, "%.0f Hz", nominal);
      if (std::isfinite(ratio)) std::snprintf(times, sizeof times, "%.1fx", ratio);
      std::printf("%-18s %8s %6d %-12s %10.4f %10.4f %10.4f %10.4f %9s %10.1f %10.2f %7ld\n", in.name.c_str(), visual,
                  r.visual_ticks, to_string(r.model), r.error.rms_n, r.error.rms_near_steps_n, r.error.rms_mid_period_n,
                  r.error.max_n, times, r.timings.haptic_us_median, r.timings.visual_ms_median, r.resets);
      rows.push_back(row_json(r, nominal));
    }
    std::printf(
        "%-18s reference: RMS force %.3f N, %.1f s simulated in %.1f s wall (all runs), hand %d tets target, "
        "%s handles\n",
        in.name.c_str(), offline::rms_force(runs.reference), in.seconds, wall_s, hand.resolution_tets,
        std::string(to_string(hand.handles)).c_str());
  }
  std::printf("machine: %s, %d cores, BLAS %s, revision %s (one thread; times are medians)\n", machine.cpu.c_str(),
              machine.cores, machine.blas.c_str(), machine.git_revision.c_str());
  if (!a.json.empty())
    write_json(a.json, {{"suite", "multirate"},
                        {"size", a.size},
                        {"haptic_hz", 1000},
                        {"method",
                         "open loop: every run replays the reference run's device poses; the reference steps "
                         "the world at every haptic tick with the linearized model, closed loop; every run "
                         "first settles the rigid bodies 1 s at 1 ms; error per tick = sqrt(sum over frames "
                         "|f_D - f_D,ref|^2), RMS and max over the run; its RMS also over the ticks within an "
                         "eighth of the visual period of the steps (near_steps: there the model fits the world at "
                         "the visual rate, and the error is mostly that world's against the every-tick world) and "
                         "of mid-period (where the linearization's own error is largest); null below 4 ticks"},
                        {"models",
                         {{"linearized",
                           "proxy under the coming step's handle-space linearization, its contacts solved each tick "
                           "(hapticd)"},
                          {"bilateral",
                           "the same linearization with the last step's pushing contacts held bilaterally (the "
                           "model before contacts released in the tick)"},
                          {"zoh", "proxy under the last visual step's coupling force, held (K = D = 0)"}}},
                        {"interactions", meta},
                        {"rows", rows},
                        {"rms_ratio_over_linearized", ratios},
                        {"threads", 1},
                        {"machine", to_json(machine)}});
}

}  // namespace

void add_multirate_suite(CLI::App& app) {
  auto args = std::make_shared<MultirateArgs>();
  CLI::App* sub = app.add_subcommand(
      "multirate", "force error of the linearized model and of a zero-order hold against a visual loop at every tick");
  sub->add_option("--size", args->size, "tiny (a smoke run of a few seconds) | default")
      ->check(CLI::IsMember({"tiny", "default"}));
  sub->add_option("--stylus-scene", args->stylus_scene, "scene of the stylus press")->check(CLI::ExistingFile);
  sub->add_option("--glove-scene", args->glove_scene, "scene of the glove grasp")->check(CLI::ExistingFile);
  sub->add_option("--glove-frames", args->glove_frames, "16 (phalanges handles) or 6 (fingertips)")
      ->check(CLI::IsMember({6, 16}));
  sub->add_option("--stylus-seconds", args->stylus_s, "length of the stylus run (default: the size's)");
  sub->add_option("--glove-seconds", args->glove_s, "length of the glove run (default: the size's)");
  sub->add_option("--models", args->models,
                  "models compared: linearized, bilateral, zoh (default: linearized bilateral zoh)")
      ->check(CLI::IsMember({"linearized", "bilateral", "zoh"}));
  sub->add_option("--json", args->json, "write the results as JSON to this file");
  sub->callback([args] { run_multirate_bench(*args); });
}

}  // namespace hapticd::bench
