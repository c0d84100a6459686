#pragma once
// The world of a scene, stepped once per visual frame in named stages: hands
// (implicit FEM step with the contacts found at the end of the last step, and
// each hand's handle-space force model), deformables (the deformable objects'
// implicit FEM steps, with the hands' contact reactions), reactions (contact
// impulses onto ODE bodies), rigid (ODE step), collide (hand skin and deformable
// surfaces vs static and rigid geometry, hand skin vs deformable objects and
// the other hands' flesh, for the next step), publish (snapshot). Built from a
// SceneDesc, building only what the scene names. Contact is the implicit
// constraint contact by default, or the penalty baseline (see WorldOptions::contact);
// rigid bodies a hand or a deformable object touches are solved implicitly
// with it either way.
#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <unordered_map>
#include <vector>

#include "hand_models/coupled_solver.hpp"
#include "hand_models/flesh.hpp"
#include "hand_models/hand.hpp"
#include "hand_models/hand_model.hpp"
#include "hand_models/handle_linearization.hpp"
#include "server/world/deformable_object.hpp"
#include "server/world/rigid_world.hpp"
#include "server/world/scene.hpp"

namespace hapticd::world {

struct WorldOptions {
  double contact_stiffness_n_m = 1000.0;  // per skin point in contact
  double contact_damping_ns_m = 1.0;
  // Per-step CHOLMOD: the handle-space model needs A_t^-1 on 2 x 6m + 1 columns
  // every step, cheap with a current factorization and costly with a lagged one.
  hand::SolverKind solver = hand::SolverKind::schur_cholmod;
  hand::DriveParams drive;    // how each handle is pulled toward its target (zero: the hand is let go)
  bool hand_contacts = true;  // false: hands pass through everything (a cost baseline for benches)
  // False: hands pass through each other, still touching everything else (a
  // cost baseline). Only scenes with two hands or more build hand-hand contact.
  bool hand_hand_contacts = true;
  // False: hands are weightless (their inertia stays), as the server runs them, so
  // a device in free space feels no virtual hand weight; objects keep gravity.
  bool hand_gravity = true;
  // The mass (flesh and handles: the density) of a hand driven by its palm alone (a stylus's) as a
  // share of its material's. A served one is light (haptic::kServedPalmHandMassScale): its device
  // renders the contacts and the flesh's give, not the avatar's mass, which the user's own hand
  // already has. Hands with finger handles (gloves) keep their material's mass.
  double palm_hand_mass_scale = 1.0;
  // False: no handle-space model in the snapshot (a caller that builds the model
  // of the coming step itself, as the server's visual loop does, skips the cost).
  bool linearize = true;
  // A stylus-driven spring hand's model takes the hand's step as one body (SpringHandConfig::
  // body_step_model); off: the springs' reaction, the hand held (the default).
  bool spring_body_step_model = false;
  // Hand contact model; unset: the scene's (constraint unless the scene says "penalty"). Constraint
  // contacts (PGS on the step's Delassus operator, speculative contacts within 2 mm, clustered rows
  // with reserves, the rows the haptic tick makes and breaks) penetrate far less; penalty stays as the
  // measured baseline (haptic-bench world and contact).
  std::optional<ContactModel> contact;
  // Constraint contacts keep the deepest skin point per object and cell of this size.
  double contact_cluster_m = 0.01;
  // The cell's other points stay in reserve and become rows of a step that
  // would carry them deeper than kReserveDepth_m (false: a baseline for tests).
  bool contact_reserves = true;
  // A rigid body beyond these (or non-finite) has diverged: the rigid stage resets it (RigidWorld::step).
  BodyBounds body_bounds;
};

// One contact of a point of flesh: a hand's skin point (hand >= 0) or a
// deformable object's surface point (deformable >= 0), against a RigidWorld
// object (object >= 0) or, for hand points, a deformable object
// (other_deformable >= 0) or another hand's flesh (other_hand >= 0). f_W is the
// force on the point's body, N; n_W points out of the other side. A hand's
// contact with another hand's flesh is at its skin point, or at a point of its
// own flesh where the other hand's skin point is (point -1); the other hand
// has the same pair the other way round (World::collide_with_hands).
struct ContactRecord {
  int hand = -1, object = -1;
  int point = -1;  // the body's contact point: a hand's skin vertex, a deformable object's surface point
  Eigen::Vector3d p_W = Eigen::Vector3d::Zero(), n_W = Eigen::Vector3d::Zero(), f_W = Eigen::Vector3d::Zero();
  double depth_m = 0;
  int deformable = -1, other_deformable = -1;
  int other_hand = -1;
};

struct WorldTimings {
  // deformable_ms: the deformable objects' implicit steps (their contact solves
  // included); collide_ms includes rebuilding their point-location grids.
  double collide_ms = 0, hands_ms = 0, contact_ms = 0, rigid_ms = 0, linearize_ms = 0, deformable_ms = 0, total_ms = 0;
};

// A deformable object's shape at the end of the last step (world frame, m);
// its surface triangles are constant: World::deformable(i).body.surface.triangles.
struct DeformableSnapshot {
  std::vector<Eigen::Vector3d> surface_W;  // surface vertices
  std::vector<Eigen::Vector3d> nodes_W;    // tet nodes
};

struct WorldSnapshot {
  long step = 0;
  double t_s = 0;
  std::vector<std::vector<hand::HandleState>> handles;  // per hand, per handle
  // Per hand: the time-implicit model of the coupling wrench on its handles,
  // F*(x, v) = F0 + K (x - x0) + D (v - v0) (all handles at once), from the last
  // step's system and anchored at its end state; empty before the first step.
  std::vector<hand::HandleLinearization> linear_models;
  std::vector<bool> linear_model_valid;
  std::vector<RigidBodyState> bodies;           // per RigidWorld object
  std::vector<DeformableSnapshot> deformables;  // per deformable object
  // The contacts the last step solved, with their forces and their depths at
  // the start of the step (before the first step: those found for it, no force).
  std::vector<ContactRecord> contacts;
  double max_penetration_m = 0;
  long resets = 0;       // of hands and deformable objects (HandState::resets), summed
  long body_resets = 0;  // of rigid bodies that diverged (RigidWorld::resets)
  WorldTimings timings;
};

class World {
 public:
  // Throws std::runtime_error (or std::invalid_argument) naming the scene
  // element it cannot build.
  explicit World(const SceneDesc& scene, const WorldOptions& options = {});

  // One step of dt_s seconds (0: the scene's dt). A visual loop that falls
  // behind its rate passes the wall-clock time since its last step, so the
  // world keeps pace with the proxies that drive it.
  void step(double dt_s = 0);

  int num_hands() const { return static_cast<int>(hands_.size()); }
  // Hand i as the scene's "model" built it (hand_factory.hpp); the world reaches it only through Hand.
  hand::Hand& hand(int i) { return *hands_[i].model; }
  const hand::Hand& hand(int i) const { return *hands_[i].model; }
  const std::string& hand_name(int i) const { return hands_[i].name; }
  int find_hand(const std::string& name) const;
  // Per handle of hand i, at the last collision: the nearest static or rigid surfaces its part of the
  // skin could reach that are not among its contacts, measured up to 10 cm, at most kClearancePlanes
  // (hand::ClearancePlane, nearest first in each direction): the haptic tick carries the handle no
  // farther before the next step finds them. Deformable objects and other hands are not measured.
  const std::vector<std::vector<hand::ClearancePlane>>& clearance(int i) const { return hands_[i].clearance; }
  // Where a point lies in hand i's deformed flesh and how deep inside its skin: built for hand-hand
  // contact (a scene with two hands or more) and for rigid meshes' vertices and deformable objects'
  // surface points (a scene with either), hand contacts on; null otherwise.
  const DeformedMeshQuery* hand_query(int i) const { return hands_[i].query.get(); }
  // The other hands' contact forces on hand i's flesh nodes over the last step, N, 3n (with its
  // query only, else empty).
  const Eigen::VectorXd& hand_contact_forces(int i) const { return hands_[i].f_hands_W; }
  int num_deformables() const { return static_cast<int>(deformables_.size()); }
  DeformableObject& deformable(int i) { return *deformables_[i]; }
  const DeformableObject& deformable(int i) const { return *deformables_[i]; }
  int find_deformable(const std::string& name) const;
  // Null when the scene has no static or rigid object.
  RigidWorld* rigid() { return rigid_.get(); }
  const WorldSnapshot& snapshot() const { return snapshot_; }
  double dt() const { return dt_; }

 private:
  // A point of a hand that touches a deformable object or another hand: where in that body.
  struct DeformableTouch {
    int object = -1;  // index of the deformable object, -1: the contact is with a RigidWorld object
    int tet = 0;      // the tet and weights where the contact's reaction goes
    Eigen::Vector4d bary = Eigen::Vector4d::Zero();
    // Hand-hand: the other hand, -1 if none. `reversed`: the skin point is the
    // other hand's (SoftBody::point_of is its skin vertex) and the contact sits
    // in this hand's flesh; else this hand's skin point in the other's flesh.
    int hand = -1;
    bool reversed = false;
  };
  struct LastContact {
    int object = -1;
    Eigen::Vector3d n_W = Eigen::Vector3d::Zero();
  };
  // What collision needs of a body of flesh (a hand, or a deformable object),
  // and what it keeps of its contacts between steps.
  struct SoftBody {
    hand::Flesh flesh;               // its tets, state and colliding points (the skin or surface vertices)
    int hand = -1, deformable = -1;  // which body it is
    // Per contact of flesh.state->contacts: world point, and for hands the deformable object or other hand touched.
    std::vector<Eigen::Vector3d> points;
    std::vector<DeformableTouch> touches;
    // Constraint contacts: each contact's cluster cell, and the impulse (N s)
    // each cell's contact had in the last step, the next step's first guess.
    std::vector<std::uint64_t> keys;
    std::vector<int> point_of;  // the point each contact is at
    // Per reserve contact of flesh.state->reserve_contacts: its point and world position.
    std::vector<int> reserve_point;
    std::vector<Eigen::Vector3d> reserve_p_W;
    std::unordered_map<std::uint64_t, Eigen::Vector3d> warm_impulse;
    std::unordered_map<std::uint64_t, int> kept_point;  // per cell, the point its contact was at last step
    // Per point: the object and normal of its last contact. A point keeps the
    // face it entered through while inside (no tunnelling through thin boxes).
    std::vector<LastContact> last;
  };

  // What the world keeps of a hand besides the hand itself.
  struct HandSlot {
    std::string name;
    std::unique_ptr<hand::Hand> model;
    std::unique_ptr<DeformedMeshQuery> query;  // hand_query()
    Eigen::AlignedBox3d skin_bounds;           // of the deformed skin, at the last collision
    bool query_current = false;                // query rebuilt for the last collision (another hand or a mesh near)
    Eigen::VectorXd f_hands_W;                 // hand_contact_forces()
    std::vector<std::vector<hand::ClearancePlane>> clearance;  // clearance()
  };

  void collide_all();
  void collide(SoftBody& body);
  int add_rigid_proxy(hand::HandState& state, int deformable);
  void collide_with_deformables(SoftBody& body, std::unordered_map<std::uint64_t, int>& cluster);
  void find_hand_hits();
  void collide_with_hands(SoftBody& body, std::unordered_map<std::uint64_t, int>& cluster);
  // Vertices of rigid meshes inside the hand's flesh (its query): a thin part (an ear) between the
  // skin points, which only the skin points would not find.
  void collide_mesh_vertices(SoftBody& body, std::vector<int>& body_of_object,
                             std::unordered_map<std::uint64_t, int>& cluster);
  // A point of another body found in a hand's flesh (`pen`, the hand's query): a contact of the flesh
  // where it lies, pushed along the reversed skin normal, the other side moving at v_other_W.
  hand::PointContact flesh_contact(const MeshPenetration& pen, const Eigen::Vector3d& v_other_W, double hand_friction,
                                   double other_friction) const;
  // Rigid object g as a body of the soft body's implicit step (joined once, with its gravity):
  // its index in state.bodies, -1 for static geometry.
  int implicit_body(hand::HandState& state, std::vector<int>& body_of_object, int g);
  // Rigid mesh g's box meets these skin bounds, grown by the speculative margin.
  bool mesh_overlaps(int g, const Eigen::AlignedBox3d& skin_bounds) const;
  // Hand-hand: before hand h steps, the constraint impulses of the hands
  // stepping before it, or its penalty contacts' forces from their far end's
  // motion (over a step of dt); after, what the other hands did to it.
  void take_hand_reactions(int h);
  void anchor_hand_contacts(int h, double dt);
  void sum_hand_forces(int h);
  void remember_impulses(SoftBody& body);
  // Adds a found contact to the body, clustered per other body and cell for constraint contacts.
  void add_contact(SoftBody& body, const hand::PointContact& c, int point, const Eigen::Vector3d& p_W, int other_key,
                   const DeformableTouch& touch, std::unordered_map<std::uint64_t, int>& cluster);
  void step_deformables();
  void apply_reactions();
  void place_solved_bodies();
  // The bodies the soft bodies solved this step: where they started, their start centre of mass and
  // their solved end-of-step velocity (all soft bodies' changes summed).
  struct SolvedBody {
    int object = -1;
    RigidBodyState start;
    Eigen::Vector3d com_W, v_W, w_W;
  };
  std::vector<SolvedBody> solved_bodies_;
  void record_contacts();
  void publish();

  double dt_;
  double step_dt_ = 0, t_s_ = 0;  // step_dt_: the last step's length, which collide_all() reaches over
  // A step this many times longer than the last collides again first (step()).
  static constexpr double kLongerStepRecollides = 1.25;
  Eigen::Vector3d gravity_m_s2_;
  bool constraint_contact_ = true;
  bool hand_hand_ = false;  // hand-hand contact built (HandSlot::query)
  long steps_ = 0;
  WorldOptions options_;
  // Before the hands: a hand of ODE bodies (hand::OdeHand) lives in the rigid world's ODE world and
  // must be destroyed first.
  std::unique_ptr<RigidWorld> rigid_;
  std::vector<HandSlot> hands_;
  std::vector<std::unique_ptr<DeformableObject>> deformables_;
  std::vector<SoftBody> soft_;  // the hands with flesh (hand order), then the deformable objects
  std::vector<int> hand_soft_;  // per hand, its body in soft_; -1: a hand of ODE bodies (no flesh)
  int flesh_hands_ = 0;
  SoftBody& deformable_soft(int d) { return soft_[flesh_hands_ + d]; }
  // The hands made of ODE bodies, stepped by the rigid world: their contacts and models after its step.
  void finish_ode_hands();
  std::vector<RigidWorld::HandContact> ode_hand_contacts_;
  std::vector<hand::PointContact> mirrored_;  // workspace: hand contacts seen from a deformable object
  // A hand's skin vertex in another hand's flesh, at the last collision.
  struct HandHit {
    int skin = -1, flesh = -1, vertex = -1;
    Eigen::Vector3d p_W = Eigen::Vector3d::Zero();
    MeshPenetration pen;
  };
  std::vector<HandHit> hand_hits_;
  WorldSnapshot snapshot_;
};

}  // namespace hapticd::world
