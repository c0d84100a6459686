#pragma once
// A deformable object of a scene (seed 004 section 7: the bunny, a 4000-triangle
// surface in 271 tets; the letters): the hand's co-rotational FEM body without
// handles (HandConfig::free_body, DESIGN.md section 3), its closed surface
// embedded in the tets for collision and display, and the query hands touch it
// through. Built only for scenes that name one.
#include <Eigen/Core>
#include <memory>
#include <string>

#include "hand_models/coupled_solver.hpp"
#include "hand_models/embedded_surface.hpp"
#include "hand_models/flesh.hpp"
#include "hand_models/hand_model.hpp"
#include "server/world/deformed_mesh_query.hpp"
#include "server/world/scene.hpp"

namespace hapticd::world {

struct DeformableObject {
  std::string name;
  // The rest shape, placed at the scene's initial pose (world frame): tet mesh,
  // closed surface and each surface vertex's tet and barycentric weights. A
  // tet_mesh without a surface file, and a box, use the mesh's own boundary,
  // subdivided so that surface points lie at most 5 mm apart.
  hand::EmbeddedBody body;
  std::unique_ptr<hand::HandModel> model;
  hand::HandState state;
  std::unique_ptr<hand::CoupledSolver> solver;
  double friction = 0.5;
  // The hands' contact forces on the nodes over the last step, N, 3n (the
  // reactions of their contacts, see World::step_deformables): with the node
  // velocities, the power the hands put into the object.
  Eigen::VectorXd f_hands_W;
  // Hand contact: where a point lies in the deformed mesh and how deep it is;
  // null when the scene has no hand to touch the object.
  std::unique_ptr<DeformedMeshQuery> query;
  Eigen::AlignedBox3d surface_bounds;  // of the deformed surface, at the last collision
  // Far from the object, where the query locates nothing (clearance planes): the rest surface's
  // coarse distance grid (far_clearance_sdf), and the rigid motion x ~ R X + t that best matches the
  // nodes' at the last collision, with the farthest any node is from where it puts it.
  MeshSdf far_sdf;
  struct RigidFit {
    Eigen::Matrix3d R = Eigen::Matrix3d::Identity();
    Eigen::Vector3d t = Eigen::Vector3d::Zero();
    double deviation_m = 0;  // infinite when the nodes are not finite
  } fit;
};

struct DeformableBuild {
  Eigen::Vector3d gravity_m_s2{0, 0, -9.81};
  double dt_s = 1.0 / 60.0;
  hand::SolverKind solver = hand::SolverKind::schur_cholmod;
  bool touched_by_hands = true;  // build the hand-contact query
};

// Loads and meshes `desc` (kind deformable): material (Young's modulus,
// Poisson ratio, Rayleigh damping) from the scene, mass from mass_kg or the
// density times the surface's enclosed volume (spread over the mesh, which
// overhangs an embedded surface), initial velocity from the scene. Throws
// std::runtime_error "object '<name>': ..." when a file cannot be read or the
// body cannot be built.
std::unique_ptr<DeformableObject> make_deformable_object(const ObjectDesc& desc, const DeformableBuild& build);

// Internals of the world's deformable stages.
namespace detail {

// Cells of the grid a deformable box of this size is meshed with (6 tets per cell).
std::array<int, 3> deformable_box_cells(const Eigen::Vector3d& size_m);

// The object as a body of flesh for the world's collision: its surface vertices are its points.
hand::Flesh flesh_of(DeformableObject& object);

// Surface vertex v of the object at its current node positions, world frame.
Eigen::Vector3d surface_point(const DeformableObject& object, int v);

// The object as one rigid body: its mass, centre of mass, inertia at its
// current shape, and the velocity and angular velocity that carry its momentum
// and angular momentum.
hand::ContactBody rigid_proxy(const DeformableObject& object);

// The rigid motion that best matches the object's current node positions to its rest shape: the
// rotation of the mass-weighted shape matching (polar factor of sum m (x - c)(X - C)^T) about the
// centres of mass, and the largest distance of a node from its image.
DeformableObject::RigidFit rigid_fit(const DeformableObject& object);

// A lower bound of the distance from p_W to the deformed surface, and the direction out of it: the rest
// surface's clearance (clearance() in mesh_sdf.hpp) at p carried back by the fit, less the fit's
// deviation. A point of the deformed surface is a convex combination of its tet's nodes, each within
// the deviation of its rigid image. False inside the surface, farther than the coarse grid reaches and
// where the bound is not positive.
bool far_clearance(const DeformableObject& object, const Eigen::Vector3d& p_W, double& gap_m, Eigen::Vector3d& n_W);

}  // namespace detail

}  // namespace hapticd::world
