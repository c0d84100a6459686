#pragma once
// The haptic loop's physics (seed 004 section 3, Fig. 2 bottom): per hand, a
// proxy of its rigid handle(s) integrated implicitly under the visual loop's
// linearized coupling force F*(x, v) = F0 + K (x - x0) + D (v - v0) and a
// two-way viscoelastic virtual coupling to the device pose; the device gets the
// coupling force reversed, mapped to device space, clamped and rate-limited
// (DESIGN.md section 5). Fixed capacities: nothing here allocates.
#include <Eigen/Cholesky>
#include <Eigen/Core>
#include <Eigen/Geometry>
#include <Eigen/LU>
#include <Eigen/QR>
#include <algorithm>
#include <cstdint>
#include <limits>

#include "hand_models/rigid_handle.hpp"

namespace hapticd::haptic {

constexpr int kMaxHapticHandles = 16;
constexpr int kMaxHapticDofs = 6 * kMaxHapticHandles;
using HapticVector = Eigen::Matrix<double, Eigen::Dynamic, 1, 0, kMaxHapticDofs, 1>;
using HapticMatrix = Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, 0, kMaxHapticDofs, kMaxHapticDofs>;

// Virtual coupling and proxy parameters, in world units (the device's are mapped in).
struct CouplingGains {
  double k_n_m = 250.0, b_ns_m = 0.4;       // translational
  double k_nm_rad = 1.0, b_nms_rad = 0.01;  // rotational
};

struct HapticPose {
  Eigen::Vector3d p_W = Eigen::Vector3d::Zero();
  Eigen::Quaterniond q_W = Eigen::Quaterniond::Identity();
};

// A hand's haptic step matrix at full model weight, A(tau) = B - tau C with B = P - h D and
// C = h K (ProxyHand::integrate; P: mass, coupling and the inertia at the model's handle
// orientations x0), prepared once per model by prepare_tick_solver so the 1 kHz tick solves in
// O(n^2): B^-1 C = U H U^T (H upper Hessenberg, U orthogonal), hence A(tau) = B U (I - tau H) U^T
// for every lookahead tau (the shifted-Hessenberg method of Laub, "Efficient multivariable
// frequency response computations", IEEE TAC 26(2), 1981, with the shift as the tick's lookahead).
struct TickSolver {
  bool prepared = false;
  // What it was prepared for: a session whose haptic period, gains or handles differ uses the LU.
  double dt_s = 0;
  CouplingGains gains;
  double mass_kg[kMaxHapticHandles]{};
  Eigen::Matrix3d inertia_B[kMaxHapticHandles];
  HapticMatrix G;             // U^T B^-1
  HapticMatrix U;             // orthogonal
  HapticVector anchor_force;  // F0 - D v0: the model's force at its anchor pose, the anchor's damping taken out
  // The tick's check of its answer v (Freivalds' randomized verification): Z (b - A(tau) v) = 0
  // for kProbes random unit rows z_i of Z, with Z B and Z C precomputed: O(n) per probe instead
  // of the two dense products of the residual b - A v. Each probe asks |z . r| <= tol |b|; a random
  // direction sees about |r| / sqrt(n) of a residual r, and less than a tenth of that with
  // probability ~0.08, so all four pass a residual of 10 sqrt(n) tol |b| (~1e-10 |b| for a glove)
  // with probability ~4e-5 and one of 100 sqrt(n) tol |b| with ~4e-13. A non-finite answer never
  // passes; a probe that objects sends the tick to the exact residual.
  static constexpr int kProbes = 4;
  Eigen::Matrix<double, kProbes, Eigen::Dynamic, Eigen::RowMajor, kProbes, kMaxHapticDofs> Z, ZB, ZC;
  // H upper Hessenberg, packed by columns: column j holds rows 0 .. min(j + 1, n - 1), so where it
  // starts does not depend on n; hessenberg_column(j)[i] is H(i, j).
  static constexpr int column_offset(int j) { return j * (j + 3) / 2; }
  static constexpr int kPackedSize = (kMaxHapticDofs - 1) * (kMaxHapticDofs + 2) / 2 + kMaxHapticDofs;
  double H[kPackedSize]{};
  double* hessenberg_column(int j) { return H + column_offset(j); }
  const double* hessenberg_column(int j) const { return H + column_offset(j); }
};

// The contacts a model lets the tick make and break (the visual step's HandleContactModel, fixed
// capacity): c contacts in frames (n, t1, t2), 3c rows; with row impulses lambda (N s over the model's
// step) the model's wrench gains G lambda and the rows' relative velocities are
// u = u0 + U_K dx + U_D (v - v0) + W lambda, with 0 <= lambda_n _|_ u_n - bias >= 0 and the Coulomb cone.
// Each tick solves that complementarity problem together with the proxies' own implicit step
// (ProxyHand::integrate), so a contact that would pull releases within the tick.
constexpr int kMaxTickContacts = 24;
// The Gauss-Seidel sweeps a tick's contact solve runs at most (ProxyHand::set_contact_sweeps).
constexpr int kDefaultTickContactSweeps = 8, kMaxTickContactSweeps = 10000;
constexpr int kMaxTickRows = 3 * kMaxTickContacts;
using TickRowVector = Eigen::Matrix<double, Eigen::Dynamic, 1, 0, kMaxTickRows, 1>;
using TickRowMatrix = Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, 0, kMaxTickRows, kMaxTickRows>;
using TickRowByDof = Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, 0, kMaxTickRows, kMaxHapticDofs>;
using TickDofByRow = Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, 0, kMaxHapticDofs, kMaxTickRows>;
struct TickContacts {
  int count = 0;          // c; 0: the model has no contact rows
  TickDofByRow G;         // 6m x 3c
  TickRowMatrix W;        // 3c x 3c
  TickRowVector u0;       // 3c, at the anchor without impulses
  TickRowByDof U_K, U_D;  // 3c x 6m
  TickRowVector lambda0;  // 3c: the solution at the anchor, the first tick's warm start
  double bias[kMaxTickContacts]{}, mu[kMaxTickContacts]{};
  // The rows' Delassus operator with the proxies' own response for a model on kMinPreparedHandles or
  // more handles, W + (tau U_K + U_D) A(tau)^-1 h G at the tick's full weight and tau = half the
  // model's step (prepare_tick_solver; the tick cannot afford 3c solves of a glove's 96 DOFs), or
  // shorter (max_lookahead_s). The tick serves such a model at that lookahead through its step
  // (ProxyHand::integrate): at the live one, from the whole step down to h, the rows overshot early
  // in a step (a fingertip proxy arriving at -0.94 m/s as a model switched left at +1.29 m/s,
  // Touch/GlovePressHold) and let the proxies sink past them late in it.
  TickRowMatrix W_proxy;
  bool proxy_prepared = false;
  // The longest lookahead the tick may solve these rows with (prepare_tick_solver,
  // prepare_contact_lookahead; with W_proxy, the one it was formed at): the operator W + (tau U_K + U_D) A(tau)^-1 h G
  // is not symmetric, and past some tau its symmetric part stops being positive semidefinite: the rows can then give
  // energy, and the sweeps diverge or throw the proxy around (after a 92 ms step of a stalled server, at tau 0.085 s,
  // its least eigenvalue was -46 against 228 at the top, and the stylus's proxy swung 5-22 mm at up to 15 m/s).
  // Infinite: no bound found or none needed.
  double max_lookahead_s = std::numeric_limits<double>::infinity();
};

// One hand's handle-space model as the visual loop publishes it.
struct HapticModel {
  int handles = 0;  // 0: no model yet (the proxy then feels only the device)
  HapticVector F0;  // 6m, N and N m on each handle
  HapticMatrix K, D;
  HapticPose x0[kMaxHapticHandles];
  Eigen::Vector3d v0[kMaxHapticHandles], w0[kMaxHapticHandles];
  bool in_contact = false;
  bool handle_in_contact[kMaxHapticHandles]{};  // per handle: a skin point of its part touches something
  // The model is the force at the end of the coming visual step as a function of
  // the handle's state then: this is when that step ends (the proxy time base,
  // ns; 0 = unknown).
  std::uint64_t t_end_ns = 0;
  double step_s = 0;  // the length of that step, s
  TickContacts contacts;
  // Per handle, the nearest surfaces the model does not hold (World::clearance): the tick
  // carries the handle from x0 no closer to them than their gaps.
  hand::ClearancePlane clearance[kMaxHapticHandles][hand::kClearancePlanes];
  int clearance_count[kMaxHapticHandles]{};
  // Per handle, the farthest of its skin points from it, m (when skin_known: the world's models).
  // Beyond hand::kClearanceLook_m the planes above say nothing: the tick carries no skin point
  // farther than that from where they were measured (hand::free_travel_share).
  bool skin_known = false;
  double skin_radius_m[kMaxHapticHandles]{};
  // The hand's re-sync count the visual loop had applied (ProxyTargets::resyncs):
  // a model from before a re-sync describes the hand where it no longer is.
  std::uint32_t resyncs = 0;
  // Filled by prepare_tick_solver (the visual thread); whoever changes F0, K, D, x0, v0 or w0
  // clears solver.prepared or prepares again: the tick takes the model's matrix and anchor force
  // from the solver, and its probes check the answer against the matrix as prepared.
  TickSolver solver;
};

// Gloves and larger: below, the dense LU of the 6m system is as cheap as the prepared solve.
constexpr int kMinPreparedHandles = 4;

// Makes the stiffness K (6m x 6m) the tick renders on proxies coupled at `gains` passive: its
// symmetric part S loses its positive eigenvalues, measured against the coupling's stiffness C
// (k_n_m on each handle's translation, k_nm_rad on its rotation): the generalized eigenvalues mu of
// S against C above zero are set to zero, the least change of C^-1/2 S C^-1/2 (Frobenius) that does
// it. The antisymmetric part is kept. A K with none is left bit for bit. Returns the largest mu
// removed (0 when none was). O(m^3) on the visual thread (TickSolverPreparer).
double passive_stiffness(HapticMatrix& K, const CouplingGains& gains);
// Prepares model.solver for proxies of these handle masses, inertias (body frame) and gains
// stepped at `haptic_dt_s` (ProxyHand::configure's arguments and integrate's dt): an LU of B, a
// Hessenberg decomposition of B^-1 C, O(n^3) on the visual thread. Clears it and returns false
// when the model has fewer than kMinPreparedHandles handles, other than `handles`, or is not finite.
bool prepare_tick_solver(HapticModel& model, int handles, const double* mass_kg, const Eigen::Matrix3d* inertia_B,
                         const CouplingGains& gains, double haptic_dt_s);
// For a model on fewer handles (the tick forms its contact operator itself): sets
// model.contacts.max_lookahead_s to the longest lookahead, the model's step halved until it holds,
// at which that operator's symmetric part is positive semidefinite (to 1e-9 of its largest
// diagonal entry) for these proxies; h at the least. O(c^3) on the visual thread.
void prepare_contact_lookahead(HapticModel& model, const double* mass_kg, const Eigen::Matrix3d* inertia_B,
                               const CouplingGains& gains, double haptic_dt_s);

struct DeviceLimits {
  double max_force_n = 8.0, max_torque_nm = 0.5, max_force_rate_n_s = 1000.0;
};

// Device space D to world: x_W = offset_W + scale R_WD x_D. A tracked frame
// then carries its handle at a fixed pose in it (a glove's phalanx frame and
// the handle on that phalanx's flesh, FrameToHandle): identity for a stylus,
// whose pose is its handle's.
struct DeviceMap {
  double scale = 1.0;
  Eigen::Vector3d offset_W = Eigen::Vector3d::Zero();
  Eigen::Quaterniond R_WD = Eigen::Quaterniond::Identity();
  Eigen::Vector3d handle_p_F[kMaxHapticHandles];  // world units, in the frame
  Eigen::Quaterniond handle_q_F[kMaxHapticHandles];
  DeviceMap();
  DeviceMap(double scale, const Eigen::Vector3d& offset_W, const Eigen::Quaterniond& R_WD);
  // Handle j's pose when its frame is at (p_D, q_D).
  HapticPose to_world(int j, const Eigen::Vector3d& p_D, const Eigen::Quaterniond& q_D) const;
  // The frame as such (no handle offset).
  HapticPose to_world(const Eigen::Vector3d& p_D, const Eigen::Quaterniond& q_D) const;
  // The inverse of to_world(j, .): frame j's pose in device space when its handle is at `handle_W`.
  void to_device(int j, const HapticPose& handle_W, Eigen::Vector3d& p_D, Eigen::Quaterniond& q_D) const;
};

// Coupling gains for a device whose declared stiffness is k_dev (N/m in device
// space): world stiffness k_dev / scale^2 keeps the device-side stiffness at its
// limit, and the damping B = 1.5 k T / 2 at the haptic period T leaves the sampled coupling's
// low-frequency damping B - k T / 2 positive. Colgate and Schenkel's passivity condition is on the
// device's own damping b > k T / 2 + |B| (bench/haptic_rate_bench.cpp): B costs passivity too.
// The rotation keeps CouplingGains' 1 N m/rad and 0.01 N m s/rad (a stylus's handle).
CouplingGains coupling_gains_for(double device_stiffness_n_m, double scale, double haptic_period_s);
// A glove's rotational coupling damper, N m s/rad: the margin times k T / 2, as the translation's.
// A glove's distal joint (5e-6 kg m^2, 0.0022 N m s/rad, sim::GloveParams) does not meet
// b > k T / 2 + |B| with the stylus's 0.01 N m s/rad (B T / I = 2): every pressed fingertip rang at
// 500 Hz (+-1.2 mrad a tick), +0.012 J/s each (GlovePressHold); with 7.5e-4 it needs 1.25e-3.
double glove_rotational_damping(const CouplingGains& gains, double haptic_rate_hz);
// That margin: the coupling damping is this many times k T / 2 (no unit).
constexpr double kCouplingDampingMargin = 1.5;
// The least coupling damping, device space, N s/m: where k T / 2 all but vanishes (a soft device,
// a fast haptic rate) the coupling still damps.
constexpr double kMinCouplingDamping_ns_m = 0.5;

// The passivity controller's energy budget per device, J, shared evenly by its frames (a glove's 16 get
// 6.25e-6 J each): a frame's controller damps while its observer's energy is below minus its share
// (the rendering has given out more than it took), taking the whole deficit back within the damping
// it may add (kMaxPassivityDamping_ns_m: a strongly active rendering can run the deficit past the
// budget for a while, less far than without it). The observer books each reply against the device's
// motion while it held it, exactly. With 1e-4 J per frame a glove could keep 1.6 mJ, and its
// grasp-release ended at +0.2 and +0.3 mJ; a stylus at 1e-5 J ended
// VirtualCoupling.PassivityControllerTakesBackWhatAnActiveModelGivesOut at +1.1 mJ where 1e-4 leaves
// -1.0 mJ: there the active model rings the proxy, the observer swings by up to 10 mJ within a stroke,
// dipping to -3 mJ with either budget (the capped damping, on the filtered velocity, does not keep
// up), and the test's last instant lands on either side.
constexpr double kPassivityBudget_J = 1e-4;
// Device-space damping the passivity controller may add, N s/m (a Phantom-class
// device renders a few N s/m stably at 1 kHz).
constexpr double kMaxPassivityDamping_ns_m = 5.0;
// Its rotational damping is the translational one times this (a lever of 2 cm, a phalanx's), m^2.
constexpr double kPassivityRotationWeight_m2 = 4e-4;

// The shortest interval the device's velocity is taken over, s (a 10 kHz device): samples read
// closer together than that, with no interval of the device's own, still give a finite velocity.
constexpr double kMinSampleInterval_s = 1e-4;

// How far ahead of the tick a model's step end may lie for the proxy's extrapolation to it, s: 100 ms
// (six visual steps at 60 Hz) bounds x + tau v when a model's time stamp is far off the haptic clock.
constexpr double kMaxModelLookahead_s = 0.1;

// How long ProxyHand::predict_device carries an overdue device, s: 20 ms, twenty samples of a 1 kHz
// device. A device that really stopped while its samples were missing is then met at most its speed
// times this off (the error that holding it makes, the other way, for one that moved on).
constexpr double kMaxDevicePrediction_s = 0.02;

// How far a device may come back from a gap in its samples from where it was for the gap to be bridged
// instead of re-synced (ProxyHand::commit_sample), world m and rad: a press's depth several times
// over, and what the clutch drifts out of in 0.3 s.
constexpr double kMaxBridgedStretch_m = 0.03, kMaxBridgedStretch_rad = 0.5;
// How fast what a bridged gap left between the device and the device the proxies follow is taken out
// while the hand is near nothing (no contact, no contact rows), carrying the proxies along, m/s and
// rad/s.
constexpr double kClutchDrift_m_s = 0.1, kClutchDrift_rad_s = 1.0;

struct ReplyWrench {
  Eigen::Vector3d f_D = Eigen::Vector3d::Zero(), tau_D = Eigen::Vector3d::Zero();  // on the device, device frame
  bool clamped = false;
};

// One hand's proxies and the device state that drives them.
class ProxyHand {
 public:
  // `mass_kg` and `inertia_kg_m2` per handle (the simulated handles'); `handles` <= kMaxHapticHandles.
  void configure(int handles, const double* mass_kg, const Eigen::Matrix3d* inertia_B, const CouplingGains& gains,
                 const DeviceLimits& limits, const DeviceMap& map);
  // The passivity controller of reply(), on by default (kPassivityBudget_J). Off: the rendering's
  // own passivity, unguarded (the tests of the model switch it off).
  void set_passivity_control(bool on) { passivity_control_ = on; }
  // At most this many Gauss-Seidel sweeps in a tick's contact solve (clamped to 1..kMaxTickContactSweeps);
  // kDefaultTickContactSweeps in hapticd. A benchmark's knob: the solve's cost against its exactness.
  void set_contact_sweeps(int sweeps) { contact_sweeps_limit_ = std::clamp(sweeps, 1, kMaxTickContactSweeps); }
  // Frames after the first are driven by actuators that push against the first (a glove's finger
  // actuators on its palm): their ports move at their velocity relative to the first frame's body,
  // which is what those actuators do work through; the first frame's port stays absolute.
  void set_fingers_grounded_on_palm(bool on) { fingers_on_palm_ = on; }

  // A pose sample: the device pose of every handle in device space (set_device_pose
  // for each, then commit_sample with the time the sample was read). A first sample, or one
  // after a gap longer than `resync_gap_s` that the device came back from farther than
  // kMaxBridgedStretch_m, re-syncs: the proxies jump onto the
  // device so the coupling force starts from zero (no force jump); commit_sample
  // returns true then; the samples after it that were read faster than the device took them (the
  // rest of a stalled server's queue) re-sync onto themselves too, uncounted. A nearer gap is
  // bridged: the device's motion across it (and its queue's) is a clutch, not felt.
  // `sample_interval_s`: the device's own time since its last sample (its timestamps), for the
  // device velocity the coupling's damper acts on; without one (NaN) the time between reads, at
  // least kMinSampleInterval_s. `waited_s`: how much longer than the device's quickest samples this
  // one waited to be read (its read time less its timestamp, over the least of those; NaN: unknown).
  void set_device_pose(int j, const Eigen::Vector3d& p_D, const Eigen::Quaterniond& q_D);
  bool commit_sample(double t_s, double resync_gap_s,
                     double sample_interval_s = std::numeric_limits<double>::quiet_NaN(),
                     double waited_s = std::numeric_limits<double>::quiet_NaN());
  // Where the device is taken to be at `t_s` (commit_sample's clock) for the next integrate(). While
  // its samples come at its own pace, its last sample. Once the last sample is overdue (read at least
  // the device's own interval ago), it is carried along the device's filtered velocity by one
  // interval's motion for each sample that pace would have brought since, at most
  // kMaxDevicePrediction_s in all: the proxy follows the device as if its samples had kept coming.
  // Counted (overdue_device_ticks). A device whose samples stop for a few milliseconds (its
  // own servo loop or its link stalled) goes on moving; held at its last sample, the proxy stopped
  // under it, and the sample after the gap found the device a gap's motion away from the proxy: a
  // jolt against the motion of the coupling stiffness times that distance (0.5 N after 9 missed ticks
  // of a stylus lifting at 8 cm/s). The replies are always computed at the sample (reply()).
  void predict_device(double t_s);

  // Advances the proxies by dt under `model` and the coupling (the 1 kHz tick).
  // `lookahead_s`: time left until the model's step ends. The model gives the
  // force at that time from the handle's state then, so it is evaluated at the
  // proxy's pose extrapolated to it (x + lookahead v): evaluated at the current
  // pose, a moving hand's momentum would push the proxy along (an active force).
  // Negative: the model's step ended that long ago (a late model); it is evaluated at the
  // proxy's pose, its anchor where the world left the hand. A model whose contact operator was
  // prepared at one lookahead (TickContacts::W_proxy) keeps that lookahead, late or not.
  // `model_weight` in [0, 1] blends the model with the safe model (the haptic loop fades a stale
  // model so): the model's influence (F0, K, D) is scaled by it, and the safe model's by
  // 1 - weight. The safe model is a damper between the proxy and its device, part of the coupling
  // and felt by the device (reply()), that makes the proxy's motion on the coupling spring critically
  // damped: a proxy released from a stiff model settles onto a still device without ringing, and a
  // device moving through free space carries its proxy along without drag. Nothing acts between
  // proxy and device that the device does not feel (SafeModelBlend: every blend is passive at the
  // device's port). Two earlier safe models: a spring and damper toward the device, unfelt, gave
  // energy back half faded (-9e-5 J over four 2 mm cycles at 1 Hz: the device did work through them
  // it never paid); a damper on the proxy's own velocity, against the world, dragged a device moving
  // through free space while a model faded ((1 - w) b v: 0.77 N at 0.1 m/s half faded). The model's
  // contacts and clearance planes hold at every weight, so the safe model brings the proxy to its
  // device only as far as the world's surfaces let it (HapticCore decides how long the device feels
  // them: ServerOptions::model_contacts_hold_s).
  // A late model (lookahead_s < 0) takes its K (x - x0) at the proxies' pose of its first late tick.
  // A solve with contacts that fails or throws a proxy past kMaxProxySpeed_m_s is solved again
  // without the lookahead, and if still too fast the proxies hold still for the tick (both counted);
  // a non-finite model or state resets the proxies onto the device (counted).
  void integrate(const HapticModel& model, double dt_s, double lookahead_s = 0, double model_weight = 1);

  // The wrench for handle j now: coupling force reversed, in device space,
  // about the tracked frame's origin, scaled by `output_scale` (session ramp),
  // clamped and rate-limited against the last reply for this handle,
  // `dt_since_last_s` ago. With set_passivity_control(true), a time-domain
  // passivity controller (Hannaford and Ryu) guards the device port: an
  // observer sums the work the device does on the rendering, and while the
  // rendering has given out more than it took by over its share of kPassivityBudget_J (multi-rate
  // lag, gating, a model that changed under the finger) the reply adds the damping
  // that takes the deficit back, up to kMaxPassivityDamping. The same damping acts on the
  // proxy at the next integrate(): the coupling saturates at the device's limits, so an active
  // model could otherwise carry the proxy away from the device (a two-port controller).
  // `gated`: the frame is not to be felt (a glove's part touching nothing; output_scale is then 0):
  // its stretch is booked unfelt and stays so after the gate opens, released only as the device
  // backs out of it. `unfelt_share`: how much of its held reply the device was not feeling when it
  // took this sample (its watchdog fading the reply out: no reply for that long); when > 0, what the
  // stretch grew by since the last reply is booked unfelt too (the device held an older reply),
  // released the same way, and at the sample that bridged a gap in the device's samples
  // (commit_sample) that share of the whole stretch.
  ReplyWrench reply(int j, double output_scale, double dt_since_last_s, bool gated = false, double unfelt_share = 0);

  // Puts every proxy on its device pose and zeroes velocities.
  void resync();
  // resync() after a fault: also zeroes the force at once (no ramp) and counts a reset.
  void reset();

  int handles() const { return handles_; }
  const HapticPose& proxy(int j) const { return proxy_[j]; }
  const Eigen::Vector3d& proxy_velocity(int j) const { return v_[j]; }
  const Eigen::Vector3d& proxy_angular_velocity(int j) const { return w_[j]; }
  const HapticPose& device(int j) const { return device_[j]; }
  const Eigen::Vector3d& device_velocity(int j) const { return v_dev_[j]; }  // filtered, world
  const Eigen::Vector3d& device_angular_velocity(int j) const { return w_dev_[j]; }
  long resets() const { return resets_; }
  long clamps() const { return clamps_; }
  // Ticks of a model on kMinPreparedHandles or more handles that the dense LU solved: the model had
  // no prepared solver or one for other parameters, it was fading (weight < 1), or the prepared
  // solve did not reach 1e-12 of the right-hand side in six refinements.
  long solver_fallbacks() const { return solver_fallbacks_; }
  // Ticks whose prepared answer a probe objected to (TickSolver::Z), checked then against the exact
  // residual (and refined, or left to the dense LU).
  long solver_refinements() const { return solver_refinements_; }
  // The last tick's contact impulses (N s over the model's step, in the model's rows), the sweeps
  // it took, and the ticks whose contact solve stopped at its sweep limit without an exact answer.
  const TickRowVector& contact_impulses() const { return lambda_; }
  int contact_sweeps() const { return contact_sweeps_; }
  long contact_unconverged() const { return contact_unconverged_; }
  // The contact solves run (one a tick with contact rows, one more for a lookahead fallback) and
  // their sweeps summed: the solve's work, counted, where its wall time is the machine's noise too.
  long contact_solves() const { return contact_solves_; }
  long contact_sweeps_total() const { return contact_sweeps_total_; }
  // Ticks whose solve with contacts failed (non-finite, or a proxy past kMaxProxySpeed_m_s) with the
  // lookahead to the model's step end and were solved again without it, and ticks at which the
  // proxies then held still instead, too fast still (integrate()).
  long lookahead_fallbacks() const { return lookahead_fallbacks_; }
  // Ticks at which predict_device carried an overdue device on.
  long overdue_device_ticks() const { return overdue_device_ticks_; }
  // Gaps in the device's samples bridged by a clutch, not re-synced (commit_sample).
  long bridged_gaps() const { return bridged_gaps_; }
  long contact_holds() const { return contact_holds_; }
  // Replies the passivity controller added damping to.
  long passivity_actions() const { return passivity_actions_; }
  // Ticks at which a handle was held at its model's clearance (HapticModel::clearance).
  long clearance_limits() const { return clearance_limits_; }
  // Of those, the ticks at which the skin's travel bound (HapticModel::skin_radius_m) held it.
  long travel_limits() const { return travel_limits_; }
  // The passivity observer's energy of frame j: the work its device has done on the rendering, J.
  double energy_in(int j) const { return energy_in_[j]; }
  // The energy the controller's damping took back at frame j, J.
  double passivity_damped_j(int j) const { return damped_j_[j]; }
  bool has_device_pose() const { return have_device_; }
  const CouplingGains& gains() const { return gains_; }

 private:
  int handles_ = 0;
  CouplingGains gains_;
  DeviceLimits limits_;
  DeviceMap map_;
  double mass_[kMaxHapticHandles]{};
  Eigen::Matrix3d inertia_B_[kMaxHapticHandles];
  // The safe model per handle (integrate()): the damper between proxy and device, and its share in
  // the last integration (1 - the model's weight), which reply() renders.
  double safe_b_ns_m_[kMaxHapticHandles]{}, safe_b_nms_rad_[kMaxHapticHandles]{};
  double safe_share_ = 0;
  HapticPose proxy_[kMaxHapticHandles], device_[kMaxHapticHandles], pending_[kMaxHapticHandles];
  HapticPose predicted_[kMaxHapticHandles];  // the device where the coupling pulls the proxy (predict_device)
  Eigen::Vector3d v_[kMaxHapticHandles], w_[kMaxHapticHandles];
  Eigen::Vector3d v_dev_[kMaxHapticHandles], w_dev_[kMaxHapticHandles];  // filtered device velocity
  double t_dev_ = 0;
  // The device's pace (predict_device) and its own interval at its last sample (commit_sample's dt_v).
  double sample_interval_s_ = 0, last_interval_s_ = std::numeric_limits<double>::infinity();
  bool have_device_ = false;
  bool resync_following_ = false;  // re-synced, and every sample since came from a queue
  bool bridging_ = false;          // bridged a gap, and every sample since came from a queue
  bool bridged_now_ = false;       // the last sample committed bridged a gap
  double gap_t_s_ = 0;             // the last gap, re-synced or bridged (commit_sample's clock)
  int queue_paced_ = 0;            // samples in a row read at the device's pace (commit_sample)
  // The last integrate()'s model had the hand touching something or contact rows near it (a bridged
  // gap's clutch drifts out only when not).
  bool near_contact_ = false;
  // The device's motion across bridged gaps (world, m and rad; commit_sample): the proxies are coupled
  // to the device less it, and the device feels the coupling so; it shrinks as the device backs out
  // (reply()) and drifts out while the hand is near nothing (integrate()).
  Eigen::Vector3d clutch_p_W_[kMaxHapticHandles], clutch_theta_W_[kMaxHapticHandles];
  Eigen::Vector3d last_f_D_[kMaxHapticHandles], last_tau_D_[kMaxHapticHandles];
  Eigen::Vector3d last_r_D_[kMaxHapticHandles];  // the last reply's lever from the frame's origin, device space
  // The device's motion since the last reply (world, m and rad): what the last reply, held by the
  // device, did work over.
  Eigen::Vector3d moved_p_W_[kMaxHapticHandles], moved_theta_W_[kMaxHapticHandles];
  // A gated frame's unfelt stretch, device minus proxy (world, m and rad): reply().
  Eigen::Vector3d unfelt_p_W_[kMaxHapticHandles], unfelt_theta_W_[kMaxHapticHandles];
  // The stretch and twist at the last reply (reply(): `unfelt_share` of their growth is unfelt).
  Eigen::Vector3d last_stretch_p_W_[kMaxHapticHandles], last_twist_W_[kMaxHapticHandles];
  bool motion_booked_[kMaxHapticHandles]{};  // reply() has booked moved_*_W_[j]: the next sample starts anew
  double energy_in_[kMaxHapticHandles]{};    // passivity observer: work the device has done on the rendering, J
  double damped_j_[kMaxHapticHandles]{};
  double passivity_b_[kMaxHapticHandles]{};  // the controller's last damping, device units N s/m
  bool passivity_control_ = true;
  int contact_sweeps_limit_ = kDefaultTickContactSweeps;
  bool fingers_on_palm_ = false;
  long resets_ = 0, clamps_ = 0, passivity_actions_ = 0, solver_fallbacks_ = 0, solver_refinements_ = 0;
  long clearance_limits_ = 0, travel_limits_ = 0;
  // The prepared solve of A(tau) v = b (TickSolver), refined against the exact matrix; false
  // when it does not converge (v_next_ is then to be recomputed).
  bool solve_prepared(const HapticModel& model, double h, double tau);
  // y = A(tau)^-1 rhs through the prepared factors (TickSolver), into dv_.
  void apply_prepared(const TickSolver& s, double tau, const HapticVector& rhs);
  bool solver_matches(const TickSolver& s, double dt) const;
  // Takes out of each handle's v_next_ what would carry it past its model's clearance planes
  // (HapticModel::clearance): a handle already past one may only come back.
  void limit_to_clearance(const HapticModel& model, double dt);
  // The model's contacts (TickContacts) on the contact-free answer v_next_: the impulses of this
  // tick into lambda_, v_next_ updated by weight times their effect; `dense`: lu_ (one handle: lu6_)
  // holds A(tau). False on a failure.
  bool solve_contacts(const HapticModel& model, double dt, double tau, bool dense);
  // integrate()'s implicit step into v_next_ with lookahead tau.
  enum class TickSolve { solved, too_fast, failed };  // too_fast: a proxy past kMaxProxySpeed_m_s
  // `late`: the model's step has ended (integrate()'s lookahead_s < 0): its K term is frozen.
  TickSolve solve_velocities(const HapticModel& model, double dt, double tau, double weight, bool late);
  // The active set of the sweeps' answer solved exactly, kept if it is a solution (solve_contacts):
  // true then.
  bool polish_contacts(const TickContacts& c);
  // lambda_ + delta_a_ over the a active rows of polish_contacts, into lambda_ if it is a solution;
  // else which rows broke a condition (an active row's impulse, an inactive row's separation).
  enum class Correction { solution, breaks_active, breaks_inactive };
  Correction try_correction(const TickContacts& c, int a);
  // cod_'s least-norm solution of b (its solve(), which allocates a temporary, without the heap).
  const TickRowVector& least_norm_solve(const TickRowVector& b);
  // delta_a_ for redundant active rows (W_AA singular; a <= kMaxRedundantRows): the one that keeps the
  // conditions.
  bool redistribute(const TickContacts& c, int a);
  // Entry (row, col) of the tick's Delassus operator (solve_contacts).
  double delassus(const TickContacts& c, int row, int col) const;
  // The rows' velocities: u_ = u_free + W lambda_, plus P_ y_ in the low-rank form (low_rank_:
  // the operator W + P_ Q_, never formed; else the model's prepared W_proxy).
  TickRowVector u_, lambda_, candidate_, u_candidate_, rhs_a_, delta_a_;
  HapticVector y_, dy_;
  bool low_rank_ = false;
  int active_[kMaxTickRows]{};
  // The active set of this tick's polish that failed (polish_contacts), failed_a_ rows; 0: none.
  int failed_active_[kMaxTickRows]{};
  int failed_a_ = 0;
  TickRowMatrix W_aa_;
  Eigen::PartialPivLU<TickRowMatrix> lu_rows_;
  Eigen::CompleteOrthogonalDecomposition<TickRowMatrix> cod_;
  TickRowVector u_now_, x_a_, x0_a_, b_a_, r_a_, z_;
  // least_norm_solve's workspace.
  TickRowVector cod_c_, cod_y_, cod_solved_;
  double cod_work_[kMaxTickRows]{};
  TickRowMatrix null_;  // redistribute's null-space basis (a x k)
  HapticVector x_look_, rhs_;
  TickDofByRow Q_;
  TickRowByDof P_;
  Eigen::Matrix3d blocks_[kMaxTickContacts];  // the operator's diagonal blocks
  double tangent_step_[kMaxTickContacts]{};
  std::uint64_t lambda_t_end_ns_ = 0;
  std::uint32_t lambda_resyncs_ = 0;
  bool warm_start_valid_ = false;  // lambda_ may start the next tick under the same model
  int contact_sweeps_ = 0;
  long contact_unconverged_ = 0, lookahead_fallbacks_ = 0, contact_holds_ = 0, overdue_device_ticks_ = 0;
  long bridged_gaps_ = 0;
  long contact_solves_ = 0, contact_sweeps_total_ = 0;
  // Workspace of the implicit step, sized once. The block diagonal part of A per handle:
  // translational (a multiple of the identity) and rotational.
  double a_lin_[kMaxHapticHandles]{};
  Eigen::Matrix3d a_rot_[kMaxHapticHandles];
  HapticMatrix A_;
  HapticVector b_, x_rel_, v_next_, v0_, r_, c_, dv_;
  // A late model's K term (integrate()): the proxies' displacement from its anchor at the first tick
  // past its step's end (late_t_end_ns_: that model's; 0: none frozen).
  std::uint64_t late_t_end_ns_ = 0;
  HapticVector late_x_rel_;
  // apply_prepared's elimination: the column being reduced, each step's multiplier, and whether
  // the step swapped its two columns (partial pivoting).
  HapticVector column_, multiplier_;
  bool swapped_[kMaxHapticDofs]{};
  Eigen::PartialPivLU<HapticMatrix> lu_;
  // One handle's (a stylus's) A and its inverse, at fixed size (solve_velocities).
  Eigen::PartialPivLU<Eigen::Matrix<double, 6, 6>> lu6_;
  Eigen::Matrix<double, 6, 6> a_inv6_;
};

}  // namespace hapticd::haptic
