#pragma once
// The strict scene-file loader. A scene is one JSON object (SI units, world z up):
//
//   {
//     "version": 1,                        required; the only version
//     "name": "blocks",                    optional; default: file name without extension
//     "gravity": [0, 0, -9.81],            m/s^2, each component in [-100, 100]
//     "visual_rate_hz": 60,                in [10, 1000]
//     "dt_s": 0.0166667,                   in [1e-4, 0.1]; default 1 / visual_rate_hz
//     "contact": "constraint",             constraint | penalty
//     "materials": { "<name>": <material>, ... },
//     "objects": [ <object>, ... ],  "joints": [ <joint>, ... ],
//     "hands": [ <hand>, ... ],      "devices": [ <device>, ... ]
//   }
//   <material>  { "youngs_modulus_pa", "poisson_ratio", "density_kg_m3", "friction",
//                 "friction_static", "restitution", "rayleigh_alpha_per_s", "rayleigh_beta_s" }
//               (all optional, defaults and ranges as in MaterialDesc)
//   <pose>      { "position": [x, y, z], "orientation": {"w": .., "x": .., "y": .., "z": ..} }
//               (both optional; the quaternion needs all four components, is normalised, must be non-zero)
//   <object>    { "name", "kind": static | rigid | deformable, "shape": <shape>, "pose", "material",
//                 "mass_kg", "density_kg_m3", "linear_velocity", "angular_velocity" }
//   <shape>     { "type": "box", "size": [x, y, z] } | { "type": "sphere", "radius" }
//               | { "type": "capsule" | "cylinder", "radius", "length" }
//               | { "type": "plane", "normal": [x, y, z], "offset" }
//               | { "type": "mesh", "file": "*.obj", "scale" }
//               | { "type": "tet_mesh", "file": "*.node" | "*.msh", "scale", "surface": "*.obj",
//                   "embedding": "<file>" }
//               (every shape key is required except "scale", default 1, and "surface" with
//               "embedding", which come together or not at all)
//   <joint>     { "name", "type": hinge | ball | fixed | slider, "body_a", "body_b", "anchor": [x, y, z],
//                 "axis": [x, y, z], "limits": [lo, hi] }
//   <hand>      { "name", "model": fem | spring | soft_pad | contact_point, "side": right | left,
//                 "resolution_tets", "handles": palm | fingertips | phalanges, "material", "pose",
//                 "coupling_stiffness_n_m", "coupling_damping_ns_m" }
//   <device>    { "name", "kind": stylus | glove, "hand",
//                 "workspace": { "scale", "offset": [x, y, z], "orientation": <quaternion> },
//                 "max_force_n", "max_torque_nm", "max_force_rate_n_s", "stiffness_n_m" }
//
// Rules (each violation is a SceneError naming the key path):
//  - Unknown and duplicate keys are errors, as are wrong types, non-finite numbers and
//    out-of-range values. Every number has a range, stated with its field in scene.hpp: what
//    loads builds a World that steps and serves its devices (their force, torque and slew
//    limits are bounded by the wire's, protocol/limits.hpp, so the Welcome carrying them encodes). Names ("name" keys
//    and material keys) are 1-64 letters, digits,
//    '_' or '-', unique across objects, joints, hands and devices; "world" is reserved.
//  - "material" is the name of a "materials" entry or an inline <material>; an inline
//    material starts from the owner's defaults (MaterialDesc, or HandDesc's for hands).
//  - Objects: "name", "kind" and "shape" are required. Static objects take no mass,
//    density or velocity. Rigid and deformable objects take "mass_kg" or a density
//    ("density_kg_m3" on the object or in an inline material), not both; with neither the
//    material's density applies. Planes are static only, tet_mesh is deformable only, and
//    deformable objects are tet_mesh or box. Shape keys not used by the type are errors.
//  - Files are relative to the scene file's directory (or absolute), must be readable
//    regular files, and are stored as absolute paths; a .node needs its .ele beside it.
//  - Joints: "name", "type", "body_a", "body_b" required; body_a an object, body_b an
//    object or "world"; "anchor" required for hinge and ball, "axis" required for hinge
//    and slider and rejected otherwise, "limits" for hinge (rad) and slider (m) only.
//  - Hands: only "name" is required; a "spring" or "contact_point" hand (rigid ODE segments)
//    does not touch deformable objects and is refused in a scene with one. Devices: "name", "kind", "hand" required;
//    each hand is driven by at most one device; the workspace maps device coordinates to world: x_W = offset + scale *
//    (orientation * x_D).
//  - Materials: friction_static, when given, is >= friction. A named material's density
//    is only a default, so "mass_kg" with a named material is fine.
#include <nlohmann/json_fwd.hpp>
#include <stdexcept>
#include <string>

#include "server/world/scene.hpp"

namespace hapticd::world {

// what(): "<file>: <key path>: <problem>", e.g.
// "stylus_bunny.json: objects[2].material.friction: must be >= 0, got -0.2". JSON syntax
// errors carry a position: "<file>:<line>:<column>: <key path>: <problem>", the column
// (in bytes) of the last byte the JSON parser read: the offending byte, or the end of an
// overflowing number; the key path says where in the tree and may be empty. File-level
// problems ("cannot open") have no key path.
class SceneError : public std::runtime_error {
 public:
  SceneError(std::string file, std::string key_path, std::string problem, int line = 0, int column = 0);
  const std::string& file() const { return file_; }
  const std::string& key_path() const { return key_path_; }  // e.g. "objects[2].material.friction"
  const std::string& problem() const { return problem_; }
  int line() const { return line_; }  // 1-based; 0 unless a JSON syntax error
  int column() const { return column_; }

 private:
  std::string file_, key_path_, problem_;
  int line_, column_;
};

// Reads and validates a scene file; relative asset paths resolve against its directory.
// Errors name the file as `path` was given.
SceneDesc load_scene(const std::string& path);

// Validates an already-parsed document (duplicate keys were already lost by the JSON
// parser). base_dir resolves relative asset paths; source_name prefixes error messages
// and gives the default scene name.
SceneDesc parse_scene(const nlohmann::json& doc, const std::string& base_dir, const std::string& source_name);

// Parses JSON text strictly (duplicate keys, syntax errors with line:column) and then
// validates it as parse_scene does.
SceneDesc parse_scene_text(const std::string& text, const std::string& base_dir, const std::string& source_name);

}  // namespace hapticd::world
