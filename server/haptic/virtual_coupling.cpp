#include "server/haptic/virtual_coupling.hpp"

#include <Eigen/Eigenvalues>
#include <algorithm>
#include <cmath>
#include <limits>
#include <random>

#include "hand_models/contact_pgs.hpp"
#include "hand_models/rigid_handle.hpp"

namespace hapticd::haptic {
namespace {

// A proxy faster than this has diverged (no hand moves a handle at 20 m/s).
constexpr double kMaxProxySpeed_m_s = 20.0;
// Device velocity: first-order low-pass of the pose differences (about 150 Hz at 1 kHz).
constexpr double kVelocityFilter = 0.6;

// The prepared solve's refinement: until the residual is this small against the right-hand side, at
// most this many corrections (then the dense LU).
constexpr double kRefineTolerance = 1e-12;
constexpr int kMaxRefinements = 6;

// The tick's contact solve (TickContacts): projected Gauss-Seidel sweeps, at most
// kDefaultTickContactSweeps (ProxyHand::set_contact_sweeps), this many before the first exact solve,
// until no impulse changes by more than this fraction of the largest.
constexpr int kTickContactFirstSweeps = 2;
// Redundant rows (ProxyHand::redistribute): W_AA's reciprocal condition number below this, and its
// singular values below this share of the largest; sets of at most this many rows; at most this many
// alternating projections, onto cones this much narrower than the contacts'.
constexpr double kRedundantRank = 1e-10;
constexpr int kMaxRedundantRows = 8, kRedistributeIterations = 200;
constexpr double kRedistributeMargin = 1e-3;
constexpr double kTickContactTolerance = 1e-10;
// How far a contact's normal velocity may fall short of its target in an answer the polish keeps,
// m/s: 0.1 nm of penetration over a 1 ms tick. The least-norm answer on a set of redundant rows
// misses targets that are not all reachable at once, mostly by 1e-12 to 1e-7 m/s (the stylus on the
// movable bunny: median 1.3e-9); refused, the tick keeps its sweeps' unconverged answer instead.
constexpr double kRowVelocityTolerance = 1e-7;

// The time since the last reply the passivity controller divides by, s: from a tick at 10 kHz (the
// fastest haptic rate hapticd accepts) to 100 ms (a reply after a pause is not a long tick).
constexpr double kMinReplyInterval_s = 1e-4;
constexpr double kMaxReplyInterval_s = 0.1;
// Squared port speed below which the passivity controller adds no damping, m^2/s^2 (10 um/s: no
// motion to damp, and the damping it would need grows without bound).
constexpr double kMinPassivitySpeed2_m2_s2 = 1e-10;

// The tick's Delassus operator for a proxy solved densely, W + P Q with P = h (tau U_K + U_D) (3c x 6m)
// and Q = A(tau)^-1 G (6m x 3c), kept in that form for pgs_sweeps_on: the rows' velocities are
// u = u_m + P y with u_m = u_free + W lambda and y = Q lambda, and an impulse moves u_m by W's columns
// and y by Q's. Forming W + P Q (3c x 6m x 3c products) at every tick cost more than the sweeps.
struct LowRankDelassus {
  const TickRowMatrix& W;
  const TickRowByDof& P;
  const TickDofByRow& Q;
  const Eigen::Matrix3d* blocks;  // W + P Q's diagonal blocks
  TickRowVector& u_m;
  HapticVector& y;
  int c;
  Eigen::Matrix3d block(int i) const { return blocks[i]; }
  Eigen::Vector3d velocity(int i) const { return u_m.segment<3>(3 * i) + P.middleRows<3>(3 * i) * y; }
  void add(int i, const Eigen::Vector3d& delta) {
    hand::add_columns(W, 3 * i, delta, u_m.head(3 * c));
    y.noalias() += Q.middleCols<3>(3 * i) * delta;
  }
};

// Limits |v| to `limit`; true if it had to.
bool clamp_norm(Eigen::Vector3d& v, double limit) {
  const double n = v.norm();
  if (n <= limit) return false;
  v *= limit / n;
  return true;
}

// Shortens v by `by`, to zero at least.
void shrink_norm(Eigen::Vector3d& v, double by) {
  const double n = v.norm();
  v *= n > by ? (n - by) / n : 0.0;
}

}  // namespace

DeviceMap::DeviceMap() {
  for (int j = 0; j < kMaxHapticHandles; ++j) handle_p_F[j].setZero(), handle_q_F[j].setIdentity();
}

DeviceMap::DeviceMap(double s, const Eigen::Vector3d& offset, const Eigen::Quaterniond& R) : DeviceMap() {
  scale = s;
  offset_W = offset;
  R_WD = R;
}

HapticPose DeviceMap::to_world(int j, const Eigen::Vector3d& p_D, const Eigen::Quaterniond& q_D) const {
  const HapticPose frame = to_world(p_D, q_D);
  return {frame.p_W + frame.q_W * handle_p_F[j], (frame.q_W * handle_q_F[j]).normalized()};
}

HapticPose DeviceMap::to_world(const Eigen::Vector3d& p_D, const Eigen::Quaterniond& q_D) const {
  return {offset_W + scale * (R_WD * p_D), (R_WD * q_D).normalized()};
}

void DeviceMap::to_device(int j, const HapticPose& handle_W, Eigen::Vector3d& p_D, Eigen::Quaterniond& q_D) const {
  // The frame carries its handle at (handle_p_F, handle_q_F).
  const Eigen::Quaterniond q_frame_W = (handle_W.q_W * handle_q_F[j].conjugate()).normalized();
  const Eigen::Vector3d p_frame_W = handle_W.p_W - q_frame_W * handle_p_F[j];
  p_D = R_WD.conjugate() * (p_frame_W - offset_W) / scale;
  q_D = (R_WD.conjugate() * q_frame_W).normalized();
}

namespace {

// B = P - h D, P as ProxyHand::integrate builds it under a model: mass, coupling, and each
// proxy's inertia at its handle's anchor orientation x0. The tick's matrix is A(tau) = B - h tau K.
HapticMatrix proxy_matrix(const HapticModel& model, const double* mass_kg, const Eigen::Matrix3d* inertia_B,
                          const CouplingGains& gains, double dt) {
  HapticMatrix B = -dt * model.D;
  for (int j = 0; j < model.handles; ++j) {
    const Eigen::Matrix3d R = model.x0[j].q_W.toRotationMatrix();
    Eigen::Matrix3d P_rot = R * inertia_B[j] * R.transpose();
    P_rot.diagonal().array() += dt * gains.b_nms_rad + dt * dt * gains.k_nm_rad;
    B.block<3, 3>(6 * j, 6 * j).diagonal().array() += mass_kg[j] + dt * gains.b_ns_m + dt * dt * gains.k_n_m;
    B.block<3, 3>(6 * j + 3, 6 * j + 3) += P_rot;
  }
  return B;
}

// The rows' operator with the proxies' response at lookahead tau, W + (tau U_K + U_D) A(tau)^-1 h G,
// into `out`; false if it is not finite.
bool contact_operator(const HapticModel& model, const HapticMatrix& B, double dt, double tau, TickRowMatrix& out) {
  const TickContacts& c = model.contacts;
  const HapticMatrix A = B - (tau * dt) * model.K;
  const TickDofByRow X = Eigen::PartialPivLU<HapticMatrix>(A).solve(dt * c.G);
  out = c.W;
  out.noalias() += (tau * c.U_K + c.U_D) * X;
  return out.allFinite();
}

// Its symmetric part is positive semidefinite, to 1e-9 of its largest diagonal entry: the rows
// take energy, never give it, whatever the impulses.
bool monotone(const TickRowMatrix& op) {
  TickRowMatrix S = 0.5 * (op + op.transpose());
  const double scale = std::max(S.diagonal().cwiseAbs().maxCoeff(), 1e-300);
  S.diagonal().array() += 1e-9 * scale;
  return Eigen::LLT<TickRowMatrix>(S).info() == Eigen::Success;
}

// The longest lookahead from `tau` halved down to h (h at the least) at which the operator is
// monotone, and the operator there.
double monotone_lookahead(const HapticModel& model, const HapticMatrix& B, double dt, double tau, TickRowMatrix& op) {
  tau = std::max(tau, dt);
  while (contact_operator(model, B, dt, tau, op) && !monotone(op) && tau > dt) tau = std::max(0.5 * tau, dt);
  return tau;
}

}  // namespace

void prepare_contact_lookahead(HapticModel& model, const double* mass_kg, const Eigen::Matrix3d* inertia_B,
                               const CouplingGains& gains, double dt) {
  TickContacts& c = model.contacts;
  c.max_lookahead_s = std::numeric_limits<double>::infinity();
  const int n = 6 * model.handles;
  if (c.count == 0 || !(dt > 0) || model.K.rows() != n || model.D.rows() != n) return;
  const HapticMatrix B = proxy_matrix(model, mass_kg, inertia_B, gains, dt);
  const double top = std::min(std::max(model.step_s, dt), kMaxModelLookahead_s);
  TickRowMatrix op;
  const double tau = monotone_lookahead(model, B, dt, top, op);
  if (tau < top) c.max_lookahead_s = tau;
}

double passive_stiffness(HapticMatrix& K, const CouplingGains& gains) {
  // A stiffness with a positive eigenvalue pushes the handles further along it the further they go: a
  // spring that gives energy. The flesh around a pressed finger can be so (the geometric stiffness of
  // a phalanx held in stretched flesh: turned, it is turned further), and the world steps through it,
  // but the tick, rendering it between visual steps, feeds the device. Measured on the glove pressed
  // into the fixed box and held at 12 Hz (GlovePressHold): the ring finger's middle phalanx, gated
  // (touching nothing) and held 17 mm from its device by its neighbours' flesh, had a rotational
  // eigenvalue of up to +7.3 N m/rad against its coupling's 1 N m/rad; its proxy spun up to
  // 2000 rad/s and the held glove gained +0.145 J (+0.024 J with the passivity controller).
  // Removed: -0.016 J either way, under every perturbation of K tried (1e-6 to 1e-4). Keeping the
  // eigenvalues below half the coupling's instead (the proxy then still has a rest) left +0.052 J and
  // +0.0056 J there. Measured against the coupling (rather than in N/m and N m/rad mixed), the
  // change is the least in the force it makes for the proxies' displacement under a coupling force.
  // Cost for a 16-handle glove (96 DOFs, this host): the Cholesky test 0.01-0.03 ms each model, the
  // eigendecomposition, only for a model that has such an eigenvalue, 0.9 ms.
  const int n = static_cast<int>(K.rows());
  if (n == 0 || n % 6 != 0 || K.cols() != n || !K.allFinite() || !(gains.k_n_m > 0) || !(gains.k_nm_rad > 0)) return 0;
  Eigen::VectorXd root_c(n);  // C^1/2
  for (int i = 0; i < n; ++i) root_c[i] = std::sqrt(i % 6 < 3 ? gains.k_n_m : gains.k_nm_rad);
  // M = C^-1/2 S C^-1/2; -M positive definite: nothing to remove.
  const Eigen::MatrixXd M =
      root_c.cwiseInverse().asDiagonal() * (0.5 * (K + K.transpose())) * root_c.cwiseInverse().asDiagonal();
  if (Eigen::LLT<Eigen::MatrixXd>(-M).info() == Eigen::Success) return 0;
  const Eigen::SelfAdjointEigenSolver<Eigen::MatrixXd> eigen(M);
  if (eigen.info() != Eigen::Success) return 0;
  double largest = 0;
  for (int i = 0; i < n; ++i) {
    const double mu = eigen.eigenvalues()[i];
    if (!(mu > 0)) continue;
    const Eigen::VectorXd u = root_c.cwiseProduct(eigen.eigenvectors().col(i));  // C^1/2 v
    K.noalias() -= mu * u * u.transpose();
    largest = std::max(largest, mu);
  }
  return largest;
}

bool prepare_tick_solver(HapticModel& model, int handles, const double* mass_kg, const Eigen::Matrix3d* inertia_B,
                         const CouplingGains& gains, double dt) {
  TickSolver& s = model.solver;
  s.prepared = false;
  const int m = model.handles, n = 6 * m;
  if (m < kMinPreparedHandles || m != handles || m > kMaxHapticHandles || !(dt > 0) || model.K.rows() != n ||
      model.K.cols() != n || model.D.rows() != n || model.D.cols() != n || !model.K.allFinite() || !model.D.allFinite())
    return false;
  const HapticMatrix B = proxy_matrix(model, mass_kg, inertia_B, gains, dt);
  for (int j = 0; j < m; ++j) {
    s.mass_kg[j] = mass_kg[j];
    s.inertia_B[j] = inertia_B[j];
  }
  const Eigen::PartialPivLU<HapticMatrix> lu(B);
  // E = B^-1 C = U H U^T, C = h K.
  const HapticMatrix E = lu.solve(dt * model.K);
  const Eigen::HessenbergDecomposition<HapticMatrix> hessenberg(E);
  s.U = hessenberg.matrixQ();
  const HapticMatrix H = hessenberg.matrixH();
  for (int j = 0; j < n; ++j) {
    double* column = s.hessenberg_column(j);
    for (int i = 0; i <= std::min(j + 1, n - 1); ++i) column[i] = H(i, j);
  }
  s.G.noalias() = s.U.transpose() * lu.inverse();
  HapticVector v0(n);
  for (int j = 0; j < m; ++j) v0.segment<3>(6 * j) = model.v0[j], v0.segment<3>(6 * j + 3) = model.w0[j];
  s.anchor_force.noalias() = model.F0 - model.D * v0;
  // The probes: Gaussian directions (uniform on the sphere), from a fixed seed so that a run
  // stays deterministic (the offline mode's bit-identical replays).
  std::mt19937_64 rng(0x5eed);
  std::normal_distribution<double> normal;
  s.Z.resize(TickSolver::kProbes, n);
  for (int i = 0; i < TickSolver::kProbes; ++i) {
    for (int k = 0; k < n; ++k) s.Z(i, k) = normal(rng);
    s.Z.row(i).normalize();
  }
  s.ZB.noalias() = s.Z * B;
  s.ZC.noalias() = dt * (s.Z * model.K);
  if (!s.G.allFinite() || !s.U.allFinite() || !H.allFinite() || !s.anchor_force.allFinite() || !s.ZB.allFinite() ||
      !s.ZC.allFinite())
    return false;
  TickContacts& c = model.contacts;
  c.proxy_prepared = false;
  c.max_lookahead_s = std::numeric_limits<double>::infinity();
  if (c.count > 0) {
    // The contacts' Delassus operator with the proxies' response at the model's mid-step
    // lookahead, or shorter where it is not monotone there; the tick serves the model at that one
    // lookahead through its step (integrate). At the live one the rows overshot early in a step,
    // the proxies' response to their impulses being larger than the operator says (a fingertip
    // proxy arriving at -0.94 m/s as a model switched left at +1.29 m/s and flew 7 mm out,
    // Touch/GlovePressHold), and undershot late in it, letting the proxies sink past them.
    const double mid = std::max(0.5 * model.step_s, dt);
    const double tau = monotone_lookahead(model, B, dt, mid, c.W_proxy);
    if (!c.W_proxy.allFinite()) return false;
    c.max_lookahead_s = tau;
    c.proxy_prepared = true;
  }
  s.dt_s = dt;
  s.gains = gains;
  s.prepared = true;
  return true;
}

CouplingGains coupling_gains_for(double device_stiffness_n_m, double scale, double period_s) {
  CouplingGains g;
  const double s2 = scale * scale;
  g.k_n_m = device_stiffness_n_m / s2;
  g.b_ns_m = std::max(kCouplingDampingMargin * 0.5 * device_stiffness_n_m * period_s, kMinCouplingDamping_ns_m) / s2;
  return g;
}

double glove_rotational_damping(const CouplingGains& gains, double haptic_rate_hz) {
  return kCouplingDampingMargin * 0.5 * gains.k_nm_rad / haptic_rate_hz;
}

void ProxyHand::configure(int handles, const double* mass_kg, const Eigen::Matrix3d* inertia_B,
                          const CouplingGains& gains, const DeviceLimits& limits, const DeviceMap& map) {
  handles_ = std::clamp(handles, 0, kMaxHapticHandles);
  gains_ = gains;
  limits_ = limits;
  map_ = map;
  for (int j = 0; j < handles_; ++j) {
    mass_[j] = mass_kg[j];
    inertia_B_[j] = inertia_B[j];
    // Critical damping of the proxy on the coupling (2 sqrt(k m), the rotation with the inertia's
    // trace), with the coupling's own damper.
    const auto damping = [](double k_c, double b_c, double inertia) {
      return std::max(2.0 * std::sqrt(k_c * inertia) - b_c, 0.0);
    };
    safe_b_ns_m_[j] = damping(gains_.k_n_m, gains_.b_ns_m, mass_[j]);
    safe_b_nms_rad_[j] = damping(gains_.k_nm_rad, gains_.b_nms_rad, inertia_B_[j].trace());
  }
  const int n = 6 * handles_;
  A_.resize(n, n);
  column_.resize(n);
  multiplier_.resize(n);
  b_.resize(n);
  x_rel_.resize(n);
  late_x_rel_.resize(n);
  v_next_.resize(n);
  v0_.resize(n);
  r_.resize(n);
  c_.resize(n);
  dv_.resize(n);
  x_look_.resize(n);
  rhs_.resize(n);
  lambda_.resize(0);

  lu_ = Eigen::PartialPivLU<HapticMatrix>(n);
  have_device_ = false;
  last_interval_s_ = std::numeric_limits<double>::infinity();
  for (int j = 0; j < kMaxHapticHandles; ++j) {
    v_[j].setZero(), w_[j].setZero(), v_dev_[j].setZero(), w_dev_[j].setZero();
    last_f_D_[j].setZero(), last_tau_D_[j].setZero(), last_r_D_[j].setZero();
    moved_p_W_[j].setZero(), moved_theta_W_[j].setZero();
    unfelt_p_W_[j].setZero(), unfelt_theta_W_[j].setZero();
    last_stretch_p_W_[j].setZero(), last_twist_W_[j].setZero();
    clutch_p_W_[j].setZero(), clutch_theta_W_[j].setZero();
    energy_in_[j] = 0, damped_j_[j] = 0, passivity_b_[j] = 0;
  }
  near_contact_ = bridging_ = bridged_now_ = false;
}

void ProxyHand::reset() {
  ++resets_;
  resync();
  warm_start_valid_ = false;  // impulses that diverged must not start the next tick
  for (int j = 0; j < handles_; ++j)
    last_f_D_[j].setZero(), last_tau_D_[j].setZero(), energy_in_[j] = 0, passivity_b_[j] = 0;
}

void ProxyHand::resync() {
  resync_following_ = true;
  late_t_end_ns_ = 0;  // a late model's frozen displacement was the proxy's before the jump
  for (int j = 0; j < handles_; ++j) {
    proxy_[j] = predicted_[j] = device_[j];
    v_[j].setZero(), w_[j].setZero(), v_dev_[j].setZero(), w_dev_[j].setZero();
    unfelt_p_W_[j].setZero(), unfelt_theta_W_[j].setZero();
    last_stretch_p_W_[j].setZero(), last_twist_W_[j].setZero();
    moved_p_W_[j].setZero(), moved_theta_W_[j].setZero();
    clutch_p_W_[j].setZero(), clutch_theta_W_[j].setZero();
  }
}

void ProxyHand::set_device_pose(int j, const Eigen::Vector3d& p_D, const Eigen::Quaterniond& q_D) {
  if (j >= 0 && j < handles_) pending_[j] = map_.to_world(j, p_D, q_D);
}

bool ProxyHand::commit_sample(double t_s, double resync_gap_s, double sample_interval_s, double waited_s) {
  const double dt = t_s - t_dev_;
  // A gap is the device's: a sample it took within the re-sync gap of the one before is none, however
  // late it was read (a server stopped meanwhile, whose haptic loop catches the proxies up along the
  // samples that waited: HapticCore::catch_up). Re-synced there, the proxies dropped the force they
  // held and a pressing stylus sank into the bunny, to be pushed back out with energy (ServerStalls).
  const bool has_interval = std::isfinite(sample_interval_s) && sample_interval_s > 0;
  const bool device_paced = has_interval && sample_interval_s <= resync_gap_s;
  const bool gap = have_device_ && dt >= 0 && (has_interval ? !device_paced : !(dt <= resync_gap_s));
  // A gap is bridged, not re-synced, when the device came back within kMaxBridgedStretch_m (and _rad)
  // of where it was. Its reply faded out meanwhile (its watchdog) and, pressing, it sank into the
  // object unfelt; re-synced onto it, the proxies were inside the object and the hand pushed them,
  // and the stylus, back out: +1.1e-2 to +1.8e-2 J (ServerStalls: a stylus pressing into the movable
  // bunny through a 100-300 ms gap), and +0.4e-3 to +2.8e-3 J for a gap that began just above it.
  // Bridged, the device's motion across the gap is a clutch: the proxies are coupled to the device
  // less it, as if it had stayed where the gap began, and the device feels that coupling. A deeper
  // press is felt from there; the clutch shrinks as the device backs out, the force it feels never
  // growing meanwhile (reply()), and drifts out while the hand is near nothing (integrate()). A gap
  // farther than the bound re-syncs.
  bool bridge = gap;
  for (int j = 0; j < handles_ && bridge; ++j)
    bridge = (clutch_p_W_[j] + pending_[j].p_W - device_[j].p_W).norm() <= kMaxBridgedStretch_m &&
             (clutch_theta_W_[j] + hand::rotation_difference(pending_[j].q_W, device_[j].q_W)).norm() <=
                 kMaxBridgedStretch_rad;
  const bool resync_now = !have_device_ || dt < 0 || (gap && !bridge);
  // Samples read faster than the device took them (under half its interval, or kMinSampleInterval_s
  // without one), or that waited to be read half an interval longer than its quickest samples did,
  // come from a queue: after a re-sync they re-sync the proxies onto themselves too, and after a
  // bridged gap their motion joins the clutch, until one comes at the device's pace (or the re-sync
  // gap has passed since the gap). A device whose samples
  // stopped and then came as a queue (time-stamped with the gap: its driver or link held them; or a
  // server stalled past the gap with no time stamps to tell) re-syncs on the oldest pose of the
  // queue, the rest are read at once, and the proxies are to start where the device is now (from
  // 50 ms back they were 26 mm behind a stroking stylus, and rang on the coupling at up to 8 m/s).
  // Read times alone miss a queue whose reading was interrupted (the server descheduled again
  // midway, a busy machine): the rest of it, read at once a few milliseconds later, left the proxies
  // behind the device by their count of samples' motion (0.84-2.54 N in 16 of 120 runs of
  // HapticServer.AQueueReadAfterAGapResyncsOnceOntoItsNewestPose with both cores busy). A sample
  // read about one interval after the one before (an interruption of 0.5-1.5 intervals) neither was
  // read at once nor waited longer: one such sample inside a queue, or right after its gap, does not
  // end it, two in a row do (a device that resumes at its pace after a gap has its first sample's
  // motion re-synced onto or put into the clutch too). Ended at the first, the rest of the queue's
  // slide was felt: 1.5-3.0 N in 11 of 20 runs with two `yes` loops on the 2 cores (the sample read
  // 0.97 ms after the one before, its interval 1 ms), and under ASan 2.4-2.7 N in 3 of 20 where the
  // gap's own sample was followed by such a one (0.66 ms).
  const bool read_at_once = has_interval ? dt < 0.5 * sample_interval_s : dt < kMinSampleInterval_s;
  const bool waited = has_interval && std::isfinite(waited_s) && waited_s > 0.5 * sample_interval_s;
  if (resync_now || bridge) gap_t_s_ = t_s;
  // A gap's sample is a queue's oldest (its reading may be interrupted right after it); a session's
  // first sample, or one from a clock set back, starts none.
  const bool restart = !have_device_ || dt < 0;
  queue_paced_ = restart ? 1 : resync_now || bridge || read_at_once || waited ? 0 : queue_paced_ + 1;
  const bool queued = queue_paced_ <= 1 && t_s - gap_t_s_ <= resync_gap_s;
  bridging_ = !resync_now && (bridge || (bridging_ && queued));
  if (bridge) ++bridged_gaps_;
  bridged_now_ = bridge;
  // The device's velocity is its motion over its own interval between the two samples. When they
  // are read is no measure of it: a server that was stalled reads the samples queued meanwhile
  // microseconds apart (8 us after 50 ms stopped made a tip moving at 0.01 m/s look like up to
  // 212 m/s, and the coupling's damper pushed the device at its force limit).
  const double dt_v =
      has_interval ? std::max(sample_interval_s, kMinSampleInterval_s) : std::max(dt, kMinSampleInterval_s);
  for (int j = 0; j < handles_; ++j) {
    if (!resync_now && dt > 0) {
      const Eigen::Vector3d moved = pending_[j].p_W - device_[j].p_W;
      const Eigen::Vector3d turned = hand::rotation_difference(pending_[j].q_W, device_[j].q_W);
      if (motion_booked_[j]) moved_p_W_[j].setZero(), moved_theta_W_[j].setZero(), motion_booked_[j] = false;
      if (bridging_) {
        // Into the clutch, as if the device had not moved (no velocity either). It held a reply
        // that faded out at a pace only it knew: the observer books none of that motion (a press
        // into the faded reply is no work it did). From where the proxies were coupled to: the
        // device carried along its velocity while its samples were overdue (predict_device).
        clutch_p_W_[j] += pending_[j].p_W - predicted_[j].p_W;
        clutch_theta_W_[j] += hand::rotation_difference(pending_[j].q_W, predicted_[j].q_W);
      } else {
        v_dev_[j] += kVelocityFilter * (moved / dt_v - v_dev_[j]);
        w_dev_[j] += kVelocityFilter * (turned / dt_v - w_dev_[j]);
        moved_p_W_[j] += moved, moved_theta_W_[j] += turned;
      }
    }
    device_[j] = pending_[j];
    predicted_[j] = device_[j];
  }
  t_dev_ = t_s;
  // The device's pace: the shorter of its last two intervals, so that the sample after a gap does not
  // make the gap its pace.
  sample_interval_s_ = std::min(dt_v, last_interval_s_);
  last_interval_s_ = dt_v;
  have_device_ = true;
  if (resync_now || (resync_following_ && queued))
    resync();
  else
    resync_following_ = false;
  return resync_now;
}

void ProxyHand::predict_device(double t_s) {
  if (!have_device_) return;
  // The samples the device's pace would have brought by now, each its interval's motion on.
  const double age = t_s - t_dev_;
  const double missed = age >= sample_interval_s_ ? std::floor(age / sample_interval_s_) * sample_interval_s_ : 0.0;
  const double overdue = std::clamp(missed, 0.0, kMaxDevicePrediction_s);
  if (overdue > 0) ++overdue_device_ticks_;
  for (int j = 0; j < handles_; ++j) {
    predicted_[j].p_W = device_[j].p_W + overdue * v_dev_[j];
    predicted_[j].q_W = hand::rotate_by(device_[j].q_W, overdue * w_dev_[j]);
  }
}

void ProxyHand::integrate(const HapticModel& model, double dt, double lookahead_s, double model_weight) {
  if (handles_ == 0 || !have_device_) return;
  const double weight = std::clamp(model_weight, 0.0, 1.0);
  const bool contacts_on = model.handles == handles_ && model.contacts.count > 0;
  // seed 004 section 3: F* is taken at the pose extrapolated to the model's step end, x + tau v'
  // (tau >= h), no further than the model's contact rows stay monotone (TickContacts::max_lookahead_s).
  // A model whose rows' operator was prepared at one lookahead (TickContacts::W_proxy) is served at
  // that one through its step: the rows' impulses and the proxies' response to them then agree. And
  // past its step's end while the next model is late: dropped to h there, the force law changed under
  // every pressed finger at a time set by the next model's lateness, and a glove pressed into the box
  // and held still, each model reaching the tick 45-59 ms after its 60 ms step began (16 Hz, a busy
  // machine), was pumped ~1 mJ a step on a phalanx: +0.020 and +0.026 J over 4 s, models on time -0.05
  // (GloveLateModels/GlovePressHold).
  const bool served_prepared = contacts_on && model.contacts.proxy_prepared;
  const double tau =
      served_prepared ? model.contacts.max_lookahead_s
                      : std::max(std::min(lookahead_s, contacts_on ? model.contacts.max_lookahead_s : lookahead_s), dt);
  // A model that arrives after its step's end (the visual step took longer than the step it
  // simulated) keeps its anchor where the world left the hand: the world has not moved it since.
  // Carried along by the handle's velocity for the time since (as if the flesh kept moving), the
  // anchor of a press went on into the object while the model was late, the late model then pushed
  // the stylus back out harder than it had pressed in, and a press under four CPU-bound competitors
  // (models up to ~90 ms late at 8-9 Hz) gave the stylus +0.7 to +3.1 mJ (Touch/LateModels).
  // Nor does its stiffness K follow the proxy past the step's end: K is the hand's answer to a
  // handle displaced within the step it linearizes (for a light free hand, its flesh's inertia over
  // that step), and a proxy that travels on for a stalled visual step's 100-300 ms would stretch it
  // far outside it. Its K (x - x0) is taken at the proxy's pose of the first late tick (frozen until
  // the next model; the contact rows keep the proxy's live pose): a stylus lifting away from the
  // bunny during a 300 ms stall was pulled 0.37-0.57 N toward it (press_hold_lift_busy.sh).
  near_contact_ = model.handles == handles_ && (model.in_contact || model.contacts.count > 0);
  // Near nothing, a bridged gap's clutch drifts out and carries the proxies with it: the stretch, and
  // so the force, stays as it was (let go of the proxies, they rang on the lightly damped coupling:
  // 0.31 N at 5 cm/s). Without a clutch nothing is touched (not even the proxies' bits).
  if (!near_contact_)
    for (int j = 0; j < handles_; ++j) {
      if (clutch_p_W_[j].isZero(0) && clutch_theta_W_[j].isZero(0)) continue;
      const Eigen::Vector3d c_p = clutch_p_W_[j], c_theta = clutch_theta_W_[j];
      shrink_norm(clutch_p_W_[j], kClutchDrift_m_s * dt);
      shrink_norm(clutch_theta_W_[j], kClutchDrift_rad_s * dt);
      proxy_[j].p_W += c_p - clutch_p_W_[j];
      proxy_[j].q_W = hand::rotate_by(proxy_[j].q_W, c_theta - clutch_theta_W_[j]);
    }
  const bool late = lookahead_s < 0;
  TickSolve solve = solve_velocities(model, dt, tau, weight, late);
  if (solve != TickSolve::solved && contacts_on && tau > dt) {
    // The tick's contact operator W + (tau U_K + U_D) h A(tau)^-1 G is not symmetric: the
    // flesh's response to a handle's displacement and a contact's pull on the handles differ by
    // the handle's spin and by a touched body's motion. Its part that tau scales can make it
    // indefinite, and then the sweeps diverge: on the stylus bunny after a 100 ms visual step
    // (kMaxStep_s: a stalled or loaded machine) its symmetric part's least eigenvalue was -22
    // at tau = 0.08 s and -0.2 at tau = h, and the proxies, kicked past kMaxProxySpeed_m_s, were
    // reset hundreds of times. The tick then solves again without the lookahead (tau = h),
    // warm-started from the model's own impulses: the contacts still hold, only the proxy's
    // motion toward the step end is not anticipated.
    ++lookahead_fallbacks_;
    warm_start_valid_ = false;
    solve = solve_velocities(model, dt, dt, weight, late);
  }
  if (solve == TickSolve::too_fast && contacts_on) {
    // A proxy centimetres from its model's anchor (the device moved on while the whole server
    // was stalled, and the world has not stepped since) is outside the model's linearization: its
    // rows ask the light proxy to undo the handle spring's pull on the flesh within one tick, and
    // threw it at 25-60 m/s. The proxy holds still for this tick instead: a finite answer, so
    // nothing is reset; the device keeps feeling the coupling to a still proxy (continuous and
    // passive), and the next tick, or the next model, tries again.
    ++contact_holds_;
    warm_start_valid_ = false;
    v_next_.setZero();
    solve = TickSolve::solved;
  }
  if (solve != TickSolve::solved) {
    // Safety (DESIGN.md section 5): a non-finite or absurd state never propagates;
    // the proxies restart on the device and the force drops to zero at once.
    reset();
    return;
  }
  for (int j = 0; j < handles_; ++j) {
    // The passivity controller's damping on the proxy's side (reply()), implicit: it only slows
    // the proxy, so it takes energy out whatever the coupling between handles.
    const double b_W = passivity_b_[j] / (map_.scale * map_.scale);
    const double b_rot = passivity_b_[j] * kPassivityRotationWeight_m2;
    v_[j] = v_next_.segment<3>(6 * j) / (1.0 + dt * b_W / mass_[j]);
    w_[j] = v_next_.segment<3>(6 * j + 3) / (1.0 + dt * b_rot * 3.0 / inertia_B_[j].trace());
    proxy_[j].p_W += dt * v_[j];
    proxy_[j].q_W = hand::rotate_by(proxy_[j].q_W, dt * w_[j]);
  }
}

ProxyHand::TickSolve ProxyHand::solve_velocities(const HapticModel& model, double dt, double tau, double weight,
                                                  bool late) {
  // The model's contacts and clearance planes hold at any weight: they are where the world's
  // surfaces are, and the world, which follows the proxies, must not be driven into them by a proxy
  // that the safe model carried through (a stalled or failed world resumes there). The device does
  // not feel them on a faded model: HapticCore scales its output by the weight.
  const bool has_model = model.handles == handles_;
  const bool use_model = has_model && weight > 0;  // F0, K and D, scaled by the weight
  const bool contacts_on = has_model && model.contacts.count > 0;
  const double safe = safe_share_ = 1.0 - weight;  // the safe model's share (reply() renders its damper)
  // seed 004 section 3: implicit Euler of the proxies under F* and the coupling, F* at x + tau v':
  //   [M - h D - h tau K + h B_c + h^2 K_c] v' = M v + h [F0 + K (x - x0) - D v0 + K_c (x_dev - x) + B_c v_dev].
  b_.setZero();
  // The proxies' rotational inertia in world axes: for a glove-sized model (the prepared solver's,
  // faded or not), at the model's anchor orientations (its linearization point) rather than the
  // proxies' own, so that the system matrix is fixed for the model's life and
  // prepare_tick_solver's factors solve it exactly. The two differ by a proxy's turn within one
  // visual step, on an inertia of ~2 % of the coupling's rotational damping per tick for a
  // phalanx: second order next to the model's own linearization error.
  const bool anchor_inertia = use_model && handles_ >= kMinPreparedHandles;
  for (int j = 0; j < handles_; ++j) {
    const Eigen::Matrix3d R = (anchor_inertia ? model.x0[j].q_W : proxy_[j].q_W).toRotationMatrix();
    const Eigen::Matrix3d I_W = R * inertia_B_[j] * R.transpose();
    a_lin_[j] = mass_[j] + dt * gains_.b_ns_m + dt * dt * gains_.k_n_m;
    a_rot_[j] = I_W;
    a_rot_[j].diagonal().array() += dt * gains_.b_nms_rad + dt * dt * gains_.k_nm_rad;
    // The coupling saturates at the device's limits (issue 17, item 3): the proxy, and through it the
    // hand, is never pulled harder than the device can push back (reply() clamps the same wrench), so a
    // user pressing past the limit moves the device, not the hand through the object. The explicit
    // wrench at the tick's start is scaled down to the limit; A keeps the full b + h k (the tick's
    // matrix does not change), which only damps the proxy's velocity change within the tick.
    // The safe model, implicit like the coupling: a damper between proxy and device that the device
    // feels (reply() adds it to the coupling's), saturated with the coupling.
    const double b = safe * safe_b_ns_m_[j], b_rot = safe * safe_b_nms_rad_[j];
    a_lin_[j] += dt * b;
    a_rot_[j].diagonal().array() += dt * b_rot;
    const Eigen::Vector3d dp = predicted_[j].p_W - proxy_[j].p_W - clutch_p_W_[j];
    const Eigen::Vector3d dq = hand::rotation_difference(predicted_[j].q_W, proxy_[j].q_W) - clutch_theta_W_[j];
    const Eigen::Vector3d f_c = gains_.k_n_m * dp + (gains_.b_ns_m + b) * (v_dev_[j] - v_[j]);
    const Eigen::Vector3d tau_c = gains_.k_nm_rad * dq + (gains_.b_nms_rad + b_rot) * (w_dev_[j] - w_[j]);
    const double f_max = limits_.max_force_n / map_.scale;
    const double sat = f_c.norm() > f_max ? f_max / f_c.norm() : 1.0;
    const double sat_rot = tau_c.norm() > limits_.max_torque_nm ? limits_.max_torque_nm / tau_c.norm() : 1.0;
    b_.segment<3>(6 * j) = mass_[j] * v_[j] + dt * (sat * f_c + (gains_.b_ns_m + b) * v_[j]);
    b_.segment<3>(6 * j + 3) = I_W * w_[j] + dt * (sat_rot * tau_c + (gains_.b_nms_rad + b_rot) * w_[j]);
    if (has_model) {
      x_rel_.segment<3>(6 * j) = proxy_[j].p_W - model.x0[j].p_W;
      x_rel_.segment<3>(6 * j + 3) = hand::rotation_difference(proxy_[j].q_W, model.x0[j].q_W);
      v0_.segment<3>(6 * j) = model.v0[j];
      v0_.segment<3>(6 * j + 3) = model.w0[j];
    }
  }
  const double h = weight * dt;
  // The prepared solver serves gloves at full weight with the parameters it was prepared for.
  const bool prepared =
      use_model && handles_ >= kMinPreparedHandles && weight == 1.0 && solver_matches(model.solver, dt);
  if (use_model) {
    if (!late) {
      late_t_end_ns_ = 0;
    } else if (late_t_end_ns_ != model.t_end_ns) {
      late_t_end_ns_ = model.t_end_ns;
      late_x_rel_ = x_rel_;
    }
    b_.noalias() += h * (model.K * (late ? late_x_rel_ : x_rel_));
    if (prepared) {
      b_.noalias() += h * model.solver.anchor_force;
    } else {
      b_.noalias() += h * model.F0;
      // - h D v0: D couples the handles, so handle j's anchor velocity acts through its columns of D
      // on all 6m rows, not only on handle j's.
      b_.noalias() -= h * (model.D * v0_);
    }
  }
  bool ok = b_.allFinite();
  for (int j = 0; ok && j < handles_; ++j) ok = std::isfinite(a_lin_[j]) && a_rot_[j].allFinite();
  bool solved = false, dense = false;
  if (ok && handles_ >= kMinPreparedHandles) {
    if (!use_model && !contacts_on) {
      // No model: A is block diagonal, each handle's blocks solved alone.
      for (int j = 0; j < handles_; ++j) {
        v_next_.segment<3>(6 * j) = b_.segment<3>(6 * j) / a_lin_[j];
        v_next_.segment<3>(6 * j + 3) = a_rot_[j].ldlt().solve(Eigen::Vector3d(b_.segment<3>(6 * j + 3)));
      }
      solved = true;
    } else {
      solved = prepared && solve_prepared(model, h, tau);
      if (!solved) ++solver_fallbacks_;
    }
  }
  if (ok && !solved) {
    A_.setZero();
    for (int j = 0; j < handles_; ++j) {
      A_.block<3, 3>(6 * j, 6 * j).diagonal().setConstant(a_lin_[j]);
      A_.block<3, 3>(6 * j + 3, 6 * j + 3) = a_rot_[j];
    }
    if (use_model) {
      A_.noalias() -= h * model.D;
      A_.noalias() -= (h * tau) * model.K;
    }
    ok = A_.allFinite();
    if (ok && handles_ == 1) {
      // A stylus's 6 x 6 system at fixed size, and the rows' Q = A^-1 G by its inverse: Eigen's
      // dynamic-size LU and its blocked triangular solves of G (6 x 3c) took 17 % of the ticks'
      // instructions on a stylus press (callgrind, Touch/SlowVisualPress at 60 Hz).
      lu6_.compute(A_.topLeftCorner<6, 6>());
      v_next_.noalias() = lu6_.solve(b_.head<6>());
      dense = true;
    } else if (ok) {
      lu_.compute(A_);
      v_next_.noalias() = lu_.solve(b_);
      dense = true;
    }
  }
  if (ok && contacts_on) ok = solve_contacts(model, dt, tau, dense);
  if (!ok || !v_next_.allFinite()) return TickSolve::failed;
  for (int j = 0; j < handles_; ++j)
    if (!(v_next_.segment<3>(6 * j).norm() < kMaxProxySpeed_m_s)) return TickSolve::too_fast;
  if (has_model) limit_to_clearance(model, dt);
  return TickSolve::solved;
}

void ProxyHand::limit_to_clearance(const HapticModel& model, double dt) {
  // The model knows the contacts its step found and nothing beyond them: carried past the nearest
  // skin point that is not one of them, the proxy could pass through a surface (a hard press that
  // slides off a body and falls onto the table within one slow visual step), and the world, driven
  // to it, would follow. Each plane bounds how far the handle's displacement from x0 closes its gap;
  // a velocity that would pass one is scaled down, the handle's whole velocity, so that kinetic
  // energy only goes down (pushing back along the normal instead would spin a phalanx proxy, whose
  // rotational inertia is tiny, when a turn closes the gap). The planes hold only surfaces within
  // hand::kClearanceLook_m of the skin: the handle's skin goes no farther from x0 than that either
  // (a stylus that jumped 8 cm during a stall, 16 cm in the world, went 19.5 mm into the movable
  // bunny and 2.9 m through the fixed one past planes that did not reach that far; with this bound
  // nothing resets: StalledServer).
  for (int j = 0; j < handles_; ++j) {
    const int planes = std::min(model.clearance_count[j], hand::kClearancePlanes);
    if (planes <= 0 && !model.skin_known) continue;
    const Eigen::Vector3d dx = proxy_[j].p_W - model.x0[j].p_W;
    const Eigen::Vector3d dtheta = hand::rotation_difference(proxy_[j].q_W, model.x0[j].q_W);
    const Eigen::Vector3d move = dt * v_next_.segment<3>(6 * j), turn = dt * v_next_.segment<3>(6 * j + 3);
    const double keep = planes > 0 ? hand::clearance_share(model.clearance[j], planes, dx, dtheta, move, turn) : 1.0;
    const double travel =
        model.skin_known ? hand::free_travel_share(dx, dtheta, move, turn, model.skin_radius_m[j]) : 1.0;
    if (std::min(keep, travel) < 1.0) {
      v_next_.segment<6>(6 * j) *= std::min(keep, travel);
      ++clearance_limits_;
      if (travel < keep) ++travel_limits_;
    }
  }
}

bool ProxyHand::solve_contacts(const HapticModel& model, double dt, double tau, bool dense) {
  const TickContacts& c = model.contacts;
  const int n = 6 * handles_, r = 3 * c.count;
  if (c.count > kMaxTickContacts || c.G.rows() != n || c.G.cols() != r || c.W.rows() != r || c.U_K.cols() != n)
    return false;
  // The rows' velocities at the proxies' contact-free answer v: the model's pose is taken at the
  // lookahead x + tau v as for F* (integrate).
  x_look_.noalias() = x_rel_ + tau * v_next_;
  dv_.noalias() = v_next_ - v0_;
  u_.noalias() = c.u0;
  u_.noalias() += c.U_K * x_look_;
  u_.noalias() += c.U_D * dv_;
  // Impulses lambda change the proxies' velocities by A^-1 dt G lambda, and the rows' by that through
  // tau U_K + U_D besides the flesh's W lambda: the Delassus operator of the proxies and the flesh,
  // W + P Q (LowRankDelassus) when lu_ (a stylus: lu6_) holds A, the prepared W_proxy otherwise.
  // A fading model's contacts hold at full strength (integrate).
  low_rank_ = dense;
  if (dense) {
    if (handles_ == 1) {
      a_inv6_ = lu6_.inverse();
      Q_.noalias() = a_inv6_.lazyProduct(c.G);
    } else {
      Q_.noalias() = lu_.solve(c.G);
    }
    P_.noalias() = (dt * tau) * c.U_K;
    P_.noalias() += dt * c.U_D;
    for (int i = 0; i < c.count; ++i) {
      blocks_[i] = c.W.block<3, 3>(3 * i, 3 * i);
      blocks_[i].noalias() += P_.middleRows<3>(3 * i) * Q_.middleCols<3>(3 * i);
    }
  } else if (c.proxy_prepared) {
    for (int i = 0; i < c.count; ++i) blocks_[i] = c.W_proxy.block<3, 3>(3 * i, 3 * i);
  } else {
    return false;
  }
  // Warm start: the last tick's impulses under the same model, else the model's own at its anchor.
  const bool same_model = warm_start_valid_ && model.t_end_ns == lambda_t_end_ns_ && model.resyncs == lambda_resyncs_ &&
                          lambda_.size() == r;
  if (!same_model) lambda_ = c.lambda0;
  for (int i = 0; i < c.count; ++i) {
    lambda_.segment<3>(3 * i) = hand::project_to_cone(lambda_.segment<3>(3 * i), c.mu[i]);
    tangent_step_[i] = hand::pgs_tangent_step(blocks_[i], 0);
  }
  // A few sweeps find the active set, which the polish then solves exactly; the rest of the sweeps
  // only when that is not a solution. All 8 sweeps at every tick made the first tick of each model
  // (warm-started from the model's own impulses) the tick's p99: 45 us against a median of 1.4 us,
  // the stylus press on the movable bunny at 30 Hz.
  bool converged = false;
  const auto sweeps = [&](int count) {
    if (low_rank_) {
      LowRankDelassus op{c.W, P_, Q_, blocks_, u_, y_, c.count};
      return hand::pgs_sweeps_on(op, c.bias, c.mu, tangent_step_, c.count, lambda_, count, kTickContactTolerance,
                                 converged);
    }
    hand::DenseDelassus<TickRowMatrix, TickRowVector> op{c.W_proxy, u_, c.count};
    return hand::pgs_sweeps_on(op, c.bias, c.mu, tangent_step_, c.count, lambda_, count, kTickContactTolerance,
                               converged);
  };
  if (low_rank_) {
    u_.noalias() += c.W * lambda_;
    y_.noalias() = Q_ * lambda_;
  } else {
    u_.noalias() += c.W_proxy * lambda_;
  }
  ++contact_solves_;
  failed_a_ = 0;
  const int first = std::min(kTickContactFirstSweeps, contact_sweeps_limit_);
  contact_sweeps_ = sweeps(first);
  contact_sweeps_total_ += contact_sweeps_;
  if (!lambda_.allFinite()) return false;
  const bool exact = polish_contacts(c) || converged;
  if (!exact && contact_sweeps_limit_ > first) {
    const int more = sweeps(contact_sweeps_limit_ - first);
    contact_sweeps_ += more;
    contact_sweeps_total_ += more;
    if (!lambda_.allFinite()) return false;
    if (!polish_contacts(c) && !converged) ++contact_unconverged_;
  } else if (!exact) {
    ++contact_unconverged_;
  }
  lambda_t_end_ns_ = model.t_end_ns;
  lambda_resyncs_ = model.resyncs;
  warm_start_valid_ = true;
  // v += A^-1 dt G lambda.
  if (dense) {
    v_next_.noalias() += dt * (Q_ * lambda_);
    return true;
  }
  rhs_.noalias() = dt * (c.G * lambda_);
  b_ += rhs_;
  return solve_prepared(model, dt, tau);
}

double ProxyHand::delassus(const TickContacts& c, int row, int col) const {
  return low_rank_ ? c.W(row, col) + P_.row(row).dot(Q_.col(col)) : c.W_proxy(row, col);
}

bool ProxyHand::polish_contacts(const TickContacts& c) {
  // The active set the sweeps found: pushing normals, and both tangents of a contact inside its cone
  // (sticking). A sliding contact's tangent impulse stays as the sweeps left it. On that set the
  // problem is linear, W_AA lambda_A = target_A - (u - W lambda)_A, solved exactly; the answer
  // replaces the sweeps' if it keeps every condition (PGS converges linearly, and slowly where the
  // proxies' response makes the rows stiff).
  int a = 0;
  bool sliding = false;
  for (int i = 0; i < c.count; ++i) {
    const double ln = lambda_[3 * i];
    if (ln <= 0) continue;
    active_[a++] = 3 * i;
    if (lambda_.segment<2>(3 * i + 1).norm() < (1 - 1e-9) * c.mu[i] * ln)
      active_[a++] = 3 * i + 1, active_[a++] = 3 * i + 2;
    else
      sliding = true;
  }
  if (a == 0) return false;
  // The set this tick's first polish failed on, too large to redistribute, with no sliding contact
  // (whose fixed tangent impulses the sweeps move): its linear system and so its answer are the same.
  // On the stylus press on the movable bunny (sets of ~10 of 24 rows, the bunny's redundant supports
  // among them) nearly every polish failed, and the second one took 12 % of the ticks' instructions.
  if (!sliding && a == failed_a_ && std::equal(active_, active_ + a, failed_active_)) return false;
  // The rows' velocities now, every row (the low-rank operator keeps them in two parts).
  u_now_ = u_;
  if (low_rank_) u_now_.noalias() += P_ * y_;
  W_aa_.resize(a, a);
  rhs_a_.resize(a);
  for (int i = 0; i < a; ++i) {
    const int row = active_[i];
    // The target: the bias on a normal row, no slip on a tangent row.
    rhs_a_[i] = (row % 3 == 0 ? c.bias[row / 3] : 0.0) - u_now_[row];
    for (int k = 0; k < a; ++k) W_aa_(i, k) = delassus(c, row, active_[k]);
  }
  // rhs_a_ = target - u now; the correction d of the active impulses solves W_AA d = rhs_a_.
  Correction result = Correction::breaks_active;
  if (a <= kMaxRedundantRows) {
    lu_rows_.compute(W_aa_);
    delta_a_.noalias() = lu_rows_.solve(rhs_a_);
    if (delta_a_.allFinite()) result = try_correction(c, a);
    // An active row broke a condition: redundant rows give W_AA a vanishing pivot (rcond ~1e-17 for
    // the tool on three points), a wrong set does not. (An inactive row pushed in: the set is wrong,
    // whatever impulses the active rows pass among themselves.)
    if (result == Correction::breaks_active && lu_rows_.rcond() < kRedundantRank && redistribute(c, a))
      result = try_correction(c, a);
  } else {
    // A larger set takes its least-norm correction. Of the stylus's sets on the movable bunny (10-15
    // rows, its redundant supports among them) partial pivoting answered 1 of 1551; the least-norm
    // correction answers half, the others being wrong sets (a normal it makes pull, a contact it
    // pushes out of its cone). Not redistributed: that costs O(a) per null-space dimension per
    // projection, and these sets have several.
    cod_.setThreshold(kRedundantRank);
    cod_.compute(W_aa_);
    delta_a_ = least_norm_solve(rhs_a_);
    if (delta_a_.allFinite()) result = try_correction(c, a);
  }
  if (result != Correction::solution && !sliding && a > kMaxRedundantRows) {
    failed_a_ = a;
    std::copy(active_, active_ + a, failed_active_);
  }
  return result == Correction::solution;
}

const TickRowVector& ProxyHand::least_norm_solve(const TickRowVector& b) {
  // As Eigen's CompleteOrthogonalDecomposition::solve (A P = Q [T 0; 0 0] Z): c = Q^* b, T z = c's
  // first rank rows, y = Z^* [z; 0], x = P y; Z^*'s reflections applied with a workspace of ours,
  // where Eigen's allocates one on the heap.
  const Eigen::Index rank = cod_.rank(), cols = cod_.cols();
  cod_solved_.setZero(cols);
  if (rank == 0) return cod_solved_;
  cod_c_ = b;
  cod_c_.applyOnTheLeft(cod_.householderQ().setLength(rank).adjoint());
  cod_y_.setZero(cols);
  cod_y_.head(rank) = cod_c_.head(rank);
  cod_.matrixQTZ().topLeftCorner(rank, rank).triangularView<Eigen::Upper>().solveInPlace(cod_y_.head(rank));
  if (rank < cols)
    for (Eigen::Index k = 0; k < rank; ++k) {
      if (k != rank - 1) cod_y_.row(k).swap(cod_y_.row(rank - 1));
      cod_y_.segment(rank - 1, cols - rank + 1)
          .applyHouseholderOnTheLeft(cod_.matrixQTZ().row(k).tail(cols - rank).adjoint(), cod_.zCoeffs()(k), cod_work_);
      if (k != rank - 1) cod_y_.row(k).swap(cod_y_.row(rank - 1));
    }
  cod_solved_.noalias() = cod_.colsPermutation() * cod_y_;
  return cod_solved_;
}

ProxyHand::Correction ProxyHand::try_correction(const TickContacts& c, int a) {
  // lambda_ + delta_a_ on the active rows, kept if it keeps every condition.
  const int r = 3 * c.count;
  candidate_ = lambda_;
  for (int i = 0; i < a; ++i) candidate_[active_[i]] += delta_a_[i];
  // u += (W + P Q) d over the active columns.
  u_candidate_ = u_now_;
  const TickRowMatrix& W = low_rank_ ? c.W : c.W_proxy;
  dy_.setZero(6 * handles_);
  for (int i = 0; i < a; ++i) {
    u_candidate_.head(r) += W.col(active_[i]).head(r) * delta_a_[i];
    if (low_rank_) dy_.noalias() += Q_.col(active_[i]) * delta_a_[i];
  }
  if (low_rank_) u_candidate_.noalias() += P_ * dy_;
  const auto pushed_in = [&](int i) { return u_candidate_[3 * i] - c.bias[i] < -kRowVelocityTolerance; };
  for (int i = 0; i < c.count; ++i)  // the rows out of the set first (their impulses stay 0)
    if (lambda_[3 * i] <= 0 && pushed_in(i)) return Correction::breaks_inactive;
  for (int i = 0; i < c.count; ++i) {
    const double ln = candidate_[3 * i];
    if (ln < 0 || candidate_.segment<2>(3 * i + 1).norm() > c.mu[i] * ln * (1 + 1e-9) + 1e-300 || pushed_in(i))
      return Correction::breaks_active;
  }
  // The answer; the rows' velocities are not needed past it (the next tick starts them afresh).
  lambda_ = candidate_;
  return Correction::solution;
}

bool ProxyHand::redistribute(const TickContacts& c, int a) {
  // Redundant rows (more of them on a rigid body than it has DOFs: a tool resting on a body at three
  // points, nine rows of rank six) make W_AA singular. Its answers then form an affine set, the
  // least-norm correction plus any impulses the rows pass among themselves without moving anything
  // (W_AA's null space, of a few dimensions), and partial pivoting picks one of 1e4-1e8 N s that
  // fails every check. The one kept is found by alternating projections between that set and the
  // conditions on the active rows (normals >= 0, a sticking contact's impulse in its cone, a sliding
  // one's normal at least its fixed tangent over mu), both convex, so that they converge to a point
  // of both where one exists; run in the null space's coordinates, each costs O(a) per dimension.
  cod_.setThreshold(kRedundantRank);
  cod_.compute(W_aa_);
  const int k = a - static_cast<int>(cod_.rank());
  if (k == 0) return false;  // not redundant: the set itself is wrong
  // An orthonormal basis N of the null space: unit vectors less their least-norm images
  // (I - W^+ W) e_j, by Gram-Schmidt.
  null_.resize(a, k);
  int found = 0;
  for (int j = 0; j < a && found < k; ++j) {
    r_a_.setZero(a);
    r_a_[j] = 1;
    b_a_ = W_aa_.col(j);
    r_a_ -= least_norm_solve(b_a_);
    for (int q = 0; q < found; ++q) r_a_ -= null_.col(q).dot(r_a_) * null_.col(q);
    const double norm = r_a_.norm();
    if (norm > 1e-6) null_.col(found++) = r_a_ / norm;
  }
  if (found < k) return false;
  // x0 = lambda_A + the least-norm correction; x = x0 + N z.
  x0_a_.resize(a);
  for (int i = 0; i < a; ++i) x0_a_[i] = lambda_[active_[i]];
  x0_a_ += least_norm_solve(rhs_a_);
  z_.setZero(k);
  x_a_ = x0_a_;
  for (int iteration = 0; iteration < kRedistributeIterations; ++iteration) {
    bool inside = true;
    for (int q = 0; q < a;) {
      const int i = active_[q] / 3;
      const bool sticking = q + 2 < a && active_[q + 1] == 3 * i + 1;
      if (sticking) {
        // Onto the cone |t| <= mu n (Euclidean), narrowed by kRedistributeMargin so that a contact the
        // redundancy lets stick is left inside it: along its edge through (n, |t|) where outside.
        const double n = x_a_[q], t = std::hypot(x_a_[q + 1], x_a_[q + 2]);
        const double mu = (1 - kRedistributeMargin) * c.mu[i];
        if (t > mu * n * (1 + 1e-12)) {
          inside = false;
          if (mu * t <= -n) {
            x_a_.segment<3>(q).setZero();
          } else {
            const double n_edge = (n + mu * t) / (1 + mu * mu);
            x_a_[q] = n_edge;
            x_a_.segment<2>(q + 1) *= t > 0 ? mu * n_edge / t : 0.0;
          }
        }
        q += 3;
      } else {
        const double least = c.mu[i] > 0 ? lambda_.segment<2>(3 * i + 1).norm() / c.mu[i] : 0.0;
        if (x_a_[q] < least) inside = false, x_a_[q] = least;
        q += 1;
      }
    }
    if (inside) break;
    // Back onto the set: the nearest x0 + N z.
    r_a_ = x_a_ - x0_a_;
    z_.noalias() = null_.transpose() * r_a_;
    x_a_ = x0_a_;
    x_a_.noalias() += null_ * z_;
  }
  for (int i = 0; i < a; ++i) delta_a_[i] = x_a_[i] - lambda_[active_[i]];
  return delta_a_.allFinite();
}

bool ProxyHand::solver_matches(const TickSolver& s, double dt) const {
  if (!s.prepared || s.dt_s != dt || s.gains.k_n_m != gains_.k_n_m || s.gains.b_ns_m != gains_.b_ns_m ||
      s.gains.k_nm_rad != gains_.k_nm_rad || s.gains.b_nms_rad != gains_.b_nms_rad)
    return false;
  for (int j = 0; j < handles_; ++j)
    if (s.mass_kg[j] != mass_[j] || s.inertia_B[j] != inertia_B_[j]) return false;
  return true;
}

void ProxyHand::apply_prepared(const TickSolver& s, double tau, const HapticVector& rhs) {
  const int n = 6 * handles_;
  // c = U^T B^-1 rhs; (I - tau H) y = c; v = U y.
  c_.noalias() = s.G * rhs;
  // M = I - tau H is upper Hessenberg. Column operations from the right reduce it to upper
  // triangular, M Q = R: step i (n - 1 down to 1) takes the larger of the two entries of row i
  // (in the column reduced so far, w, and in M's column i - 1) as pivot, swapping the two columns
  // if it is the latter (partial pivoting, |multiplier| <= 1), and subtracts the pivot column from
  // the other, which becomes the next w. Column i of R is then final, so R z = c is back-solved
  // column by column as it goes; y = Q z follows by replaying the steps. R is never stored: the
  // tick reads H once, in order, and writes n numbers.
  double* __restrict w = column_.data();
  double* __restrict c = c_.data();
  double* __restrict multiplier = multiplier_.data();
  const double* last = s.hessenberg_column(n - 1);
  for (int r = 0; r < n; ++r) w[r] = -tau * last[r];
  w[n - 1] += 1.0;
  for (int i = n - 1; i >= 1; --i) {
    const double* __restrict h = s.hessenberg_column(i - 1);  // M's column i - 1 is e_{i-1} - tau h, rows 0 .. i
    const double w_i = w[i], m_i = -tau * h[i];
    swapped_[i] = std::abs(m_i) > std::abs(w_i);
    if (swapped_[i]) {
      // M's column i - 1 is the pivot; w, less it, becomes the next w.
      const double l = w_i / m_i, z = c[i] / m_i;
      for (int r = 0; r < i; ++r) {
        const double p = -tau * h[r];
        c[r] -= z * p;
        w[r] -= l * p;
      }
      c[i - 1] -= z;
      w[i - 1] -= l;
      multiplier[i] = l;
      c[i] = z;
    } else {
      const double l = m_i / w_i, z = c[i] / w_i;
      for (int r = 0; r < i; ++r) {
        const double p = w[r];
        c[r] -= z * p;
        w[r] = -tau * h[r] - l * p;
      }
      w[i - 1] += 1.0;
      multiplier[i] = l;
      c[i] = z;
    }
  }
  c[0] /= w[0];
  // y = Q z, Q = T_{n-1} E_{n-1} ... T_1 E_1: E_i subtracted multiplier_i times column i from
  // column i - 1, T_i swapped the two.
  for (int i = 1; i < n; ++i) {
    c[i] -= multiplier[i] * c[i - 1];
    if (swapped_[i]) std::swap(c[i], c[i - 1]);
  }
  dv_.noalias() = s.U * c_;
}

bool ProxyHand::solve_prepared(const HapticModel& model, double h, double tau) {
  const TickSolver& s = model.solver;
  const double b2 = b_.squaredNorm(), limit2 = kRefineTolerance * kRefineTolerance * b2;
  apply_prepared(s, tau, b_);
  v_next_ = dv_;
  // The factors are of the very matrix the tick solves (integrate takes the proxies' inertia at the
  // model's anchors), so one application is exact but for rounding. The probes check it (TickSolver::Z);
  // if one objects, the residual against the exact matrix, b - A v, decides, and a rounding-level
  // miss is refined.
  bool probes_pass = v_next_.allFinite();
  for (int i = 0; probes_pass && i < TickSolver::kProbes; ++i) {
    const double z_r = s.Z.row(i).dot(b_) - (s.ZB.row(i) - tau * s.ZC.row(i)).dot(v_next_);
    probes_pass = std::abs(z_r) <= kRefineTolerance * std::sqrt(b2);
  }
  if (probes_pass) return true;
  ++solver_refinements_;
  for (int corrections = 0;; ++corrections) {
    r_.noalias() = h * (model.D * v_next_);
    r_.noalias() += (h * tau) * (model.K * v_next_);
    r_ += b_;
    for (int j = 0; j < handles_; ++j) {
      r_.segment<3>(6 * j) -= a_lin_[j] * v_next_.segment<3>(6 * j);
      r_.segment<3>(6 * j + 3) -= a_rot_[j] * v_next_.segment<3>(6 * j + 3);
    }
    const double r2 = r_.squaredNorm();
    if (!std::isfinite(r2)) return false;
    if (r2 <= limit2) return true;
    if (corrections == kMaxRefinements) return false;
    apply_prepared(s, tau, r_);
    v_next_ += dv_;
  }
}

namespace {

// Shrinks an unfelt stretch u as far as the felt stretch s - u keeps its length (energy): u times
// max(0, 2 s.u / u.u - 1), where |s - l u| = |s - u|. A device backing out of where its gate
// opened gets its unfelt share back at no cost; one pressing on keeps it.
void release_unfelt(Eigen::Vector3d& u, const Eigen::Vector3d& s) {
  const double uu = u.squaredNorm();
  if (uu == 0) return;
  const double l = std::max(2.0 * s.dot(u) / uu - 1.0, 0.0);
  if (l < 1.0) u *= l;
}

}  // namespace

ReplyWrench ProxyHand::reply(int j, double output_scale, double dt_since_last_s, bool gated, double unfelt_share) {
  ReplyWrench r;
  if (j < 0 || j >= handles_ || !have_device_) return r;
  // The coupling wrench on the proxy; the device feels it reversed (f_D = s R^T f_W keeps power equal).
  // The coupling's damper with the safe model's share of the last integration (solve_velocities).
  // A gated frame's stretch is unfelt, and stays so after its gate opens until the device backs out
  // of it (release_unfelt): a frame whose gate flips from one visual step to the next is then felt
  // as a spring that only ever engages where its gate opened. Felt in full at once, the stretch the
  // proxy built while its device sank in unfelt pushed the device out each time the gate opened,
  // from deeper each time (a relay: ~12 mJ a cycle on a glove's phalanx resting on a box's edge,
  // Touch/GlovePressHold).
  // A bridged gap's clutch is released as the device backs out (as a gated frame's unfelt stretch,
  // below), and the device feels the coupling to itself less what is left of it.
  const Eigen::Vector3d full_stretch = device_[j].p_W - proxy_[j].p_W;
  const Eigen::Vector3d full_twist = hand::rotation_difference(device_[j].q_W, proxy_[j].q_W);
  release_unfelt(clutch_p_W_[j], full_stretch);
  release_unfelt(clutch_theta_W_[j], full_twist);
  const Eigen::Vector3d stretch = full_stretch - clutch_p_W_[j], twist = full_twist - clutch_theta_W_[j];
  if (gated) {
    unfelt_p_W_[j] = stretch, unfelt_theta_W_[j] = twist;
  } else if (unfelt_share > 0 && bridged_now_) {
    // Cut off for longer than the re-sync gap, the device sank on past its stretch while its reply
    // faded: that share of all it would feel is unfelt. Felt again where the device had sunk to, the
    // stretch from before the gap pushed it back out: +1.1e-2 J in one 80 ms stop of the whole
    // process pressing the chaos test's wall (scripts/chaos-process-stops).
    unfelt_p_W_[j] += unfelt_share * (stretch - unfelt_p_W_[j]);
    unfelt_theta_W_[j] += unfelt_share * (twist - unfelt_theta_W_[j]);
  } else if (unfelt_share > 0) {
    // What the stretch grew by since the last reply went unfelt: the device held the reply from
    // before, then less. Unfelt in the faded share only, the rest pushed a device that sank through
    // a 30 ms stop back out, and pulled one lifting through it (0.92 N; ServerStalls, a stopped
    // machine) or gave the chaos test's wall up to +5.6e-4 J in four such stops
    // (scripts/chaos-process-stops 30).
    unfelt_p_W_[j] += stretch - last_stretch_p_W_[j];
    unfelt_theta_W_[j] += twist - last_twist_W_[j];
  } else {
    release_unfelt(unfelt_p_W_[j], stretch);
    release_unfelt(unfelt_theta_W_[j], twist);
  }
  last_stretch_p_W_[j] = stretch, last_twist_W_[j] = twist;
  const double b_c = gains_.b_ns_m + safe_share_ * safe_b_ns_m_[j];
  const double b_c_rot = gains_.b_nms_rad + safe_share_ * safe_b_nms_rad_[j];
  const Eigen::Vector3d f_W = gains_.k_n_m * (stretch - unfelt_p_W_[j]) + b_c * (v_dev_[j] - v_[j]);
  const Eigen::Vector3d tau_W = gains_.k_nm_rad * (twist - unfelt_theta_W_[j]) + b_c_rot * (w_dev_[j] - w_[j]);
  const Eigen::Matrix3d R_DW = map_.R_WD.toRotationMatrix().transpose();
  // About the frame's origin: the handle sits at r = q_frame handle_p_F from it.
  const Eigen::Vector3d r_W = device_[j].q_W * (map_.handle_q_F[j].conjugate() * map_.handle_p_F[j]);
  Eigen::Vector3d f = -output_scale * map_.scale * (R_DW * f_W);
  Eigen::Vector3d tau = -output_scale * (R_DW * (tau_W + r_W.cross(f_W)));
  if (!f.allFinite() || !tau.allFinite()) {
    reset();
    return r;
  }
  const double dt = std::clamp(dt_since_last_s, kMinReplyInterval_s, kMaxReplyInterval_s);
  // The port's power is f . v + tau . w with both about the handle; tau about
  // the frame's origin adds r x f, and v there lacks w x r: the same power. A finger actuator that
  // pushes against the palm does work only through the finger's motion relative to the palm: counted
  // against its own velocity, a glove lifting a box with its palm was credited with the box's weight
  // on its fingers times the lift (the observer found its ports passive, -0.01 to -0.03 J, while the
  // glove gained +0.017 to +0.037 J: Touch/GraspRelease).
  const auto port = [&](const Eigen::Vector3d& v_W, const Eigen::Vector3d& w_W, const Eigen::Vector3d& v0_W,
                        const Eigen::Vector3d& w0_W, Eigen::Vector3d& v_D, Eigen::Vector3d& w_D) {
    Eigen::Vector3d v = v_W, w = w_W;
    if (fingers_on_palm_ && j > 0) {
      v -= v0_W + w0_W.cross(device_[j].p_W - device_[0].p_W);
      w -= w0_W;
    }
    v_D = R_DW * v / map_.scale;
    w_D = R_DW * w;
  };
  Eigen::Vector3d v_D, w_D, moved_D, turned_D;
  port(v_dev_[j], w_dev_[j], v_dev_[0], w_dev_[0], v_D, w_D);
  const Eigen::Vector3d r_D = R_DW * r_W / map_.scale;
  // The observer: the device held the last reply while it moved from its last pose to this one, so
  // that reply's work is exactly its wrench times this motion (against the filtered velocity times the
  // interval instead, it lagged the motion and missed +0.002 J of a glove's grasp).
  if (!motion_booked_[j]) {
    port(moved_p_W_[j], moved_theta_W_[j], moved_p_W_[0], moved_theta_W_[0], moved_D, turned_D);
    energy_in_[j] -= last_f_D_[j].dot(moved_D) + (last_tau_D_[j] - last_r_D_[j].cross(last_f_D_[j])).dot(turned_D);
    motion_booked_[j] = true;
  }
  // Passivity controller: the damping that brings the observer's deficit back to zero this tick,
  // shared by the two channels in proportion to what each can take.
  const double v2 = v_D.squaredNorm() + kPassivityRotationWeight_m2 * w_D.squaredNorm();
  passivity_b_[j] = 0;
  if (passivity_control_ && energy_in_[j] < -kPassivityBudget_J / handles_ && v2 > kMinPassivitySpeed2_m2_s2) {
    const double b = std::min(-energy_in_[j] / (dt * v2), kMaxPassivityDamping_ns_m);
    damped_j_[j] += b * v2 * dt;
    passivity_b_[j] = b;
    f -= b * v_D;  // at the handle, so about the frame's origin with its moment
    tau -= b * kPassivityRotationWeight_m2 * w_D + r_D.cross(b * v_D);
    ++passivity_actions_;
  }
  r.clamped = clamp_norm(f, limits_.max_force_n);
  r.clamped = clamp_norm(tau, limits_.max_torque_nm) || r.clamped;
  // Slew limit against the last reply: a jump of the target force becomes a ramp.
  Eigen::Vector3d df = f - last_f_D_[j], dtau = tau - last_tau_D_[j];
  const double torque_rate = limits_.max_force_rate_n_s * limits_.max_torque_nm / limits_.max_force_n;
  r.clamped = clamp_norm(df, limits_.max_force_rate_n_s * dt) || r.clamped;
  r.clamped = clamp_norm(dtau, torque_rate * dt) || r.clamped;
  r.f_D = last_f_D_[j] + df;
  r.tau_D = last_tau_D_[j] + dtau;
  last_f_D_[j] = r.f_D;
  last_tau_D_[j] = r.tau_D;
  last_r_D_[j] = r_D;
  if (r.clamped) ++clamps_;
  return r;
}

}  // namespace hapticd::haptic
