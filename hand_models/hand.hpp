#pragma once
// What the world and the haptic loop need from any hand model (DESIGN.md section 2): its handles
// and the frames devices drive them by, one step toward its targets with the contacts the world
// found, its skin points, the handle-space force model the haptic loop renders (seed 004 section
// 3), and a reset. The deformable FEM hand of seed 004 (FemHand) and the articulated spring hand of
// seed 002 (spring::SpringHand) implement it; the contact-point hand of seed 001 and the soft-pad
// hand of seed 000 are to implement it too, chosen by a scene's "model", without the haptic loop
// knowing which it renders.
//
// Contacts: the world finds them against a hand's flesh (flesh.hpp), a tet mesh whose contacts are
// points embedded in its tets, the FEM hand's and every deformable object's alike. A hand model
// without such flesh (a rigid hand of seeds 001 and 002) returns none; made of ODE bodies
// (spring/ode_hand.hpp), it touches the world through ODE's contacts instead.
#include <Eigen/Core>
#include <Eigen/Geometry>
#include <string>
#include <string_view>
#include <vector>

#include "hand_models/flesh.hpp"
#include "hand_models/handle_linearization.hpp"
#include "hand_models/rigid_handle.hpp"

namespace hapticd::hand {

// A handle as a device link sees it: the rigid body a device frame drives.
struct HandleInfo {
  double mass_kg = 0;
  Eigen::Matrix3d inertia_B = Eigen::Matrix3d::Identity();  // about the centre of mass, handle frame
  // Where the handle sits in the tracked frame that drives it (a glove's phalanx; identity for a
  // stylus, whose frame is the handle's own).
  FrameToHandle in_frame;
};

class Hand {
 public:
  virtual ~Hand() = default;
  // The scene's "model" of this hand ("fem", ...).
  virtual std::string_view model_name() const = 0;
  virtual bool left() const = 0;

  // --- Handles: the rigid frames devices drive.
  virtual int num_handles() const = 0;
  // `tracked_frames`: how many frames the driving device tracks (1: a stylus on the palm).
  virtual HandleInfo handle_info(int j, int tracked_frames) const = 0;
  virtual const std::vector<HandleState>& handles() const = 0;
  // Handle j's drive target; false (target kept) when it is not finite.
  virtual bool set_target(int j, const HandleTarget& target) = 0;
  // Moves the whole hand rigidly so that handle 0 sits at the pose, at rest (a re-synced device).
  virtual void place(const Eigen::Vector3d& p_W, const Eigen::Quaterniond& q_W) = 0;

  // --- Stepping.
  // The length of the coming step, s (the model of the coming step is built for it).
  virtual void set_step_length(double dt_s) = 0;
  // One step toward the targets with the contacts the world gave it; with `model`, the handle-space
  // model at the step's end too. Nothing non-finite leaves a step: a hand that fails resets itself.
  virtual void step(HandleLinearization* model) = 0;
  // After a step that was broken off (a throw): a hand whose positions are whole keeps its shape
  // and contacts and stops moving; any other is placed rigidly at `fallback` (handle 0), at rest.
  virtual void recover(const Eigen::Vector3d& fallback_p_W, const Eigen::Quaterniond& fallback_q_W) = 0;
  // Resets so far (failed steps and recoveries).
  virtual long resets() const = 0;

  // --- What the haptic loop renders.
  // The handle-space model of the coming step from the current state (seed 004 section 3):
  // F*(x, v) = F0 + K (x - x0) + D (v - v0), and with ContactLinearization::unilateral the contact
  // rows the haptic tick solves (HandleContactModel); false when it cannot be built.
  virtual bool linearize_next_step(HandleLinearization& out, ContactLinearization contacts) = 0;
  // The flesh's wrench on the handles now (seed 004 eq. 4-5), 6m: the zeroth order of that model.
  virtual Eigen::VectorXd coupling_wrench() const = 0;

  // --- Skin: the points that collide, for contact flags and display.
  virtual int num_skin_points() const = 0;
  virtual Eigen::Vector3d skin_point(int i) const = 0;
  // The handle whose part of the hand skin point i is on (a glove frame's contact flag); -1: none.
  virtual int skin_handle(int i) const = 0;

  // --- Collision: the flesh the world embeds this hand's contacts in (its points are the skin
  // points above), or null for a hand that has none. Valid as long as the hand.
  virtual Flesh* flesh() { return nullptr; }
};

}  // namespace hapticd::hand
