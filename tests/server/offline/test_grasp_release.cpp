// Touch that lets go, for gloves (issue 17): the simulated glove (16 frames: palm and phalanges)
// lowers its palm over the box, closes on it in a tripod grasp, lifts it, opens and holds open,
// closed loop through the lockstep runner (hapticd's own haptic tick and visual step), on
// glove_grasp.json and two_hands.json (whose second hand, undriven, stays where it is), at visual
// rates of 15, 30 and 60 Hz, the passivity controller on as in hapticd. The grasp is the world
// tests' tripod of the 5 cm box (test_world_glove.cpp, box_grasp: the box turned -30 degrees, the
// thumb on its near face, index and middle on its far face), here commanded to the glove rather
// than set on the hand. Asserted:
//   - no reset of a proxy or of the world;
//   - the box was lifted (at least 2 cm of the palm's 5 cm);
//   - the released box falls: it ends on the table, within 2 mm of its height at the start, at rest;
//   - one second after the hand has opened, no frame feels more than 0.01 N.
// GraspReleaseEnergy asserts the issue's energy bound on the same runs: energy put into the glove
// <= 0 (the work of the rendered forces on the palm and the joints,
// GloveSimulation::passivity_energy_j; the run ends open, in free space, holding nothing).
#include <gtest/gtest.h>
#include <unistd.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <numbers>
#include <stdexcept>
#include <string>

#include "clients/sim/glove_trajectory.hpp"
#include "server/offline/offline_run.hpp"
#include "server/world/scene_loader.hpp"

namespace hapticd::offline {
namespace {

constexpr double kPeriod = 1e-3;
constexpr double kDeg = std::numbers::pi / 180.0;
constexpr double kBoxYaw = -30 * kDeg;
const Eigen::Vector3d kBoxInHand(-0.040, 0.050, -0.052);  // the box's centre in the palm frame, grasped
constexpr double kAboveM = 0.04, kLiftM = 0.05;
// The motion, in seconds from the start: open above the box, down over it, closed, held, lifted,
// held up, opened, then open until the end.
constexpr double kDownAt = 0.3, kCloseAt = 0.8, kLiftAt = 1.55, kOpenAt = 3.05, kOpenedAt = 3.55, kEndS = 5.55;
constexpr double kQuietN = 0.01;  // "no force" one second after the hand has opened

double ease(double t, double from, double to) {
  const double s = std::clamp((t - from) / (to - from), 0.0, 1.0);
  return 0.5 * (1.0 - std::cos(std::numbers::pi * s));
}

// The motion as a glove CSV file (GloveTrajectory::from_csv: t, the 20 angles in degrees, the palm's
// offset in m), every 10 ms.
std::string write_trajectory() {
  const sim::JointVector open = sim::GloveTrajectory::grasp().angles(0);
  // box_grasp's closed posture (degrees; per finger abduction, flexion 1, 2, 3).
  const double closed_deg[20] = {-30, 30, 20, 60, -4, 5, 70, 65, 0, 15, 95, 40, 8, 0, 6, 6, 16, 0, 6, 6};
  const std::string path =
      (std::filesystem::temp_directory_path() / ("hapticd_grasp_release_" + std::to_string(::getpid()) + ".csv"))
          .string();
  std::ofstream f(path);
  for (int k = 0; k * 0.01 <= kEndS + 1e-9; ++k) {
    const double t = k * 0.01;
    const double close = ease(t, kCloseAt, kCloseAt + 0.5) - ease(t, kOpenAt, kOpenedAt);
    const double z = -kAboveM * ease(t, kDownAt, kCloseAt) + kLiftM * ease(t, kLiftAt, kLiftAt + 1.0);
    f << t;
    for (int i = 0; i < 20; ++i) f << ',' << (1 - close) * open[i] / kDeg + close * closed_deg[i];
    f << ",0,0," << z << '\n';
  }
  return path;
}

// The shipped scene with its box turned as the grasp wants it and the hand (and its device's
// workspace) 4 cm above where the grasp holds it.
world::SceneDesc grasp_scene(const std::string& name) {
  world::SceneDesc s = world::load_scene(std::string(HAPTICD_SCENES_DIR) + "/" + name + ".json");
  for (world::ObjectDesc& o : s.objects) {
    if (o.name != "box") continue;
    o.pose.q_W = Eigen::Quaterniond(Eigen::AngleAxisd(kBoxYaw, Eigen::Vector3d::UnitZ()));
    const Eigen::Vector3d palm = o.pose.p_W - kBoxInHand + Eigen::Vector3d(0, 0, kAboveM);
    s.devices[0].workspace.offset_W += palm - s.hands[0].pose.p_W;
    s.hands[0].pose.p_W = palm;
  }
  return s;
}

struct GraspCase {
  const char* scene;
  int visual_hz;
};

std::string case_name(const ::testing::TestParamInfo<GraspCase>& info) {
  return std::string(info.param.scene) + "_" + std::to_string(info.param.visual_hz) + "Hz";
}

// One closed-loop run of the grasp, lift and release.
struct GraspRun {
  double energy_j = 0;                                // put into the glove over the run
  double energy_at_lift_j = 0, energy_at_open_j = 0;  // so far when the lift and the opening begin
  long resets = 0;
  double box_z0 = 0, box_top = 0;  // the box's height at the start and its highest
  world::RigidBodyState box_end;
  double felt_late_n = 0;  // the largest frame force from a second after the hand has opened
  double observed_j = 0;   // the server's passivity observer: work the frames did on the rendering
};

GraspRun run_grasp(const GraspCase& c) {
  const world::SceneDesc scene = grasp_scene(c.scene);
  OfflineOptions options;
  options.visual_every_ticks = static_cast<int>(std::lround(1.0 / (c.visual_hz * kPeriod)));
  OfflineLoops loops(scene, options);
  const int box = loops.world().rigid()->find("box");
  if (box < 0) throw std::runtime_error(std::string(c.scene) + " has no box");
  GraspRun run;
  run.box_z0 = run.box_top = loops.world().snapshot().bodies[box].p_WO.z();

  Eigen::Vector3d palm_D;
  Eigen::Quaterniond q_D;
  loops.frame_pose_at_handle(0, palm_D, q_D);
  const std::string csv = write_trajectory();
  sim::GloveTrajectory motion = sim::GloveTrajectory::from_csv(csv, {palm_D.x(), palm_D.y(), palm_D.z()});
  std::filesystem::remove(csv);
  motion.set_palm_orientation(q_D);
  const bool left = scene.hands[0].side == world::HandSide::left;
  SimulatedGlove glove(std::move(motion), sim::kGloveFramesAll, left, kPeriod);

  const long lift_tick = std::lround(kLiftAt / kPeriod), open_tick = std::lround(kOpenAt / kPeriod);
  const OfflineTrace trace = run_offline(loops, glove, std::lround(kEndS / kPeriod), [&](long tick) {
    run.box_top = std::max(run.box_top, loops.world().snapshot().bodies[box].p_WO.z());
    if (tick == lift_tick) run.energy_at_lift_j = glove.simulation().passivity_energy_j();
    if (tick == open_tick) run.energy_at_open_j = glove.simulation().passivity_energy_j();
  });
  for (std::size_t k = 0; k < trace.replies.size(); ++k)
    if (static_cast<double>(k) * kPeriod > kOpenedAt + 1.0)
      for (int j = 0; j < trace.replies[k].frames; ++j)
        run.felt_late_n = std::max(run.felt_late_n, trace.replies[k].wrench[j].f_D.norm());
  run.energy_j = glove.simulation().passivity_energy_j();
  for (int j = 0; j < loops.proxy().handles(); ++j) run.observed_j += loops.proxy().energy_in(j);
  run.resets = trace.resets;
  run.box_end = loops.world().snapshot().bodies[box];
  std::printf(
      "%s at %d Hz: energy %+.4f J (%+.4f closing and holding, %+.4f lifting, %+.4f opening), resets %ld, "
      "server observer %+.4f J in, box lifted %.1f mm, ends %+.2f mm from its start at %.4f m/s; a second after "
      "opening %.4f N\n",
      c.scene, c.visual_hz, run.energy_j, run.energy_at_lift_j, run.energy_at_open_j - run.energy_at_lift_j,
      run.energy_j - run.energy_at_open_j, run.resets, run.observed_j, 1e3 * (run.box_top - run.box_z0),
      1e3 * (run.box_end.p_WO.z() - run.box_z0), run.box_end.v_WO.norm(), run.felt_late_n);
  return run;
}

const auto kGraspCases = ::testing::Values(GraspCase{"glove_grasp", 15}, GraspCase{"glove_grasp", 30},
                                           GraspCase{"glove_grasp", 60}, GraspCase{"two_hands", 30});

class GraspRelease : public ::testing::TestWithParam<GraspCase> {};

TEST_P(GraspRelease, LiftsTheBoxResetsNothingLetsItFallAndFallsQuiet) {
  const GraspRun run = run_grasp(GetParam());
  EXPECT_EQ(run.resets, 0);
  EXPECT_GT(run.box_top - run.box_z0, 0.02) << "the grasp did not lift the box";
  EXPECT_NEAR(run.box_end.p_WO.z(), run.box_z0, 0.002) << "the released box is not back on the table";
  EXPECT_LT(run.box_end.v_WO.norm(), 0.01) << "the released box is still moving";
  EXPECT_LT(run.felt_late_n, kQuietN) << "the open hand still feels the box";
}

INSTANTIATE_TEST_SUITE_P(Touch, GraspRelease, kGraspCases, case_name);

// The issue's energy bound on the same runs: a known fault of issue 17, run by tests/CMakeLists.txt
// as one ctest expected to fail. Measured: +0.011 to +0.030 J, most of it (+0.011 to +0.018 J) while
// the closed hand lifts the box; closing and holding give -0.007 to +0.017 J, opening up to +0.007 J.
// The server's passivity observer finds the frames' ports passive on the same runs (the glove did
// +0.009 to +0.026 J of work on the rendering): it counts each frame's force against that frame's
// own velocity, as if every frame were grounded, while the simulated glove's finger actuators push
// against its palm (GloveSimulation: the finger frames' forces act through joint torques only).
// The box's weight rendered on the fingers then does no work on the glove as its palm lifts it, and
// what the observer books as work done on the rendering never left the glove: for such a glove the
// observer and its controller would have to measure the finger frames relative to the palm.
class GraspReleaseEnergy : public ::testing::TestWithParam<GraspCase> {};

TEST_P(GraspReleaseEnergy, PutsNoEnergyIntoTheGlove) {
  const GraspRun run = run_grasp(GetParam());
  EXPECT_LE(run.energy_j, 0.0) << "the rendering put energy into the glove";
}

INSTANTIATE_TEST_SUITE_P(Issue17KnownFault, GraspReleaseEnergy, kGraspCases, case_name);

}  // namespace
}  // namespace hapticd::offline
