#include <gtest/gtest.h>
#include <cstdio>
#include <cstdlib>
#include "server/offline/touch.hpp"
namespace hapticd::offline {
// The e2e press-hold-lift (tests/e2e/press_hold_lift_busy.sh) in the lockstep runner.
TEST(ScratchDiag, E2e) {
  const int every = std::getenv("EVERY") ? std::atoi(std::getenv("EVERY")) : 17;
  OfflineOptions o; o.visual_every_ticks = every; o.settle_s = 0.5;
  o.model_delay_ticks = std::getenv("DELAY") ? std::atoi(std::getenv("DELAY")) : 0;
  o.passivity_control = std::getenv("NOPC") == nullptr;
  if (std::getenv("MASS")) o.palm_hand_mass_scale = std::atof(std::getenv("MASS"));
  auto z = [](double t) {
    if (t < 0.5) return 0.0;
    if (t < 1.5) return -0.02 * (t - 0.5);
    if (t < 3.5) return -0.02;
    if (t < 4.0) return -0.02 + 0.08 * (t - 3.5);
    return 0.02;
  };
  OfflineLoops loops(press_scene("movable_bunny"), o);
  Eigen::Vector3d start_D; Eigen::Quaterniond q_D;
  loops.frame_pose_at_handle(0, start_D, q_D);
  SimulatedStylus stylus(start_D, [&](double t) { return Eigen::Vector3d(0, 0, z(t)); }, 1e-3);
  const OfflineTrace tr = run_offline(loops, stylus, 6000);
  double first = 1; long touch = -1;
  for (size_t k = 0; k < tr.replies.size(); ++k) if (tr.replies[k].in_contact[0]) { touch = k; first = z(k * 1e-3); break; }
  double pull = 0, tpull = 0;
  for (size_t k = 3500; k < tr.replies.size(); ++k) {
    const double t = k * 1e-3;
    if (z(t) > first && -tr.replies[k].wrench[0].f_D.z() > pull) pull = -tr.replies[k].wrench[0].f_D.z(), tpull = t;
    if (std::getenv("V") && k < 3800 && k % 10 == 0) std::printf("t %.3f cmd %.4f p %.4f fz %.3f c %d\n", t, z(t), tr.poses[k].p_D[0].z() - start_D.z(), tr.replies[k].wrench[0].f_D.z(), tr.replies[k].in_contact[0]);
  }
  std::printf("touch at %ld (%.1f mm); pull while lifting %.3f N at %.3f s; energy %+.5f J\n", touch, 1e3 * first, pull, tpull, stylus.energy_j());
}
}
