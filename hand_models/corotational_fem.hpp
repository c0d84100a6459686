#pragma once
// Linear co-rotational FEM on linear tetrahedra (seed 004 section 4, after
// Mueller & Gross 2004): the constant element data of one deformable body and
// the per-step kernels (rotations, forces, warped stiffness).
#include <Eigen/Core>
#include <vector>

#include "hand_models/tet_mesh.hpp"

namespace hapticd::hand {

// Soft-tissue defaults (E, nu of skin and fat in the tens of kPa and ~0.45;
// density of the hand ~1070 kg/m^3); Rayleigh damping D = alpha M + beta K.
struct Material {
  double youngs_modulus_pa = 50e3;
  double poisson_ratio = 0.45;
  double density_kg_m3 = 1070.0;
  double rayleigh_alpha_per_s = 1.0;
  double rayleigh_beta_s = 0.005;
};

// Throws std::invalid_argument naming the first out-of-range field.
void validate(const Material& material);

using Matrix12d = Eigen::Matrix<double, 12, 12>;
using Vector12d = Eigen::Matrix<double, 12, 1>;

class CorotationalFem {
 public:
  // `stiffness_scale`: per element, its Young's modulus over the material's
  // (empty: all 1), e.g. a glove hand's soft joint flesh.
  CorotationalFem(const TetMesh& mesh, const Material& material, const std::vector<double>& stiffness_scale = {});

  int num_nodes() const { return num_nodes_; }
  int num_tets() const { return static_cast<int>(tets_.size()); }
  const std::vector<Tet>& tets() const { return tets_; }
  const Material& material() const { return material_; }
  // Lumped nodal masses (a quarter of each adjacent tet's mass), kg.
  const Eigen::VectorXd& lumped_mass() const { return mass_; }
  double rest_volume(int e) const { return volume_[e]; }
  double stiffness_scale(int e) const { return stiffness_[e]; }
  // Rest-state linear stiffness of element e (K_e = k V B^T C B, k its stiffness scale), N/m,
  // node-major 3x3 blocks.
  const Matrix12d& rest_stiffness(int e) const { return Ke_[e]; }

  // Deformation gradient F = Ds Dm^-1 of element e at positions x (3n vector).
  Eigen::Matrix3d deformation_gradient(int e, const Eigen::VectorXd& x) const;

  // Rotation of every element: polar decomposition of F, made a proper rotation
  // for inverted and flat elements (the sign of the smallest singular value is
  // flipped instead, Irving et al. 2004), so R is always in SO(3). R holds the
  // previous rotations on input when it has one per element (a warm start for
  // the Newton polar iteration; the result does not depend on it).
  void compute_rotations(const Eigen::VectorXd& x, std::vector<Eigen::Matrix3d>& R) const;

  // Adds the elastic forces f_a = -R K_e (R^T x - X) to f (3n), using the
  // stress form f_a = -k V R sigma(eps) g_a with eps = sym(R^T F) - I.
  void add_elastic_forces(const Eigen::VectorXd& x, const std::vector<Eigen::Matrix3d>& R,
                          Eigen::VectorXd& f) const;

  // Warped stiffness block R K_ab R^T of element e for local nodes a, b (the
  // positive semi-definite co-rotational stiffness; df/dx ~ -this).
  Eigen::Matrix3d warped_block(int e, int a, int b, const Eigen::Matrix3d& R) const;

  // All blocks R K_ab R^T of element e at once, from the rotated shape gradients
  // R g_a: K_ab = V (lambda g_a g_b^T + mu g_b g_a^T + mu (g_a . g_b) I) makes each
  // block two outer products (4x cheaper than two 3x3 products; same values).
  void warped_blocks(int e, const Eigen::Matrix3d& R, double scale, Eigen::Matrix3d blocks[4][4]) const;

  // Elastic force of one element as a 12-vector (for tests and references).
  Vector12d element_force(int e, const Eigen::VectorXd& x) const;
  // Exact derivative of element_force, including the derivative of the polar
  // rotation; used to check the warped stiffness against finite differences.
  Matrix12d element_exact_tangent(int e, const Eigen::VectorXd& x) const;

 private:
  Eigen::Matrix3d stress(const Eigen::Matrix3d& strain) const;

  int num_nodes_ = 0;
  Material material_;
  double lambda_ = 0, mu_ = 0;
  std::vector<Tet> tets_;
  std::vector<Eigen::Matrix3d> Dm_inv_;
  std::vector<Eigen::Matrix<double, 3, 4>> grad_;  // shape function gradients g_a (columns)
  std::vector<double> volume_;
  std::vector<double> stiffness_;  // per element: Young's modulus over the material's
  std::vector<Matrix12d> Ke_;
  Eigen::VectorXd mass_;
};

// Polar rotation of F that is always a proper rotation (see compute_rotations).
Eigen::Matrix3d rotation_of(const Eigen::Matrix3d& F);

}  // namespace hapticd::hand
