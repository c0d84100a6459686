#pragma once
// The world of a scene, stepped once per visual frame in named stages:
// collide (hand skin vs static and rigid geometry), hands (implicit FEM step
// with the contacts), reactions (contact forces onto ODE bodies), rigid (ODE
// step, with each hand's handle-space force model), reactions, rigid (ODE),
// collide (for the next step), publish (snapshot). Built from a SceneDesc, building only what the
// scene names. Contact is the implicit penalty baseline by default, or constraint
// contact (experimental, see WorldOptions::contact); rigid bodies a hand touches
// are solved implicitly with it either way.
#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <unordered_map>
#include <vector>

#include "hand_models/coupled_solver.hpp"
#include "hand_models/handle_linearization.hpp"
#include "hand_models/hand_model.hpp"
#include "hand_models/press_scenario.hpp"
#include "hand_models/procedural_hand.hpp"
#include "server/world/rigid_world.hpp"
#include "server/world/scene.hpp"

namespace hapticd {

struct WorldOptions {
  double contact_stiffness_n_m = 1000.0;  // per skin point in contact
  double contact_damping_ns_m = 1.0;
  // Per-step CHOLMOD: the handle-space model needs A_t^-1 on 2 x 6m + 1 columns
  // every step, cheap with a current factorization and costly with a lagged one.
  SolverKind solver = SolverKind::schur_cholmod;
  DriveParams drive;  // how each handle is pulled toward its target (zero: the hand is let go)
  bool hand_contacts = true;  // false: hands pass through everything (a cost baseline for benches)
  // False: hands are weightless (their inertia stays), as the server runs them, so
  // a device in free space feels no virtual hand weight; objects keep gravity.
  bool hand_gravity = true;
  // Hand contact model. Penalty by default for now: constraint contacts (PGS on the
  // step's Delassus operator, speculative contacts within 2 mm) hold a resting hand
  // without penetration, but every skin point near a surface is a contact and the
  // step slows to ~150 ms until skin points are clustered. Unset: follow the scene.
  std::optional<ContactModel> contact = ContactModel::penalty;
  // Constraint contacts keep the deepest skin point per object and cell of this size.
  double contact_cluster_m = 0.01;
};

struct WorldHand {
  std::string name;
  ProceduralHand shape;  // mesh, skeleton and the skin used for contact
  std::unique_ptr<HandModel> model;
  HandState state;
  std::unique_ptr<CoupledSolver> solver;
  double friction = 0.5;
};

struct ContactRecord {
  int hand = -1, object = -1;
  Eigen::Vector3d p_W = Eigen::Vector3d::Zero(), n_W = Eigen::Vector3d::Zero(), f_W = Eigen::Vector3d::Zero();
  double depth_m = 0;
};

struct WorldTimings {
  double collide_ms = 0, hands_ms = 0, contact_ms = 0, rigid_ms = 0, linearize_ms = 0, total_ms = 0;
};

struct WorldSnapshot {
  long step = 0;
  double t_s = 0;
  std::vector<std::vector<HandleState>> handles;  // per hand, per handle
  // Per hand: the time-implicit model of the coupling wrench on its handles,
  // F*(x, v) = F0 + K (x - x0) + D (v - v0) (all handles at once), from the last
  // step's system and anchored at its end state; empty before the first step.
  std::vector<HandleLinearization> linear_models;
  std::vector<bool> linear_model_valid;
  std::vector<RigidBodyState> bodies;             // per RigidWorld object
  std::vector<ContactRecord> contacts;
  double max_penetration_m = 0;
  long resets = 0;
  WorldTimings timings;
};

class World {
 public:
  // Throws std::runtime_error (or std::invalid_argument) naming the scene
  // element it cannot build.
  explicit World(const SceneDesc& scene, const WorldOptions& options = {});

  void step();

  int num_hands() const { return static_cast<int>(hands_.size()); }
  WorldHand& hand(int i) { return *hands_[i]; }
  const WorldHand& hand(int i) const { return *hands_[i]; }
  int find_hand(const std::string& name) const;
  // Null when the scene has no static or rigid object.
  RigidWorld* rigid() { return rigid_.get(); }
  const WorldSnapshot& snapshot() const { return snapshot_; }
  double dt() const { return dt_; }

 private:
  void collide(int h);
  void apply_reactions();
  void publish();

  double dt_;
  Eigen::Vector3d gravity_m_s2_;
  bool constraint_contact_ = true;
  long steps_ = 0;
  WorldOptions options_;
  std::vector<std::unique_ptr<WorldHand>> hands_;
  std::unique_ptr<RigidWorld> rigid_;
  std::vector<std::vector<Eigen::Vector3d>> contact_points_;  // per hand, per contact: world point
  // Constraint contacts: per hand, each contact's cluster cell, and the impulse
  // (N s) each cell's contact had in the last step, the next step's first guess.
  std::vector<std::vector<std::uint64_t>> contact_keys_;
  std::vector<std::unordered_map<std::uint64_t, Eigen::Vector3d>> warm_impulse_;
  // Per hand, per skin vertex: the object and normal of its last contact. A point
  // keeps the face it entered through while inside (no tunnelling through thin boxes).
  struct LastContact {
    int object = -1;
    Eigen::Vector3d n_W = Eigen::Vector3d::Zero();
  };
  std::vector<std::vector<LastContact>> last_contact_;
  WorldSnapshot snapshot_;
};

}  // namespace hapticd
