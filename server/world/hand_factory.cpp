#include "server/world/hand_factory.hpp"

#include <stdexcept>
#include <string>

#include "hand_models/contact_point/contact_point_hand.hpp"
#include "hand_models/fem_hand.hpp"
#include "hand_models/procedural_handles.hpp"
#include "hand_models/spring/spring_hand.hpp"

namespace hapticd::world {
namespace {

int handle_count(HandleSet set) {
  switch (set) {
    case HandleSet::palm:
      return 1;
    case HandleSet::fingertips:
      return 6;
    case HandleSet::phalanges:
      return 16;
  }
  return 1;
}

// Seed 004's deformable hand: the procedural hand's flesh on its handles.
std::unique_ptr<hand::Hand> make_fem_hand(const HandDesc& d, const HandBuild& build) {
  auto h = std::make_unique<hand::FemHand>();
  hand::ProceduralHandOptions shape_options;
  shape_options.target_tets = d.resolution_tets;
  shape_options.left = d.side == HandSide::left;
  h->left_side = shape_options.left;
  // A hand driven by more than its palm (a glove) needs fingers that move on their own.
  shape_options.separate_fingers = d.handles != HandleSet::palm;
  h->shape = make_procedural_hand(shape_options);
  hand::HandConfig config;
  config.dt_s = build.dt_s;
  config.gravity_m_s2 = build.gravity_m_s2;
  config.material.youngs_modulus_pa = d.material.youngs_modulus_pa;
  config.material.poisson_ratio = d.material.poisson_ratio;
  config.material.density_kg_m3 = embedding_density(h->shape, d.material.density_kg_m3);
  if (d.handles == HandleSet::palm) config.material.density_kg_m3 *= build.palm_mass_scale;
  config.material.rayleigh_alpha_per_s = d.material.rayleigh_alpha_per_s;
  config.material.rayleigh_beta_s = d.material.rayleigh_beta_s;
  config.coupling.stiffness_n_m = d.coupling_stiffness_n_m;
  config.coupling.damping_ns_m = d.coupling_damping_ns_m;
  config.handles = procedural_handles(h->shape, handle_count(d.handles));
  // A glove hand's joints are soft flesh between its bones: bending a finger costs little work.
  config.element_stiffness = procedural_joint_stiffness(h->shape, handle_count(d.handles), hand::kGloveJointStiffness);
  config.drive = build.drive;
  h->friction = d.material.friction;
  h->model = std::make_unique<hand::HandModel>(h->shape.mesh, config);
  h->skin_handles = procedural_skin_handles(h->shape, handle_count(d.handles));
  h->state = make_rest_state(*h->model);
  // The hand frame's pose places the rest mesh: handle 0 goes where it sits in that frame.
  const Eigen::Vector3d p_handle = d.pose.p_W + d.pose.q_W * h->model->handles()[0].p_WH_rest;
  place_hand(*h->model, h->state, p_handle, d.pose.q_W, 0);
  // The element rotations start at the placement (the polar factors of the rigidly placed rest
  // shape). Started at the identity, a hand placed half a turn round (a left hand turned palm up to
  // face a right hand) has F = R, symmetric, which the polar decomposition keeps as a stretch: its
  // first step flung the flesh at 11 m/s.
  h->state.R.assign(h->state.R.size(), d.pose.q_W.normalized().toRotationMatrix());
  h->solver = make_solver(build.solver);
  return h;
}

// The hand `build` makes, its constructor's std::invalid_argument named after the scene's hand.
template <class Build>
std::unique_ptr<hand::Hand> named(const HandDesc& d, Build build) {
  try {
    return build();
  } catch (const std::invalid_argument& e) {
    throw std::runtime_error("hands." + d.name + ": " + e.what());
  }
}

// Seed 002's articulated spring hand, in the rigid world's ODE world.
std::unique_ptr<hand::Hand> make_spring_hand(const HandDesc& d, const HandBuild& build) {
  if (!build.ode_world || !build.ode_space)
    throw std::runtime_error("hands." + d.name + ": the spring hand needs the world's ODE world");
  hand::spring::SpringHandConfig config;
  config.left = d.side == HandSide::left;
  config.handles = handle_count(d.handles);
  config.friction = d.material.friction;
  config.friction_static = d.material.static_friction();
  config.gravity_m_s2 = build.gravity_m_s2;
  config.params.gravity = build.gravity_m_s2.squaredNorm() > 0;
  config.body_step_model = build.spring_body_step_model;
  return named(d, [&] {
    return std::make_unique<hand::spring::SpringHand>(build.ode_world, build.ode_space, config, d.pose.p_W, d.pose.q_W);
  });
}

// Seed 001's contact-point hand: kinematic, touching the rigid world's objects through its own
// contact points.
std::unique_ptr<hand::Hand> make_contact_point_hand(const HandDesc& d, const HandBuild& build) {
  hand::contact_point::ContactPointHandConfig config;
  config.left = d.side == HandSide::left;
  config.handles = handle_count(d.handles);
  config.friction = d.material.friction;
  config.friction_static = d.material.static_friction();
  config.touches = build.hand_contacts;
  return named(d,
               [&] { return std::make_unique<hand::contact_point::ContactPointHand>(config, d.pose.p_W, d.pose.q_W); });
}

}  // namespace

std::unique_ptr<hand::Hand> make_hand(const HandDesc& desc, const HandBuild& build) {
  switch (desc.model) {
    case HandModelKind::fem:
      return make_fem_hand(desc, build);
    case HandModelKind::spring:
      return make_spring_hand(desc, build);
    case HandModelKind::contact_point:
      return make_contact_point_hand(desc, build);
    case HandModelKind::soft_pad:
      break;
  }
  throw std::runtime_error("hands." + desc.name + ": model \"" + std::string(to_string(desc.model)) +
                           "\" is not built yet (only \"fem\", \"spring\" and \"contact_point\")");
}

}  // namespace hapticd::world
