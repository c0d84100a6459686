#include "hand_models/corotational_fem.hpp"

#include <Eigen/Dense>
#include <Eigen/SVD>
#include <cmath>
#include <stdexcept>
#include <string>

namespace hapticd::hand {
namespace {

Eigen::Matrix3d skew(const Eigen::Vector3d& a) {
  Eigen::Matrix3d m;
  m << 0, -a.z(), a.y(), a.z(), 0, -a.x(), -a.y(), a.x(), 0;
  return m;
}

Eigen::Vector3d axial(const Eigen::Matrix3d& w) { return {w(2, 1), w(0, 2), w(1, 0)}; }

void require(bool ok, const char* field, const std::string& why) {
  if (!ok) throw std::invalid_argument(std::string("material.") + field + ": " + why);
}

}  // namespace

void validate(const Material& m) {
  require(std::isfinite(m.youngs_modulus_pa) && m.youngs_modulus_pa > 0, "youngs_modulus_pa", "must be > 0");
  require(std::isfinite(m.poisson_ratio) && m.poisson_ratio > -1.0 && m.poisson_ratio < 0.5, "poisson_ratio",
          "must be in (-1, 0.5)");
  require(std::isfinite(m.density_kg_m3) && m.density_kg_m3 > 0, "density_kg_m3", "must be > 0");
  require(std::isfinite(m.rayleigh_alpha_per_s) && m.rayleigh_alpha_per_s >= 0, "rayleigh_alpha_per_s",
          "must be >= 0");
  require(std::isfinite(m.rayleigh_beta_s) && m.rayleigh_beta_s >= 0, "rayleigh_beta_s", "must be >= 0");
}

namespace {

// X^-T = cof(X) / det X, from the columns' cross products.
Eigen::Matrix3d inverse_transpose(const Eigen::Matrix3d& X, double det) {
  Eigen::Matrix3d C;
  C.col(0) = X.col(1).cross(X.col(2));
  C.col(1) = X.col(2).cross(X.col(0));
  C.col(2) = X.col(0).cross(X.col(1));
  return C / det;
}

// Orthogonal polar factor by Higham's scaled Newton iteration X <- (g X + X^-T / g) / 2,
// g = |det X|^(-1/3); converges quadratically for det F > 0 (to the same R as the SVD).
// Returns false if it did not converge in the iteration budget.
bool newton_polar(const Eigen::Matrix3d& F, Eigen::Matrix3d& R) {
  Eigen::Matrix3d X = F;
  for (int k = 0; k < 12; ++k) {
    const double det = X.col(0).dot(X.col(1).cross(X.col(2)));
    if (!(det > 0)) return false;
    const double g = std::cbrt(1.0 / det);
    const Eigen::Matrix3d next = 0.5 * (g * X + inverse_transpose(X, det) / g);
    const double change = (next - X).squaredNorm();
    X = next;
    if (change < 1e-28) {
      R = X;
      return true;
    }
  }
  return false;
}

// Below this volume ratio det F, the SVD path decides (flat and inverted elements).
constexpr double kNewtonMinDetF = 1e-2;

}  // namespace

Eigen::Matrix3d rotation_of(const Eigen::Matrix3d& F) {
  Eigen::JacobiSVD<Eigen::Matrix3d> svd(F, Eigen::ComputeFullU | Eigen::ComputeFullV);
  Eigen::Matrix3d U = svd.matrixU();
  const Eigen::Matrix3d& V = svd.matrixV();
  // Inverted or reflected: flip the axis of the smallest singular value so R stays in SO(3).
  if (U.determinant() * V.determinant() < 0) U.col(2) = -U.col(2);
  return U * V.transpose();
}

CorotationalFem::CorotationalFem(const TetMesh& mesh, const Material& material,
                                 const std::vector<double>& stiffness_scale)
    : num_nodes_(mesh.num_nodes()), material_(material), tets_(mesh.tets) {
  validate(material);
  const double E = material.youngs_modulus_pa, nu = material.poisson_ratio;
  lambda_ = E * nu / ((1 + nu) * (1 - 2 * nu));
  mu_ = E / (2 * (1 + nu));
  const size_t ne = tets_.size();
  if (!stiffness_scale.empty() && stiffness_scale.size() != ne)
    throw std::invalid_argument("element stiffness: must have one entry per tet (" + std::to_string(ne) +
                                "), got " + std::to_string(stiffness_scale.size()));
  for (double k : stiffness_scale)
    if (!(std::isfinite(k) && k > 0))
      throw std::invalid_argument("element stiffness: must be > 0 (a factor on the Young's modulus)");
  stiffness_ = stiffness_scale.empty() ? std::vector<double>(ne, 1.0) : stiffness_scale;
  Dm_inv_.resize(ne);
  grad_.resize(ne);
  volume_.resize(ne);
  Ke_.resize(ne);
  mass_ = Eigen::VectorXd::Zero(num_nodes_);
  for (size_t e = 0; e < ne; ++e) {
    const Tet& t = tets_[e];
    Eigen::Matrix3d Dm;
    for (int k = 0; k < 3; ++k) Dm.col(k) = mesh.X[t[k + 1]] - mesh.X[t[0]];
    volume_[e] = Dm.determinant() / 6.0;
    if (!(volume_[e] > 0)) throw MeshError("tet " + std::to_string(e) + " is not positively oriented");
    Dm_inv_[e] = Dm.inverse();
    // g_a for a = 1..3 are the rows of Dm^-1; g_0 = -(g_1 + g_2 + g_3).
    Eigen::Matrix<double, 3, 4> g;
    g.rightCols<3>() = Dm_inv_[e].transpose();
    g.col(0) = -g.rightCols<3>().rowwise().sum();
    grad_[e] = g;
    // Isotropic linear elasticity: K_ab = V (lambda g_a g_b^T + mu g_b g_a^T + mu (g_a . g_b) I).
    for (int a = 0; a < 4; ++a) {
      for (int b = 0; b < 4; ++b) {
        Ke_[e].block<3, 3>(3 * a, 3 * b) =
            stiffness_[e] * volume_[e] * (lambda_ * g.col(a) * g.col(b).transpose() + mu_ * g.col(b) * g.col(a).transpose() +
                          mu_ * g.col(a).dot(g.col(b)) * Eigen::Matrix3d::Identity());
      }
    }
    const double node_mass = material.density_kg_m3 * volume_[e] / 4.0;
    for (int k = 0; k < 4; ++k) mass_[t[k]] += node_mass;
  }
}

Eigen::Matrix3d CorotationalFem::deformation_gradient(int e, const Eigen::VectorXd& x) const {
  const Tet& t = tets_[e];
  Eigen::Matrix3d Ds;
  const Eigen::Vector3d x0 = x.segment<3>(3 * t[0]);
  for (int k = 0; k < 3; ++k) Ds.col(k) = x.segment<3>(3 * t[k + 1]) - x0;
  return Ds * Dm_inv_[e];
}

void CorotationalFem::compute_rotations(const Eigen::VectorXd& x, std::vector<Eigen::Matrix3d>& R) const {
  const bool warm = R.size() == tets_.size();
  if (!warm) R.assign(tets_.size(), Eigen::Matrix3d::Identity());
  for (size_t e = 0; e < tets_.size(); ++e) {
    const Eigen::Matrix3d F = deformation_gradient(static_cast<int>(e), x);
    // Warm start: the polar factor of R_prev^T F is near identity, so Newton takes 2-3 iterations.
    Eigen::Matrix3d Q;
    const Eigen::Matrix3d S = R[e].transpose() * F;
    // Already the polar factor (the same state assembled again): kept bit for bit,
    // so the same state gives the same A_t and its factorization can be reused.
    if (warm && (S - S.transpose()).cwiseAbs().maxCoeff() <= 1e-14 * S.cwiseAbs().maxCoeff() &&
        S.determinant() > kNewtonMinDetF)
      continue;
    if (F.determinant() > kNewtonMinDetF && newton_polar(S, Q)) {
      R[e] = R[e] * Q;
    } else {
      R[e] = rotation_of(F);
    }
  }
}

Eigen::Matrix3d CorotationalFem::stress(const Eigen::Matrix3d& strain) const {
  return lambda_ * strain.trace() * Eigen::Matrix3d::Identity() + 2 * mu_ * strain;
}

void CorotationalFem::add_elastic_forces(const Eigen::VectorXd& x, const std::vector<Eigen::Matrix3d>& R,
                                         Eigen::VectorXd& f) const {
  for (size_t e = 0; e < tets_.size(); ++e) {
    const Eigen::Matrix3d S = R[e].transpose() * deformation_gradient(static_cast<int>(e), x);
    const Eigen::Matrix3d strain = 0.5 * (S + S.transpose()) - Eigen::Matrix3d::Identity();
    // f_a = -V R sigma g_a, identical to -R K_e (R^T x - X) for linear tets.
    const Eigen::Matrix<double, 3, 4> fe = -stiffness_[e] * volume_[e] * (R[e] * stress(strain)) * grad_[e];
    for (int k = 0; k < 4; ++k) f.segment<3>(3 * tets_[e][k]) += fe.col(k);
  }
}

Eigen::Matrix3d CorotationalFem::warped_block(int e, int a, int b, const Eigen::Matrix3d& R) const {
  return R * Ke_[e].block<3, 3>(3 * a, 3 * b) * R.transpose();
}

void CorotationalFem::warped_blocks(int e, const Eigen::Matrix3d& R, double scale, Eigen::Matrix3d blocks[4][4]) const {
  const Eigen::Matrix<double, 3, 4> g = R * grad_[e];
  const Eigen::Matrix<double, 3, 4>& g0 = grad_[e];
  const double kV = scale * stiffness_[e] * volume_[e];
  const double s_lambda = kV * lambda_, s_mu = kV * mu_;
  for (int a = 0; a < 4; ++a) {
    for (int b = a; b < 4; ++b) {
      Eigen::Matrix3d B = s_lambda * g.col(a) * g.col(b).transpose() + s_mu * g.col(b) * g.col(a).transpose();
      B.diagonal().array() += s_mu * g0.col(a).dot(g0.col(b));
      blocks[a][b] = B;
      if (b != a) blocks[b][a] = B.transpose();
    }
  }
}

Vector12d CorotationalFem::element_force(int e, const Eigen::VectorXd& x) const {
  const Eigen::Matrix3d F = deformation_gradient(e, x);
  const Eigen::Matrix3d R = rotation_of(F);
  const Eigen::Matrix3d S = R.transpose() * F;
  const Eigen::Matrix3d strain = 0.5 * (S + S.transpose()) - Eigen::Matrix3d::Identity();
  const Eigen::Matrix<double, 3, 4> fe = -stiffness_[e] * volume_[e] * (R * stress(strain)) * grad_[e];
  return Eigen::Map<const Vector12d>(fe.data());
}

Matrix12d CorotationalFem::element_exact_tangent(int e, const Eigen::VectorXd& x) const {
  const Eigen::Matrix3d F = deformation_gradient(e, x);
  const Eigen::Matrix3d R = rotation_of(F);
  const Eigen::Matrix3d S = R.transpose() * F;
  const Eigen::Matrix3d strain = 0.5 * (S + S.transpose()) - Eigen::Matrix3d::Identity();
  const Eigen::Matrix3d sigma = stress(strain);
  const Eigen::Matrix3d G = S.trace() * Eigen::Matrix3d::Identity() - S;
  const Eigen::Matrix3d G_inv = G.inverse();
  Matrix12d K;
  for (int c = 0; c < 4; ++c) {
    for (int i = 0; i < 3; ++i) {
      // dF for a unit displacement of local node c along axis i.
      const Eigen::Matrix3d dF = Eigen::Vector3d::Unit(i) * grad_[e].col(c).transpose();
      const Eigen::Matrix3d RtdF = R.transpose() * dF;
      // dR = R [w]x with (tr S I - S) w = axial(R^T dF - dF^T R) (derivative of the polar rotation).
      const Eigen::Vector3d w = G_inv * axial(RtdF - RtdF.transpose());
      const Eigen::Matrix3d dS = RtdF - skew(w) * S;
      const Eigen::Matrix3d dstrain = 0.5 * (dS + dS.transpose());
      const Eigen::Matrix3d dP = R * skew(w) * sigma + R * stress(dstrain);
      const Eigen::Matrix<double, 3, 4> dfe = -stiffness_[e] * volume_[e] * dP * grad_[e];
      K.col(3 * c + i) = Eigen::Map<const Vector12d>(dfe.data());
    }
  }
  return K;
}

}  // namespace hapticd::hand
