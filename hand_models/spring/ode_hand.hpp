#pragma once
// A hand made of ODE bodies (the rigid hands of seeds 001 and 002): the world's RigidWorld steps its
// bodies with the objects, in one ODE world, so they touch through ODE's contacts. It has no flesh
// (Hand::flesh() is null); the world calls these around its ODE steps instead.
#include <ode/ode.h>

#include <vector>

#include "hand_models/hand.hpp"

namespace hapticd::hand {

// A contact of an OdeHand's geom with an object, as ODE found it in the last ODE step.
struct OdeHandContact {
  int handle = 0;  // the handle of the touching geom's part (geom_handle)
  Eigen::Vector3d p_W = Eigen::Vector3d::Zero();
  Eigen::Vector3d n_W = Eigen::Vector3d::UnitZ();  // out of the object, toward the hand
  double depth_m = 0;
  double mu = 0.5;  // the pair's Coulomb coefficient in that step
};

class OdeHand : public Hand {
 public:
  // After the world's ODE steps: this hand's contacts in the last of them (the rows its model
  // carries into the haptic tick).
  virtual void set_contacts(const std::vector<OdeHandContact>& contacts) = 0;
  // Before each ODE step of length h: the forces that drive the hand toward its targets.
  virtual void before_ode_step(double h) = 0;
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
  // The handle whose part of the hand geom i is (a device frame's contact flag); skin point j of an
  // OdeHand is on handle j, where the world records the geom's contacts.
  virtual int geom_handle(int i) const = 0;
};

}  // namespace hapticd::hand
