#include "server/world/scene_loader.hpp"

#include <algorithm>
#include <charconv>
#include <climits>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <initializer_list>
#include <iterator>
#include <limits>
#include <map>
#include <nlohmann/json.hpp>
#include <numbers>
#include <optional>
#include <string_view>
#include <type_traits>
#include <utility>
#include <vector>

#include "protocol/limits.hpp"
#include "server/world/rigid_world.hpp"

namespace hapticd::world {

namespace {

std::string scene_error_message(const std::string& file, const std::string& key_path, const std::string& problem,
                                int line, int column) {
  std::string message = file;
  if (line > 0) message += ":" + std::to_string(line) + ":" + std::to_string(column);
  message += ": ";
  if (!key_path.empty()) message += key_path + ": ";
  return message + problem;
}

}  // namespace

SceneError::SceneError(std::string file, std::string key_path, std::string problem, int line, int column)
    : std::runtime_error(scene_error_message(file, key_path, problem, line, column)),
      file_(std::move(file)),
      key_path_(std::move(key_path)),
      problem_(std::move(problem)),
      line_(line),
      column_(column) {}

namespace {

namespace fs = std::filesystem;
using json = nlohmann::json;
using Eigen::Vector3d;

constexpr double kInf = std::numeric_limits<double>::infinity();
constexpr std::size_t kMaxDepth = 64;  // scenes nest about 5 deep; the cap bounds hostile input
constexpr std::size_t kMaxNameLength = 64;
constexpr std::size_t kMaxEchoedText = 60;    // user text quoted in messages is cut here
constexpr std::size_t kMaxEchoedPath = 1000;  // file paths are quoted nearly whole: the user must find them

// ---------------------------------------------------------------------------
// Messages

// A problem at a key path; parse_scene adds the file name.
struct KeyError {
  std::string path, problem;
};

[[noreturn]] void fail(std::string path, std::string problem) { throw KeyError{std::move(path), std::move(problem)}; }

// User text in messages: control bytes escaped so a message stays one readable line.
std::string escaped(std::string_view text, std::size_t max_length = kMaxEchoedText) {
  std::string out;
  for (std::size_t i = 0; i < text.size() && i < max_length; ++i) {
    const auto c = static_cast<unsigned char>(text[i]);
    if (c < 0x20 || c == 0x7f) {
      char hex[8];
      std::snprintf(hex, sizeof hex, "\\x%02x", static_cast<unsigned>(c));
      out += hex;
    } else {
      out += static_cast<char>(c);
    }
  }
  if (text.size() > max_length) out += "...";
  return out;
}

std::string in_quotes(std::string_view text, std::size_t max_length = kMaxEchoedText) {
  return "'" + escaped(text, max_length) + "'";
}

// Shortest text that reads back as the same double.
std::string fmt(double value) {
  char buffer[32];
  const auto result = std::to_chars(buffer, buffer + sizeof buffer, value);
  return std::string(buffer, result.ptr);
}

std::string join(std::initializer_list<std::string_view> items, std::string_view separator = ", ") {
  std::string out;
  for (std::string_view item : items) {
    if (!out.empty()) out += separator;
    out += item;
  }
  return out;
}

std::string join_key(const std::string& path, std::string_view key) {
  return path.empty() ? escaped(key) : path + "." + escaped(key);
}

std::string index_path(const std::string& path, std::size_t index) { return path + "[" + std::to_string(index) + "]"; }

std::string type_name(const json& value) {
  switch (value.type()) {
    case json::value_t::null:
      return "null";
    case json::value_t::boolean:
      return "boolean";
    case json::value_t::number_integer:
    case json::value_t::number_unsigned:
      return "integer";
    case json::value_t::number_float:
      return "number";
    case json::value_t::string:
      return "string";
    case json::value_t::array:
      return "array";
    case json::value_t::object:
      return "object";
    case json::value_t::binary:
      return "binary";
    case json::value_t::discarded:
      break;
  }
  return "discarded";
}

// ---------------------------------------------------------------------------
// Typed getters: each takes a JSON value and its key path, and returns the value or fails.

// An interval of accepted values; the default accepts every finite number.
struct Range {
  double lo = -kInf, hi = kInf;
  bool lo_open = false, hi_open = false;

  bool contains(double v) const { return (lo_open ? v > lo : v >= lo) && (hi_open ? v < hi : v <= hi); }
  std::string text() const {
    if (hi == kInf) return (lo_open ? "> " : ">= ") + fmt(lo);
    if (lo == -kInf) return (hi_open ? "< " : "<= ") + fmt(hi);
    return std::string("in ") + (lo_open ? "(" : "[") + fmt(lo) + ", " + fmt(hi) + (hi_open ? ")" : "]");
  }
};
constexpr Range kAny{};  // directions and quaternion components: normalised, any finite non-zero value does
constexpr Range kUnitInterval{0, 1, false, false};

// The range of every number a scene gives (scene.hpp states each with its field). Physically sensible
// bounds, each tight enough that what passes builds and steps a World without tripping an assertion
// (ODE's included), and that a device link's limits fit the Welcome that carries them.
// A rigid body beyond BodyBounds is reset as diverged: a scene starts within them.
constexpr BodyBounds kBodyBounds{};
constexpr double kMaxDistanceM = kBodyBounds.max_distance_m;     // |position|, offsets, anchors, slider limits
constexpr Range kCoordinate{-kMaxDistanceM, kMaxDistanceM};       // one component of a position
constexpr Range kGravity{-100, 100};                              // m/s^2 per component: 10 g
constexpr Range kVisualRate{10, 1000};                            // Hz; 1 / rate is then a valid dt_s
constexpr Range kTimeStep{1e-4, 0.1};                             // s: 10 kHz to 10 Hz
constexpr Range kYoungsModulus{100, 1e9};                         // Pa: a soft gel to a stiff plastic
constexpr Range kPoissonRatio{-0.9, 0.49};                        // 0.5 (incompressible) has no FEM step
constexpr Range kDensity{1, 25000};                               // kg/m^3: aerogel-light to osmium
constexpr Range kFriction{0, 10};
constexpr Range kRayleighAlpha{0, 1000};                          // 1/s
constexpr Range kRayleighBeta{0, 1};                              // s
constexpr Range kLength{0.001, 100};                              // m: sizes, radii and lengths of shapes
constexpr Range kDeformableLength{0.001, 1};                      // m: its tets and distance grids stay small
constexpr Range kMeshScale{0.01, 100};
constexpr Range kMass{kMinMassKg, kMaxMassKg};                    // kg
constexpr double kMaxSpeedMS = kBodyBounds.max_speed_m_s;         // |linear_velocity|
constexpr double kMaxAngularSpeedRadS = kBodyBounds.max_angular_speed_rad_s;
constexpr Range kHingeLimit{-std::numbers::pi, std::numbers::pi};  // rad: ODE's hinge stops
constexpr Range kCouplingStiffness{1, 1e6};                       // N/m per node
constexpr Range kCouplingDamping{0, 1000};                        // N s/m per node
constexpr Range kWorkspaceScale{0.01, 100};
constexpr Range kDeviceStiffness{1, 1e5};                         // N/m
// Device limits go out in the Welcome as float32, which the encoder refuses beyond the wire's
// limits: the upper bounds are those limits. The lower ones keep them positive as float32.
constexpr Range kMaxForce{0.01, protocol::kMaxForceN};
constexpr Range kMaxTorque{0.001, protocol::kMaxTorqueNm};
constexpr Range kMaxForceRate{1, protocol::kMaxForceRateNPerS};
constexpr Range kFeedbackCoefficient{0, 10};  // seed 002 section 4.5's a1..a4

double get_number(const json& value, const std::string& path, const Range& range = kAny) {
  if (!value.is_number()) fail(path, "expected a number, got " + type_name(value));
  const double v = value.get<double>();
  if (!std::isfinite(v)) fail(path, "must be finite, got " + fmt(v));
  if (!range.contains(v)) fail(path, "must be " + range.text() + ", got " + fmt(v));
  return v;
}

long long get_integer(const json& value, const std::string& path, long long lo, long long hi) {
  const auto out_of_range = [&](const std::string& got) {
    fail(path, "must be in [" + std::to_string(lo) + ", " + std::to_string(hi) + "], got " + got);
  };
  if (value.is_number_unsigned()) {  // may exceed long long: compare unsigned first
    const auto v = value.get<json::number_unsigned_t>();
    if (hi < 0 || v > static_cast<json::number_unsigned_t>(hi)) out_of_range(std::to_string(v));
    const auto s = static_cast<long long>(v);
    if (s < lo) out_of_range(std::to_string(v));
    return s;
  }
  if (value.is_number_integer()) {
    const auto v = value.get<json::number_integer_t>();
    if (v < lo || v > hi) out_of_range(std::to_string(v));
    return v;
  }
  if (!value.is_number_float()) fail(path, "expected an integer, got " + type_name(value));
  // 1.7e3 is an integer too, and integers beyond 2^64 reach us as doubles.
  const double v = value.get<double>();
  if (!std::isfinite(v) || std::trunc(v) != v) fail(path, "expected an integer, got number " + fmt(v));
  constexpr double kTwoTo63 = 9223372036854775808.0;  // converting beyond long long is undefined
  if (v < -kTwoTo63 || v >= kTwoTo63) out_of_range(fmt(v));
  const auto i = static_cast<long long>(v);
  if (i < lo || i > hi) out_of_range(fmt(v));
  return i;
}

const std::string& get_string(const json& value, const std::string& path) {
  if (!value.is_string()) fail(path, "expected a string, got " + type_name(value));
  return value.get_ref<const std::string&>();
}

// Names identify things in messages, the protocol and file keys: keep them plain.
void check_name(const std::string& name, const std::string& path) {
  if (name.empty()) fail(path, "must not be empty");
  if (name.size() > kMaxNameLength) fail(path, "name longer than " + std::to_string(kMaxNameLength) + " characters");
  for (const char c : name) {
    const bool ok = (c >= 'a' && c <= 'z') || (c >= 'A' && c <= 'Z') || (c >= '0' && c <= '9') || c == '_' || c == '-';
    if (!ok) fail(path, "name " + in_quotes(name) + " may only contain letters, digits, '_' and '-'");
  }
}

std::string get_name(const json& value, const std::string& path) {
  const std::string& name = get_string(value, path);
  check_name(name, path);
  return name;
}

template <class E, std::size_t N>
E get_choice(const json& value, const std::string& path, const EnumName<E> (&table)[N], std::string_view what) {
  const std::string& text = get_string(value, path);
  std::string expected;
  for (const EnumName<E>& entry : table) {
    if (entry.name == text) return entry.value;
    expected += (expected.empty() ? "" : ", ") + std::string(entry.name);
  }
  fail(path, "unknown " + std::string(what) + " " + in_quotes(text) + " (expected " + expected + ")");
}

Vector3d get_vec3(const json& value, const std::string& path, const Range& range = kAny) {
  if (!value.is_array()) fail(path, "expected an array of 3 numbers, got " + type_name(value));
  if (value.size() != 3) fail(path, "expected 3 numbers, got " + std::to_string(value.size()));
  Vector3d v;
  for (int i = 0; i < 3; ++i) v[i] = get_number(value[i], index_path(path, i), range);
  return v;
}

// A vector whose length is at most max_norm (each component finite).
Vector3d get_bounded_vec3(const json& value, const std::string& path, double max_norm, std::string_view unit) {
  const Vector3d v = get_vec3(value, path);
  const double norm = v.stableNorm();
  if (!(norm <= max_norm))
    fail(path, "length must be <= " + fmt(max_norm) + " " + std::string(unit) + ", got " + fmt(norm));
  return v;
}

// stableNorm: components near 1e±200 must neither overflow nor vanish.
Vector3d get_direction(const json& value, const std::string& path) {
  const Vector3d v = get_vec3(value, path);
  const double norm = v.stableNorm();
  if (!(norm > 0)) fail(path, "must be a non-zero vector");
  return v / norm;
}

// ---------------------------------------------------------------------------
// One JSON object at a key path. allow() comes first so a misspelt key is
// reported as unknown rather than as a missing required key.
class Obj {
 public:
  Obj(const json& value, std::string path) : value_(value), path_(std::move(path)) {
    if (!value.is_object()) fail(path_, "expected an object, got " + type_name(value));
  }

  const std::string& path() const { return path_; }
  std::string at(std::string_view key) const { return join_key(path_, key); }
  bool has(std::string_view key) const { return value_.contains(key); }

  void allow(std::initializer_list<std::string_view> keys, std::string_view owner = "") const {
    for (auto it = value_.begin(); it != value_.end(); ++it) {
      if (std::find(keys.begin(), keys.end(), it.key()) != keys.end()) continue;
      if (owner.empty()) fail(at(it.key()), "unknown key (expected one of: " + join(keys) + ")");
      fail(at(it.key()), "unknown key for " + std::string(owner) + " (expected one of: " + join(keys) + ")");
    }
  }

  // nullptr when absent and optional.
  const json* find(std::string_view key, bool required = false) const {
    const auto it = value_.find(key);
    if (it != value_.end()) return &*it;
    if (required) fail(at(key), "missing required key");
    return nullptr;
  }
  const json& get(std::string_view key) const { return *find(key, true); }

  // Each getter: a missing key yields `fallback`, or is an error without one.
  double number(std::string_view key, const Range& range = kAny, std::optional<double> fallback = {}) const {
    const json* v = find(key, !fallback);
    return v ? get_number(*v, at(key), range) : *fallback;
  }
  int integer(std::string_view key, int lo, int hi, std::optional<int> fallback = {}) const {
    const json* v = find(key, !fallback);
    return v ? static_cast<int>(get_integer(*v, at(key), lo, hi)) : *fallback;
  }
  const std::string& string(std::string_view key) const { return get_string(get(key), at(key)); }
  std::string name(std::string_view key) const { return get_name(get(key), at(key)); }
  template <class E, std::size_t N>
  E choice(std::string_view key, const EnumName<E> (&table)[N], std::string_view what,
           std::optional<std::type_identity_t<E>> fallback = {}) const {
    const json* v = find(key, !fallback);
    return v ? get_choice(*v, at(key), table, what) : *fallback;
  }
  Vector3d vec3(std::string_view key, const Range& range = kAny, std::optional<Vector3d> fallback = {}) const {
    const json* v = find(key, !fallback);
    return v ? get_vec3(*v, at(key), range) : *fallback;
  }
  Vector3d bounded_vec3(std::string_view key, double max_norm, std::string_view unit,
                        std::optional<Vector3d> fallback = {}) const {
    const json* v = find(key, !fallback);
    return v ? get_bounded_vec3(*v, at(key), max_norm, unit) : *fallback;
  }
  // A position in the world: within kMaxDistanceM of the origin.
  Vector3d position(std::string_view key, std::optional<Vector3d> fallback = {}) const {
    return bounded_vec3(key, kMaxDistanceM, "m", fallback);
  }
  Vector3d direction(std::string_view key) const { return get_direction(get(key), at(key)); }
  Obj object(std::string_view key) const { return Obj(get(key), at(key)); }

  // Every entry of a map-like object, its value as an Obj.
  template <class F>
  void for_each_entry(F&& f) const {
    for (auto it = value_.begin(); it != value_.end(); ++it) f(it.key(), Obj(it.value(), at(it.key())));
  }

  // An optional array of objects, each handed to `f` with its key path.
  template <class F>
  void for_each(std::string_view key, F&& f) const {
    const json* array = find(key);
    if (!array) return;
    if (!array->is_array()) fail(at(key), "expected an array, got " + type_name(*array));
    for (std::size_t i = 0; i < array->size(); ++i) f(Obj((*array)[i], index_path(at(key), i)));
  }

 private:
  const json& value_;
  std::string path_;
};

// {"w", "x", "y", "z"}, all required, normalised.
Eigen::Quaterniond get_quaternion(const Obj& o) {
  o.allow({"w", "x", "y", "z"});
  Eigen::Vector4d c(o.number("w"), o.number("x"), o.number("y"), o.number("z"));
  const double norm = c.stableNorm();
  if (!(norm > 0)) fail(o.path(), "zero quaternion: needs a non-zero norm");
  c /= norm;
  return Eigen::Quaterniond(c[0], c[1], c[2], c[3]);
}

Pose get_pose(const Obj& o) {
  o.allow({"position", "orientation"});
  Pose pose;
  pose.p_W = o.position("position", pose.p_W);
  if (o.has("orientation")) pose.q_W = get_quaternion(o.object("orientation"));
  return pose;
}

// ---------------------------------------------------------------------------
// Files

bool has_control_byte(std::string_view text) {
  return std::any_of(text.begin(), text.end(), [](char c) { return static_cast<unsigned char>(c) < 0x20; });
}

void check_readable(const fs::path& file, const std::string& key_path, std::string_view note = "") {
  std::error_code ec;
  const fs::file_status status = fs::status(file, ec);
  if (!ec && fs::exists(status) && !fs::is_regular_file(status))
    fail(key_path, in_quotes(file.string(), kMaxEchoedPath) + " is not a regular file" + std::string(note));
  const bool readable = !ec && fs::is_regular_file(status) && std::ifstream(file, std::ios::binary).is_open();
  if (!readable) fail(key_path, "cannot open " + in_quotes(file.string(), kMaxEchoedPath) + std::string(note));
}

// A file key: relative to base_dir, extension (lower-cased) one of `extensions`
// unless that is empty, must be readable. Returns the absolute path.
std::string get_file(const Obj& o, std::string_view key, const fs::path& base_dir,
                     std::initializer_list<std::string_view> extensions) {
  const std::string path = o.at(key);
  const std::string& name = o.string(key);
  if (name.empty()) fail(path, "must not be empty");
  if (has_control_byte(name)) fail(path, "file name " + in_quotes(name) + " contains a control character");
  fs::path file(name);
  if (file.is_relative()) file = base_dir / file;
  file = file.lexically_normal();
  std::string extension = file.extension().string();
  std::transform(extension.begin(), extension.end(), extension.begin(),
                 [](char c) { return (c >= 'A' && c <= 'Z') ? static_cast<char>(c - 'A' + 'a') : c; });
  if (extensions.size() > 0 && std::find(extensions.begin(), extensions.end(), extension) == extensions.end())
    fail(path, "expected a " + join(extensions, " or ") + " file, got " + in_quotes(name, kMaxEchoedPath));
  check_readable(file, path);
  if (extension == ".node") check_readable(fs::path(file).replace_extension(".ele"), path, " (the .node's .ele)");
  return file.string();
}

// ---------------------------------------------------------------------------
// Scene parts

using MaterialTable = std::map<std::string, MaterialDesc, std::less<>>;

struct Context {
  fs::path base_dir;
  MaterialTable materials;
  std::map<std::string, std::string, std::less<>> first_use;  // entity name -> key path of its definition

  // Entity names share one namespace so messages and the protocol can name anything unambiguously.
  std::string register_name(const Obj& o) {
    std::string name = o.name("name");
    if (name == "world") fail(o.at("name"), "'world' is reserved (joints use it for the fixed world)");
    const auto [it, inserted] = first_use.emplace(name, o.at("name"));
    if (!inserted) fail(o.at("name"), "duplicate name " + in_quotes(name) + " (first used at " + it->second + ")");
    return name;
  }
};

MaterialDesc parse_material(const Obj& o, MaterialDesc m) {
  o.allow({"youngs_modulus_pa", "poisson_ratio", "density_kg_m3", "friction", "friction_static", "restitution",
           "rayleigh_alpha_per_s", "rayleigh_beta_s"});
  m.youngs_modulus_pa = o.number("youngs_modulus_pa", kYoungsModulus, m.youngs_modulus_pa);
  m.poisson_ratio = o.number("poisson_ratio", kPoissonRatio, m.poisson_ratio);
  m.density_kg_m3 = o.number("density_kg_m3", kDensity, m.density_kg_m3);
  m.friction = o.number("friction", kFriction, m.friction);
  m.friction_static = o.number("friction_static", kFriction, m.friction_static);
  m.restitution = o.number("restitution", kUnitInterval, m.restitution);
  m.rayleigh_alpha_per_s = o.number("rayleigh_alpha_per_s", kRayleighAlpha, m.rayleigh_alpha_per_s);
  m.rayleigh_beta_s = o.number("rayleigh_beta_s", kRayleighBeta, m.rayleigh_beta_s);
  // Coulomb: sticking never holds less than sliding.
  if (m.friction_static >= 0 && m.friction_static < m.friction)
    fail(o.at("friction_static"), "must be >= friction (" + fmt(m.friction) + "), got " + fmt(m.friction_static));
  return m;
}

// A "material" value: the name of a "materials" entry, or an inline material
// starting from `defaults`. Sets *inline_density when the inline one gives a density.
MaterialDesc get_material_ref(const Obj& owner, const MaterialTable& table, const MaterialDesc& defaults,
                              bool* inline_density) {
  *inline_density = false;
  const json* value = owner.find("material");
  if (!value) return defaults;
  const std::string path = owner.at("material");
  if (value->is_string()) {
    const std::string& name = value->get_ref<const std::string&>();
    const auto it = table.find(name);
    if (it != table.end()) return it->second;
    std::string defined;
    for (const auto& entry : table) defined += (defined.empty() ? "" : ", ") + entry.first;
    fail(path, "no material named " + in_quotes(name) +
                   (defined.empty() ? " (the scene defines no materials)" : " (defined: " + defined + ")"));
  }
  if (!value->is_object())
    fail(path, "expected a material name or an inline material object, got " + type_name(*value));
  const Obj inline_material(*value, path);
  *inline_density = inline_material.has("density_kg_m3");
  return parse_material(inline_material, defaults);
}

ShapeDesc parse_shape(const Obj& o, BodyKind kind, const fs::path& base_dir) {
  o.allow({"type", "size", "radius", "length", "normal", "offset", "file", "scale", "surface", "embedding"});
  ShapeDesc s;
  s.type = o.choice("type", kShapeTypeNames, "shape");
  const std::string type_path = o.at("type");
  if (s.type == ShapeType::plane && kind != BodyKind::static_body)
    fail(type_path, "a plane can only be static (it is unbounded)");
  if (s.type == ShapeType::tet_mesh && kind != BodyKind::deformable)
    fail(type_path, "tet_mesh is for deformable objects (rigid and static objects use mesh)");
  if (kind == BodyKind::deformable && s.type != ShapeType::tet_mesh && s.type != ShapeType::box)
    fail(type_path, "deformable objects need a tet_mesh or box shape, got " + std::string(to_string(s.type)));
  const Range& length = kind == BodyKind::deformable ? kDeformableLength : kLength;
  switch (s.type) {
    case ShapeType::box:
      o.allow({"type", "size"}, "a box");
      s.size = o.vec3("size", length);
      break;
    case ShapeType::sphere:
      o.allow({"type", "radius"}, "a sphere");
      s.radius = o.number("radius", length);
      break;
    case ShapeType::capsule:
    case ShapeType::cylinder:
      o.allow({"type", "radius", "length"}, s.type == ShapeType::capsule ? "a capsule" : "a cylinder");
      s.radius = o.number("radius", length);
      s.length = o.number("length", length);
      break;
    case ShapeType::plane:
      o.allow({"type", "normal", "offset"}, "a plane");
      s.normal = o.direction("normal");
      s.offset = o.number("offset", kCoordinate);
      break;
    case ShapeType::mesh:
      o.allow({"type", "file", "scale"}, "a mesh");
      s.file = get_file(o, "file", base_dir, {".obj"});
      s.scale = o.number("scale", kMeshScale, 1.0);
      break;
    case ShapeType::tet_mesh:
      o.allow({"type", "file", "scale", "surface", "embedding"}, "a tet_mesh");
      s.file = get_file(o, "file", base_dir, {".node", ".msh"});
      s.scale = o.number("scale", kMeshScale, 1.0);
      // An embedding places a surface's vertices in the tets: one is no use without the other.
      if (o.has("surface") != o.has("embedding"))
        fail(o.at(o.has("surface") ? "surface" : "embedding"),
             o.has("surface") ? "needs \"embedding\" (the surface's barycentric embedding in the tets)"
                              : "needs \"surface\" (the OBJ surface it embeds)");
      if (o.has("surface")) s.surface_file = get_file(o, "surface", base_dir, {".obj"});
      if (o.has("embedding")) s.embedding_file = get_file(o, "embedding", base_dir, {});
      break;
  }
  return s;
}

// Volume of a primitive shape, m^3; 0 for shapes read from files (their volume is known once built).
double primitive_volume(const ShapeDesc& s) {
  const double pi = std::numbers::pi;
  switch (s.type) {
    case ShapeType::box: return s.size.prod();
    case ShapeType::sphere: return 4.0 / 3.0 * pi * s.radius * s.radius * s.radius;
    case ShapeType::capsule: return pi * s.radius * s.radius * (s.length + 4.0 / 3.0 * s.radius);
    case ShapeType::cylinder: return pi * s.radius * s.radius * s.length;
    default: return 0;
  }
}

ObjectDesc parse_object(const Obj& o, Context& ctx) {
  o.allow(
      {"name", "kind", "shape", "pose", "material", "mass_kg", "density_kg_m3", "linear_velocity", "angular_velocity"});
  ObjectDesc d;
  d.name = ctx.register_name(o);
  d.kind = o.choice("kind", kBodyKindNames, "body kind");
  d.shape = parse_shape(o.object("shape"), d.kind, ctx.base_dir);
  if (o.has("pose")) d.pose = get_pose(o.object("pose"));
  bool inline_density = false;
  d.material = get_material_ref(o, ctx.materials, MaterialDesc{}, &inline_density);

  if (d.kind == BodyKind::static_body) {
    for (const char* key : {"mass_kg", "density_kg_m3"})
      if (o.has(key)) fail(o.at(key), "static objects have no mass");
    for (const char* key : {"linear_velocity", "angular_velocity"})
      if (o.has(key)) fail(o.at(key), "static objects do not move");
    return d;
  }
  // One source of mass: an explicit mass, or a density stated for this object.
  const bool own_density = o.has("density_kg_m3");
  if (own_density && inline_density)
    fail(o.at("density_kg_m3"), "the inline material also gives density_kg_m3; give one of them");
  if (o.has("mass_kg") && (own_density || inline_density))
    fail(own_density ? o.at("density_kg_m3") : o.at("material") + ".density_kg_m3",
         "conflicts with mass_kg: give a mass or a density, not both");
  d.mass_kg = o.number("mass_kg", kMass, -1.0);
  if (own_density) d.material.density_kg_m3 = o.number("density_kg_m3", kDensity);
  // A mass from the density is bounded as a given one is (ODE wants a positive definite inertia).
  if (const double volume = primitive_volume(d.shape); d.mass_kg < 0 && volume > 0) {
    const double mass_kg = d.material.density_kg_m3 * volume;
    if (!kMass.contains(mass_kg))
      fail(o.path(), "its mass (density " + fmt(d.material.density_kg_m3) + " kg/m^3 x volume " + fmt(volume) +
                         " m^3 = " + fmt(mass_kg) + " kg) must be " + kMass.text() +
                         " kg; give mass_kg or change the size or density");
  }
  d.linear_velocity = o.bounded_vec3("linear_velocity", kMaxSpeedMS, "m/s", Vector3d::Zero());
  d.angular_velocity = o.bounded_vec3("angular_velocity", kMaxAngularSpeedRadS, "rad/s", Vector3d::Zero());
  return d;
}

// body_b may be "world"; deformable bodies cannot be jointed.
std::string get_joint_body(const Obj& o, std::string_view key, const std::vector<ObjectDesc>& objects, bool allow_world,
                           bool* rigid) {
  const std::string& name = o.string(key);
  *rigid = false;
  if (name == "world") {
    if (!allow_world) fail(o.at(key), "must be an object; put \"world\" in body_b");
    return name;
  }
  const auto it = std::find_if(objects.begin(), objects.end(), [&](const ObjectDesc& x) { return x.name == name; });
  if (it == objects.end()) fail(o.at(key), "no object named " + in_quotes(name));
  if (it->kind == BodyKind::deformable)
    fail(o.at(key), "object " + in_quotes(name) + " is deformable; joints connect rigid and static bodies");
  *rigid = it->kind == BodyKind::rigid;
  return name;
}

JointDesc parse_joint(const Obj& o, Context& ctx, const std::vector<ObjectDesc>& objects) {
  o.allow({"name", "type", "body_a", "body_b", "anchor", "axis", "limits"});
  JointDesc d;
  d.name = ctx.register_name(o);
  d.type = o.choice("type", kJointTypeNames, "joint type");
  bool a_rigid = false, b_rigid = false;
  d.body_a = get_joint_body(o, "body_a", objects, false, &a_rigid);
  d.body_b = get_joint_body(o, "body_b", objects, true, &b_rigid);
  if (d.body_a == d.body_b) fail(o.at("body_b"), "joins " + in_quotes(d.body_a) + " to itself");
  if (!a_rigid && !b_rigid) fail(o.at("body_b"), "a joint needs at least one rigid body");

  const bool has_axis = d.type == JointType::hinge || d.type == JointType::slider;
  const bool needs_anchor = d.type == JointType::hinge || d.type == JointType::ball;
  d.anchor_W = needs_anchor ? o.position("anchor") : o.position("anchor", d.anchor_W);
  if (has_axis) {
    d.axis_W = o.direction("axis");
  } else if (o.has("axis")) {
    fail(o.at("axis"), "only hinge and slider joints have an axis");
  }
  if (const json* limits = o.find("limits")) {
    const std::string path = o.at("limits");
    if (!has_axis) fail(path, "only hinge and slider joints have limits");
    if (!limits->is_array() || limits->size() != 2)
      fail(path, "expected [lo, hi], got " +
                     (limits->is_array() ? std::to_string(limits->size()) + " elements" : type_name(*limits)));
    const Range& range = d.type == JointType::hinge ? kHingeLimit : kCoordinate;
    d.lo = get_number((*limits)[0], index_path(path, 0), range);
    d.hi = get_number((*limits)[1], index_path(path, 1), range);
    if (d.lo > d.hi) fail(path, "lo must be <= hi, got [" + fmt(d.lo) + ", " + fmt(d.hi) + "]");
    d.limited = true;
  }
  return d;
}

HandDesc parse_hand(const Obj& o, Context& ctx) {
  o.allow({"name", "model", "side", "resolution_tets", "handles", "material", "pose", "coupling_stiffness_n_m",
           "coupling_damping_ns_m"});
  HandDesc d;
  d.name = ctx.register_name(o);
  d.model = o.choice("model", kHandModelNames, "hand model", d.model);
  d.side = o.choice("side", kHandSideNames, "hand side", d.side);
  d.resolution_tets = o.integer("resolution_tets", kMinHandTets, kMaxHandTets, d.resolution_tets);
  d.handles = o.choice("handles", kHandleSetNames, "handle set", d.handles);
  bool inline_density = false;
  d.material = get_material_ref(o, ctx.materials, d.material, &inline_density);
  if (o.has("pose")) d.pose = get_pose(o.object("pose"));
  d.coupling_stiffness_n_m = o.number("coupling_stiffness_n_m", kCouplingStiffness, d.coupling_stiffness_n_m);
  d.coupling_damping_ns_m = o.number("coupling_damping_ns_m", kCouplingDamping, d.coupling_damping_ns_m);
  return d;
}

DeviceDesc parse_device(const Obj& o, Context& ctx, const std::vector<HandDesc>& hands,
                        std::map<std::string, std::string, std::less<>>& driver_of_hand) {
  o.allow({"name", "kind", "hand", "workspace", "max_force_n", "max_torque_nm", "max_force_rate_n_s", "stiffness_n_m",
           "force_output", "actuator_line", "feedback_a"});
  DeviceDesc d;
  d.name = ctx.register_name(o);
  d.kind = o.choice("kind", kDeviceKindNames, "device kind");
  d.hand = o.string("hand");
  if (std::none_of(hands.begin(), hands.end(), [&](const HandDesc& h) { return h.name == d.hand; }))
    fail(o.at("hand"), "no hand named " + in_quotes(d.hand));
  const auto [it, inserted] = driver_of_hand.emplace(d.hand, o.path());
  if (!inserted) fail(o.at("hand"), "hand " + in_quotes(d.hand) + " is already driven by " + it->second);
  if (o.has("workspace")) {
    const Obj w = o.object("workspace");
    w.allow({"scale", "offset", "orientation"});
    d.workspace.scale = w.number("scale", kWorkspaceScale, d.workspace.scale);
    d.workspace.offset_W = w.position("offset", d.workspace.offset_W);
    if (w.has("orientation")) d.workspace.R_WD = get_quaternion(w.object("orientation"));
  }
  d.max_force_n = o.number("max_force_n", kMaxForce, d.max_force_n);
  d.max_torque_nm = o.number("max_torque_nm", kMaxTorque, d.max_torque_nm);
  d.max_force_rate_n_s = o.number("max_force_rate_n_s", kMaxForceRate, d.max_force_rate_n_s);
  d.stiffness_n_m = o.number("stiffness_n_m", kDeviceStiffness, d.stiffness_n_m);
  d.force_output = o.choice("force_output", kGloveForceOutputNames, "force output", d.force_output);
  if (o.has("actuator_line")) d.actuator_line_F = o.direction("actuator_line");
  if (d.kind != DeviceKind::glove && (o.has("force_output") || o.has("actuator_line")))
    fail(o.at(o.has("force_output") ? "force_output" : "actuator_line"), "only a glove has finger outputs");
  if (d.force_output == GloveForceOutput::finger_lines) {
    const auto hand = std::find_if(hands.begin(), hands.end(), [&](const HandDesc& h) { return h.name == d.hand; });
    if (hand->handles == HandleSet::palm)
      fail(o.at("force_output"), "finger_lines needs the hand's handles to be fingertips or phalanges");
    if (const json* a = o.find("feedback_a")) {
      const std::string path = o.at("feedback_a");
      if (!a->is_array() || a->size() != 4)
        fail(path, "expected an array of 4 numbers (a1, a2, a3, a4), got " +
                       (a->is_array() ? std::to_string(a->size()) + " elements" : type_name(*a)));
      for (int k = 0; k < 4; ++k) d.feedback_a[k] = get_number((*a)[k], index_path(path, k), kFeedbackCoefficient);
      if (hand->handles != HandleSet::phalanges && (d.feedback_a[0] > 0 || d.feedback_a[1] > 0 || d.feedback_a[2] > 0))
        fail(path, "the joint torques' coefficients a1..a3 need a hand with phalanx handles (a 16-frame glove)");
    }
  } else if (o.has("feedback_a")) {
    fail(o.at("feedback_a"), "feedback_a needs \"force_output\": \"finger_lines\"");
  }
  return d;
}

SceneDesc parse_document(const json& doc, const fs::path& base_dir, const std::string& source_name) {
  const Obj top(doc, "");
  // Version first: a newer file should say so rather than fail on its new keys.
  const long long version = get_integer(top.get("version"), "version", LLONG_MIN, LLONG_MAX);
  if (version != 1) fail("version", "unsupported version " + std::to_string(version) + " (this build reads 1)");
  top.allow({"version", "name", "gravity", "visual_rate_hz", "dt_s", "contact", "materials", "objects", "joints",
             "hands", "devices"});

  SceneDesc scene;
  scene.path = source_name;
  scene.name = top.has("name") ? top.name("name") : fs::path(source_name).stem().string();
  scene.gravity_m_s2 = top.vec3("gravity", kGravity, scene.gravity_m_s2);
  scene.visual_rate_hz = top.number("visual_rate_hz", kVisualRate, scene.visual_rate_hz);
  // kVisualRate keeps the default within kTimeStep.
  scene.dt_s = top.number("dt_s", kTimeStep, 1.0 / scene.visual_rate_hz);
  scene.contact = top.choice("contact", kContactModelNames, "contact model", scene.contact);

  Context ctx;
  ctx.base_dir = base_dir;
  if (top.has("materials")) {
    top.object("materials").for_each_entry([&](const std::string& key, const Obj& value) {
      check_name(key, value.path());
      MaterialDesc m = parse_material(value, MaterialDesc{});
      m.name = key;
      ctx.materials.emplace(key, m);
      scene.materials.push_back(std::move(m));
    });
  }
  top.for_each("objects", [&](const Obj& o) { scene.objects.push_back(parse_object(o, ctx)); });
  top.for_each("joints", [&](const Obj& o) { scene.joints.push_back(parse_joint(o, ctx, scene.objects)); });
  top.for_each("hands", [&](const Obj& o) {
    scene.hands.push_back(parse_hand(o, ctx));
    // The rigid hands' ODE segments collide with rigid and static objects only: a deformable object
    // would pass through them unseen.
    const HandDesc& h = scene.hands.back();
    const auto deformable = std::find_if(scene.objects.begin(), scene.objects.end(),
                                         [](const ObjectDesc& d) { return d.kind == BodyKind::deformable; });
    const bool rigid_hand = h.model == HandModelKind::spring || h.model == HandModelKind::contact_point;
    if (rigid_hand && deformable != scene.objects.end())
      fail(o.at("model"), "the " + std::string(to_string(h.model)) + " hand does not touch deformable objects, and " +
                              in_quotes(deformable->name) + " is one (use \"fem\", or make it rigid)");
  });
  std::map<std::string, std::string, std::less<>> driver_of_hand;
  top.for_each("devices",
               [&](const Obj& o) { scene.devices.push_back(parse_device(o, ctx, scene.hands, driver_of_hand)); });
  return scene;
}

// ---------------------------------------------------------------------------
// Strict JSON text parsing

// nlohmann's DOM builder plus: duplicate keys rejected (nlohmann keeps the last
// silently), nesting capped, and the key path of a syntax error remembered.
class StrictJsonBuilder {
 public:
  explicit StrictJsonBuilder(json& root) : root_(root) {}

  bool null() { return put(nullptr); }
  bool boolean(bool v) { return put(v); }
  bool number_integer(json::number_integer_t v) { return put(v); }
  bool number_unsigned(json::number_unsigned_t v) { return put(v); }
  bool number_float(json::number_float_t v, const json::string_t& /*text*/) { return put(v); }
  bool string(json::string_t& v) { return put(std::move(v)); }
  bool binary(json::binary_t& v) { return put(json::binary(std::move(v))); }
  bool start_object(std::size_t /*size*/) { return open(json::object()); }
  bool start_array(std::size_t /*size*/) { return open(json::array()); }
  bool end_object() { return close(); }
  bool end_array() { return close(); }
  bool key(json::string_t& key) {
    Frame& top = stack_.back();
    if (top.node->contains(key)) {
      error_ = KeyError{join_key(top.path, key), "duplicate key"};
      return false;
    }
    top.key = std::move(key);
    return true;
  }
  bool parse_error(std::size_t position, const std::string& /*last_token*/, const json::exception& ex) {
    error_position_ = position;
    error_ = KeyError{here(), ex.what()};
    return false;
  }

  const std::optional<KeyError>& error() const { return error_; }
  const std::optional<std::size_t>& error_position() const { return error_position_; }  // syntax errors only

 private:
  struct Frame {
    json* node;
    std::string path;
    std::string key;  // the object's latest key
  };

  // Key path of the value being read now.
  std::string here() const {
    if (stack_.empty()) return "";
    const Frame& top = stack_.back();
    if (top.node->is_object()) return top.key.empty() ? top.path : join_key(top.path, top.key);
    return index_path(top.path, top.node->size());
  }
  // Where the next value goes; pointers stay valid because only the innermost container grows.
  json* slot() {
    if (stack_.empty()) return &root_;
    Frame& top = stack_.back();
    if (top.node->is_object()) return &(*top.node)[top.key];
    top.node->push_back(nullptr);
    return &top.node->back();
  }
  template <class T>
  bool put(T&& value) {
    *slot() = json(std::forward<T>(value));
    return true;
  }
  bool open(json empty) {
    if (stack_.size() >= kMaxDepth) {
      error_ = KeyError{here(), "nested deeper than " + std::to_string(kMaxDepth) + " levels"};
      return false;
    }
    std::string path = here();
    json* node = slot();
    *node = std::move(empty);
    stack_.push_back({node, std::move(path), {}});
    return true;
  }
  bool close() {
    stack_.pop_back();
    return true;
  }

  json& root_;
  std::vector<Frame> stack_;
  std::optional<KeyError> error_;
  std::optional<std::size_t> error_position_;
};

// nlohmann counts the bytes read when it failed, the last being the offending one.
std::pair<int, int> line_column(const std::string& text, std::size_t position) {
  const std::size_t end = std::min(position > 0 ? position - 1 : 0, text.size());
  std::size_t line = 1, line_start = 0;
  for (std::size_t i = 0; i < end; ++i) {
    if (text[i] == '\n') {
      ++line;
      line_start = i + 1;
    }
  }
  const auto clamp = [](std::size_t v) { return static_cast<int>(std::min<std::size_t>(v, INT_MAX)); };
  return {clamp(line), clamp(end - line_start + 1)};
}

// "[json.exception.parse_error.101] parse error at line 1, column 5: syntax error ..." -> "syntax error ...".
std::string describe_json_error(std::string what) {
  if (what.starts_with("[json.exception.")) {
    const std::size_t end = what.find("] ");
    if (end != std::string::npos) what.erase(0, end + 2);
  }
  if (what.starts_with("parse error")) {
    const std::size_t end = what.find(": ");
    if (end != std::string::npos) what.erase(0, end + 2);
  }
  return escaped(what, 200);
}

fs::path absolute_dir(const std::string& dir) {
  std::error_code ec;
  fs::path path = dir.empty() ? fs::current_path(ec) : fs::absolute(dir, ec);
  return ec ? fs::path(dir) : path.lexically_normal();
}

}  // namespace

SceneDesc parse_scene(const nlohmann::json& doc, const std::string& base_dir, const std::string& source_name) {
  try {
    return parse_document(doc, absolute_dir(base_dir), source_name);
  } catch (const KeyError& e) {
    throw SceneError(source_name, e.path, e.problem);
  }
}

SceneDesc parse_scene_text(const std::string& text, const std::string& base_dir, const std::string& source_name) {
  json doc;
  StrictJsonBuilder builder(doc);
  bool ok = false;
  try {
    ok = json::sax_parse(text, &builder, json::input_format_t::json, /*strict=*/true, /*ignore_comments=*/false);
  } catch (const json::exception& e) {  // not expected with a SAX; reported rather than leaked
    throw SceneError(source_name, "", describe_json_error(e.what()));
  }
  if (!ok) {
    const KeyError error = builder.error().value_or(KeyError{"", "invalid JSON"});
    if (!builder.error_position()) throw SceneError(source_name, error.path, error.problem);
    const auto [line, column] = line_column(text, *builder.error_position());
    throw SceneError(source_name, error.path, describe_json_error(error.problem), line, column);
  }
  return parse_scene(doc, base_dir, source_name);
}

SceneDesc load_scene(const std::string& path) {
  std::error_code ec;
  const fs::file_status status = fs::status(path, ec);
  if (!ec && fs::exists(status) && !fs::is_regular_file(status)) throw SceneError(path, "", "not a regular file");
  std::ifstream in(path, std::ios::binary);
  if (!in.is_open()) throw SceneError(path, "", "cannot open");
  std::string text((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  if (in.bad()) throw SceneError(path, "", "read error");
  return parse_scene_text(text, fs::absolute(path, ec).parent_path().string(), path);
}

}  // namespace hapticd::world
