#pragma once
// A hand made of ODE bodies (the rigid hands of seeds 001 and 002): the world's RigidWorld steps its
// bodies with the objects, in one ODE world, so they touch through ODE's contacts. It has no flesh
// (Hand::flesh() is null); the world calls these around its ODE steps instead.
#include <ode/ode.h>

#include <vector>

#include "hand_models/hand.hpp"
#include "hand_models/hand_model.hpp"
#include "hand_models/skeleton/hand_skeleton.hpp"

namespace hapticd::hand {

// What a hand that finds its own contacts (the contact-point hand of seed 001, whose phalanges do not
// collide through ODE) asks of the world's objects, indexed as the world's (RigidWorld) are.
class RigidObjects {
 public:
  virtual ~RigidObjects() = default;
  virtual int object_count() const = 0;
  // Point p_W against object i: depth > 0 inside, the unit normal out of the object; with margin_m > 0
  // also points up to that far outside (depth < 0: a gap). p + depth n is then on the surface. False
  // when farther.
  virtual bool surface_near(int i, const Eigen::Vector3d& p_W, double margin_m, double& depth_m,
                            Eigen::Vector3d& n_W) const = 0;
  // The first point where the segment from -> to enters object i's surface, and the normal there.
  virtual bool ray_hit(int i, const Eigen::Vector3d& from_W, const Eigen::Vector3d& to_W, Eigen::Vector3d& hit_W,
                       Eigen::Vector3d& n_W) const = 0;
  // The object's frame in the world (its geometry moves with it).
  virtual Eigen::Isometry3d object_pose(int i) const = 0;
  // A rigid body the world moves (false: static geometry, which nothing moves).
  virtual bool object_dynamic(int i) const = 0;
  // Mass, world inertia, centre of mass and velocities of a dynamic object.
  virtual ContactBody object_body(int i) const = 0;
  // Adds a force at the centre of mass and a torque to a dynamic object for the coming ODE step.
  virtual void add_object_wrench(int i, const Eigen::Vector3d& f_W, const Eigen::Vector3d& torque_W) = 0;
  // The object's Coulomb coefficients: sliding and sticking.
  virtual double object_friction(int i) const = 0;
  virtual double object_friction_static(int i) const = 0;
};

// A contact of an OdeHand's geom with an object, as ODE found it in the last ODE step.
struct OdeHandContact {
  int handle = 0;  // the handle of the touching geom's part (geom_handle)
  Eigen::Vector3d p_W = Eigen::Vector3d::Zero();
  Eigen::Vector3d n_W = Eigen::Vector3d::UnitZ();  // out of the object, toward the hand
  double depth_m = 0;
  double mu = 0.5;  // the pair's Coulomb coefficient in that step
  int geom = -1;    // the touching geom (OdeHand::geom's index)
};

// The handles of a rigid hand (seeds 001 and 002) are the tracked frames themselves, with no body of
// their own: the palm's, and for a glove each phalanx's segment frame.
namespace tracked_frames {
// A frame's haptic proxy: a 1 cm ball of `mass_kg` (light, so the device stays light in free space).
inline HandleInfo info(double mass_kg) {
  HandleInfo out;
  out.mass_kg = mass_kg;
  out.inertia_B = Eigen::Matrix3d::Identity() * 0.4 * mass_kg * 1e-4;
  return out;
}
// Frame j takes the target; false (the frame kept) for an index out of range or a non-finite target.
inline bool set(std::vector<HandleState>& frames, int j, const HandleTarget& target) {
  if (j < 0 || j >= static_cast<int>(frames.size()) || !target.p_W.allFinite() || !target.q_W.coeffs().allFinite() ||
      !target.v_W.allFinite() || !target.w_W.allFinite() || !(target.q_W.norm() > 0))
    return false;
  HandleState& h = frames[static_cast<std::size_t>(j)];
  h.p_WH = target.p_W;
  h.q_WH = target.q_W.normalized();
  h.v_WH = target.v_W;
  h.w_WH = target.w_W;
  return true;
}
// The phalanx frame j >= 1 of a glove of `frames` frames tracks: a 16-frame glove's every phalanx, a
// 6-frame glove's distal ones.
inline int phalanx(std::size_t frames, int j) { return frames == 1 + kHandFingers ? 3 * (j - 1) + 2 : j - 1; }
// The frames of a hand whose palm is at (p_W, q_W) in posture `pose`, at rest.
inline void place(std::vector<HandleState>& frames, const Eigen::Vector3d& p_W, const Eigen::Quaterniond& q_W,
                  const SkeletonPose& pose) {
  for (HandleState& h : frames) h = HandleState{};
  frames[0].p_WH = p_W;
  frames[0].q_WH = q_W;
  for (std::size_t j = 1; j < frames.size(); ++j) {
    const int i = phalanx(frames.size(), static_cast<int>(j));
    frames[j].p_WH = p_W + q_W * pose.centre[i];
    frames[j].q_WH = q_W * Eigen::Quaterniond(pose.R[i]);
  }
}
}  // namespace tracked_frames

class OdeHand : public Hand {
 public:
  // After the world's ODE steps: this hand's contacts in the last of them (the rows its model
  // carries into the haptic tick).
  virtual void set_contacts(const std::vector<OdeHandContact>& contacts) = 0;
  // Before each ODE step of length h: the forces that drive the hand toward its targets, and for a
  // hand that finds its own contacts, their forces on the objects.
  virtual void before_ode_step(double h, RigidObjects& objects) = 0;
  // A hand that finds its own contacts (no geoms): those of the last ODE step, appended, each on the
  // handle of its part, with the force on the hand (N) and the object's index.
  struct OwnContact {
    int handle = 0, object = -1;
    int geom = -1;  // the hand's touching geom (geom's index), -1 for a hand without geoms
    Eigen::Vector3d p_W = Eigen::Vector3d::Zero(), n_W = Eigen::Vector3d::UnitZ(), f_W = Eigen::Vector3d::Zero();
    double depth_m = 0, mu = 0;
  };
  virtual void own_contacts(std::vector<OwnContact>&) const {}
  // The longest ODE step its bodies take stably (the world's rigid step is cut to it).
  virtual double max_ode_step_s() const = 0;
  // After the world's ODE steps: a hand whose bodies went non-finite, too fast or too far from their
  // targets is placed back on them, at rest, and the reset counted.
  virtual void after_ode_steps() = 0;
  // Coulomb coefficients of its surface: sliding and sticking.
  virtual double friction() const = 0;
  virtual double friction_static() const = 0;
  // The geoms its bodies collide with (the world marks them as the hand's).
  virtual int num_geoms() const = 0;
  virtual dGeomID geom(int i) const = 0;
  // The handle whose part of the hand geom i is (a device frame's contact flag); the world records
  // the geom's contacts at the first skin point on that handle.
  virtual int geom_handle(int i) const = 0;
};

}  // namespace hapticd::hand
