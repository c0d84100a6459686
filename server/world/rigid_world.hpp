#pragma once
// The rigid part of the world, owned by ODE (DESIGN.md section 3): bodies and
// static geometry of a scene, joints, rigid-rigid contact with Coulomb friction.
// Built only when the scene has a rigid object ("model only what a scene needs").
#include <ode/ode.h>

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <memory>
#include <string>
#include <vector>

#include "hand_models/hand_model.hpp"
#include "hand_models/spring/ode_hand.hpp"
#include "hand_models/spring/spring_hand_rig.hpp"
#include "server/world/mesh_sdf.hpp"
#include "server/world/scene.hpp"

namespace hapticd::world {

using hand::ensure_ode_for_this_thread;  // spring_hand_rig.hpp
using hand::ode_messages;                // spring_hand_rig.hpp

struct RigidBodyState {
  Eigen::Vector3d p_WO = Eigen::Vector3d::Zero();  // object frame origin (as in the scene), m
  Eigen::Quaterniond q_WO = Eigen::Quaterniond::Identity();
  Eigen::Vector3d v_WO = Eigen::Vector3d::Zero();  // velocity of the centre of mass, m/s
  Eigen::Vector3d w_W = Eigen::Vector3d::Zero();   // angular velocity, rad/s
};

// Beyond these bounds, or with any non-finite value, a rigid body has diverged
// (DESIGN.md section 5): RigidWorld::step resets it. With its mass and inertia
// fixed, the speeds bound its kinetic energy too (m v^2 / 2 + I_max w^2 / 2).
struct BodyBounds {
  double max_speed_m_s = 50.0;              // of the centre of mass; as a hand's (HandConfig::max_speed_m_s)
  double max_angular_speed_rad_s = 1000.0;  // a 1 cm ball rolling at 10 m/s
  double max_distance_m = 1000.0;           // of the centre of mass from the world origin
};

class RigidWorld : public hand::RigidObjects {
 public:
  // ODE's exact big-matrix step up to this many bodies, its iterative QuickStep beyond.
  static constexpr int kExactStepMaxBodies = 64;

  // Builds every static and rigid object and every joint of `scene`. Throws
  // std::runtime_error naming the object when a shape cannot be built.
  // With `dynamics_for_hands`, the dynamics world exists even without a rigid body (a scene whose
  // hand is made of ODE bodies).
  explicit RigidWorld(const SceneDesc& scene, bool dynamics_for_hands = false);
  ~RigidWorld();
  RigidWorld(const RigidWorld&) = delete;
  RigidWorld& operator=(const RigidWorld&) = delete;

  // Whether a dynamics world exists (the scene has a rigid body).
  bool has_dynamics() const { return world_ != nullptr; }
  // Stages: check (a body set to a state beyond its bounds since the last step
  // goes back to its last good pose), collide and integrate (ODE) in substeps of
  // at most kMaxSubstep_s that make up dt, check (a body the step carried beyond
  // its bounds goes back to its pose at the start of the step). A reset body is
  // at rest and counted (resets()); nothing non-finite leaves a step. Nothing
  // without dynamics.
  void step(double dt);
  // ODE's contacts hold a body on a face only while one step cannot carry it far
  // past it: the scenes' mesh bunny stepped alone at 67 ms (a visual loop slowed
  // to 15 Hz) fell through the 4 cm table top to the floor, and at 100 ms hopped
  // on it; at 1/60 s and 1/30 s it rests within 0.1 mm. No shorter: a body a hand
  // touches was solved with the hand over the whole step (its supports as rows),
  // and substeps at 30 Hz made the stylus press on the movable bunny's model miss
  // the world's step by 3.8 N RMS (Multirate tests; 0.23 N in one step).
  static constexpr double kMaxSubstep_s = 1.0 / 30.0;
  void set_bounds(const BodyBounds& bounds) { bounds_ = bounds; }
  const BodyBounds& bounds() const { return bounds_; }
  // Rigid bodies reset by step() so far.
  long resets() const { return resets_; }

  int num_objects() const { return static_cast<int>(objects_.size()); }
  // Index of the object called `name`, -1 if the world does not hold it.
  int find(const std::string& name) const;
  const std::string& name(int i) const { return objects_[i].name; }
  bool is_dynamic(int i) const { return objects_[i].body != nullptr; }
  bool is_mesh(int i) const { return !objects_[i].sdf.empty(); }
  // A mesh's vertices in its geom's frame (x, y, z after one another); empty for other objects.
  const std::vector<double>& mesh_vertices(int i) const { return objects_[i].vertices; }
  double mass_kg(int i) const;
  RigidBodyState state(int i) const;
  void set_state(int i, const RigidBodyState& s);
  // Changes body i's velocity (centre of mass, m/s) and angular velocity (rad/s) by these amounts now.
  void add_velocity(int i, const Eigen::Vector3d& dv_W, const Eigen::Vector3d& dw_W);
  // Body i's velocity was solved to its end-of-step value with the step's gravity in it (a hand
  // solved it implicitly with its supports) and handed over less one substep's gravity: the coming
  // step adds gravity to it in its first substep only.
  void hold_gravity_for_next_step(int i);
  // How many substeps step(dt) takes (1e-9: a step of kMaxSubstep_s, rounded, is one).
  static int substeps(double dt) { return std::max(1, static_cast<int>(std::ceil(dt / kMaxSubstep_s - 1e-9))); }
  // Mass, world inertia, centre of mass and velocity of rigid body i, for a hand
  // that solves its contacts with the body implicitly.
  hand::ContactBody contact_body(int i) const;

  // Velocity of the material point of object i at world point p (zero for static geometry).
  Eigen::Vector3d point_velocity(int i, const Eigen::Vector3d& p_W) const;
  double friction(int i) const { return objects_[i].friction; }
  // Penetration of world point p into object i: depth > 0 and the unit normal
  // out of the object; false when outside. Exact for planes, spheres, boxes,
  // capsules and cylinders; meshes use their signed distance grid (3 mm cells,
  // exact within 1.8 cm of the surface; deeper points keep a depth of 1.8 cm).
  // `entry_n_W`, when non-zero, is the normal the point had on entering a box:
  // the depth is then measured to that face while the point is inside.
  // `margin_m` > 0 also reports points up to that far outside (depth < 0: a gap).
  bool penetration(int i, const Eigen::Vector3d& p_W, double& depth_m, Eigen::Vector3d& n_W,
                   const Eigen::Vector3d& entry_n_W = Eigen::Vector3d::Zero(), double margin_m = 0) const;
  // A mesh's clearance: the distance from an outside point p_W to mesh i and the direction out of
  // it there, up to 10 cm. Within 1.65 cm the distance grid penetration() uses answers; beyond it a
  // coarser one (1.5 cm cells) gives a lower bound, its trilinear error (0.87 of a cell) taken off.
  // False for other shapes, inside the mesh, and farther. For clearance planes only, never a
  // contact: its gap is short of the surface by up to twice that error.
  bool far_clearance(int i, const Eigen::Vector3d& p_W, double& gap_m, Eigen::Vector3d& n_W) const;

  // Contacts of rigid body i with every other object (ODE's collision, the
  // same as its own step would find): normal out of the other object into body
  // i, depth >= 0, friction the pair's kinetic coefficient, `other` its index.
  struct BodyContact {
    int other = -1;
    Eigen::Vector3d p_W = Eigen::Vector3d::Zero(), n_W = Eigen::Vector3d::UnitZ();
    double depth_m = 0, friction = 0.5;
  };
  void contacts_of(int i, std::vector<BodyContact>& out) const;
  // A box's or a mesh's supports are its corners or vertices on static geometry, measured by
  // penetration() with gaps up to `margin_m` (speculative supports: depth < 0 is a gap the next step
  // may close but not cross), up to 16 per object spread over the patch, and ODE's contacts on other
  // bodies. ODE reports only what touches: the scenes' bunny rocking on its two feet at a 15 Hz step
  // had supports under one foot at a time, so a hand's step tipped it about that foot and the other
  // went into the table, by 10 degrees from one step to the next.
  // Other shapes: contacts_of, remembering what body i touched on static objects: when ODE
  // finds nothing (its trimesh collider loses a contact at exactly zero depth,
  // and a body balanced on one vertex would then have no support for a whole
  // step), the last contacts found move with the body instead, their depth
  // reduced by how far it has lifted, kept while within `margin_m` (speculative
  // supports: depth < 0 is a gap the next step may close but not cross) and
  // for kSupportMemorySteps steps of the world after ODE last found them.
  static constexpr long kSupportMemorySteps = 5;
  void supports_of(int i, std::vector<BodyContact>& out, double margin_m);
  // A box's corners or a mesh's vertices, world frame; false (and none) for other shapes.
  bool support_points(int i, std::vector<Eigen::Vector3d>& points_W) const;

  // --- Hands made of ODE bodies (hand::OdeHand), stepped with the objects: each ODE step of step()
  // is at most as long as every such hand's max_ode_step_s(), and the hands' before_ode_step() and
  // after_ode_steps() run around them. Their geoms touch objects through ODE's contacts (friction:
  // the pair's as for objects; no bounce, seed 002 section 4.6.2), not each other. The hand must be
  // built in ode_world() and space() and outlive nothing of this world.
  dWorldID ode_world() const { return world_; }
  // `id`: what the hand's contacts name it by (HandContact::hand).
  void add_hand(hand::OdeHand* hand, int id);
  // A hand's contacts in the last ODE step: the force on the hand (N) and the normal out of the
  // object, toward the hand.
  struct HandContact : hand::OdeHand::OwnContact {
    int hand = -1;
  };
  void hand_contacts(std::vector<HandContact>& out) const;

  // --- The objects as a hand that finds its own contacts sees them (hand::RigidObjects).
  int object_count() const override { return num_objects(); }
  bool surface_near(int i, const Eigen::Vector3d& p_W, double margin_m, double& depth_m,
                    Eigen::Vector3d& n_W) const override {
    return penetration(i, p_W, depth_m, n_W, Eigen::Vector3d::Zero(), margin_m);
  }
  // ODE's ray against the object's geom (the closest hit).
  bool ray_hit(int i, const Eigen::Vector3d& from_W, const Eigen::Vector3d& to_W, Eigen::Vector3d& hit_W,
               Eigen::Vector3d& n_W) const override;
  Eigen::Isometry3d object_pose(int i) const override;
  bool object_dynamic(int i) const override { return is_dynamic(i); }
  hand::ContactBody object_body(int i) const override { return contact_body(i); }
  void add_object_wrench(int i, const Eigen::Vector3d& f_W, const Eigen::Vector3d& torque_W) override;
  double object_friction(int i) const override { return friction(i); }
  double object_friction_static(int i) const override { return objects_[i].friction_static; }

  dSpaceID space() const { return space_; }
  dGeomID geom(int i) const { return objects_[i].geom; }
  // Object index of an ODE geom of this world, -1 for a foreign geom.
  int object_of(dGeomID g) const;
  int contacts_last_step() const { return contacts_last_step_; }

 private:
  struct Object {
    std::string name;
    dBodyID body = nullptr;  // null for static geometry
    dGeomID geom = nullptr;
    Eigen::Vector3d com_O = Eigen::Vector3d::Zero();  // centre of mass in the object frame
    double friction = 0.5, friction_static = 0.5, restitution = 0;
    dTriMeshDataID trimesh = nullptr;
    MeshSdf sdf, far_sdf;  // meshes only (far_clearance)
    std::vector<double> vertices;
    std::vector<dTriIndex> indices;
    bool gravity_held = false;  // hold_gravity_for_next_step()
  };
  static void near_callback(void* data, dGeomID a, dGeomID b);
  void collide(dGeomID a, dGeomID b);
  void collide_hand(dGeomID hand_geom, dGeomID object_geom, bool hand_first);
  // ODE's contact with friction between two bodies (either may be null): the sliding or sticking
  // coefficient by their relative speed there, the first friction direction along the slide.
  static dContact friction_contact(const dContactGeom& geom, dBodyID b1, dBodyID b2, double mu_sliding,
                                   double mu_sticking);
  bool within_bounds(const RigidBodyState& s) const;
  // Resets every body beyond its bounds to its last good pose, at rest; then remembers every pose as good.
  void check_bodies();

  dWorldID world_ = nullptr;
  dSpaceID space_ = nullptr;
  mutable dGeomID ray_ = nullptr;  // ray_hit's, in no space, made at its first use
  // OdeHands (add_hand), their geoms' data -1 - index; the last ODE step's contacts of theirs, with
  // the feedback ODE filled (reserved: the vector never moves while the joints point into it).
  std::vector<hand::OdeHand*> hands_;
  std::vector<int> hand_ids_;
  struct HandJoint {
    HandContact contact;
    bool hand_first = true;  // the hand's body is the joint's first
  };
  static constexpr int kMaxHandContacts = 1024;
  std::vector<HandJoint> hand_joints_;
  std::vector<dJointFeedback> hand_feedback_;
  dJointGroupID contacts_ = nullptr;
  std::vector<Object> objects_;
  std::vector<dJointID> joints_;
  double dt_ = 1.0 / 60.0;
  int contacts_last_step_ = 0;
  struct RememberedSupport {
    BodyContact contact;
    Eigen::Vector3d p_O;  // the contact point in the body's frame
  };
  struct Memory {
    long step = 0;  // steps_ when found
    std::vector<RememberedSupport> supports;
  };
  std::vector<Memory> remembered_;  // per object, for supports_of
  long steps_ = 0;
  BodyBounds bounds_;
  std::vector<RigidBodyState> last_good_;  // per object: its state at the end of the last check
  long resets_ = 0;
};

namespace detail {

// Penetration of point p_W into a primitive ODE geom (plane, sphere, box,
// capsule, cylinder): depth > 0 and the unit normal out of the geom; false when
// outside or for other geom classes.
bool point_penetration(dGeomID geom, const Eigen::Vector3d& p_W, double& depth_m, Eigen::Vector3d& n_W,
                       const Eigen::Vector3d& entry_n_W = Eigen::Vector3d::Zero(), double margin_m = 0);

}  // namespace detail

}  // namespace hapticd::world
