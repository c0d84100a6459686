#include "server/world/rigid_world.hpp"

#include <algorithm>
#include <cmath>
#include <numbers>
#include <stdexcept>

#include "hand_models/embedded_surface.hpp"

namespace hapticd::world {
namespace {

constexpr int kMaxContactsPerPair = 8;
// A body's supports on one piece of static geometry (supports_of), for the soft bodies' solves that
// hold it: 8 left a mesh's other vertices free to go into the table, and the bunny pressed by the
// hand rocked on them, 0.5-0.9 mm into the table at up to 0.55 rad/s in a cycle of four visual steps
// (a light served hand passed it to the device: +0.0004 J over the gentle press at 60 Hz); with 16,
// 0.17 mm and 0.25 rad/s, and that press takes energy out (-0.0012 J).
constexpr int kMaxSupportsPerPair = 16;
// What ODE is asked for per pair before the contacts are thinned to kMaxContactsPerPair.
constexpr int kCandidateContactsPerPair = 64;
constexpr double kMinContactSpacing_m = 1e-3;
constexpr double kGapWeight = 4.0;
// Contacts are stiff but not rigid (ERP and CFM of a ~1e6 N/m spring at 60 Hz).
constexpr double kContactErp = 0.2, kContactCfm = 1e-7;
// Below this tangential speed a contact is sticking: static friction applies.
constexpr double kStickSpeed_m_s = 1e-3;

// Indices of up to N of n contacts spread over their patch: the deepest, then each
// time the one farthest from those kept less kGapWeight times how much shallower it is than the
// deepest (a vertex 2 cm above the table is no support for a body resting on it), none closer than
// kMinContactSpacing_m to a kept one. Returns how many, in `kept`.
template <int N, class Position, class Depth>
int spread_contacts(int n, const Position& position, const Depth& depth, int (&kept)[N]) {
  if (n <= 0) return 0;
  std::vector<double> nearest(n);
  int first = 0;
  for (int k = 1; k < n; ++k)
    if (depth(k) > depth(first)) first = k;
  int count = 0;
  for (int next = first; next >= 0 && count < N;) {
    kept[count++] = next;
    const Eigen::Vector3d p = position(next);
    int best = -1;
    double best_score = 0;
    for (int k = 0; k < n; ++k) {
      const double d = (position(k) - p).norm();
      nearest[k] = count == 1 ? d : std::min(nearest[k], d);
      if (nearest[k] <= kMinContactSpacing_m) continue;
      const double score = nearest[k] - kGapWeight * (depth(first) - depth(k));
      if (best < 0 || score > best_score) best = k, best_score = score;
    }
    next = best;
  }
  return count;
}

// Up to kMaxContactsPerPair contacts of geoms a and b into `out` (ODE's order of geoms and its
// normal), spread over the contact patch (spread_contacts): what contacts_of reports. ODE's trimesh
// collider lists its first contacts from neighbouring triangles (the scenes' bunny tipped onto a
// foot: 8 contacts within 5 mm). ODE's own step keeps ODE's first contacts: spread there too, the
// stylus press on the movable bunny at 30 Hz rendered 0.53 N RMS from the world stepped every tick
// instead of 0.42 N (Multirate tests).
int collide_spread(dGeomID a, dGeomID b, dContactGeom (&out)[kMaxContactsPerPair]) {
  dContactGeom all[kCandidateContactsPerPair];
  const int n = dCollide(a, b, kCandidateContactsPerPair, all, sizeof(dContactGeom));
  int kept[kMaxContactsPerPair];
  const int count = spread_contacts(
      n, [&](int k) { return Eigen::Vector3d(all[k].pos[0], all[k].pos[1], all[k].pos[2]); },
      [&](int k) { return all[k].depth; }, kept);
  for (int k = 0; k < count; ++k) out[k] = all[kept[k]];
  return count;
}

void to_ode(const Eigen::Quaterniond& q, dQuaternion out) {
  out[0] = q.w(), out[1] = q.x(), out[2] = q.y(), out[3] = q.z();
}
Eigen::Vector3d from_ode(const dReal* v) { return {v[0], v[1], v[2]}; }

// Mass of a shape: `mass_kg` if > 0, else density times the shape's volume.
void set_mass(dMass& m, const ShapeDesc& s, double mass_kg, double density, dGeomID geom) {
  const double pi = std::numbers::pi;
  double volume = 0;
  switch (s.type) {
    case ShapeType::box:
      volume = s.size.prod();
      break;
    case ShapeType::sphere:
      volume = 4.0 / 3.0 * pi * std::pow(s.radius, 3);
      break;
    case ShapeType::capsule:
      volume = pi * s.radius * s.radius * s.length + 4.0 / 3.0 * pi * std::pow(s.radius, 3);
      break;
    case ShapeType::cylinder:
      volume = pi * s.radius * s.radius * s.length;
      break;
    case ShapeType::mesh:
      dMassSetTrimesh(&m, density, geom);
      volume = m.mass / density;
      break;
    default:
      throw std::logic_error("no rigid mass for this shape");
  }
  const double total = mass_kg > 0 ? mass_kg : density * volume;
  switch (s.type) {
    case ShapeType::box:
      dMassSetBoxTotal(&m, total, s.size.x(), s.size.y(), s.size.z());
      break;
    case ShapeType::sphere:
      dMassSetSphereTotal(&m, total, s.radius);
      break;
    case ShapeType::capsule:
      dMassSetCapsuleTotal(&m, total, 3, s.radius, s.length);
      break;
    case ShapeType::cylinder:
      dMassSetCylinderTotal(&m, total, 3, s.radius, s.length);
      break;
    case ShapeType::mesh:
      dMassSetTrimeshTotal(&m, total, geom);
      break;
    default:
      break;
  }
}

Eigen::Vector3d geom_position(dGeomID g) {
  const dReal* p = dGeomGetPosition(g);
  return {p[0], p[1], p[2]};
}

Eigen::Matrix3d geom_rotation(dGeomID g) {
  dQuaternion q;
  dGeomGetQuaternion(g, q);
  return Eigen::Quaterniond(q[0], q[1], q[2], q[3]).toRotationMatrix();
}

}  // namespace

namespace detail {

bool point_penetration(dGeomID geom, const Eigen::Vector3d& p, double& depth, Eigen::Vector3d& n,
                       const Eigen::Vector3d& entry_n, double margin) {
  const int cls = dGeomGetClass(geom);
  if (cls == dPlaneClass) {
    dVector4 plane;
    dGeomPlaneGetParams(geom, plane);
    n = Eigen::Vector3d(plane[0], plane[1], plane[2]);
    depth = plane[3] - n.dot(p);
    return depth > -margin;
  }
  const Eigen::Matrix3d R = geom_rotation(geom);
  const Eigen::Vector3d q = R.transpose() * (p - geom_position(geom));  // point in the geom frame
  Eigen::Vector3d n_local = Eigen::Vector3d::UnitZ();
  switch (cls) {
    case dSphereClass: {
      const double r = dGeomSphereGetRadius(geom), d = q.norm();
      depth = r - d;
      n_local = d > 0 ? Eigen::Vector3d(q / d) : Eigen::Vector3d::UnitZ();
      break;
    }
    case dBoxClass: {
      dVector3 size;
      dGeomBoxGetLengths(geom, size);
      depth = INFINITY;
      for (int k = 0; k < 3; ++k) {
        const double d = 0.5 * size[k] - std::abs(q[k]);
        if (d < depth) {
          depth = d;
          n_local = (q[k] >= 0 ? 1.0 : -1.0) * Eigen::Vector3d::Unit(k);
        }
      }
      if (depth > 0 && !entry_n.isZero()) {
        // Inside: the face opposite the entry face never takes over (a point
        // pushed past the middle of a thin plate is still pushed back out the
        // way it came); a side face nearer than the entry face does (a point
        // that slid over an edge).
        Eigen::Index k;
        const Eigen::Vector3d e = R.transpose() * entry_n;
        e.cwiseAbs().maxCoeff(&k);
        const double sign = e[k] >= 0 ? 1.0 : -1.0;
        if (n_local.dot(sign * Eigen::Vector3d::Unit(k)) < -0.5) {
          n_local = sign * Eigen::Vector3d::Unit(k);
          depth = 0.5 * size[k] - sign * q[k];
        }
      }
      break;
    }
    case dCapsuleClass: {
      dReal r, len;
      dGeomCapsuleGetParams(geom, &r, &len);
      const Eigen::Vector3d axis_point(0, 0, std::clamp(q.z(), -0.5 * len, 0.5 * len));
      const double d = (q - axis_point).norm();
      depth = r - d;
      n_local = d > 0 ? Eigen::Vector3d((q - axis_point) / d) : Eigen::Vector3d::UnitX();
      break;
    }
    case dCylinderClass: {
      dReal r, len;
      dGeomCylinderGetParams(geom, &r, &len);
      const double rho = std::hypot(q.x(), q.y());
      const double side = r - rho, cap = 0.5 * len - std::abs(q.z());
      depth = std::min(side, cap);
      if (side < cap) {
        n_local = rho > 0 ? Eigen::Vector3d(q.x() / rho, q.y() / rho, 0) : Eigen::Vector3d::UnitX();
      } else {
        n_local = Eigen::Vector3d(0, 0, q.z() >= 0 ? 1.0 : -1.0);
      }
      break;
    }
    default:
      return false;  // meshes: RigidWorld::penetration uses their distance grid
  }
  n = R * n_local;
  return depth > -margin;
}

}  // namespace detail

RigidWorld::RigidWorld(const SceneDesc& scene, bool dynamics_for_hands) : dt_(scene.dt_s) {
  ensure_ode_for_this_thread();
  space_ = dHashSpaceCreate(nullptr);
  contacts_ = dJointGroupCreate(0);
  hand_joints_.reserve(kMaxHandContacts);
  hand_feedback_.reserve(kMaxHandContacts);
  // Static geometry alone is collision-only: the dynamics world exists only for rigid bodies.
  if (scene.needs_rigid_world() || dynamics_for_hands) {
    world_ = dWorldCreate();
    dWorldSetGravity(world_, scene.gravity_m_s2.x(), scene.gravity_m_s2.y(), scene.gravity_m_s2.z());
    dWorldSetERP(world_, kContactErp);
    dWorldSetCFM(world_, kContactCfm);
  }
  objects_.reserve(scene.objects.size());
  for (const ObjectDesc& o : scene.objects) {
    if (o.kind == BodyKind::deformable) continue;
    Object obj;
    obj.name = o.name;
    obj.friction = o.material.friction;
    obj.friction_static = o.material.static_friction();
    obj.restitution = o.material.restitution;
    const ShapeDesc& s = o.shape;
    switch (s.type) {
      case ShapeType::box:
        obj.geom = dCreateBox(space_, s.size.x(), s.size.y(), s.size.z());
        break;
      case ShapeType::sphere:
        obj.geom = dCreateSphere(space_, s.radius);
        break;
      case ShapeType::capsule:
        obj.geom = dCreateCapsule(space_, s.radius, s.length);
        break;
      case ShapeType::cylinder:
        obj.geom = dCreateCylinder(space_, s.radius, s.length);
        break;
      case ShapeType::plane:
        obj.geom = dCreatePlane(space_, s.normal.x(), s.normal.y(), s.normal.z(), s.offset);
        break;
      case ShapeType::mesh: {
        const hand::SurfaceMesh surface = hand::load_obj(s.file);
        for (const Eigen::Vector3d& v : surface.vertices)
          for (int k = 0; k < 3; ++k) obj.vertices.push_back(s.scale * v[k]);
        for (const hand::Triangle& t : surface.triangles)
          for (int k = 0; k < 3; ++k) obj.indices.push_back(static_cast<dTriIndex>(t[k]));
        obj.trimesh = dGeomTriMeshDataCreate();
        dGeomTriMeshDataBuildDouble(obj.trimesh, obj.vertices.data(), 3 * sizeof(double),
                                    static_cast<int>(surface.vertices.size()), obj.indices.data(),
                                    static_cast<int>(obj.indices.size()), 3 * sizeof(dTriIndex));
        obj.geom = dCreateTriMesh(space_, obj.trimesh, nullptr, nullptr, nullptr);
        hand::SurfaceMesh scaled = surface;
        for (Eigen::Vector3d& v : scaled.vertices) v *= s.scale;
        obj.sdf = MeshSdf(scaled, 0.003, 6);  // distances exact to 6 cells (1.8 cm, more for a mesh over 38 cm)
        obj.far_sdf = far_clearance_sdf(scaled);
        break;
      }
      case ShapeType::tet_mesh:
        throw std::runtime_error("object '" + o.name + "': a tet_mesh shape is deformable only");
    }
    dQuaternion q;
    to_ode(o.pose.q_W, q);
    if (o.kind == BodyKind::rigid) {
      obj.body = dBodyCreate(world_);
      dMass m;
      dMassSetZero(&m);
      set_mass(m, s, o.mass_kg, o.material.density_kg_m3, obj.geom);
      if (!(m.mass > 0) || !std::isfinite(m.mass))
        throw std::runtime_error("object '" + o.name + "': mass is not positive (is the mesh closed and outward?)");
      // The loader bounds given masses and primitives' masses; a mesh's comes from its volume only now.
      if (!(m.mass >= kMinMassKg && m.mass <= kMaxMassKg))
        throw std::runtime_error("object '" + o.name + "': mass " + std::to_string(m.mass) +
                                 " kg from the mesh's volume is "
                                 "outside [" +
                                 std::to_string(kMinMassKg) + ", " + std::to_string(kMaxMassKg) +
                                 "] kg: give mass_kg or change the scale or density");
      // dBodySetMass asserts this (an abort, not an exception): a mesh can give an inertia that is not positive
      // definite.
      if (!dMassCheck(&m))
        throw std::runtime_error("object '" + o.name + "': its inertia is not positive definite (is the mesh closed?)");
      // ODE wants the centre of mass at the body origin: shift the geometry instead.
      obj.com_O = Eigen::Vector3d(m.c[0], m.c[1], m.c[2]);
      dMassTranslate(&m, -m.c[0], -m.c[1], -m.c[2]);
      dBodySetMass(obj.body, &m);
      dGeomSetBody(obj.geom, obj.body);
      if (!obj.com_O.isZero()) dGeomSetOffsetPosition(obj.geom, -obj.com_O.x(), -obj.com_O.y(), -obj.com_O.z());
      const Eigen::Vector3d p_com = o.pose.p_W + o.pose.q_W * obj.com_O;
      dBodySetPosition(obj.body, p_com.x(), p_com.y(), p_com.z());
      dBodySetQuaternion(obj.body, q);
      dBodySetLinearVel(obj.body, o.linear_velocity.x(), o.linear_velocity.y(), o.linear_velocity.z());
      dBodySetAngularVel(obj.body, o.angular_velocity.x(), o.angular_velocity.y(), o.angular_velocity.z());
    } else if (s.type != ShapeType::plane) {
      dGeomSetPosition(obj.geom, o.pose.p_W.x(), o.pose.p_W.y(), o.pose.p_W.z());
      dGeomSetQuaternion(obj.geom, q);
    }
    dGeomSetData(obj.geom, reinterpret_cast<void*>(static_cast<std::intptr_t>(objects_.size())));
    objects_.push_back(std::move(obj));
  }
  for (const JointDesc& j : scene.joints) {
    auto body_of = [&](const std::string& n) -> dBodyID {
      const int i = find(n);
      return i >= 0 ? objects_[i].body : nullptr;
    };
    dJointID joint = nullptr;
    switch (j.type) {
      case JointType::hinge:
        joint = dJointCreateHinge(world_, nullptr);
        break;
      case JointType::ball:
        joint = dJointCreateBall(world_, nullptr);
        break;
      case JointType::fixed:
        joint = dJointCreateFixed(world_, nullptr);
        break;
      case JointType::slider:
        joint = dJointCreateSlider(world_, nullptr);
        break;
    }
    dBodyID a = body_of(j.body_a), b = j.body_b == "world" ? nullptr : body_of(j.body_b);
    if (a == nullptr) std::swap(a, b);  // ODE: a joint to the static environment has body 2 = 0
    dJointAttach(joint, a, b);
    const Eigen::Vector3d& p = j.anchor_W;
    const Eigen::Vector3d& ax = j.axis_W;
    switch (j.type) {
      case JointType::hinge:
        dJointSetHingeAnchor(joint, p.x(), p.y(), p.z());
        dJointSetHingeAxis(joint, ax.x(), ax.y(), ax.z());
        if (j.limited) {
          dJointSetHingeParam(joint, dParamLoStop, j.lo);
          dJointSetHingeParam(joint, dParamHiStop, j.hi);
        }
        break;
      case JointType::ball:
        dJointSetBallAnchor(joint, p.x(), p.y(), p.z());
        break;
      case JointType::fixed:
        dJointSetFixed(joint);
        break;
      case JointType::slider:
        dJointSetSliderAxis(joint, ax.x(), ax.y(), ax.z());
        if (j.limited) {
          dJointSetSliderParam(joint, dParamLoStop, j.lo);
          dJointSetSliderParam(joint, dParamHiStop, j.hi);
        }
        break;
    }
    joints_.push_back(joint);
  }
  // The scene's poses: the first good state of every body.
  for (int i = 0; i < num_objects(); ++i) last_good_.push_back(state(i));
}

RigidWorld::~RigidWorld() {
  ensure_ode_for_this_thread();
  for (dJointID j : joints_) dJointDestroy(j);
  dJointGroupDestroy(contacts_);
  for (Object& o : objects_) {
    dGeomDestroy(o.geom);
    if (o.trimesh) dGeomTriMeshDataDestroy(o.trimesh);
    if (o.body) dBodyDestroy(o.body);
  }
  dSpaceDestroy(space_);
  if (ray_) dGeomDestroy(ray_);
  if (world_) dWorldDestroy(world_);
}

bool RigidWorld::ray_hit(int i, const Eigen::Vector3d& from, const Eigen::Vector3d& to, Eigen::Vector3d& hit,
                         Eigen::Vector3d& n) const {
  const Eigen::Vector3d d = to - from;
  const double length = d.norm();
  if (!(length > 0) || !std::isfinite(length)) return false;
  if (!ray_) {
    ensure_ode_for_this_thread();
    ray_ = dCreateRay(nullptr, length);
    dGeomRaySetClosestHit(ray_, 1);
  }
  dGeomRaySetLength(ray_, length);
  dGeomRaySet(ray_, from.x(), from.y(), from.z(), d.x() / length, d.y() / length, d.z() / length);
  dContactGeom c;
  if (dCollide(ray_, objects_[i].geom, 1, &c, sizeof(dContactGeom)) < 1) return false;
  hit = from_ode(c.pos);
  n = from_ode(c.normal).normalized();
  if (n.dot(d) > 0) n = -n;  // out of the object, against the ray that entered it
  return hit.allFinite() && n.allFinite();
}

Eigen::Isometry3d RigidWorld::object_pose(int i) const {
  const RigidBodyState s = state(i);
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  T.linear() = s.q_WO.toRotationMatrix();
  T.translation() = s.p_WO;
  return T;
}

void RigidWorld::add_object_wrench(int i, const Eigen::Vector3d& f, const Eigen::Vector3d& torque) {
  dBodyID b = objects_[i].body;
  if (!b || !f.allFinite() || !torque.allFinite()) return;
  dBodyAddForce(b, f.x(), f.y(), f.z());
  dBodyAddTorque(b, torque.x(), torque.y(), torque.z());
}

int RigidWorld::find(const std::string& n) const {
  for (size_t i = 0; i < objects_.size(); ++i)
    if (objects_[i].name == n) return static_cast<int>(i);
  return -1;
}

int RigidWorld::object_of(dGeomID g) const {
  for (size_t i = 0; i < objects_.size(); ++i)
    if (objects_[i].geom == g) return static_cast<int>(i);
  return -1;
}

double RigidWorld::mass_kg(int i) const {
  if (!objects_[i].body) return INFINITY;
  dMass m;
  dBodyGetMass(objects_[i].body, &m);
  return m.mass;
}

RigidBodyState RigidWorld::state(int i) const {
  const Object& o = objects_[i];
  RigidBodyState s;
  if (o.body == nullptr) {
    if (dGeomGetClass(o.geom) != dPlaneClass) {
      s.p_WO = from_ode(dGeomGetPosition(o.geom));
      dQuaternion q;
      dGeomGetQuaternion(o.geom, q);
      s.q_WO = Eigen::Quaterniond(q[0], q[1], q[2], q[3]);
    }
    return s;
  }
  const dReal* q = dBodyGetQuaternion(o.body);
  s.q_WO = Eigen::Quaterniond(q[0], q[1], q[2], q[3]);
  s.p_WO = from_ode(dBodyGetPosition(o.body)) - s.q_WO * o.com_O;
  s.v_WO = from_ode(dBodyGetLinearVel(o.body));
  s.w_W = from_ode(dBodyGetAngularVel(o.body));
  return s;
}

void RigidWorld::set_state(int i, const RigidBodyState& s) {
  const Object& o = objects_[i];
  if (o.body == nullptr) return;
  const Eigen::Vector3d p = s.p_WO + s.q_WO * o.com_O;
  dQuaternion q;
  to_ode(s.q_WO.normalized(), q);
  dBodySetPosition(o.body, p.x(), p.y(), p.z());
  dBodySetQuaternion(o.body, q);
  dBodySetLinearVel(o.body, s.v_WO.x(), s.v_WO.y(), s.v_WO.z());
  dBodySetAngularVel(o.body, s.w_W.x(), s.w_W.y(), s.w_W.z());
}

Eigen::Vector3d RigidWorld::point_velocity(int i, const Eigen::Vector3d& p) const {
  if (objects_[i].body == nullptr) return Eigen::Vector3d::Zero();
  dVector3 v;
  dBodyGetPointVel(objects_[i].body, p.x(), p.y(), p.z(), v);
  return from_ode(v);
}

bool RigidWorld::far_clearance(int i, const Eigen::Vector3d& p, double& gap, Eigen::Vector3d& n) const {
  const Object& o = objects_[i];
  if (o.far_sdf.empty()) return false;  // not a mesh (a plane has no rotation)
  const Eigen::Matrix3d R = geom_rotation(o.geom);
  Eigen::Vector3d n_local;
  if (!clearance(o.sdf, o.far_sdf, R.transpose() * (p - geom_position(o.geom)), gap, n_local)) return false;
  n = R * n_local;
  return true;
}

bool RigidWorld::penetration(int i, const Eigen::Vector3d& p, double& depth, Eigen::Vector3d& n,
                             const Eigen::Vector3d& entry_n, double margin) const {
  const Object& o = objects_[i];
  if (o.sdf.empty()) return detail::point_penetration(o.geom, p, depth, n, entry_n, margin);
  // Into the geom's frame (the mesh's own coordinates).
  const dReal* gp = dGeomGetPosition(o.geom);
  dQuaternion q;
  dGeomGetQuaternion(o.geom, q);
  const Eigen::Quaterniond R(q[0], q[1], q[2], q[3]);
  double distance;
  Eigen::Vector3d n_local;
  if (!o.sdf.query(R.conjugate() * (p - from_ode(gp)), distance, n_local) || distance >= margin) return false;
  depth = -distance;
  n = R * n_local;
  return true;
}

hand::ContactBody RigidWorld::contact_body(int i) const {
  hand::ContactBody b;
  dBodyID body = objects_[i].body;
  dMass m;
  dBodyGetMass(body, &m);
  b.mass_kg = m.mass;
  Eigen::Matrix3d I_B;
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c) I_B(r, c) = m.I[4 * r + c];  // ODE's dMatrix3 rows are padded to 4
  const dReal* q = dBodyGetQuaternion(body);
  const Eigen::Matrix3d R = Eigen::Quaterniond(q[0], q[1], q[2], q[3]).toRotationMatrix();
  b.inertia_W = R * I_B * R.transpose();
  b.p_com_W = from_ode(dBodyGetPosition(body));
  b.v_W = from_ode(dBodyGetLinearVel(body));
  b.w_W = from_ode(dBodyGetAngularVel(body));
  dVector3 g;
  dWorldGetGravity(world_, g);
  b.gravity_W = dBodyGetGravityMode(body) ? from_ode(g) : Eigen::Vector3d::Zero();
  return b;
}

void RigidWorld::add_velocity(int i, const Eigen::Vector3d& dv_W, const Eigen::Vector3d& dw_W) {
  dBodyID body = objects_[i].body;
  if (!body || !dv_W.allFinite() || !dw_W.allFinite()) return;
  const Eigen::Vector3d v = from_ode(dBodyGetLinearVel(body)) + dv_W, w = from_ode(dBodyGetAngularVel(body)) + dw_W;
  dBodySetLinearVel(body, v.x(), v.y(), v.z());
  dBodySetAngularVel(body, w.x(), w.y(), w.z());
}

void RigidWorld::hold_gravity_for_next_step(int i) {
  if (objects_[i].body) objects_[i].gravity_held = true;
}

void RigidWorld::contacts_of(int i, std::vector<BodyContact>& out) const {
  out.clear();
  struct Query {
    const RigidWorld* world;
    dGeomID self;
    std::vector<BodyContact>* out;
  } query{this, objects_[i].geom, &out};
  auto callback = [](void* data, dGeomID a, dGeomID b) {
    const Query& q = *static_cast<Query*>(data);
    const dGeomID other = a == q.self ? b : a;
    if (other == q.self) return;
    dContactGeom contacts[kMaxContactsPerPair];
    // Geom order (self, other): ODE's normal then points out of the other into self.
    const int n = collide_spread(q.self, other, contacts);
    const int j = q.world->object_of(other);
    if (j < 0) return;
    const Object& oa = q.world->objects_[q.world->object_of(q.self)];
    const Object& ob = q.world->objects_[j];
    for (int k = 0; k < n; ++k)
      q.out->push_back({j, from_ode(contacts[k].pos), from_ode(contacts[k].normal), contacts[k].depth,
                        std::sqrt(oa.friction * ob.friction)});
  };
  dSpaceCollide2(objects_[i].geom, reinterpret_cast<dGeomID>(space_), &query, callback);
}

bool RigidWorld::support_points(int i, std::vector<Eigen::Vector3d>& points_W) const {
  const Object& o = objects_[i];
  points_W.clear();
  const bool box = dGeomGetClass(o.geom) == dBoxClass;
  if (o.vertices.empty() && !box) return false;
  const Eigen::Vector3d origin = from_ode(dGeomGetPosition(o.geom));
  dQuaternion q;
  dGeomGetQuaternion(o.geom, q);
  const Eigen::Quaterniond R(q[0], q[1], q[2], q[3]);
  if (box) {
    dVector3 size;
    dGeomBoxGetLengths(o.geom, size);
    for (int c = 0; c < 8; ++c)
      points_W.push_back(origin + R * Eigen::Vector3d((c & 1 ? 0.5 : -0.5) * size[0], (c & 2 ? 0.5 : -0.5) * size[1],
                                                      (c & 4 ? 0.5 : -0.5) * size[2]));
    return true;
  }
  for (size_t v = 0; 3 * v + 2 < o.vertices.size(); ++v)
    points_W.push_back(origin + R * Eigen::Vector3d(o.vertices[3 * v], o.vertices[3 * v + 1], o.vertices[3 * v + 2]));
  return true;
}

void RigidWorld::supports_of(int i, std::vector<BodyContact>& out, double margin_m) {
  std::vector<Eigen::Vector3d> points;
  if (support_points(i, points)) {
    // On static geometry, the body's own vertices measured against it, gaps within the margin too;
    // on other bodies, ODE's contacts.
    contacts_of(i, out);
    out.erase(std::remove_if(out.begin(), out.end(), [&](const BodyContact& c) { return !is_dynamic(c.other); }),
              out.end());
    dReal aabb[6];
    dGeomGetAABB(objects_[i].geom, aabb);
    const Eigen::AlignedBox3d reach(Eigen::Vector3d(aabb[0], aabb[2], aabb[4]) - Eigen::Vector3d::Constant(margin_m),
                                    Eigen::Vector3d(aabb[1], aabb[3], aabb[5]) + Eigen::Vector3d::Constant(margin_m));
    std::vector<BodyContact> near;
    for (int j = 0; j < num_objects(); ++j) {
      if (j == i || is_dynamic(j)) continue;
      if (dGeomGetClass(objects_[j].geom) != dPlaneClass) {
        dReal other[6];
        dGeomGetAABB(objects_[j].geom, other);
        if (!reach.intersects(Eigen::AlignedBox3d(Eigen::Vector3d(other[0], other[2], other[4]),
                                                  Eigen::Vector3d(other[1], other[3], other[5]))))
          continue;
      }
      near.clear();
      const double mu = std::sqrt(objects_[i].friction * objects_[j].friction);
      for (const Eigen::Vector3d& p : points) {
        double depth;
        Eigen::Vector3d n;
        if (penetration(j, p, depth, n, Eigen::Vector3d::Zero(), margin_m) && depth > -margin_m)
          near.push_back({j, p, n, depth, mu});
      }
      int kept[kMaxSupportsPerPair];
      const int count = spread_contacts(
          static_cast<int>(near.size()), [&](int k) { return near[k].p_W; }, [&](int k) { return near[k].depth_m; },
          kept);
      for (int k = 0; k < count; ++k) out.push_back(near[kept[k]]);
    }
    return;
  }
  contacts_of(i, out);
  remembered_.resize(objects_.size());
  Memory& memory = remembered_[i];
  const RigidBodyState pose = state(i);
  if (!out.empty()) {
    memory.step = steps_;
    memory.supports.clear();
    for (const BodyContact& c : out)
      if (!is_dynamic(c.other)) memory.supports.push_back({c, pose.q_WO.conjugate() * (c.p_W - pose.p_WO)});
    return;
  }
  if (steps_ - memory.step > kSupportMemorySteps) return;  // too old: the body may have gone off an edge
  for (const RememberedSupport& r : memory.supports) {
    BodyContact c = r.contact;
    const Eigen::Vector3d p_W = pose.p_WO + pose.q_WO * r.p_O;
    c.depth_m -= c.n_W.dot(p_W - c.p_W);  // the normal points into the body: lifting opens a gap
    c.p_W = p_W;
    if (c.depth_m > -margin_m) out.push_back(c);
  }
}

void RigidWorld::near_callback(void* data, dGeomID a, dGeomID b) { static_cast<RigidWorld*>(data)->collide(a, b); }

void RigidWorld::add_hand(hand::OdeHand* hand, int id) {
  const auto index = static_cast<std::intptr_t>(hands_.size());
  for (int i = 0; i < hand->num_geoms(); ++i) dGeomSetData(hand->geom(i), reinterpret_cast<void*>(-1 - index));
  hands_.push_back(hand);
  hand_ids_.push_back(id);
}

void RigidWorld::hand_contacts(std::vector<HandContact>& out) const {
  out.clear();
  for (size_t k = 0; k < hand_joints_.size(); ++k) {  // hand_feedback_[k] is joint k's
    HandContact c = hand_joints_[k].contact;
    c.f_W = hand_joints_[k].hand_first ? from_ode(hand_feedback_[k].f1) : from_ode(hand_feedback_[k].f2);
    out.push_back(c);
  }
  std::vector<hand::OdeHand::OwnContact> own;
  for (size_t h = 0; h < hands_.size(); ++h) {
    own.clear();
    hands_[h]->own_contacts(own);
    for (const hand::OdeHand::OwnContact& o : own) {
      HandContact c;
      static_cast<hand::OdeHand::OwnContact&>(c) = o;
      c.hand = hand_ids_[h];
      out.push_back(c);
    }
  }
}

dContact RigidWorld::friction_contact(const dContactGeom& geom, dBodyID b1, dBodyID b2, double mu_sliding,
                                      double mu_sticking) {
  dContact c{};
  c.geom = geom;
  const Eigen::Vector3d p = from_ode(c.geom.pos), normal = from_ode(c.geom.normal);
  // Relative sliding velocity at the contact decides static vs kinetic friction
  // and aligns the first friction direction with it (ODE's friction pyramid is
  // then exact along the slide).
  Eigen::Vector3d v_rel = Eigen::Vector3d::Zero();
  dVector3 v;
  if (b1) dBodyGetPointVel(b1, p.x(), p.y(), p.z(), v), v_rel += from_ode(v);
  if (b2) dBodyGetPointVel(b2, p.x(), p.y(), p.z(), v), v_rel -= from_ode(v);
  const Eigen::Vector3d v_t = v_rel - v_rel.dot(normal) * normal;
  const bool sliding = v_t.norm() > kStickSpeed_m_s;
  c.surface.mode = dContactApprox1 | dContactSoftERP | dContactSoftCFM | dContactMu2;
  c.surface.mu = c.surface.mu2 = sliding ? mu_sliding : mu_sticking;
  c.surface.soft_erp = kContactErp;
  c.surface.soft_cfm = kContactCfm;
  if (sliding) {
    c.surface.mode |= dContactFDir1;
    const Eigen::Vector3d dir = v_t.normalized();
    c.fdir1[0] = dir.x(), c.fdir1[1] = dir.y(), c.fdir1[2] = dir.z();
  }
  return c;
}

void RigidWorld::collide(dGeomID a, dGeomID b) {
  dBodyID ba = dGeomGetBody(a), bb = dGeomGetBody(b);
  if (ba == nullptr && bb == nullptr) return;
  if (ba && bb && dAreConnectedExcluding(ba, bb, dJointTypeContact)) return;
  const auto ia = reinterpret_cast<std::intptr_t>(dGeomGetData(a)),
             ib = reinterpret_cast<std::intptr_t>(dGeomGetData(b));
  if (ia < 0 && ib < 0) return;  // two hands' geoms: hand-hand contact is not built for rigid hands
  if (ia < 0 || ib < 0) return collide_hand(ia < 0 ? a : b, ia < 0 ? b : a, ia < 0);
  dContactGeom contacts[kMaxContactsPerPair];
  const int n = dCollide(a, b, kMaxContactsPerPair, contacts, sizeof(dContactGeom));
  if (n <= 0) return;
  const Object& oa = objects_[ia];
  const Object& ob = objects_[ib];
  for (int k = 0; k < n; ++k) {
    dContact c = friction_contact(contacts[k], ba, bb, std::sqrt(oa.friction * ob.friction),
                                  std::sqrt(oa.friction_static * ob.friction_static));
    const double e = std::max(oa.restitution, ob.restitution);
    if (e > 0) {
      c.surface.mode |= dContactBounce;
      c.surface.bounce = e;
      c.surface.bounce_vel = 0.05;
    }
    dJointAttach(dJointCreateContact(world_, contacts_, &c), ba, bb);
    ++contacts_last_step_;
  }
}

void RigidWorld::collide_hand(dGeomID hand_geom, dGeomID object_geom, bool hand_first) {
  dContactGeom contacts[kMaxContactsPerPair];
  dGeomID first = hand_first ? hand_geom : object_geom, second = hand_first ? object_geom : hand_geom;
  const int n = dCollide(first, second, kMaxContactsPerPair, contacts, sizeof(dContactGeom));
  if (n <= 0) return;
  const int h = static_cast<int>(-1 - reinterpret_cast<std::intptr_t>(dGeomGetData(hand_geom)));
  const int g = static_cast<int>(reinterpret_cast<std::intptr_t>(dGeomGetData(object_geom)));
  const hand::OdeHand& hand = *hands_[h];
  const Object& o = objects_[g];
  int geom = 0;
  while (geom < hand.num_geoms() && hand.geom(geom) != hand_geom) ++geom;
  dBodyID b_first = dGeomGetBody(first), b_second = dGeomGetBody(second);
  for (int k = 0; k < n; ++k) {
    // No bounce off a hand (seed 002 section 4.6.2).
    const dContact c = friction_contact(contacts[k], b_first, b_second, std::sqrt(hand.friction() * o.friction),
                                        std::sqrt(hand.friction_static() * o.friction_static));
    const Eigen::Vector3d p = from_ode(c.geom.pos), normal = from_ode(c.geom.normal);
    dJointID j = dJointCreateContact(world_, contacts_, &c);
    dJointAttach(j, b_first, b_second);
    ++contacts_last_step_;
    if (static_cast<int>(hand_joints_.size()) >= kMaxHandContacts) continue;
    HandJoint hj;
    hj.hand_first = hand_first;
    hj.contact.hand = hand_ids_[h];
    hj.contact.handle = geom < hand.num_geoms() ? hand.geom_handle(geom) : -1;
    hj.contact.geom = geom < hand.num_geoms() ? geom : -1;
    hj.contact.object = g;
    hj.contact.p_W = p;
    // ODE's normal points from the second geom into the first: out of the object toward the hand.
    hj.contact.n_W = hand_first ? normal : Eigen::Vector3d(-normal);
    hj.contact.depth_m = c.geom.depth;
    hj.contact.mu = c.surface.mu;
    hand_joints_.push_back(hj);
    hand_feedback_.emplace_back();
    dJointSetFeedback(j, &hand_feedback_.back());
  }
}

bool RigidWorld::within_bounds(const RigidBodyState& s) const {
  const bool finite = s.p_WO.allFinite() && s.q_WO.coeffs().allFinite() && s.v_WO.allFinite() && s.w_W.allFinite();
  return finite && s.p_WO.norm() <= bounds_.max_distance_m && s.v_WO.norm() <= bounds_.max_speed_m_s &&
         s.w_W.norm() <= bounds_.max_angular_speed_rad_s && std::abs(s.q_WO.norm() - 1.0) < 1e-3;
}

void RigidWorld::check_bodies() {
  for (size_t i = 0; i < objects_.size(); ++i) {
    if (!objects_[i].body) continue;
    const int k = static_cast<int>(i);
    const RigidBodyState s = state(k);
    if (within_bounds(s)) {
      last_good_[i] = s;
      continue;
    }
    RigidBodyState rest = last_good_[i];
    rest.v_WO.setZero(), rest.w_W.setZero();
    set_state(k, rest);
    ++resets_;
  }
}

void RigidWorld::step(double dt) {
  if (world_ == nullptr) return;
  ensure_ode_for_this_thread();
  ++steps_;
  check_bodies();  // states set from outside since the last step
  int bodies = 0;
  for (const Object& o : objects_) bodies += o.body != nullptr;
  int n = substeps(dt);
  for (const hand::OdeHand* hand : hands_) {
    const double h_max = hand->max_ode_step_s();
    if (h_max > 0 && std::isfinite(h_max)) n = std::max(n, static_cast<int>(std::ceil(dt / h_max - 1e-9)));
  }
  for (int k = 0; k < n; ++k) {
    if (k == 1)
      for (const Object& o : objects_)
        if (o.gravity_held) dBodySetGravityMode(o.body, 0);
    contacts_last_step_ = 0;  // the last substep's
    hand_joints_.clear();
    hand_feedback_.clear();
    for (hand::OdeHand* hand : hands_) hand->before_ode_step(dt / n, *this);
    dSpaceCollide(space_, this, &RigidWorld::near_callback);
    if (bodies <= kExactStepMaxBodies) {
      dWorldStep(world_, dt / n);
    } else {
      dWorldQuickStep(world_, dt / n);
    }
    dJointGroupEmpty(contacts_);  // the hands' contact forces stay in hand_feedback_
  }
  for (Object& o : objects_)
    if (o.gravity_held) dBodySetGravityMode(o.body, 1), o.gravity_held = false;
  check_bodies();  // divergence in the step
  for (hand::OdeHand* hand : hands_) hand->after_ode_steps();
}

}  // namespace hapticd::world
