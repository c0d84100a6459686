#pragma once
// Touch that makes and breaks contact (issue 17), scripted for the lockstep runner: the simulated
// stylus's press, hold and lift, and the simulated glove's grasp, lift and release. Shared by the
// tests (tests/server/offline/test_press_hold_lift.cpp, test_grasp_release.cpp) and
// `haptic-bench touch`.
#include <Eigen/Geometry>
#include <string>

#include "clients/sim/glove_trajectory.hpp"
#include "server/offline/offline_run.hpp"

namespace hapticd::offline {

// What a scripted touch ended with.
struct TouchRun {
  OfflineTrace trace;
  double energy_j = 0;           // work of the rendered forces on the device over the run (> 0: put in)
  double penetration_max_m = 0;  // deepest skin point inside anything after any visual step
};

// --- Press, hold, lift (the simulated stylus) ------------------------------------------------------

struct Press {
  double depth_m;   // device units, below the start
  double down_m_s;  // device speed down
  double up_m_s;    // and up
};

// The commanded tip height (device units, relative to the start): still for 0.3 s, down to the
// depth, held 0.5 s, up to 1 cm above the start, held 1.2 s.
struct PressSchedule {
  explicit PressSchedule(const Press& p);
  double z(double t_s) const;
  static constexpr double kClearance = 0.01;  // the lift ends 1 cm above the start
  Press press;
  double down_start, down_end, up_start, up_end, end;
};

// stylus_bunny.json with the hand over `object`: movable_bunny (the scene itself), fixed_bunny (the
// bunny static), deformable_bunny (deformable_bunny.json, the hand placed as in stylus_bunny),
// table_edge (half the palm over the table's +x edge) or free_space (40 cm above everything); with
// "spring_" before the name (not the deformable bunny's), the same with seed 002's spring hand.
// Throws std::invalid_argument for another name.
world::SceneDesc press_scene(const std::string& object);

// The lockstep runner as the movable bunny's press tests run it (SampleGaps, VisualStalls): 59 Hz
// (the world every 17 ticks), the bodies settled 0.5 s first, the passivity controller off (the
// rendering's own behaviour).
OfflineOptions movable_bunny_press_options();

// The press-hold-lift of `schedule` on `scene` through loops built with `options` (the scene's own
// contact model unless the options say otherwise), the stylus starting at its handle.
TouchRun run_press_hold_lift(const world::SceneDesc& scene, const PressSchedule& schedule,
                             const OfflineOptions& options);

// What the device felt around the lift.
struct AfterLift {
  long touch = -1;       // the first tick flagged InContact
  double largest = 0;    // the largest force of the run, N
  double pull = 0;       // the largest force toward the object (-z) once the commanded tip is back above
                         // the height where it first touched, after one haptic and one visual period, N
  double after = 0;      // the largest force one second after the lift, N
  bool flagged = false;  // InContact then
};
AfterLift after_lift(const OfflineTrace& trace, const PressSchedule& schedule, const OfflineOptions& options);

// --- Grasp, lift, release (the simulated glove, 16 frames) -------------------------------------------

// What the glove grasps and how (issue 18's comparison: the same three grasps for every hand model).
enum class GraspKind {
  // The world tests' tripod of the 5 cm box (test_world_glove.cpp's box_grasp: the box turned -30
  // degrees about z, the thumb on its near face, index and middle on its far face), from above.
  tripod_box,
  // A power grasp of the 6 cm rubber ball from above: the palm on its top, the four fingers spread
  // and curled around its far side and under its equator, the thumb on its near side.
  power_ball,
  // A two-finger pinch of a thin plate (10 x 8 cm, 4 mm, 34 g, the table's material) lying on the
  // table with 4 cm over its +x edge: the glove's pinch posture (the thumb's tip under the plate, the index's distal
  // phalanx
  // on it), the hand turned so the pinch closes vertically, approached along the table from +x.
  pinch_plate,
};
const char* grasp_name(GraspKind kind);  // "grasp_box", "grasp_ball", "pinch_plate"
// The object a grasp holds: "box", "ball" or "plate".
const char* grasp_object(GraspKind kind);

// The motion, in seconds from the start: open 4 cm away from the grasp (above it; the pinch: beside
// the plate, along the table), moving in to it, closed, held, lifted 5 cm, held up, opened, withdrawn
// 4 cm the way it came in, then still until the end.
struct GraspSchedule {
  static constexpr double kDownAt = 0.3, kCloseAt = 0.8, kGrippedAt = 1.3, kLiftAt = 1.55, kHeldAt = 2.55;
  static constexpr double kOpenAt = 3.05, kOpenedAt = 3.55, kWithdrawnAt = 4.05, kEnd = 5.55;
  static constexpr double kAboveM = 0.04, kLiftM = 0.05;
};

// `scene` (glove_grasp.json or two_hands.json: a rigid "box" (5 cm) and "ball" (6 cm) on a static
// "table" box) prepared for `kind`: the box turned as the tripod wants it, or a plate added on the
// table's +x edge; the first hand, its orientation and its device's workspace placed where the
// grasp starts. Throws std::invalid_argument when the scene has no such object, table or hand.
world::SceneDesc grasp_scene(world::SceneDesc scene, GraspKind kind = GraspKind::tripod_box);

// The glove motion of GraspSchedule for `kind` with a palm starting at `palm_D` with orientation
// `q_D` (device).
sim::GloveTrajectory grasp_release_trajectory(const Eigen::Vector3d& palm_D, const Eigen::Quaterniond& q_D,
                                              GraspKind kind = GraspKind::tripod_box);

struct GraspRun : TouchRun {
  double energy_at_lift_j = 0, energy_at_open_j = 0;  // the glove's energy so far when lifting and opening begin
  double observed_j = 0;           // the server's passivity observer: work the frames did on the rendering, J
  double object_z0 = 0, object_top = 0;  // the grasped object's height at the start and its highest, m
  // How far it moved in the palm's frame while held up (from the lift's end to the opening), m.
  double hold_slip_m = 0;
  world::RigidBodyState object_end;  // its state at the end
  // While the closed hand grips it on the table (from the closing's end to the lift), per tick on
  // average: the magnitudes of the world's contact forces on it, summed, and of the forces on the
  // glove's frames, summed (their torques left out), N. Transparent rendering has them alike.
  double squeeze_world_n = 0, squeeze_felt_n = 0;
  double release_n = 0;  // the largest frame force once the hand is open, after one haptic and one visual period
  double after_n = 0;    // the largest frame force from a second after the hand has opened
};

// The work the replies of `trace` did on a glove's frames, J (> 0: put in), each reply held over the
// motion to the next pose: with every frame a grounded port (its own motion, as the proxies take it),
// and with the finger frames' actuators pushing against the palm's frame (frame 0), as the simulated
// glove's are: their motion relative to the palm's body, which is what its own account books
// (sim::GloveSimulation::passivity_energy_j). The two differ by the work of the finger forces over
// the palm's motion.
struct FrameWork {
  double grounded_j = 0, on_palm_j = 0;
};
FrameWork frame_work(const OfflineTrace& trace);

// The grasp, lift and release of `kind` on `scene` (as grasp_scene makes it for `kind`) with the
// 16-frame simulated glove.
GraspRun run_grasp_release(const world::SceneDesc& scene, const OfflineOptions& options,
                           GraspKind kind = GraspKind::tripod_box);

}  // namespace hapticd::offline
