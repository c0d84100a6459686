#include "hand_models/hand_model.hpp"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <stdexcept>

#include "hand_models/contact_pgs.hpp"
#include "hand_models/contact_solve.hpp"
#include "hand_models/coupled_solver.hpp"
#include "hand_models/handle_linearization.hpp"

namespace hapticd::hand {
namespace {

using Clock = std::chrono::steady_clock;
double ms_since(Clock::time_point t0) {
  return std::chrono::duration<double, std::milli>(Clock::now() - t0).count();
}

void require(bool ok, const std::string& path, const std::string& why) {
  if (!ok) throw std::invalid_argument(path + ": " + why);
}

bool finite_nonneg(double x) { return std::isfinite(x) && x >= 0; }

// Value index of entry (row, col) in a compressed column-major matrix.
int find_entry(const Eigen::SparseMatrix<double>& A, int row, int col) {
  const int* begin = A.innerIndexPtr() + A.outerIndexPtr()[col];
  const int* end = A.innerIndexPtr() + A.outerIndexPtr()[col + 1];
  const int* it = std::lower_bound(begin, end, row);
  if (it == end || *it != row) throw std::logic_error("entry outside the tool pattern");
  return static_cast<int>(it - A.innerIndexPtr());
}

// Adds a 3x3 block whose top-left entry sits at value index `base` of column 3J.
void add_block(double* values, const AssemblyMap& map, int base, int J, const Eigen::Matrix3d& block) {
  const int offset = base - map.column_start[3 * J];
  for (int c = 0; c < 3; ++c) {
    double* col = values + map.column_start[3 * J + c] + offset;
    for (int r = 0; r < 3; ++r) col[r] += block(r, c);
  }
}

Matrix6d handle_mass_matrix(const RigidHandle& h, const HandleState& s) {
  const Eigen::Matrix3d R = s.q_WH.toRotationMatrix();
  Matrix6d M = Matrix6d::Zero();
  M.topLeftCorner<3, 3>() = h.mass_kg * Eigen::Matrix3d::Identity();
  M.bottomRightCorner<3, 3>() = R * h.inertia_B * R.transpose();
  return M;
}

// Velocity of the other body at a contact: the known one, or for an implicit body
// its current (or, with `next`, its just-solved) rigid velocity at the point.
Eigen::Vector3d other_velocity(const PointContact& c, const Tet& t, const HandState& s, bool next) {
  if (c.body < 0) return c.v_other_W;
  const ContactBody& b = s.bodies[c.body];
  Eigen::Vector3d v = b.v_W, w = b.w_W;
  if (next) v += b.dv_W, w += b.dw_W;
  return v + w.cross(embedded_value(t, c.bary, s.x) - b.p_com_W);
}

// The 3x3 block C = h D_c + h^2 K_c of a contact: what it adds to eq. 7 between
// the two points it joins (scaled by their weights), and its friction factor.
Eigen::Matrix3d contact_block(const PointContact& c, const Eigen::Vector3d& u_rel, double h) {
  const Eigen::Vector3d& n = c.n_W;
  const Eigen::Matrix3d nn = n * n.transpose(), T = Eigen::Matrix3d::Identity() - nn;
  const double c_t = c.friction * c.stiffness_n_m * c.depth_m / std::max((T * u_rel).norm(), PointContact::kStickSpeed_m_s);
  return h * (c.damping_ns_m * nn + c_t * T) + h * h * c.stiffness_n_m * nn;
}

// Penalty contact (PointContact): forces into f_t, stiffness and damping blocks into A_t.
void assemble_contact(const HandModel& model, const PointContact& c, HandState& s, double* values, double h) {
  const Tet& t = model.mesh().tets[c.tet];
  const AssemblyMap& map = model.assembly_map();
  const Eigen::Vector3d& n = c.n_W;
  const Eigen::Matrix3d nn = n * n.transpose();
  const Eigen::Vector3d u_rel = embedded_value(t, c.bary, s.v) - other_velocity(c, t, s, false);
  const Eigen::Matrix3d C = contact_block(c, u_rel, h);
  // Velocity-independent part (C / h minus the stiffness part is the damping D_c); an implicit body's motion enters through the
  // coupling blocks instead of as a known velocity.
  const Eigen::Vector3d v_known = c.body >= 0 ? Eigen::Vector3d::Zero() : c.v_other_W;
  const Eigen::Vector3d f = c.stiffness_n_m * c.depth_m * n + (C - h * h * c.stiffness_n_m * nn) / h * v_known;
  for (int a = 0; a < 4; ++a) {
    if (c.bary[a] == 0) continue;
    s.f_t.segment<3>(3 * t[a]) += c.bary[a] * f;
    for (int b = 0; b < 4; ++b)
      if (c.bary[b] != 0)
        add_block(values, map, map.element_block[c.tet][4 * a + b], t[b], c.bary[a] * c.bary[b] * C);
  }
}

// A contact with an implicit body: its blocks between the hand point and the
// body's 6 DOFs (column `col`), J_B = [I, -[rho]x] mapping body velocity to the point.
void assemble_body_contact(const HandModel& model, const PointContact& c, HandState& s, int col, double h,
                           std::vector<Eigen::Triplet<double>>& th, std::vector<Eigen::Triplet<double>>& ht) {
  const Tet& t = model.mesh().tets[c.tet];
  const ContactBody& B = s.bodies[c.body];
  const Eigen::Vector3d p = embedded_value(t, c.bary, s.x);
  Eigen::Matrix<double, 3, 6> J;
  J << Eigen::Matrix3d::Identity(), -skew(p - B.p_com_W);
  const Eigen::Vector3d u_rel = embedded_value(t, c.bary, s.v) - other_velocity(c, t, s, false);
  const Eigen::Matrix3d C = contact_block(c, u_rel, h);
  const Eigen::Vector3d f0 = c.stiffness_n_m * c.depth_m * c.n_W;
  s.system.A_h.block<6, 6>(col, col) += J.transpose() * C * J;
  s.system.b_h.segment<6>(col) -= h * J.transpose() * f0;  // the reaction of the elastic part
  for (int a = 0; a < 4; ++a) {
    if (c.bary[a] == 0) continue;
    const Eigen::Matrix<double, 3, 6> coupling = -c.bary[a] * C * J;
    for (int r = 0; r < 3; ++r)
      for (int k = 0; k < 6; ++k) {
        th.emplace_back(3 * t[a] + r, col + k, coupling(r, k));
        ht.emplace_back(col + k, 3 * t[a] + r, coupling(r, k));
      }
  }
}

}  // namespace

void validate(const HandConfig& c) {
  validate(c.material);
  require(std::isfinite(c.coupling.stiffness_n_m) && c.coupling.stiffness_n_m > 0, "coupling.stiffness_n_m",
          "must be > 0");
  require(finite_nonneg(c.coupling.damping_ns_m), "coupling.damping_ns_m", "must be >= 0");
  require(finite_nonneg(c.drive.stiffness_n_m), "drive.stiffness_n_m", "must be >= 0");
  require(finite_nonneg(c.drive.damping_ns_m), "drive.damping_ns_m", "must be >= 0");
  require(finite_nonneg(c.drive.rot_stiffness_nm_rad), "drive.rot_stiffness_nm_rad", "must be >= 0");
  require(finite_nonneg(c.drive.rot_damping_nms_rad), "drive.rot_damping_nms_rad", "must be >= 0");
  require(std::isfinite(c.floor.height_m), "floor.height_m", "must be finite");
  require(finite_nonneg(c.floor.stiffness_n_m), "floor.stiffness_n_m", "must be >= 0");
  require(finite_nonneg(c.floor.damping_ns_m), "floor.damping_ns_m", "must be >= 0");
  require(c.gravity_m_s2.allFinite(), "gravity_m_s2", "must be finite");
  require(std::isfinite(c.dt_s) && c.dt_s > 0 && c.dt_s <= 1.0, "dt_s", "must be in (0, 1] s");
  require(std::isfinite(c.max_speed_m_s) && c.max_speed_m_s > 0, "max_speed_m_s", "must be > 0");
  if (c.free_body)
    require(c.handles.empty(), "handles", "a free body has no handles");
  else
    require(!c.handles.empty(), "handles", "a hand needs at least one handle");
  for (size_t i = 0; i < c.handles.size(); ++i) {
    const std::string path = "handles[" + std::to_string(i) + "]";
    require(c.handles[i].seed.allFinite(), path + ".seed", "must be finite");
    require(std::isfinite(c.handles[i].radius_m) && c.handles[i].radius_m > 0, path + ".radius_m", "must be > 0");
    for (int node : c.handles[i].nodes) require(node >= 0, path + ".nodes", "must be node indices");
  }
}

HandModel::HandModel(TetMesh mesh, HandConfig config)
    : mesh_(std::move(mesh)),
      config_(std::move(config)),
      fem_((validate(config_), mesh_), config_.material, config_.element_stiffness) {
  for (size_t i = 0; i < config_.handles.size(); ++i) {
    const HandleSpec& spec = config_.handles[i];
    handles_.push_back(make_handle(mesh_, fem_.lumped_mass(), spec.seed, spec.radius_m, spec.nodes,
                                   spec.name.empty() ? "handle" + std::to_string(i) : spec.name));
  }
  // A_t couples the nodes of each tet: 3x3 blocks for every node pair, plus every diagonal block.
  const int n = mesh_.num_nodes();
  std::vector<Eigen::Triplet<double>> entries;
  entries.reserve(mesh_.tets.size() * 144 + 9 * n);
  auto add_pattern_block = [&](int I, int J) {
    for (int r = 0; r < 3; ++r)
      for (int c = 0; c < 3; ++c) entries.emplace_back(3 * I + r, 3 * J + c, 1.0);
  };
  for (int i = 0; i < n; ++i) add_pattern_block(i, i);
  for (const Tet& t : mesh_.tets)
    for (int a = 0; a < 4; ++a)
      for (int b = 0; b < 4; ++b) add_pattern_block(t[a], t[b]);
  pattern_.resize(3 * n, 3 * n);
  pattern_.setFromTriplets(entries.begin(), entries.end());
  pattern_.makeCompressed();
  std::fill(pattern_.valuePtr(), pattern_.valuePtr() + pattern_.nonZeros(), 0.0);
  map_.column_start.assign(pattern_.outerIndexPtr(), pattern_.outerIndexPtr() + 3 * n + 1);
  map_.diagonal_block.resize(n);
  for (int i = 0; i < n; ++i) map_.diagonal_block[i] = find_entry(pattern_, 3 * i, 3 * i);
  node_tet_.assign(n, {-1, -1});
  for (size_t e = 0; e < mesh_.tets.size(); ++e)
    for (int k = 0; k < 4; ++k)
      if (node_tet_[mesh_.tets[e][k]].first < 0) node_tet_[mesh_.tets[e][k]] = {static_cast<int>(e), k};
  map_.element_block.resize(mesh_.tets.size());
  for (size_t e = 0; e < mesh_.tets.size(); ++e) {
    const Tet& t = mesh_.tets[e];
    for (int a = 0; a < 4; ++a)
      for (int b = 0; b < 4; ++b) map_.element_block[e][4 * a + b] = find_entry(pattern_, 3 * t[a], 3 * t[b]);
  }
}

double step_length(const HandModel& model, const HandState& s) {
  return s.dt_s > 0 && std::isfinite(s.dt_s) ? s.dt_s : model.config().dt_s;
}

HandState make_rest_state(const HandModel& model) {
  HandState s;
  const int n = model.num_nodes(), m = model.num_handles();
  s.x.resize(3 * n);
  for (int i = 0; i < n; ++i) s.x.segment<3>(3 * i) = model.mesh().X[i];
  s.v = Eigen::VectorXd::Zero(3 * n);
  s.handles.resize(m);
  s.targets.resize(m);
  for (int j = 0; j < m; ++j) {
    s.handles[j].p_WH = model.handles()[j].p_WH_rest;
    s.targets[j].p_W = s.handles[j].p_WH;
  }
  s.R.assign(model.mesh().tets.size(), Eigen::Matrix3d::Identity());  // warm start of the polar iteration
  s.f_t = Eigen::VectorXd::Zero(3 * n);
  s.f_ext = Eigen::VectorXd::Zero(3 * n);
  s.system.A_t = model.tool_pattern();
  s.system.A_th.resize(3 * n, 6 * m);
  s.system.A_ht.resize(6 * m, 3 * n);
  s.system.A_h = Eigen::MatrixXd::Zero(6 * m, 6 * m);
  s.system.b_t = Eigen::VectorXd::Zero(3 * n);
  s.system.b_h = Eigen::VectorXd::Zero(6 * m);
  s.v_t_next = Eigen::VectorXd::Zero(3 * n);
  s.v_h_next = Eigen::VectorXd::Zero(6 * m);
  return s;
}

void place_hand(const HandModel& model, HandState& s, const Eigen::Vector3d& p_W, const Eigen::Quaterniond& q_W,
                int handle) {
  const RigidHandle& ref = model.handles()[handle];
  const Eigen::Quaterniond q = q_W.normalized();
  // Rest pose maps to the world by x -> p_W + q (X - p_rest).
  auto to_world = [&](const Eigen::Vector3d& X) -> Eigen::Vector3d { return p_W + q * (X - ref.p_WH_rest); };
  for (int i = 0; i < model.num_nodes(); ++i) s.x.segment<3>(3 * i) = to_world(model.mesh().X[i]);
  s.v.setZero();
  for (int j = 0; j < model.num_handles(); ++j) {
    s.handles[j] = HandleState{};
    s.handles[j].p_WH = to_world(model.handles()[j].p_WH_rest);
    s.handles[j].q_WH = q;
    s.targets[j] = HandleTarget{};
    s.targets[j].p_W = s.handles[j].p_WH;
    s.targets[j].q_W = q;
  }
}

bool valid_contact(const HandModel& model, const HandState& s, const PointContact& c) {
  if (c.body >= static_cast<int>(s.bodies.size())) return false;
  if (c.body >= 0) {
    const ContactBody& b = s.bodies[c.body];
    if (!(b.mass_kg > 0) || !std::isfinite(b.mass_kg) || !b.inertia_W.allFinite() || !b.p_com_W.allFinite() ||
        !b.v_W.allFinite() || !b.w_W.allFinite())
      return false;
  }
  return c.body >= -1 && c.tet >= 0 && c.tet < model.fem().num_tets() && c.bary.allFinite() && c.n_W.allFinite() &&
         std::abs(c.n_W.norm() - 1) < 1e-6 && std::isfinite(c.depth_m) && c.v_other_W.allFinite() &&
         finite_nonneg(c.stiffness_n_m) && finite_nonneg(c.damping_ns_m) && finite_nonneg(c.friction);
}

bool set_target(HandState& state, int handle, const HandleTarget& t) {
  if (handle < 0 || handle >= static_cast<int>(state.targets.size())) return false;
  if (!t.p_W.allFinite() || !t.q_W.coeffs().allFinite() || !t.v_W.allFinite() || !t.w_W.allFinite()) return false;
  if (t.q_W.norm() < 0.5) return false;
  state.targets[handle] = t;
  state.targets[handle].q_W.normalize();
  return true;
}

void assemble(const HandModel& model, HandState& s) {
  const HandConfig& cfg = model.config();
  const CorotationalFem& fem = model.fem();
  const AssemblyMap& map = model.assembly_map();
  const Eigen::VectorXd& mass = fem.lumped_mass();
  const double h = step_length(model, s), h2 = h * h;
  const int n = model.num_nodes(), m = model.num_handles();
  CoupledSystem& sys = s.system;

  // Tool forces that depend on position only (damping is linear in velocity and
  // enters through D: b = M v + h (f - D v), Baraff-Witkin).
  fem.compute_rotations(s.x, s.R);
  s.f_t.setZero();
  fem.add_elastic_forces(s.x, s.R, s.f_t);
  for (int i = 0; i < n; ++i) s.f_t.segment<3>(3 * i) += mass[i] * cfg.gravity_m_s2;
  // External forces come from outside too: a malformed set is dropped, never assembled.
  if (s.f_ext.size() == 3 * n && s.f_ext.allFinite()) s.f_t += s.f_ext;

  // A_t = (1 + h alpha) M + (h beta + h^2) K_el + coupling and floor blocks.
  double* values = sys.A_t.valuePtr();
  std::fill(values, values + sys.A_t.nonZeros(), 0.0);
  const double cK = h * cfg.material.rayleigh_beta_s + h2;
  Eigen::Matrix3d blocks[4][4];
  for (int e = 0; e < fem.num_tets(); ++e) {
    const Tet& t = fem.tets()[e];
    fem.warped_blocks(e, s.R[e], cK, blocks);
    for (int a = 0; a < 4; ++a)
      for (int b = 0; b < 4; ++b) add_block(values, map, map.element_block[e][4 * a + b], t[b], blocks[a][b]);
  }
  const double cM = 1.0 + h * cfg.material.rayleigh_alpha_per_s;
  for (int i = 0; i < n; ++i) add_block(values, map, map.diagonal_block[i], i, cM * mass[i] * Eigen::Matrix3d::Identity());

  // Contacts come from outside (the world): a malformed one is dropped, never assembled.
  s.active_contacts.clear();
  s.active_source.clear();
  for (PointContact& r : s.reserve_contacts) r.f_W.setZero();
  for (size_t i = 0; i < s.contacts.size(); ++i) {
    s.contacts[i].f_W.setZero();
    if (!valid_contact(model, s, s.contacts[i])) continue;
    s.active_contacts.push_back(s.contacts[i]);
    s.active_source.push_back(static_cast<int>(i));
  }
  s.floor_contacts = 0;
  if (cfg.floor.enabled) {
    for (int i = 0; i < n; ++i) {
      const double depth = cfg.floor.height_m - s.x[3 * i + 2];
      if (depth <= 0) continue;
      ++s.floor_contacts;
      PointContact c;
      const auto [tet, local] = model.node_tet(i);
      c.tet = tet;
      c.bary = Eigen::Vector4d::Unit(local);
      c.depth_m = depth;
      c.stiffness_n_m = cfg.floor.stiffness_n_m;
      c.damping_ns_m = cfg.floor.damping_ns_m;
      c.friction = cfg.floor.friction;
      s.active_contacts.push_back(c);
      s.active_source.push_back(-1);
    }
  }
  for (const PointContact& c : s.active_contacts)
    if (!c.constraint) assemble_contact(model, c, s, values, h);

  for (int i = 0; i < n; ++i) sys.b_t.segment<3>(3 * i) = mass[i] * s.v.segment<3>(3 * i);

  // Handles: mass, drive, coupling springs (eq. 8, 10, 11); then the implicit
  // contact bodies as further 6-DOF blocks.
  const int nb = static_cast<int>(s.bodies.size());
  std::vector<Eigen::Triplet<double>> th, ht;
  sys.A_h.setZero(6 * (m + nb), 6 * (m + nb));
  sys.b_h.resize(6 * (m + nb));
  sys.A_th.resize(3 * n, 6 * (m + nb));
  sys.A_ht.resize(6 * (m + nb), 3 * n);
  for (int j = 0; j < m; ++j) {
    const RigidHandle& H = model.handles()[j];
    const HandleState& hs = s.handles[j];
    const HandleTarget& tg = s.targets[j];
    const Matrix6d M_h = handle_mass_matrix(H, hs);
    Vector6d v_h;
    v_h << hs.v_WH, hs.w_WH;
    Matrix6d A = M_h;
    Vector6d W = Vector6d::Zero();
    W.head<3>() = H.mass_kg * cfg.gravity_m_s2;
    // Gyroscopic torque, explicit.
    W.tail<3>() = -hs.w_WH.cross(M_h.bottomRightCorner<3, 3>() * hs.w_WH);
    // Drive: position parts and the target-velocity part of the damping stay in b;
    // the rotational stiffness is linearized as k_r I (exact at zero error, always SPD).
    const DriveParams& dr = cfg.drive;
    W.head<3>() += -dr.stiffness_n_m * (hs.p_WH - tg.p_W) + dr.damping_ns_m * tg.v_W;
    W.tail<3>() += -dr.rot_stiffness_nm_rad * rotation_difference(hs.q_WH, tg.q_W) + dr.rot_damping_nms_rad * tg.w_W;
    A.topLeftCorner<3, 3>().diagonal().array() += h * dr.damping_ns_m + h2 * dr.stiffness_n_m;
    A.bottomRightCorner<3, 3>().diagonal().array() += h * dr.rot_damping_nms_rad + h2 * dr.rot_stiffness_nm_rad;
    const double k = cfg.coupling.stiffness_n_m, d = cfg.coupling.damping_ns_m;
    for (size_t si = 0; si < H.nodes.size(); ++si) {
      const int a = H.nodes[si];
      const SpringTerms sp = coupling_spring(s.x.segment<3>(3 * a), s.v.segment<3>(3 * a), hs, H.r_B[si], k, d);
      // Only the elastic part enters f: the damping part is linear in v and lives in D.
      const Eigen::Vector3d rho = hs.q_WH * H.r_B[si];
      const Eigen::Vector3d F_A_pos = -k * (s.x.segment<3>(3 * a) - hs.p_WH - rho);
      s.f_t.segment<3>(3 * a) += F_A_pos;
      W.head<3>() -= F_A_pos;
      W.tail<3>() += rho.cross(-F_A_pos);
      add_block(values, map, map.diagonal_block[a], a, (h * d + h2 * k) * Eigen::Matrix3d::Identity());
      A -= h * sp.dWB_dvh + h2 * sp.dWB_dxh;
      const Eigen::Matrix<double, 3, 6> Ath = -h * sp.dFA_dvh - h2 * sp.dFA_dxh;
      const Eigen::Matrix<double, 6, 3> Aht = -h * sp.dWB_dvA - h2 * sp.dWB_dxA;
      for (int r = 0; r < 3; ++r)
        for (int c = 0; c < 6; ++c) {
          th.emplace_back(3 * a + r, 6 * j + c, Ath(r, c));
          ht.emplace_back(6 * j + c, 3 * a + r, Aht(c, r));
        }
    }
    sys.A_h.block<6, 6>(6 * j, 6 * j) = A;
    sys.b_h.segment<6>(6 * j) = M_h * v_h + h * W;
  }
  for (int b = 0; b < nb; ++b) {
    const ContactBody& B = s.bodies[b];
    Matrix6d M = Matrix6d::Zero();
    M.topLeftCorner<3, 3>() = B.mass_kg * Eigen::Matrix3d::Identity();
    M.bottomRightCorner<3, 3>() = B.inertia_W;
    Vector6d v;
    v << B.v_W, B.w_W;
    sys.A_h.block<6, 6>(6 * (m + b), 6 * (m + b)) = M;
    sys.b_h.segment<6>(6 * (m + b)) = M * v;
    sys.b_h.segment<3>(6 * (m + b)) += h * B.mass_kg * B.gravity_W;
  }
  for (const PointContact& c : s.active_contacts)
    if (c.body >= 0 && !c.constraint) assemble_body_contact(model, c, s, 6 * (m + c.body), h, th, ht);
  sys.A_th.setFromTriplets(th.begin(), th.end());
  sys.A_ht.setFromTriplets(ht.begin(), ht.end());
  sys.b_t += h * s.f_t;
}

namespace {

// A free body has no target: its rest shape is fitted rigidly onto the nodes
// (mass-weighted centroid, polar rotation of the best linear map), at rest; the
// rest pose itself when the nodes are not finite.
void reset_free_body(const HandModel& model, HandState& s) {
  const Eigen::VectorXd& mass = model.fem().lumped_mass();
  const std::vector<Eigen::Vector3d>& X = model.mesh().X;
  const int n = model.num_nodes();
  Eigen::Vector3d c_x = Eigen::Vector3d::Zero(), c_X = Eigen::Vector3d::Zero();
  const double total = mass.sum();
  for (int i = 0; i < n; ++i) c_x += mass[i] * s.x.segment<3>(3 * i), c_X += mass[i] * X[i];
  c_x /= total, c_X /= total;
  Eigen::Matrix3d A = Eigen::Matrix3d::Zero(), B = Eigen::Matrix3d::Zero();
  for (int i = 0; i < n; ++i) {
    A += mass[i] * (s.x.segment<3>(3 * i) - c_x) * (X[i] - c_X).transpose();
    B += mass[i] * (X[i] - c_X) * (X[i] - c_X).transpose();
  }
  Eigen::Matrix3d R = Eigen::Matrix3d::Identity();
  if (c_x.allFinite() && A.allFinite()) {
    R = rotation_of(A * B.inverse());
  } else {
    c_x = c_X;
  }
  for (int i = 0; i < n; ++i) s.x.segment<3>(3 * i) = c_x + R * (X[i] - c_X);
  s.v.setZero();
  s.held = HeldContacts{};
  ++s.resets;
}

void reset_to_target(const HandModel& model, HandState& s) {
  if (model.num_handles() == 0) {
    reset_free_body(model, s);
    return;
  }
  const HandleTarget t = s.targets[0];
  const bool usable = t.p_W.allFinite() && t.q_W.coeffs().allFinite();
  std::vector<HandleTarget> targets = s.targets;
  place_hand(model, s, usable ? t.p_W : model.handles()[0].p_WH_rest,
             usable ? t.q_W : Eigen::Quaterniond::Identity(), 0);
  s.targets = targets;
  s.held = HeldContacts{};
  ++s.resets;
}

// The force each contact put on the body at the end of the step (its implicit
// value), normal part clamped to push only; the world applies the reaction.
void record_contact_forces(const HandModel& model, HandState& s) {
  const double h = step_length(model, s);
  for (size_t i = 0; i < s.active_contacts.size(); ++i) {
    PointContact& c = s.active_contacts[i];
    const Eigen::Vector3d& n = c.n_W;
    const Tet& t = model.mesh().tets[c.tet];
    const Eigen::Vector3d u_rel = embedded_value(t, c.bary, s.v) - other_velocity(c, t, s, true);
    const double f_n = std::max(0.0, c.stiffness_n_m * (c.depth_m - h * n.dot(u_rel)) - c.damping_ns_m * n.dot(u_rel));
    const Eigen::Vector3d u_t = u_rel - n.dot(u_rel) * n;
    const double c_t = c.friction * c.stiffness_n_m * c.depth_m /
                       std::max(u_t.norm(), PointContact::kStickSpeed_m_s);
    c.f_W = f_n * n - c_t * u_t;
    if (s.active_source[i] >= 0) s.contacts[s.active_source[i]].f_W = c.f_W;
  }
}

bool within_bounds(const HandState& s, double max_speed) {
  if (!s.v_t_next.allFinite() || !s.v_h_next.allFinite()) return false;
  for (int i = 0; i < s.v_t_next.size() / 3; ++i)
    if (s.v_t_next.segment<3>(3 * i).squaredNorm() > max_speed * max_speed) return false;
  for (int j = 0; j < s.v_h_next.size() / 6; ++j)
    if (s.v_h_next.segment<3>(6 * j).squaredNorm() > max_speed * max_speed) return false;
  return true;
}

}  // namespace


StepStatus step(const HandModel& model, HandState& s, CoupledSolver& solver, HandleLinearization* linearization) {
  const auto t0 = Clock::now();
  assemble(model, s);
  s.timings = StepTimings{};
  s.timings.assembly_ms = ms_since(t0);
  SolveReport report;
  bool solved = solver.solve(s.system, s.v_h_next, s.v_t_next, report);
  std::vector<Eigen::Vector3d> impulses;
  const auto t_contact = Clock::now();
  if (solved) solved = solve_constraint_contacts(model, s, solver, impulses);
  s.timings.contact_ms = ms_since(t_contact);
  s.timings.factor_ms = report.factor_ms;
  s.timings.schur_ms = report.schur_ms;
  s.timings.solve_ms = report.solve_ms;
  s.timings.iterations = report.iterations;
  s.timings.factorizations = report.factorizations;
  const auto t1 = Clock::now();
  StepStatus status = StepStatus::ok;
  if (!solved) {
    status = StepStatus::reset_solver_failed;
  } else if (!within_bounds(s, model.config().max_speed_m_s)) {
    status = StepStatus::reset_diverged;
  }
  for (ContactBody& b : s.bodies) b.dv_W.setZero(), b.dw_W.setZero();
  bool linearized = false;
  if (linearization && status == StepStatus::ok && model.num_handles() > 0) {
    const auto t_lin = Clock::now();
    linearized = linearize_handles(model, s, solver, *linearization, s.held.rows() > 0 ? &s.held : nullptr);
    s.timings.linearize_ms = ms_since(t_lin);
  }
  if (status != StepStatus::ok) {
    reset_to_target(model, s);
  } else {
    const double h = step_length(model, s);
    // Checked before the update, so a reset still sees the start-of-step nodes.
    const bool finite_end = (s.x + h * s.v_t_next).allFinite();
    if (finite_end) {
      s.v = s.v_t_next;
      s.x += h * s.v;
    }
    for (size_t b = 0; b < s.bodies.size(); ++b) {
      ContactBody& B = s.bodies[b];
      const int col = 6 * (model.num_handles() + static_cast<int>(b));
      B.dv_W = s.v_h_next.segment<3>(col) - B.v_W;
      B.dw_W = s.v_h_next.segment<3>(col + 3) - B.w_W;
    }
    for (int j = 0; j < model.num_handles(); ++j) {
      HandleState& hs = s.handles[j];
      hs.v_WH = s.v_h_next.segment<3>(6 * j);
      hs.w_WH = s.v_h_next.segment<3>(6 * j + 3);
      hs.p_WH += h * hs.v_WH;
      hs.q_WH = rotate_by(hs.q_WH, h * hs.w_WH);
    }
    if (!finite_end) {
      status = StepStatus::reset_diverged;
      for (ContactBody& b : s.bodies) b.dv_W.setZero(), b.dw_W.setZero();
      reset_to_target(model, s);
    } else {
      record_contact_forces(model, s);
      for (size_t i = 0; i < s.active_contacts.size(); ++i) {
        if (!s.active_contacts[i].constraint) continue;
        s.active_contacts[i].f_W = impulses[i] / h;  // the impulse spread over the step
        const int source = s.active_source[i];
        if (source >= 0) s.contacts[source].f_W = s.active_contacts[i].f_W;
        if (source <= kReserveSource) s.reserve_contacts[kReserveSource - source].f_W = s.active_contacts[i].f_W;
      }
      if (linearized) {
        // The model is linear: anchoring it at the end-of-step state is exact.
        linearization->F0 = linearization->evaluate(s.handles);
        linearization->x0 = s.handles;
      }
    }
  }
  if (linearization && (!linearized || status != StepStatus::ok)) *linearization = HandleLinearization{};
  s.timings.integrate_ms = ms_since(t1);
  s.timings.total_ms = ms_since(t0);
  return status;
}

double total_energy(const HandModel& model, const HandState& s) {
  const HandConfig& cfg = model.config();
  const CorotationalFem& fem = model.fem();
  const Eigen::VectorXd& mass = fem.lumped_mass();
  double E = 0.0;
  for (int i = 0; i < model.num_nodes(); ++i) {
    const Eigen::Vector3d x = s.x.segment<3>(3 * i);
    E += 0.5 * mass[i] * s.v.segment<3>(3 * i).squaredNorm() - mass[i] * cfg.gravity_m_s2.dot(x);
    const double depth = cfg.floor.height_m - x.z();
    if (cfg.floor.enabled && depth > 0) E += 0.5 * cfg.floor.stiffness_n_m * depth * depth;
  }
  // Elastic: V/2 eps:sigma per element, eps = sym(R^T F) - I.
  const double E_y = cfg.material.youngs_modulus_pa, nu = cfg.material.poisson_ratio;
  const double lambda = E_y * nu / ((1 + nu) * (1 - 2 * nu)), mu = E_y / (2 * (1 + nu));
  for (int e = 0; e < fem.num_tets(); ++e) {
    const Eigen::Matrix3d F = fem.deformation_gradient(e, s.x);
    const Eigen::Matrix3d S = rotation_of(F).transpose() * F;
    const Eigen::Matrix3d eps = 0.5 * (S + S.transpose()) - Eigen::Matrix3d::Identity();
    E += fem.stiffness_scale(e) * fem.rest_volume(e) * (mu * eps.squaredNorm() + 0.5 * lambda * eps.trace() * eps.trace());
  }
  for (int j = 0; j < model.num_handles(); ++j) {
    const RigidHandle& H = model.handles()[j];
    const HandleState& hs = s.handles[j];
    const Matrix6d M = handle_mass_matrix(H, hs);
    Vector6d v;
    v << hs.v_WH, hs.w_WH;
    E += 0.5 * v.dot(M * v) - H.mass_kg * cfg.gravity_m_s2.dot(hs.p_WH);
    E += 0.5 * cfg.drive.stiffness_n_m * (hs.p_WH - s.targets[j].p_W).squaredNorm();
    E += 0.5 * cfg.drive.rot_stiffness_nm_rad * rotation_difference(hs.q_WH, s.targets[j].q_W).squaredNorm();
    for (size_t si = 0; si < H.nodes.size(); ++si) {
      const Eigen::Vector3d x_B = hs.p_WH + hs.q_WH * H.r_B[si];
      E += 0.5 * cfg.coupling.stiffness_n_m * (s.x.segment<3>(3 * H.nodes[si]) - x_B).squaredNorm();
    }
  }
  return E;
}

Eigen::Vector3d linear_momentum(const HandModel& model, const HandState& s) {
  Eigen::Vector3d p = Eigen::Vector3d::Zero();
  const Eigen::VectorXd& mass = model.fem().lumped_mass();
  for (int i = 0; i < model.num_nodes(); ++i) p += mass[i] * s.v.segment<3>(3 * i);
  for (int j = 0; j < model.num_handles(); ++j) p += model.handles()[j].mass_kg * s.handles[j].v_WH;
  return p;
}

}  // namespace hapticd::hand
