// `haptic-bench hands [--size tiny|default] [--json FILE] [--tick-sweeps N]`
//
// Every hand model on the same scripted interactions (issue 18), closed loop through the lockstep
// runner (hapticd's haptic tick and visual step, the passivity controller on as in hapticd), each
// scripted as the touch tests script it (server/offline/touch.hpp):
//   table_press  the simulated stylus presses 2 cm (device) into the table's edge (stylus_bunny.json,
//                half the palm over the edge) at 2 cm/s, holds 0.5 s, lifts at 5 cm/s;
//   bunny_press  the same on the movable bunny;
//   grasp_box    the simulated 16-frame glove lowers its palm over the 5 cm box of glove_grasp.json,
//                closes in a tripod grasp, lifts it 5 cm, opens;
//   grasp_ball   the same with a power grasp of the scene's 6 cm, 50 g rubber ball;
//   pinch_plate  the glove comes along the table to a thin plate (10 x 8 cm, 4 mm, 34 g, 4 cm over the
//                table's edge), pinches its edge between the thumb's tip and the index, lifts it 5 cm, opens.
// Models: "fem" (seed 004, the scenes' hands), "spring" (seed 002), "contact_point" (seed 001), each
// at a 30 Hz visual step and once with the world stepped at every haptic tick. That run is the
// reference for "what the hand should feel", the same for every model: the model's own world without
// the multi-rate split, so the error is the rendering's (the linearized model between visual steps),
// not the hand model's.
//
// JSON (--json FILE): {"suite": "hands", "size", "tick_contact_sweeps", "haptic_hz": 1000, "method", "rows": [...], "wall_s",
// "threads": 1, "machine": {...}}. One row per (interaction, model, visual rate):
//   interaction         string  "table_press" | "bunny_press" | "grasp_box" | "grasp_ball" | "pinch_plate"
//   model               string  "fem" | "spring" | "contact_point"
//   visual_hz           number  30, or 1000 for the reference
//   energy_j            number  work of the rendered forces on the device over the run (> 0: put in)
//   release_n           number  the force toward the object after the lift (presses) / the largest frame
//                               force once the glove is open, after one haptic and one visual period, N
//   after_n             number  the largest force from one second after the lift / the opening, N
//   rms_force_error_n   number  RMS over ticks of sqrt(sum over frames |f_D - f_D,ref|^2) against the
//                               same model's reference run, N (0 on the reference row)
//   max_force_error_n   number  its largest value, N
//   penetration_max_mm  number  the deepest point of the hand inside anything after any visual step, mm
//   tick_us_median, tick_us_p99       one haptic tick's wall time, us
//   visual_ms_median, visual_ms_p99   one visual step's wall time (world step and model), ms
//   resets              number  proxy and world resets
//   lift_mm             number  the grasps: how high the object's centre rose (the palm rises 50 mm), else 0
//   hold_slip_mm        number  the grasps: how far the object moved in the palm's frame while held up, else 0
//   grasped             bool    the grasps: the object's centre rose 40 mm or more
//   squeeze_world_n     number  the grasps: while the closed hand grips the object before the lift, the
//                               world's contact forces on it (sum of magnitudes, mean per tick), N; else 0
//   squeeze_felt_n      number  the grasps: the same for the forces the glove's frames felt (torques left
//                               out), N; else 0
//   reference           bool    the world stepped at every tick
// and "timing": the contact-point hand's world step with 0, 6, 16 and 32 phalanges in contact (seed
// 001 section 5.2: 0.6, 0.9 and 1.5 ms for 6, 16 and 32 phalanges, PhysX with the whole scene): one
// row per count, {"phalanges", "hands", "contacts", "step_ms_median", "step_ms_p99"}: that many of
// the glove-driven hands' shapes (one hand up to 16, two for 32) pressed 2 mm into a 200 g tile each,
// the tiles on a floor side by side, a 60 Hz world stepped 300 times (the first 60 not timed).
#include "hands_bench.hpp"

#include <spdlog/spdlog.h>

#include <chrono>
#include <cstdio>
#include <memory>
#include <string>
#include <vector>

#include "bench_common.hpp"
#include "hand_models/contact_point/contact_point_hand.hpp"
#include "server/offline/multirate.hpp"
#include "server/offline/touch.hpp"
#include "server/world/scene_loader.hpp"
#include "server/world/world.hpp"
#include "touch_runs.hpp"

namespace hapticd::bench {
namespace {

constexpr int kVisualEveryTicks = 33;  // 30 Hz
constexpr double kGraspedM = 0.04;


struct Model {
  const char* name;
  world::HandModelKind kind;
  const char* press_prefix;  // offline::press_scene's
};
constexpr Model kModels[] = {{"fem", world::HandModelKind::fem, ""},
                             {"spring", world::HandModelKind::spring, "spring_"},
                             {"contact_point", world::HandModelKind::contact_point, "contact_point_"}};

struct Row : TouchOutcome {
  std::string interaction, model;
  bool grasp = false;  // a glove's grasp (lift_m, hold_slip_m and the squeezes are its), not a press
  int every = kVisualEveryTicks;
  offline::ForceError error;
  bool reference = false;
};

offline::OfflineOptions options_for(int every, int tick_sweeps) {
  offline::OfflineOptions o;
  o.tick_contact_sweeps = tick_sweeps;
  o.haptic_period_s = 1e-3;
  o.visual_every_ticks = every;
  return o;
}

Row row_of(const TouchOutcome& outcome, int every) {
  Row r;
  static_cast<TouchOutcome&>(r) = outcome;
  r.every = every;
  return r;
}

Row press_row(const world::SceneDesc& scene, int every, int tick_sweeps) {
  return row_of(bench_press(scene, options_for(every, tick_sweeps)), every);
}

Row grasp_row(const world::SceneDesc& scene, int every, offline::GraspKind kind, int tick_sweeps) {
  return row_of(bench_grasp(scene, options_for(every, tick_sweeps), kind), every);
}

world::SceneDesc with_model(world::SceneDesc scene, world::HandModelKind kind, int fem_tets) {
  for (world::HandDesc& h : scene.hands) {
    h.model = kind;
    if (fem_tets > 0) h.resolution_tets = fem_tets;
  }
  return scene;
}

nlohmann::json row_json(const Row& r) {
  const offline::OfflineTimings& t = r.run.trace.timings;
  return {{"interaction", r.interaction},
          {"model", r.model},
          {"visual_hz", r.reference ? 1000 : 30},
          {"energy_j", r.run.energy_j},
          {"release_n", r.release_n},
          {"after_n", r.after_n},
          {"rms_force_error_n", r.error.rms_n},
          {"max_force_error_n", r.error.max_n},
          {"penetration_max_mm", 1e3 * r.run.penetration_max_m},
          {"tick_us_median", t.haptic_us_median},
          {"tick_us_p99", t.haptic_us_p99},
          {"visual_ms_median", t.visual_ms_median},
          {"visual_ms_p99", t.visual_ms_p99},
          {"resets", r.run.trace.resets},
          {"lift_mm", 1e3 * r.lift_m},
          {"hold_slip_mm", 1e3 * r.hold_slip_m},
          {"grasped", r.grasp && r.lift_m >= kGraspedM},
          {"squeeze_world_n", r.squeeze_world_n},
          {"squeeze_felt_n", r.squeeze_felt_n},
          {"reference", r.reference}};
}

struct TimingRow {
  int phalanges = 0, hands = 0, contacts = 0;
  double step_ms_median = 0, step_ms_p99 = 0;
};

// `phalanges` of the contact-point hands' shapes flat on tiles, 2 mm in, each in its own 12 cm cell.
TimingRow time_phalanges(int phalanges) {
  namespace cp = hand::contact_point;
  world::SceneDesc scene;
  scene.dt_s = 1.0 / 60.0;
  world::ObjectDesc floor;
  floor.name = "floor";
  floor.kind = world::BodyKind::static_body;
  floor.shape.type = world::ShapeType::plane;
  floor.shape.normal = {0, 0, 1};
  scene.objects.push_back(floor);
  // Under each pressed phalanx a 200 g tile (10 x 10 x 2 cm) on the floor: the step solves the
  // hand's contacts on a moving body and ODE's on the floor, as a scene's interaction would.
  constexpr double kCell = 0.12, kTile = 0.02;
  for (int k = 0; k < phalanges; ++k) {
    world::ObjectDesc tile;
    tile.name = "tile" + std::to_string(k);
    tile.shape.type = world::ShapeType::box;
    tile.shape.size = {0.1, 0.1, kTile};
    tile.mass_kg = 0.2;
    tile.pose.p_W = {kCell * (k % 8), kCell * (k / 8), 0.5 * kTile};
    scene.objects.push_back(tile);
  }
  const int hands = phalanges > cp::kContactPointShapes ? 2 : 1;
  for (int h = 0; h < hands; ++h) {
    world::HandDesc d;
    d.name = "hand" + std::to_string(h);
    d.model = world::HandModelKind::contact_point;
    d.handles = world::HandleSet::phalanges;
    d.pose.p_W = {0, 0.5 * h, 1};
    scene.hands.push_back(d);
  }
  world::World w(scene);
  const double depth = 0.002;
  for (int h = 0; h < hands; ++h) {
    auto& hand = dynamic_cast<cp::ContactPointHand&>(w.hand(h));
    for (int s = 0; s < cp::kContactPointShapes; ++s) {
      const int k = h * cp::kContactPointShapes + s;
      hand::HandleTarget t;
      // Shape s lying flat: the palm face down, a capsule along x with its side down.
      const double lowest = s == 0 ? hand::kPalmHalfThickness_m : hand.project_to_surface(s, {0, 0, -1}).norm();
      t.p_W = {kCell * (k % 8), kCell * (k / 8), k < phalanges ? kTile + lowest - depth : 0.5};
      hand.set_target(s, t);
    }
  }
  std::vector<double> ms;
  for (int k = 0; k < 300; ++k) {
    w.step();
    if (k >= 60) ms.push_back(w.snapshot().timings.total_ms);
  }
  TimingRow r;
  r.phalanges = phalanges;
  r.hands = hands;
  for (const world::ContactRecord& c : w.snapshot().contacts) r.contacts += c.hand >= 0;
  r.step_ms_median = percentile(ms, 50);
  r.step_ms_p99 = percentile(ms, 99);
  return r;
}

void run_hands_bench(const TouchSuiteArgs& a) {
  // tiny (a smoke run): the table press only, the FEM hand at ~400 tets.
  const bool tiny = a.size == "tiny";
  const int fem_tets = tiny ? 400 : 0;
  const Machine machine = describe_machine();
  const auto t0 = std::chrono::steady_clock::now();
  const world::SceneDesc glove = world::load_scene(std::string(HAPTICD_SCENES_DIR) + "/glove_grasp.json");
  using offline::GraspKind;
  struct Interaction {
    const char* name;
    const char* press_place;  // a press: offline::press_scene's place; a grasp: nullptr
    GraspKind grasp = GraspKind::tripod_box;
  };
  const Interaction interactions[] = {{"table_press", "table_edge"},
                                      {"bunny_press", "movable_bunny"},
                                      {offline::grasp_name(GraspKind::tripod_box), nullptr, GraspKind::tripod_box},
                                      {offline::grasp_name(GraspKind::power_ball), nullptr, GraspKind::power_ball},
                                      {offline::grasp_name(GraspKind::pinch_plate), nullptr, GraspKind::pinch_plate}};
  std::vector<Row> rows;
  for (const Interaction& in : interactions) {
    const std::string name = in.name;
    if (tiny && name != "table_press") continue;
    for (const Model& m : kModels) {
      auto run = [&](int every) {
        spdlog::info("hands: {} with the {} hand at {} ticks", name, m.name, every);
        Row r = in.press_place == nullptr
                    ? grasp_row(with_model(offline::grasp_scene(glove, in.grasp), m.kind, fem_tets), every, in.grasp,
                                a.tick_sweeps)
                    : press_row(with_model(offline::press_scene(std::string(m.press_prefix) + in.press_place), m.kind,
                                           fem_tets),
                                every, a.tick_sweeps);
        r.interaction = name;
        r.model = m.name;
        r.grasp = in.press_place == nullptr;
        return r;
      };
      Row reference = run(1);
      reference.reference = true;
      Row r = run(kVisualEveryTicks);
      r.error = offline::force_error(r.run.trace, reference.run.trace);
      rows.push_back(std::move(r));
      rows.push_back(std::move(reference));
    }
  }
  std::vector<TimingRow> timing;
  for (int phalanges : {0, 6, 16, 32}) {
    spdlog::info("hands: contact-point world step with {} phalanges in contact", phalanges);
    timing.push_back(time_phalanges(phalanges));
  }
  const double wall_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();

  std::printf(
      "Hand models on the same interactions, closed loop at 1 kHz, passivity controller on: table_press / "
      "bunny_press = the stylus 2 cm into the table's edge / the movable bunny and lifted; grasp_box / grasp_ball / "
      "pinch_plate = the 16-frame glove's tripod of the 5 cm box, power grasp of the 6 cm ball, pinch of a 4 mm "
      "plate's edge, each lifted 5 cm and let go. Error against the same model's world stepped every tick.\n");
  std::printf("%-12s %-14s %7s %10s %9s %9s %9s %9s %8s %8s %8s %8s %8s %6s %7s %7s\n", "interaction", "model",
              "visual", "energy_J", "release_N", "after_N", "rms_err_N", "max_err_N", "pen_mm", "tick_med", "tick_p99",
              "vis_med", "vis_p99", "resets", "lift_mm", "slip_mm");
  nlohmann::json json_rows = nlohmann::json::array();
  for (const Row& r : rows) {
    const offline::OfflineTimings& t = r.run.trace.timings;
    std::printf("%-12s %-14s %7s %+10.4f %9.3f %9.4f %9.4f %9.4f %8.2f %8.1f %8.1f %8.2f %8.2f %6ld %7.1f %7.2f\n",
                r.interaction.c_str(), r.model.c_str(), r.reference ? "1 kHz" : "30 Hz", r.run.energy_j, r.release_n,
                r.after_n, r.error.rms_n, r.error.max_n, 1e3 * r.run.penetration_max_m, t.haptic_us_median,
                t.haptic_us_p99, t.visual_ms_median, t.visual_ms_p99, r.run.trace.resets, 1e3 * r.lift_m,
                1e3 * r.hold_slip_m);
    json_rows.push_back(row_json(r));
  }
  std::printf(
      "\nThe contact-point hand's world step with phalanges in contact (seed 001: 0.6 / 0.9 / 1.5 ms for 6 / "
      "16 / 32), each 2 mm into a 200 g tile on a floor, 60 Hz:\n%10s %6s %9s %12s %10s\n",
      "phalanges", "hands", "contacts", "median_ms", "p99_ms");
  nlohmann::json timing_rows = nlohmann::json::array();
  for (const TimingRow& t : timing) {
    std::printf("%10d %6d %9d %12.3f %10.3f\n", t.phalanges, t.hands, t.contacts, t.step_ms_median, t.step_ms_p99);
    timing_rows.push_back({{"phalanges", t.phalanges},
                           {"hands", t.hands},
                           {"contacts", t.contacts},
                           {"step_ms_median", t.step_ms_median},
                           {"step_ms_p99", t.step_ms_p99}});
  }
  std::printf("%.1f s wall (all runs); machine: %s, %d cores, BLAS %s, revision %s (one thread)\n", wall_s,
              machine.cpu.c_str(), machine.cores, machine.blas.c_str(), machine.git_revision.c_str());
  if (!a.json.empty())
    write_json(a.json,
               {{"suite", "hands"},
                {"size", a.size},
                {"tick_contact_sweeps", a.tick_sweeps},
                {"haptic_hz", 1000},
                {"method",
                 "closed loop through the lockstep runner, passivity controller on, 30 Hz visual step; "
                 "table_press and bunny_press: the stylus 2 cm (device) into the table's edge or the movable "
                 "bunny at 2 cm/s, held 0.5 s, lifted at 5 cm/s; grasp_box, grasp_ball, pinch_plate: the 16-frame "
                 "glove moves its palm in to the box / the ball / a thin plate over the table's edge, closes in a "
                 "tripod / power grasp / pinch, lifts it 5 cm, opens (server/offline/touch.hpp); "
                 "reference, for every model alike: the same model's world stepped at every haptic tick; "
                 "force error per tick = sqrt(sum over frames |f_D - f_D,ref|^2)"},
                {"rows", json_rows},
                {"timing", timing_rows},
                {"wall_s", wall_s},
                {"threads", 1},
                {"machine", to_json(machine)}});
}

}  // namespace

void add_hands_suite(CLI::App& app) {
  add_touch_suite_command(
      app, "hands", "every hand model (fem, spring, contact_point) on the same presses and grasps: cost, energy, error",
      run_hands_bench);
}

}  // namespace hapticd::bench
