#pragma once
// A deformable co-rotational FEM hand tied to m >= 1 rigid handles (seed 004
// sections 4-5): the constant HandModel, the mutable HandState, and one implicit
// Euler step (Baraff-Witkin: one linearization per step) split in named stages.
// The same body with m = 0 handles (HandConfig::free_body) is a free deformable
// object (seed 004 section 7's bunny and letters; DESIGN.md section 3: FEM bodies
// like the hand, without handles): eq. 7 then reduces to A_t v_t = b_t, plus the
// 6-DOF blocks of any rigid bodies it touches.
#include <Eigen/Core>
#include <string>
#include <vector>

#include "hand_models/corotational_fem.hpp"
#include "hand_models/coupled_system.hpp"
#include "hand_models/rigid_handle.hpp"
#include "hand_models/tet_mesh.hpp"

namespace hapticd::hand {

class CoupledSolver;
struct HandleLinearization;

// Zero-rest-length spring per coupled node (seed 004 eq. 4).
struct CouplingParams {
  double stiffness_n_m = 2000.0;
  double damping_ns_m = 2.0;
};

// Viscoelastic drive of each handle toward its target pose (the visual loop's
// end of the virtual coupling: the target is the haptic proxy or device pose).
struct DriveParams {
  double stiffness_n_m = 3000.0;
  double damping_ns_m = 30.0;
  double rot_stiffness_nm_rad = 30.0;
  double rot_damping_nms_rad = 0.3;
};

// A static penalty floor z = height_m under the hand nodes (the hand demo and
// bench scene; constraint contact with friction belongs to the world).
struct FloorParams {
  bool enabled = false;
  double height_m = 0.0;
  double stiffness_n_m = 2000.0;  // per node in contact
  double damping_ns_m = 2.0;
  double friction = 0.0;  // Coulomb coefficient (regularized, see PointContact)
};

// Penalty contact of one point embedded in the body (barycentric in a tet)
// against another body: normal force k depth - d (relative normal speed),
// Coulomb friction regularized below kStickSpeed_m_s into viscous friction.
// All of it is implicit (stiffness and damping blocks in A_t), so stiff
// contacts stay stable at visual rates. The cheap baseline of constraint contact.
struct PointContact {
  static constexpr double kStickSpeed_m_s = 0.01;
  int tet = 0;
  Eigen::Vector4d bary{1, 0, 0, 0};
  Eigen::Vector3d n_W = Eigen::Vector3d::UnitZ();  // unit, out of the other body
  double depth_m = 0;  // penetration along n_W, > 0 (a constraint contact may carry a gap, < 0)
  Eigen::Vector3d v_other_W = Eigen::Vector3d::Zero();  // the other body's velocity at the point
  double stiffness_n_m = 2000.0, damping_ns_m = 2.0, friction = 0.0;
  int other = -1;  // the caller's index of the other body (-1: static geometry)
  // Index into HandState::bodies when the other body is dynamic and solved
  // implicitly with the hand (then v_other_W is ignored); -1: static or kinematic.
  int body = -1;
  // A constraint (non-penetration with a Coulomb cone, solved by projected
  // Gauss-Seidel on the Delassus operator of the step) instead of a penalty
  // spring: stiffness and damping are then unused.
  bool constraint = false;
  // In, constraint contacts: a guess of this step's impulse (N s, world frame),
  // e.g. the last step's at the same place; it warm-starts Gauss-Seidel.
  Eigen::Vector3d warm_impulse_W = Eigen::Vector3d::Zero();
  // Out, after a step: the force the contact put on this body at the end of the step, N.
  Eigen::Vector3d f_W = Eigen::Vector3d::Zero();
};

// The most constraint contacts one step solves (its contacts and supports, 3 rows each): W (3c x 3c)
// and A^-1 J^T (the tool DOFs x 3c) are dense.
constexpr int kMaxStepContacts = 256;
// The most Gauss-Seidel sweeps of a step's constraint contacts (an easy problem stops earlier, at a
// sweep that changes no impulse by 1e-8 of the largest). A palm pressed flat on a body couples its
// rows through the flesh and the handle, and the sweeps converge slowly there: on the stylus
// bunny's 130 N press (`haptic-bench world`), the published model missed the step's force by 2.89 N
// at the median with 500 sweeps (the step's own answer unconverged), 0.88 N with 1000, 0.16 N with
// 2000, for 1.7 ms more at the median step (0.01 N with 4000, 3.7 ms more).
constexpr int kStepContactSweeps = 2000;
// Constraint contacts push a penetrating point out at this fraction of its depth per step.
constexpr double kContactDepthRecovery = 0.2;
// A reserve constraint contact (HandState::reserve_contacts) joins the step's
// rows when the step would carry it deeper than this (and deeper than it is), m.
constexpr double kReserveDepth_m = 2e-4;
// HandState::active_source of reserve r promoted to a row: kReserveSource - r.
constexpr int kReserveSource = -2;

struct HandleSpec {
  std::string name;
  Eigen::Vector3d seed = Eigen::Vector3d::Zero();
  double radius_m = 0.03;
  // Non-empty: the handle's nodes, instead of those inside the sphere (seed, radius_m).
  std::vector<int> nodes;
};

struct HandConfig {
  Material material;
  CouplingParams coupling;
  DriveParams drive;
  FloorParams floor;
  Eigen::Vector3d gravity_m_s2{0, 0, -9.81};
  double dt_s = 1.0 / 60.0;
  // Safety: a step whose node or handle speed exceeds this is a divergence.
  double max_speed_m_s = 50.0;
  // A free deformable object instead of a hand: no handles (and then `handles`
  // must be empty); a hand has at least one.
  bool free_body = false;
  std::vector<HandleSpec> handles;
  // Non-empty (one per tet): each element's Young's modulus over the
  // material's, e.g. a glove hand's soft joint flesh (procedural_joint_stiffness).
  std::vector<double> element_stiffness;
};

// Throws std::invalid_argument naming the offending field (e.g. "coupling.stiffness_n_m: must be > 0").
void validate(const HandConfig& config);

// Pattern data to assemble A_t in place: per element, the value index of each
// 3x3 block's first entry; per node, its diagonal block.
struct AssemblyMap {
  std::vector<std::array<int, 16>> element_block;
  std::vector<int> diagonal_block;
  std::vector<int> column_start;  // outer index of each column
};

class HandModel {
 public:
  HandModel(TetMesh mesh, HandConfig config);

  const TetMesh& mesh() const { return mesh_; }
  const CorotationalFem& fem() const { return fem_; }
  const HandConfig& config() const { return config_; }
  const std::vector<RigidHandle>& handles() const { return handles_; }
  int num_nodes() const { return mesh_.num_nodes(); }
  int num_handles() const { return static_cast<int>(handles_.size()); }
  // Sparsity of A_t (values zero) and how element blocks land in it.
  const Eigen::SparseMatrix<double>& tool_pattern() const { return pattern_; }
  const AssemblyMap& assembly_map() const { return map_; }
  // A tet holding node i and the node's position in it (to express a node as an embedded point).
  std::pair<int, int> node_tet(int i) const { return node_tet_[i]; }

 private:
  TetMesh mesh_;
  HandConfig config_;
  CorotationalFem fem_;
  std::vector<RigidHandle> handles_;
  Eigen::SparseMatrix<double> pattern_;
  AssemblyMap map_;
  std::vector<std::pair<int, int>> node_tet_;
};

// A rigid body touched by the hand, solved together with it for one step as an
// extra 6-DOF block of eq. 7 (next to the handles): contact springs couple it
// implicitly, so a light body pushed by stiff contacts stays stable and gets
// exactly the impulse the hand gets, reversed. Gravity and the body's other
// contacts stay with the rigid-body engine (operator splitting).
struct ContactBody {
  double mass_kg = 1.0;
  Eigen::Matrix3d inertia_W = Eigen::Matrix3d::Identity();  // about the centre of mass, world axes, kg m^2
  Eigen::Vector3d p_com_W = Eigen::Vector3d::Zero();
  Eigen::Vector3d v_W = Eigen::Vector3d::Zero(), w_W = Eigen::Vector3d::Zero();
  // The body's own gravity, m/s^2: the world's, whatever the hand's (a weightless
  // hand still carries the weight of what it holds).
  Eigen::Vector3d gravity_W{0, 0, -9.81};
  // Out, after a step: the body's velocity change over the step, from its
  // gravity, its supports and the hand's contacts together.
  Eigen::Vector3d dv_W = Eigen::Vector3d::Zero(), dw_W = Eigen::Vector3d::Zero();
};

// A contact of an implicit body with something that is not the hand (static
// geometry, or another body taken as moving at its known velocity): solved as
// a constraint with the hand's contacts, so the flesh feels the body supported
// (a bunny pressed onto a table does not give way) instead of learning it one
// step late from the rigid-body engine.
struct BodySupport {
  int body = 0;  // index into HandState::bodies
  Eigen::Vector3d p_W = Eigen::Vector3d::Zero();
  Eigen::Vector3d n_W = Eigen::Vector3d::UnitZ();  // unit, out of the support, into the body
  double depth_m = 0;
  double friction = 0.5;
  Eigen::Vector3d v_other_W = Eigen::Vector3d::Zero();  // the support's velocity at the point
};

struct HandleTarget {
  Eigen::Vector3d p_W = Eigen::Vector3d::Zero();
  Eigen::Quaterniond q_W = Eigen::Quaterniond::Identity();
  Eigen::Vector3d v_W = Eigen::Vector3d::Zero();
  Eigen::Vector3d w_W = Eigen::Vector3d::Zero();
  // The device's own motion (the tracked frame's, world): where the user is going. The proxy's
  // (v_W, w_W) is partly the rendering's doing: a proxy held against a contact moves as the model's
  // rows push it.
  Eigen::Vector3d v_device_W = Eigen::Vector3d::Zero();
  Eigen::Vector3d w_device_W = Eigen::Vector3d::Zero();
};

// Per-stage wall time of the last step, ms (measured for the stats; nothing steps by it), and
// the solver's iteration and factorization counts.
struct StepTimings {
  double assembly_ms = 0, factor_ms = 0, schur_ms = 0, solve_ms = 0, contact_ms = 0, linearize_ms = 0, integrate_ms = 0,
         total_ms = 0;
  long iterations = 0;
  int factorizations = 0;      // the solver's numeric factorizations (SolveReport::factorizations)
  int contact_iterations = 0;  // Gauss-Seidel sweeps of the constraint contacts (last round)
  int reserve_rounds = 0;      // constraint solves repeated for reserve contacts that joined
  int contacts_dropped = 0;    // constraint rows beyond kMaxStepContacts left out
  bool contact_converged = true;
};

// The constraint contacts a step ended with, as the linear constraints the
// handle-space model holds (seed 004 section 3: "accounting for contact
// constraints"): the normal row of every contact that pushes, and its tangent
// rows too while it sticks (a sliding contact keeps its friction impulse).
struct HeldContacts {
  Eigen::SparseMatrix<double> J;  // rows: held directions; columns: the DOFs of eq. 7 (handles, bodies, tool)
  Eigen::VectorXd u;              // J V at the step's solution, m/s (what the rows hold)
  Eigen::VectorXd impulse;        // every constraint contact's generalized impulse J_all^T lambda (held or sliding)
  int rows() const { return static_cast<int>(J.rows()); }
};

struct HandState {
  Eigen::VectorXd x, v;  // node positions (m) and velocities (m/s), 3n
  std::vector<HandleState> handles;
  std::vector<HandleTarget> targets;

  // Workspace, preallocated for the model; the last step's system stays readable.
  std::vector<Eigen::Matrix3d> R;
  Eigen::VectorXd f_t;
  CoupledSystem system;
  Eigen::VectorXd v_h_next, v_t_next;

  // Contacts against other bodies for the next step, set by the world; their
  // f_W is filled by the step. Floor contacts are added internally each step.
  std::vector<PointContact> contacts;
  // Constraint contacts the caller left out of `contacts` (e.g. clustered
  // away: one row per patch of skin keeps the Delassus operator small). A
  // reserve becomes a row of the step only when the step's velocities would
  // otherwise carry it deeper, and deeper than kReserveDepth_m (an active-set
  // pass; a point already deeper and coming out stays in reserve), so
  // the skin between rows cannot sink through a thin object. Static and
  // kinematic other sides or implicit bodies only. A promoted reserve's f_W
  // is filled by the step like a contact's (zero for the others).
  std::vector<PointContact> reserve_contacts;
  // External nodal forces for the next step, N, 3n (zero at rest; the caller
  // sets and clears them): e.g. another soft body's contact reactions handed
  // over by operator splitting. Explicit: they enter b, not A.
  Eigen::VectorXd f_ext;
  std::vector<ContactBody> bodies;            // the dynamic bodies contacts refer to
  std::vector<BodySupport> supports;          // those bodies' other contacts, for the next step
  std::vector<PointContact> active_contacts;  // valid contacts + floor, as last assembled
  // Per active contact: index into contacts, -1 for the floor, kReserveSource - r for reserve r.
  std::vector<int> active_source;
  HeldContacts held;  // the last step's held constraint contacts

  // The step length, s: the model's dt_s unless the caller sets another (a
  // visual loop that keeps its simulated time on the wall clock).
  double dt_s = 0;

  StepTimings timings;
  int floor_contacts = 0;
  long resets = 0;
};

// The length of the state's next step: state.dt_s when set (> 0), else the model's dt_s.
double step_length(const HandModel& model, const HandState& state);

// Rest shape, at rest, handles at their rest poses and targets on them.
HandState make_rest_state(const HandModel& model);

// Moves the whole hand rigidly so that handle `h` sits at `pose`, velocities zero.
void place_hand(const HandModel& model, HandState& state, const Eigen::Vector3d& p_W, const Eigen::Quaterniond& q_W,
                int handle = 0);

// Whether a contact is well formed for this model (tet in range, finite, unit normal).
bool valid_contact(const HandModel& model, const HandState& state, const PointContact& c);

// Sets handle h's drive target; a non-finite target is refused (returns false, target kept).
bool set_target(HandState& state, int handle, const HandleTarget& target);

// Stage 1: forces and the linear system of eq. 7 at the current state.
void assemble(const HandModel& model, HandState& state);

enum class StepStatus { ok, reset_solver_failed, reset_diverged };

// One implicit Euler step: assemble, solve (with `solver`), linearize (when
// `linearization` is given and the model has handles: the handle-space force
// model of this step's system, computed while its factorization is current,
// re-anchored at the handles' end-of-step state; cleared to zero size if it
// fails), integrate, check. A failed solve or a diverging/non-finite result
// resets the hand to rest at its first handle's target (a free body: to its rest
// shape fitted rigidly onto its start-of-step nodes, at rest) and state.resets
// counts it, instead of propagating.
StepStatus step(const HandModel& model, HandState& state, CoupledSolver& solver,
                HandleLinearization* linearization = nullptr);

// Total mechanical energy (kinetic + elastic + coupling + drive + floor + gravity), J.
double total_energy(const HandModel& model, const HandState& state);

// Linear momentum of nodes and handles, kg m/s.
Eigen::Vector3d linear_momentum(const HandModel& model, const HandState& state);

}  // namespace hapticd::hand
