#pragma once
// The contact-point hand of seed 001 (Hoell et al., section 3) behind the Hand interface (scene
// "model": "contact_point"): a kinematic hand of three capsules per finger and a box palm
// (section 3.2) that follows the tracked pose exactly, and whose shapes touch the world's objects
// only through contact points:
//  - detection (3.2): a shape without a contact takes one when a point of its surface comes within
//    ContactPointParams::threshold_m of an object (at most one contact per shape); its contact point
//    C is the closest point of the object's surface, or, for a shape that went deeper than the
//    threshold within one step (a fast hand, 3.5's continuous detection), the point where its
//    surface point entered the object on the way from its last pose;
//  - a contact area (3.2): `samples` hand points on the shape's surface around that point, each with
//    its own C on the object (fixed in the object's frame, so it moves with the object), spread
//    over a wider area on the thumb and the palm;
//  - forces (3.3, contact_point_law.hpp): gamma (C - p) per sample (none from a hand point farther
//    than the threshold outside the object: C's tangent plane stands for the surface only near it),
//    its normal part and its
//    tangential part inside the static friction cone or the kinetic force outside it; a sliding
//    sample's C moves along the surface toward the hand point (3.5: a step along the tangent plane
//    to where the spring's tangential force is the kinetic one, put back on the surface by a ray
//    from just outside it; a hit whose normal turns against the old one is an occluding part and
//    leaves C where it was), and the spring from there is the kinetic force;
//  - the objects take the opposite forces at their C (3.5: "applied via the physics engine"): per
//    ODE step, the springs on each body integrated implicitly with its mass (a 6x6 solve), so a
//    light object under a stiff contact stays stable at any step (the paper's PhysX step was
//    explicit; a 1 g ball under 1000 N/m would need 1 ms steps);
//  - the phalanges never collide through ODE (3.5: once in contact they are triggers).
// A contact whose hand points have all left the object by more than twice the threshold and its
// samples' spread ends.
//
// The device feels the sum of the hand's contact forces. The handle-space model the haptic loop
// renders is exact for this hand: each sample's eqs. 1-5 are a penalty row of the tick's
// complementarity problem (compliance 1 / (gamma h^2) on the row impulse, no impulse while the hand
// point is outside, the tangential spring clipped to the friction cone), with C held where the
// visual step left it (slid first where the world's next step would slide it); shapes within
// ContactPointParams::lookahead_m of an object with no contact yet carry one speculative row each
// (their closest point, the contact's whole gamma), so a press engages and a lift releases within
// the tick.
//
// Driven by a stylus (one handle, the palm; the fingers held at the skeleton's rest angles), by a
// glove's palm and 15 phalanx frames (16 handles, each shape on its frame) or by a glove's palm and 5
// distal phalanx frames (6 handles: each distal on its frame, the proximal and middle phalanges placed
// on the palm in the posture the frames give, joint_angles_from_distal, and pushing the palm's frame).
#include <array>
#include <vector>

#include "hand_models/contact_point/contact_point_law.hpp"
#include "hand_models/skeleton/hand_skeleton.hpp"
#include "hand_models/spring/ode_hand.hpp"

namespace hapticd::hand::contact_point {

struct ContactPointParams {
  // Eq. 1's gamma per contact (shape), shared by its samples, N/m (the paper gives none; a phalanx
  // pressed 1 mm in pushes with 1 N, the order of a fingertip pad's stiffness).
  double gamma_n_m = 1000.0;
  // A contact is made within this distance of an object's surface (section 3.2's threshold, 3.5's
  // "Default Contact Offset"); its samples push only within it.
  double threshold_m = 0.002;
  int samples = 8;  // per contact (section 5.2: 8 samples per contact point)
  // The radius of the area the samples cover: fingers, and thumb and palm (3.2: "sampled over a
  // wider area").
  double sample_radius_m = 0.003, wide_sample_radius_m = 0.006;
  // Shapes this close to an object without a contact carry a speculative row into the haptic tick.
  double lookahead_m = 0.015;
};

// At most this many samples per contact.
constexpr int kMaxContactSamples = 16;
// The palm and the 15 phalanges.
constexpr int kContactPointShapes = 1 + kHandPhalanges;

struct ContactPointHandConfig {
  ContactPointParams params;
  bool left = false;
  int handles = 1;
  double friction = 0.5, friction_static = 0.5;  // the hand's surface; a pair's is the geometric mean
  double handle_mass_kg = 0.001;                 // the haptic proxy of the tracked frame (it has no body)
  bool touches = true;                           // false: the hand passes through everything
};

class ContactPointHand : public OdeHand {
 public:
  using Vector6 = Eigen::Matrix<double, 6, 1>;
  using Matrix6 = Eigen::Matrix<double, 6, 6>;
  // The hand with its palm at (p_W, q_W). Throws std::invalid_argument for a handle count other than
  // 1, 6 or 16, or parameters out of range.
  ContactPointHand(const ContactPointHandConfig& config, const Eigen::Vector3d& p_W, const Eigen::Quaterniond& q_W);

  std::string_view model_name() const override { return "contact_point"; }
  bool left() const override { return config_.left; }
  int num_handles() const override { return static_cast<int>(handles_.size()); }
  HandleInfo handle_info(int j, int tracked_frames) const override;
  const std::vector<HandleState>& handles() const override { return handles_; }
  bool set_target(int j, const HandleTarget& target) override;
  void place(const Eigen::Vector3d& p_W, const Eigen::Quaterniond& q_W) override;
  void set_step_length(double dt_s) override { dt_s_ = dt_s; }
  void step(HandleLinearization*) override {}  // kinematic: the shapes are where the targets put them
  void recover(const Eigen::Vector3d& fallback_p_W, const Eigen::Quaterniond& fallback_q_W) override;
  long resets() const override { return resets_; }
  bool linearize_next_step(HandleLinearization& out, ContactLinearization contacts) override;
  Eigen::VectorXd coupling_wrench() const override;
  // Skin points: the palm's centre, each phalanx's centre and each fingertip.
  int num_skin_points() const override { return kContactPointShapes + kHandFingers; }
  Eigen::Vector3d skin_point(int i) const override;
  int skin_handle(int i) const override;

  void before_ode_step(double h, RigidObjects& objects) override;
  void set_contacts(const std::vector<OdeHandContact>&) override {}  // it finds its own
  void own_contacts(std::vector<OwnContact>& out) const override;
  double max_ode_step_s() const override { return 0; }  // implicit on the objects: no bound
  void after_ode_steps() override {}
  double friction() const override { return config_.friction; }
  double friction_static() const override { return config_.friction_static; }
  int num_geoms() const override { return 0; }
  dGeomID geom(int) const override { return nullptr; }
  int geom_handle(int) const override { return 0; }

  // A sample of a contact: a point of the hand (shape frame) and its contact point and normal on the
  // object (object frame), with its state in the last ODE step.
  struct Sample {
    Eigen::Vector3d p_S = Eigen::Vector3d::Zero(), C_O = Eigen::Vector3d::Zero(), n_O = Eigen::Vector3d::UnitZ();
    ContactState state = ContactState::separated;
  };
  struct Contact {
    int object = -1;  // -1: none
    int count = 0;
    std::array<Sample, kMaxContactSamples> samples;
    Eigen::Vector3d f_W = Eigen::Vector3d::Zero();  // the last ODE step's force on the hand
    Eigen::Vector3d p_W = Eigen::Vector3d::Zero();  // where it acted (the mean of its active C)
    Eigen::Vector3d n_W = Eigen::Vector3d::UnitZ();
    double depth_m = 0, mu_static = 0, mu_dynamic = 0;
  };
  const Contact& contact(int shape) const { return contacts_[shape]; }
  // Shape s (0 the palm, 1 + i phalanx i) in the world: its frame (the segment's: y along the bone).
  Eigen::Isometry3d shape_pose(int s) const;
  // The handle shape s moves with.
  int shape_handle(int s) const;
  // What object i took from the hand in the last ODE step: the force at its centre of mass and the
  // torque (the implicit springs' share of that step, as ODE was given it); zero for static geometry.
  Eigen::Matrix<double, 6, 1> applied_wrench(int object) const {
    return object >= 0 && object < static_cast<int>(applied_.size()) ? applied_[object] : Vector6::Zero();
  }
  // The point of shape s's surface nearest to p (shape frame in, shape frame out).
  Eigen::Vector3d project_to_surface(int s, const Eigen::Vector3d& p_S) const;

 private:
  // The deepest of shape s's probe points against every object within `margin_m`: its object
  // (-1: none), the point (shape frame), depth and normal.
  int probe(int s, const RigidObjects& objects, double margin_m, Eigen::Vector3d& p_S, double& depth_m,
            Eigen::Vector3d& n_W) const;
  // A new contact of shape s with `object` around probe point p_S (section 3.2).
  void make_contact(int s, int object, const Eigen::Vector3d& p_S, const Eigen::Vector3d& n_W,
                    const RigidObjects& objects);
  // Eqs. 1-5 for `sample` of contact `c` at hand point p_W as an ODE step applies them: a sample
  // outside its cone is first slid (section 3.5; `sample` is updated) and pushes from there.
  ContactForce slid_force(const Contact& c, Sample& sample, const Eigen::Isometry3d& T_O,
                          const Eigen::Vector3d& p_W) const;
  // Section 3.5's surface point update of a sliding sample.
  void slide(Sample& sample, double mu_dynamic, const Eigen::Isometry3d& T_O, const Eigen::Vector3d& p_W, int object,
             const RigidObjects& objects) const;
  // pose_ from the frames (a 6-frame glove).
  void update_posture();
  // Drops every contact (a reset).
  void clear_contacts();

  ContactPointHandConfig config_;
  std::vector<HandleState> handles_;
  std::vector<Vector6> device_v_;  // per handle: its device's velocity and angular velocity (HandleTarget)
  SkeletonPose rest_pose_;  // the stylus-driven hand's fingers
  // The posture the shapes not on a frame of their own take (a 6-frame glove's proximal and middle
  // phalanges): joint_angles_from_distal of the frames; the rest posture for a stylus.
  SkeletonPose pose_;
  HandJointAngles angles_ = rest_joint_angles();                 // pose_'s
  std::array<double, kHandPhalanges> half_length_{}, radius_{};  // the capsules' (cylinder half length)
  std::array<std::vector<Eigen::Vector3d>, kContactPointShapes> probes_S_;
  std::array<Contact, kContactPointShapes> contacts_;
  // The shapes' poses in the last ODE step (a sweep from there finds where a fast shape entered).
  std::array<Eigen::Isometry3d, kContactPointShapes> last_T_;
  bool has_last_ = false;
  // The world's objects as the last ODE step saw them (they outlive the hand).
  const RigidObjects* objects_ = nullptr;
  // Per object, in an ODE step: the samples' wrench on it about its centre of mass and their stiffness.
  std::vector<Vector6> wrench_, applied_;
  std::vector<Matrix6> stiffness_;
  double dt_s_ = 1.0 / 60.0;
  long resets_ = 0;
};

}  // namespace hapticd::hand::contact_point
