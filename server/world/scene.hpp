#pragma once
// What a simulation contains, as read from a scene file (scenes/*.json; format
// and rules in scene_loader.hpp). Plain data in SI units: later code builds only
// what a scene names ("model only what a scene needs"). Every frame is the world
// frame W (z up) unless a field says otherwise; a pose maps a local frame into W.
#include <Eigen/Core>
#include <Eigen/Geometry>
#include <array>
#include <cstddef>
#include <string>
#include <string_view>
#include <vector>

namespace hapticd::world {

// Bounds of scene values that other code builds on (scene_loader.cpp holds the rest; every field
// below states its range). The loader refuses whatever lies outside, so whatever it accepts builds
// a World that steps, passes ODE's checks, and gives a device link whose Welcome encodes.
inline constexpr int kMinHandTets = 100;     // hand_spacing_for_tets is accurate from here
inline constexpr int kMaxHandTets = 20000;   // ~90 ms a step (README, bench-hand): beyond, no visual rate is left
inline constexpr double kMinMassKg = 1e-4;   // 0.1 g: a tenth of a paper clip
inline constexpr double kMaxMassKg = 1e3;    // 1 t: contact with a hand stays solvable (1e-3..1e3 mass ratios tested)

// x_W = q_W * x_local + p_W.
struct Pose {
  Eigen::Vector3d p_W{0, 0, 0};                             // m, |p_W| <= 1000 (BodyBounds); default origin
  Eigen::Quaterniond q_W = Eigen::Quaterniond::Identity();  // unit (normalised on load); default identity
};

struct MaterialDesc {
  std::string name;                   // key in the scene's "materials" map; "" for inline and built-in materials
  double youngs_modulus_pa = 50e3;    // Young's modulus E, Pa, in [100, 1e9] (deformable bodies and hands); default 50 kPa
  double poisson_ratio = 0.45;        // in [-0.9, 0.49] (0.5 is incompressible: no FEM step); default 0.45
  double density_kg_m3 = 1000.0;      // kg/m^3, in [1, 25000] (osmium: 22590); default 1000 (hands: 1070, see HandDesc)
  double friction = 0.5;              // Coulomb (kinetic) coefficient, in [0, 10]; default 0.5
  double friction_static = -1.0;      // in [friction, 10], or -1 (the default): same as friction; read static_friction()
  double restitution = 0.0;           // in [0, 1]; default 0 (no bounce)
  double rayleigh_alpha_per_s = 1.0;  // mass-proportional damping, 1/s, in [0, 1000] (deformables, hands); default 1
  double rayleigh_beta_s = 0.005;     // stiffness-proportional damping, s, in [0, 1] (deformables, hands); default 0.005

  double static_friction() const { return friction_static < 0 ? friction : friction_static; }
};

enum class ShapeType { box, sphere, capsule, cylinder, plane, mesh, tet_mesh };

// One shape in its object's local frame; only the fields of `type` are meaningful.
struct ShapeDesc {
  ShapeType type = ShapeType::box;
  // Lengths in [0.001, 100] m; a deformable box's sides in [0.001, 1] m (its mesh and distance grids).
  Eigen::Vector3d size{0, 0, 0};    // box: full extents along local x, y, z, m
  double radius = 0;                // sphere, capsule, cylinder: m
  double length = 0;                // capsule (between the cap centres), cylinder: along local z, m
  Eigen::Vector3d normal{0, 0, 1};  // plane: unit normal (normalised on load; any finite non-zero vector); default +z
  double offset = 0;                // plane: the points x with normal . x = offset, m, in [-1000, 1000]; default 0
  std::string file;  // mesh: OBJ surface; tet_mesh: TetGen .node (its .ele beside it) or Gmsh .msh; absolute path
  // tet_mesh, optional and only together: the closed OBJ surface (collision and display) and its
  // barycentric embedding in the tets (.embed), absolute paths; "" if none (the mesh's own boundary is the surface).
  std::string surface_file;
  std::string embedding_file;
  double scale = 1.0;  // mesh, tet_mesh: uniform scale applied to the file's coordinates, in [0.01, 100]; default 1
};

enum class BodyKind {
  static_body,  // fixed in the world, infinite mass ("static" in the file)
  rigid,        // a rigid body simulated by the rigid world
  deformable,   // an FEM body (tet_mesh shape, or a box the world meshes)
};

struct ObjectDesc {
  std::string name;
  BodyKind kind = BodyKind::rigid;
  ShapeDesc shape;
  Pose pose;              // initial pose; default identity
  // Total mass, kg, in [kMinMassKg, kMaxMassKg]; -1 (the default): shape volume x material.density_kg_m3,
  // which must lie in that range too (checked on load for primitives, by the World for files).
  double mass_kg = -1;
  MaterialDesc material;  // resolved copy (a named material, an inline one, or the built-in defaults)
  // Initial, world frame, within BodyBounds (faster is a diverged body); default 0 (always 0 when static).
  Eigen::Vector3d linear_velocity{0, 0, 0};   // m/s, |v| <= 50
  Eigen::Vector3d angular_velocity{0, 0, 0};  // rad/s, |w| <= 1000
};

enum class JointType { hinge, ball, fixed, slider };

struct JointDesc {
  std::string name;
  JointType type = JointType::hinge;
  std::string body_a;                 // a rigid or static object
  std::string body_b;                 // a rigid or static object, or "world"; at least one of the two is rigid
  Eigen::Vector3d anchor_W{0, 0, 0};  // m, |anchor| <= 1000, at the initial poses (required for hinge and ball); default origin
  Eigen::Vector3d axis_W{0, 0, 1};    // unit, at the initial poses (hinge, slider: required); default +z
  bool limited = false;               // hinge and slider only; default false
  // Limits, lo <= hi: rad in [-pi, pi] for a hinge (ODE's stops), m in [-1000, 1000] for a slider (0 = initial pose).
  double lo = 0, hi = 0;
};

enum class HandModelKind {
  fem,            // co-rotational FEM flesh on rigid handles (seed 004)
  spring,         // mass-spring hand (seed 002)
  soft_pad,       // rigid hand with soft finger pads (seed 000)
  contact_point,  // point contacts only (seed 001)
};

enum class HandSide { right, left };

// MaterialDesc's defaults with flesh density (hand_models' Material: 1070 kg/m^3).
inline MaterialDesc default_hand_material() {
  MaterialDesc m;
  m.density_kg_m3 = 1070.0;
  return m;
}

// Which skeleton frames become rigid handles of an fem hand.
enum class HandleSet {
  palm,        // one handle: the palm
  fingertips,  // the palm and the five distal phalanges
  phalanges,   // the palm and all fifteen phalanges
};

struct HandDesc {
  std::string name;
  HandModelKind model = HandModelKind::fem;         // default fem
  HandSide side = HandSide::right;                  // default right
  int resolution_tets = 1700;                       // fem: target tet count, in [kMinHandTets, kMaxHandTets]; default 1700
  HandleSet handles = HandleSet::palm;              // fem: default palm
  MaterialDesc material = default_hand_material();  // flesh; default: default_hand_material()
  Pose pose;  // initial pose of the hand frame (palm centre, fingers +y, palmar side -z); default identity
  double coupling_stiffness_n_m = 2000.0;  // per coupled node, handle to flesh, N/m, in [1, 1e6]; default 2000
  double coupling_damping_ns_m = 2.0;      // per coupled node, N s/m, in [0, 1000]; default 2
};

enum class DeviceKind { stylus, glove };

// Device coordinates D (m) to world: x_W = offset_W + scale * (R_WD * x_D).
struct WorkspaceMap {
  double scale = 1.0;                                        // in [0.01, 100]; default 1
  Eigen::Vector3d offset_W{0, 0, 0};                         // m, |offset| <= 1000; default origin
  Eigen::Quaterniond R_WD = Eigen::Quaterniond::Identity();  // unit; default identity
};

// How a glove's forces reach the hand: a wrench per tracked frame, or one
// force per finger along an actuator's line of action (CyberGrasp-like).
enum class GloveForceOutput { frames, finger_lines };

struct DeviceDesc {
  std::string name;
  DeviceKind kind = DeviceKind::stylus;
  std::string hand;  // the hand it drives (each hand is driven by at most one device)
  WorkspaceMap workspace;
  // The limits travel in the Welcome as float32: their upper bounds are the wire's (protocol/limits.hpp).
  double max_force_n = 8.0;            // output force clamp, N, in [0.01, protocol::kMaxForceN]; default 8
  double max_torque_nm = 0.5;          // output torque clamp, N m, in [0.001, protocol::kMaxTorqueNm]; default 0.5
  double max_force_rate_n_s = 1000.0;  // output force slew limit, N/s, in [1, protocol::kMaxForceRateNPerS]; default 1000
  double stiffness_n_m = 1000.0;       // device-to-proxy coupling stiffness, N/m, in [1, 1e5]; default 1000
  GloveForceOutput force_output = GloveForceOutput::frames;  // gloves only; default frames
  // finger_lines: the actuator's line of action in the distal phalanx frame (y along the bone,
  // z dorsal), unit; default dorsal (the cable pulls the fingertip back, resisting flexion).
  Eigen::Vector3d actuator_line_F = Eigen::Vector3d::UnitZ();
  // finger_lines: seed 002 section 4.5's coefficients a1, a2, a3 (the finger's joint torques, base to
  // tip, as forces at the fingertip) and a4 (its fingertip force), each in [0, 10]; a1..a3 need the
  // phalanx frames of a 16-frame glove. Default 0, 0, 0, 1: the finger's forces alone.
  std::array<double, 4> feedback_a{0.0, 0.0, 0.0, 1.0};
};

enum class ContactModel { constraint, penalty };

struct SceneDesc {
  std::string name;                                 // default: the file name without directory and extension
  std::string path;                                 // the scene file as given to the loader (or the source name)
  Eigen::Vector3d gravity_m_s2{0, 0, -9.81};        // m/s^2, world frame, each component in [-100, 100]; default -9.81 z
  double visual_rate_hz = 60.0;                     // visual (simulation) loop rate, Hz, in [10, 1000]; default 60
  double dt_s = 1.0 / 60.0;                         // simulation step, s, in [1e-4, 0.1]; default 1 / visual_rate_hz
  ContactModel contact = ContactModel::constraint;  // default constraint
  std::vector<MaterialDesc> materials;              // the named materials, sorted by name
  std::vector<ObjectDesc> objects;                  // file order
  std::vector<JointDesc> joints;
  std::vector<HandDesc> hands;
  std::vector<DeviceDesc> devices;

  // A rigid-body world is built only when something in it can move (static
  // geometry alone is collision-only; joints imply a rigid body).
  bool needs_rigid_world() const {
    for (const ObjectDesc& o : objects)
      if (o.kind == BodyKind::rigid) return true;
    return false;
  }
  bool needs_deformable_objects() const {
    for (const ObjectDesc& o : objects)
      if (o.kind == BodyKind::deformable) return true;
    return false;
  }
  // nullptr when absent.
  const ObjectDesc* find_object(std::string_view object_name) const { return find(objects, object_name); }
  const HandDesc* find_hand(std::string_view hand_name) const { return find(hands, hand_name); }
  const MaterialDesc* find_material(std::string_view material_name) const { return find(materials, material_name); }
  // The device driving a hand, nullptr if none.
  const DeviceDesc* device_for_hand(std::string_view hand_name) const {
    for (const DeviceDesc& d : devices)
      if (d.hand == hand_name) return &d;
    return nullptr;
  }

 private:
  template <class T>
  static const T* find(const std::vector<T>& items, std::string_view item_name) {
    for (const T& item : items)
      if (item.name == item_name) return &item;
    return nullptr;
  }
};

// The spelling of each enum value in scene files; one table per enum, shared by
// the loader and to_string so the two cannot drift apart.
template <class E>
struct EnumName {
  std::string_view name;
  E value;
};
inline constexpr EnumName<ShapeType> kShapeTypeNames[] = {
    {"box", ShapeType::box},           {"sphere", ShapeType::sphere}, {"capsule", ShapeType::capsule},
    {"cylinder", ShapeType::cylinder}, {"plane", ShapeType::plane},   {"mesh", ShapeType::mesh},
    {"tet_mesh", ShapeType::tet_mesh}};
inline constexpr EnumName<BodyKind> kBodyKindNames[] = {
    {"static", BodyKind::static_body}, {"rigid", BodyKind::rigid}, {"deformable", BodyKind::deformable}};
inline constexpr EnumName<JointType> kJointTypeNames[] = {
    {"hinge", JointType::hinge}, {"ball", JointType::ball}, {"fixed", JointType::fixed}, {"slider", JointType::slider}};
inline constexpr EnumName<HandModelKind> kHandModelNames[] = {{"fem", HandModelKind::fem},
                                                              {"spring", HandModelKind::spring},
                                                              {"soft_pad", HandModelKind::soft_pad},
                                                              {"contact_point", HandModelKind::contact_point}};
inline constexpr EnumName<HandSide> kHandSideNames[] = {{"right", HandSide::right}, {"left", HandSide::left}};
inline constexpr EnumName<HandleSet> kHandleSetNames[] = {
    {"palm", HandleSet::palm}, {"fingertips", HandleSet::fingertips}, {"phalanges", HandleSet::phalanges}};
inline constexpr EnumName<GloveForceOutput> kGloveForceOutputNames[] = {{"frames", GloveForceOutput::frames},
                                                                           {"finger_lines", GloveForceOutput::finger_lines}};
inline constexpr EnumName<DeviceKind> kDeviceKindNames[] = {{"stylus", DeviceKind::stylus},
                                                            {"glove", DeviceKind::glove}};
inline constexpr EnumName<ContactModel> kContactModelNames[] = {{"constraint", ContactModel::constraint},
                                                                {"penalty", ContactModel::penalty}};

template <class E, std::size_t N>
constexpr std::string_view enum_name(const EnumName<E> (&table)[N], E value) {
  for (const EnumName<E>& entry : table)
    if (entry.value == value) return entry.name;
  return "?";
}
inline std::string_view to_string(ShapeType v) { return enum_name(kShapeTypeNames, v); }
inline std::string_view to_string(BodyKind v) { return enum_name(kBodyKindNames, v); }
inline std::string_view to_string(JointType v) { return enum_name(kJointTypeNames, v); }
inline std::string_view to_string(HandModelKind v) { return enum_name(kHandModelNames, v); }
inline std::string_view to_string(HandSide v) { return enum_name(kHandSideNames, v); }
inline std::string_view to_string(HandleSet v) { return enum_name(kHandleSetNames, v); }
inline std::string_view to_string(DeviceKind v) { return enum_name(kDeviceKindNames, v); }
inline std::string_view to_string(ContactModel v) { return enum_name(kContactModelNames, v); }

}  // namespace hapticd::world
