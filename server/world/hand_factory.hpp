#pragma once
// A scene's hand built as the model its "model" names (DESIGN.md section 2): the world steps it
// through the Hand interface without knowing which it is.
#include <ode/ode.h>

#include <Eigen/Core>
#include <memory>

#include "hand_models/coupled_solver.hpp"
#include "hand_models/hand.hpp"
#include "hand_models/hand_model.hpp"
#include "server/world/scene.hpp"

namespace hapticd::world {

struct HandBuild {
  double dt_s = 1.0 / 60.0;
  Eigen::Vector3d gravity_m_s2{0, 0, -9.81};  // zero: a weightless hand (as the server runs them)
  hand::SolverKind solver = hand::SolverKind::schur_cholmod;
  hand::DriveParams drive;  // how each handle is pulled toward its target
  // A palm-driven hand's density as a share of its material's (WorldOptions::palm_hand_mass_scale).
  double palm_mass_scale = 1.0;
  // Where a hand made of ODE bodies (hand::OdeHand: "spring") is built: the rigid world's.
  dWorldID ode_world = nullptr;
  dSpaceID ode_space = nullptr;
  bool spring_body_step_model = false;  // WorldOptions::spring_body_step_model
  bool hand_contacts = true;            // WorldOptions::hand_contacts (false: a hand touches nothing)
};

// The hand `desc` describes, placed at its scene pose, at rest. Throws std::runtime_error naming
// "hands.<name>" for a model that is not built yet (or not for its handles).
std::unique_ptr<hand::Hand> make_hand(const HandDesc& desc, const HandBuild& build);

}  // namespace hapticd::world
