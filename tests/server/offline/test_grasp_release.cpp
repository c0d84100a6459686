// Touch that lets go, for gloves (issue 17): the simulated glove (16 frames: palm and phalanges)
// lowers its palm over the box, closes on it in a tripod grasp, lifts it, opens and holds open,
// closed loop through the lockstep runner (hapticd's own haptic tick and visual step), on
// glove_grasp.json and two_hands.json (whose second hand, undriven, stays where it is), at visual
// rates of 5 to 60 Hz, the passivity controller on as in hapticd. The grasp is the world
// tests' tripod of the 5 cm box (test_world_glove.cpp, box_grasp: the box turned -30 degrees, the
// thumb on its near face, index and middle on its far face), here commanded to the glove rather
// than set on the hand; and the ball's power grasp (touch.hpp) at 30 Hz with each hand model
// (seed 004's FEM hand, seed 002's spring hand, seed 001's contact-point hand). Asserted:
//   - no reset of a proxy or of the world;
//   - the object was lifted (at least 2 cm of the palm's 5 cm);
//   - the released object falls: it ends on the table, within 2 mm of its height at the start, at rest
//     (the ball rolling on it, but not bouncing);
//   - one second after the hand has opened, no frame feels more than 0.01 N;
//   - the issue's energy bound: energy put into the glove <= 0 (the work of the rendered forces on the
//     palm and the joints, GloveSimulation::passivity_energy_j; the run ends open, in free space,
//     holding nothing);
//   - the server's passivity observer books what the glove's simulation measures.
#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <string>

#include "server/offline/touch.hpp"
#include "server/world/scene_loader.hpp"
#include "stiffness_scale.hpp"

namespace hapticd::offline {
namespace {

constexpr double kPeriod = 1e-3;
constexpr double kQuietN = 0.01;  // "no force" one second after the hand has opened

struct GraspCase {
  const char* scene;
  int visual_hz;
  GraspKind kind = GraspKind::tripod_box;
  world::HandModelKind model = world::HandModelKind::fem;  // the scene's own hand unless told
  const char* model_name = "";
  bool passivity_control = true;  // as in hapticd
};

std::string case_name(const ::testing::TestParamInfo<GraspCase>& info) {
  const GraspCase& c = info.param;
  return std::string(c.scene) + "_" + std::to_string(c.visual_hz) + "Hz" +
         (c.kind == GraspKind::tripod_box ? "" : std::string("_") + grasp_name(c.kind)) +
         (*c.model_name ? std::string("_") + c.model_name : "");
}

GraspRun run_grasp(const GraspCase& c) {
  OfflineOptions options;
  options.visual_every_ticks = static_cast<int>(std::lround(1.0 / (c.visual_hz * kPeriod)));
  options.passivity_control = c.passivity_control;
  // A perturbed run (OfflineOptions::model_stiffness_scale), as the known fault's figures were measured.
  apply_stiffness_scale_from_env(options);
  world::SceneDesc scene =
      grasp_scene(world::load_scene(std::string(HAPTICD_SCENES_DIR) + "/" + c.scene + ".json"), c.kind);
  if (*c.model_name)
    for (world::HandDesc& h : scene.hands) h.model = c.model;
  const GraspRun run = run_grasp_release(scene, options, c.kind);
  std::printf(
      "%s %s %s at %d Hz: energy %+.4f J (%+.4f closing and holding, %+.4f lifting, %+.4f opening), resets %ld, "
      "server observer %+.4f J in, lifted %.1f mm, ends %+.2f mm from its start at %.4f m/s; "
      "a second after opening %.4f N\n",
      c.scene, grasp_name(c.kind), c.model_name, c.visual_hz, run.energy_j, run.energy_at_lift_j,
      run.energy_at_open_j - run.energy_at_lift_j, run.energy_j - run.energy_at_open_j, run.trace.resets,
      run.observed_j, 1e3 * (run.object_top - run.object_z0), 1e3 * (run.object_end.p_WO.z() - run.object_z0),
      run.object_end.v_WO.norm(), run.after_n);
  return run;
}

// The box's tripod with the scenes' FEM hand; the ball's power grasp with each hand model.
// 5 Hz: 200 ms steps, beyond the longest the visual loop takes (kMaxStep_s, 150 ms). There the
// glove's released box went through the table to the floor (ended 750 mm below its start) until a
// held body's supports were looked for as far as gravity takes it over the step.
// That the commanded grasp itself lifts the box, with the world stepped every tick (the reference the
// slower rates approximate; touch.cpp, kTripodSqueeze), is `haptic-bench touch`'s reference row
// (grasp_release at 1000 Hz, its lift_mm): ~110 s, too long for `make test`.
const auto kGraspCases = ::testing::Values(
    GraspCase{"two_hands", 5}, GraspCase{"glove_grasp", 30}, GraspCase{"glove_grasp", 60}, GraspCase{"two_hands", 30},
    GraspCase{"glove_grasp", 30, GraspKind::power_ball, world::HandModelKind::fem, "fem"},
    GraspCase{"glove_grasp", 30, GraspKind::power_ball, world::HandModelKind::spring, "spring"},
    GraspCase{"glove_grasp", 30, GraspKind::power_ball, world::HandModelKind::contact_point, "contact_point"});

class GraspRelease : public ::testing::TestWithParam<GraspCase> {};

TEST_P(GraspRelease, LiftsItResetsNothingLetsItFallFallsQuietAndPutsNoEnergyIntoTheGlove) {
  const GraspRun run = run_grasp(GetParam());
  EXPECT_EQ(run.trace.resets, 0);
  EXPECT_GT(run.object_top - run.object_z0, 0.02) << "the grasp did not lift the object";
  EXPECT_NEAR(run.object_end.p_WO.z(), run.object_z0, 0.002) << "the released object is not back on the table";
  // At rest on it: a ball may roll on (ODE has no rolling resistance), but not bounce.
  const GraspCase& c = GetParam();
  EXPECT_LT(c.kind == GraspKind::power_ball ? std::abs(run.object_end.v_WO.z()) : run.object_end.v_WO.norm(), 0.01)
      << "the released object is still moving";
  EXPECT_LT(run.after_n, kQuietN) << "the open hand still feels the object";
  // Measured (the printout): -0.0040 J at 15 Hz, -0.0046 J (glove_grasp) and -0.0088 J (two_hands)
  // at 30 Hz, -0.0056 J at 60 Hz; -0.0002, -0.0005, -0.0001 and -0.0056 J when this was written. The controller bounds
  // what a device keeps to its budget, kPassivityBudget_J (1e-4 J) shared by its 16 frames; at 1e-4 J a frame (1.6 mJ a
  // glove) the 30 Hz runs ended at +0.0002 and +0.0003 J. Before the observer booked each reply against the glove's
  // motion while it held it (it multiplied the reply by the filtered velocity, which lags, and booked -0.0002 J of work
  // by the glove where the glove gained +0.0027 J): +0.0027, +0.0015, +0.0025 and -0.0024 J. Before the observer
  // counted the finger frames' motion relative to the palm (the simulated glove's finger actuators push against its
  // palm, GloveSimulation: their forces act through joint torques only; ProxyHand::set_fingers_grounded_on_palm), it
  // credited the rendering with the box's weight on the fingers times the palm's lift, found every port passive and
  // never acted: +0.017 to +0.037 J.
  EXPECT_LE(run.energy_j, 0.0) << "the rendering put energy into the glove";
  // The server's observer books what the glove's own simulation measures, to 0.1 mJ (0.3-45 uJ apart:
  // the work the glove's frames did on the rendering is what the rendering did not put into the
  // glove). Counted as the filtered velocity times the interval, it was 2.5 mJ off at 15 Hz.
  std::printf("observer %+.7f J against the glove's %+.7f J\n", run.observed_j, -run.energy_j);
  EXPECT_NEAR(run.observed_j, -run.energy_j, 1e-4);
  // The trace's replies over its poses, the fingers' motion taken relative to the palm's body, book
  // what the glove's own simulation measures (frame_work; measured up to 3e-5 J apart).
  const FrameWork w = frame_work(run.trace);
  std::printf("the replies' work: %+.7f J on the palm-grounded glove, %+.7f J on grounded frames\n", w.on_palm_j,
              w.grounded_j);
  EXPECT_NEAR(w.on_palm_j, run.energy_j, 1e-4);
}

INSTANTIATE_TEST_SUITE_P(Touch, GraspRelease, kGraspCases, case_name);

// A known fault of issue 17 (tests/CMakeLists.txt): glove_grasp.json at 5 and 15 Hz. Both passed before
// the tick's stiffness lost its positive eigenvalues (passive_stiffness), and two_hands.json at 5 Hz
// did not (the tripod lifted the box 12.0 mm of the 20 asked; 11.7 to 37.0 mm with K scaled by
// 1 +- 1e-6 .. 1e-4). Now two_hands lifts it 54.2 mm in each of those runs (-0.063 J), and:
//   - glove_grasp at 5 Hz lifts it 9.6 mm (+8.8e-6 J), in each run: the box slips out of the hand as it
//     rises (44.5 mm and -0.25 J before). Five models of the lift lost eigenvalues of 0.063, 0.047 and
//     0.0015-0.0023 of the coupling's stiffness. At 200 ms steps (beyond the longest the server takes,
//     kMaxStep_s) the grasp was already chaotic in how deep it is commanded: with the thumb, index and
//     middle curled 1.10, 1.12, 1.13 and 1.15 times box_grasp's posture, glove_grasp lifted 44.5, 10.0,
//     52.2 and 39.3 mm (-0.25 J, +2.5e-7 J, -0.31 J, +0.0020 J with a reset), two_hands 12.0, 24.8,
//     73.3 and 25.1 mm.
//   - glove_grasp at 15 Hz lifts it as before (38.7 mm) but ends +1.0e-5 J (-0.0006 J before): the
//     opening takes back 1.0 mJ where it took 1.5. Two models lost eigenvalues of 0.003 and 0.007.
// The opening's -0.2 to -0.5 J at 5 Hz is the glove's fingers working against the rendering as they open.
INSTANTIATE_TEST_SUITE_P(Issue17KnownFault, GraspRelease,
                         ::testing::Values(GraspCase{"glove_grasp", 5}, GraspCase{"glove_grasp", 15}), case_name);

// The issue asks the rendering to be passive with the controller off too ("the controller guards the
// port, it must not hide a wrong model"). The box's grasp at 30 Hz: -0.0008 J into the glove without
// it. It was +0.025 J (an issue 17 known fault), +0.0006 J once the tick served a glove's contact
// rows at their operator's lookahead (TickContacts::W_proxy), -0.0008 J with the tripod commanded
// into the box (kTripodSqueeze). Before, the same replies over the same poses with every frame a grounded port, as
// the proxies take them (frame_work), did -0.0010 J: the glove's finger actuators push against its
// palm, whose frame feels nothing while it touches nothing (contact gating) and never the fingers'
// reactions, so the palm's motion against the fingers' forces is work the rendering does not see.
TEST(Touch, TheBoxGraspPutsNoEnergyIntoTheGloveWithoutThePassivityController) {
  GraspCase c{"glove_grasp", 30};
  c.passivity_control = false;
  const GraspRun run = run_grasp(c);
  const FrameWork w = frame_work(run.trace);
  std::printf("the replies' work: %+.4f J on the palm-grounded glove, %+.4f J on grounded frames\n", w.on_palm_j,
              w.grounded_j);
  EXPECT_EQ(run.trace.resets, 0);
  EXPECT_LE(run.energy_j, 0.0) << "the rendering put energy into the glove";
}

}  // namespace
}  // namespace hapticd::offline
namespace hapticd::offline {
namespace {

// A 100 ms gap in the glove's samples (its link lost them; they resume with the gap in their time
// stamps) while it closes, grips, lifts, holds (and 300 ms holding) and opens, glove_grasp.json at
// 30 Hz, the controller on as in hapticd: a gap is bridged (ProxyHand::commit_sample), no reset, and
// the glove gets no more than the controller's budget (kPassivityBudget_J); the released box falls
// back to the table and the open hand is quiet. Re-synced instead (each finger's proxy onto its
// device), the gap while gripping gave +9.0e-3 J and a reset. What the glove squeezed during a gap
// while gripping is a clutch, not a tighter grip: the box then slips (lifted 30 mm of 51; 9 mm while
// the clutch was taken from the last sample, not from the device carried along while overdue).
TEST(GloveGaps, AGapInTheGlovesSamplesResetsNothingAndPutsNoEnergyIntoIt) {
  const world::SceneDesc scene =
      grasp_scene(world::load_scene(std::string(HAPTICD_SCENES_DIR) + "/glove_grasp.json"));
  const std::pair<double, double> gaps[] = {{1.0, 1.1}, {1.2, 1.3}, {1.7, 1.8}, {2.0, 2.1}, {2.0, 2.3}, {3.2, 3.3}};
  for (const auto& gap : gaps) {
    OfflineOptions options;
    options.visual_every_ticks = 33;
    options.withheld_samples_s = {gap};
    const GraspRun run = run_grasp_release(scene, options);
    std::printf("gap %.1f-%.1f s: energy %+.2e J, resets %ld, lifted %.1f mm, ends %+.2f mm, a second after %.4f N\n",
                gap.first, gap.second, run.energy_j, run.trace.resets, 1e3 * (run.object_top - run.object_z0),
                1e3 * (run.object_end.p_WO.z() - run.object_z0), run.after_n);
    EXPECT_EQ(run.trace.resets, 0) << gap.first;
    EXPECT_LE(run.energy_j, haptic::kPassivityBudget_J) << gap.first;
    EXPECT_NEAR(run.object_end.p_WO.z(), run.object_z0, 0.002) << gap.first;
    EXPECT_LT(run.after_n, kQuietN) << gap.first;
  }
}

}  // namespace
}  // namespace hapticd::offline
