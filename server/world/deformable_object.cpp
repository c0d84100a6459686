#include "server/world/deformable_object.hpp"

#include <Eigen/SVD>
#include <algorithm>
#include <cmath>
#include <map>
#include <stdexcept>

#include "hand_models/box_mesh.hpp"
#include "hand_models/mesh_io.hpp"

namespace hapticd::world {
namespace {

// A deformable box is meshed with about this many cubic cells (6 tets each):
// ~300 tets, the size of the seed's bunny mesh.
constexpr double kBoxCells = 50;

// Collision samples a body's surface at its vertices: a rigid edge would sink
// between boundary nodes a cell apart, so a mesh's own boundary is subdivided
// until its vertices lie at most this far apart.
constexpr double kSurfaceSpacing_m = 0.005;

// The mesh's boundary faces as the body's surface, each split into s^2
// triangles (s the same for every face, so neighbours share their edge points),
// every vertex embedded in the tet that holds its face.
hand::EmbeddedBody boundary_body(hand::TetMesh mesh) {
  std::map<std::array<int, 3>, int> face_tet;
  for (int e = 0; e < mesh.num_tets(); ++e)
    for (int skip = 0; skip < 4; ++skip) {
      std::array<int, 3> key;
      for (int k = 0, n = 0; k < 4; ++k)
        if (k != skip) key[n++] = mesh.tets[e][k];
      std::sort(key.begin(), key.end());
      face_tet[key] = e;  // a boundary face has one tet
    }
  double longest = 0;
  for (const hand::Triangle& t : mesh.surface)
    for (int k = 0; k < 3; ++k) longest = std::max(longest, (mesh.X[t[k]] - mesh.X[t[(k + 1) % 3]]).norm());
  const int s = std::clamp(static_cast<int>(std::ceil(longest / kSurfaceSpacing_m)), 1, 16);
  hand::EmbeddedBody body;
  // A point's identity: a node, a point on an edge (its end nodes, ordered, and
  // the step from the first), or a point inside a face.
  std::map<std::array<int, 4>, int> vertex_of;
  for (size_t f = 0; f < mesh.surface.size(); ++f) {
    const hand::Triangle& tri = mesh.surface[f];
    std::array<int, 3> key = tri;
    std::sort(key.begin(), key.end());
    const int e = face_tet.at(key);
    const hand::Tet& tet = mesh.tets[e];
    int local[3];
    for (int k = 0; k < 3; ++k) local[k] = static_cast<int>(std::find(tet.begin(), tet.end(), tri[k]) - tet.begin());
    // Grid point (i, j) has weights ((s - i - j) / s, i / s, j / s) on the face's nodes.
    auto vertex = [&](int i, int j) {
      const int w[3] = {s - i - j, i, j};
      std::array<int, 4> id;
      int nonzero = 0, first = -1, second = -1;
      for (int k = 0; k < 3; ++k)
        if (w[k] > 0) ++nonzero, (first < 0 ? first : second) = k;
      if (nonzero == 1) {
        id = {tri[first], -1, -1, -1};
      } else if (nonzero == 2) {
        const int a = std::min(tri[first], tri[second]), b = std::max(tri[first], tri[second]);
        id = {a, b, w[tri[first] == a ? first : second], -2};
      } else {
        id = {static_cast<int>(f), i, j, -3};
      }
      const auto [it, fresh] = vertex_of.try_emplace(id, static_cast<int>(body.surface.vertices.size()));
      if (fresh) {
        Eigen::Vector4d bary = Eigen::Vector4d::Zero();
        Eigen::Vector3d p = Eigen::Vector3d::Zero();
        for (int k = 0; k < 3; ++k) {
          bary[local[k]] = static_cast<double>(w[k]) / s;
          p += bary[local[k]] * mesh.X[tri[k]];
        }
        body.surface.vertices.push_back(p);
        body.surface_tet.push_back(e);
        body.surface_bary.push_back(bary);
      }
      return it->second;
    };
    for (int j = 0; j < s; ++j)
      for (int i = 0; i + j < s; ++i) {
        body.surface.triangles.push_back({vertex(i, j), vertex(i + 1, j), vertex(i, j + 1)});
        if (i + j + 2 <= s)
          body.surface.triangles.push_back({vertex(i + 1, j), vertex(i + 1, j + 1), vertex(i, j + 1)});
      }
  }
  body.mesh = std::move(mesh);
  return body;
}

hand::EmbeddedBody load_body(const ShapeDesc& s) {
  if (s.type == ShapeType::box) {
    const Eigen::Vector3d& size = s.size;
    return boundary_body(hand::make_box_mesh(size, detail::deformable_box_cells(size), -0.5 * size));
  }
  hand::TetMesh mesh = hand::load_tet_mesh(s.file);
  for (Eigen::Vector3d& X : mesh.X) X *= s.scale;
  if (s.surface_file.empty()) return boundary_body(std::move(mesh));
  hand::SurfaceMesh surface = hand::load_obj(s.surface_file);
  for (Eigen::Vector3d& v : surface.vertices) v *= s.scale;
  // Uniform scaling keeps every barycentric weight.
  return load_embedding(s.embedding_file, std::move(mesh), std::move(surface));
}

}  // namespace

namespace detail {

std::array<int, 3> deformable_box_cells(const Eigen::Vector3d& size) {
  const double h = std::cbrt(size.prod() / kBoxCells);
  std::array<int, 3> cells;
  for (int a = 0; a < 3; ++a) cells[a] = std::clamp(static_cast<int>(std::lround(size[a] / h)), 1, 32);
  return cells;
}

hand::Flesh flesh_of(DeformableObject& object) {
  hand::Flesh f;
  f.model = object.model.get();
  f.state = &object.state;
  f.point_tet = &object.body.surface_tet;
  f.point_bary = &object.body.surface_bary;
  f.rest_surface_vertices = &object.body.surface.vertices;
  f.surface_triangles = &object.body.surface.triangles;
  f.friction = object.friction;
  return f;
}

Eigen::Vector3d surface_point(const DeformableObject& o, int v) {
  const hand::Tet& t = o.body.mesh.tets[o.body.surface_tet[v]];
  Eigen::Vector3d p = Eigen::Vector3d::Zero();
  for (int k = 0; k < 4; ++k) p += o.body.surface_bary[v][k] * o.state.x.segment<3>(3 * t[k]);
  return p;
}

hand::ContactBody rigid_proxy(const DeformableObject& o) {
  const Eigen::VectorXd& m = o.model->fem().lumped_mass();
  const int n = o.model->num_nodes();
  hand::ContactBody b;
  b.mass_kg = m.sum();
  b.p_com_W.setZero();
  Eigen::Vector3d momentum = Eigen::Vector3d::Zero();
  for (int i = 0; i < n; ++i)
    b.p_com_W += m[i] * o.state.x.segment<3>(3 * i), momentum += m[i] * o.state.v.segment<3>(3 * i);
  b.p_com_W /= b.mass_kg;
  b.v_W = momentum / b.mass_kg;
  b.inertia_W.setZero();
  Eigen::Vector3d angular_momentum = Eigen::Vector3d::Zero();
  for (int i = 0; i < n; ++i) {
    const Eigen::Vector3d r = o.state.x.segment<3>(3 * i) - b.p_com_W;
    b.inertia_W += m[i] * (r.squaredNorm() * Eigen::Matrix3d::Identity() - r * r.transpose());
    angular_momentum += m[i] * r.cross(Eigen::Vector3d(o.state.v.segment<3>(3 * i)));
  }
  b.w_W = b.inertia_W.ldlt().solve(angular_momentum);
  return b;
}

DeformableObject::RigidFit rigid_fit(const DeformableObject& o) {
  const Eigen::VectorXd& m = o.model->fem().lumped_mass();
  const std::vector<Eigen::Vector3d>& X = o.body.mesh.X;
  const int n = o.model->num_nodes();
  Eigen::Vector3d C = Eigen::Vector3d::Zero(), c = Eigen::Vector3d::Zero();
  for (int i = 0; i < n; ++i) C += m[i] * X[i], c += m[i] * o.state.x.segment<3>(3 * i);
  C /= m.sum();
  c /= m.sum();
  Eigen::Matrix3d A = Eigen::Matrix3d::Zero();
  for (int i = 0; i < n; ++i) A += m[i] * (o.state.x.segment<3>(3 * i) - c) * (X[i] - C).transpose();
  DeformableObject::RigidFit fit;
  fit.deviation_m = INFINITY;
  if (!A.allFinite()) return fit;
  const Eigen::JacobiSVD<Eigen::Matrix3d> svd(A, Eigen::ComputeFullU | Eigen::ComputeFullV);
  Eigen::Matrix3d D = Eigen::Matrix3d::Identity();
  D(2, 2) = (svd.matrixU() * svd.matrixV().transpose()).determinant() < 0 ? -1 : 1;
  fit.R = svd.matrixU() * D * svd.matrixV().transpose();
  fit.t = c - fit.R * C;
  double deviation = 0;
  for (int i = 0; i < n; ++i)
    deviation = std::max(deviation, (o.state.x.segment<3>(3 * i) - fit.R * X[i] - fit.t).norm());
  fit.deviation_m = deviation;
  return fit;
}

bool far_clearance(const DeformableObject& o, const Eigen::Vector3d& p, double& gap, Eigen::Vector3d& n) {
  if (!o.query || !std::isfinite(o.fit.deviation_m)) return false;
  Eigen::Vector3d n_rest;
  if (!clearance(o.query->rest_sdf(), o.far_sdf, o.fit.R.transpose() * (p - o.fit.t), gap, n_rest)) return false;
  gap -= o.fit.deviation_m;
  n = o.fit.R * n_rest;
  return gap > 0;
}

}  // namespace detail

std::unique_ptr<DeformableObject> make_deformable_object(const ObjectDesc& desc, const DeformableBuild& build) {
  auto o = std::make_unique<DeformableObject>();
  o->name = desc.name;
  o->friction = desc.material.friction;
  try {
    o->body = load_body(desc.shape);
  } catch (const std::exception& e) {
    throw std::runtime_error("object '" + desc.name + "': " + e.what());
  }
  // The rest shape is the initial pose (the FEM is blind to where its rest shape sits).
  const Eigen::Quaterniond q = desc.pose.q_W.normalized();
  for (Eigen::Vector3d& X : o->body.mesh.X) X = desc.pose.p_W + q * X;
  for (Eigen::Vector3d& v : o->body.surface.vertices) v = desc.pose.p_W + q * v;

  // An embedded surface's mesh overhangs it: the body's mass is the surface's
  // volume times the density (or mass_kg), spread over the mesh's volume.
  const double mesh_volume = total_volume(o->body.mesh);
  const bool embedded = !desc.shape.surface_file.empty();
  const double solid_volume = embedded ? enclosed_volume(o->body.surface) : mesh_volume;
  const double mass_kg = desc.mass_kg > 0 ? desc.mass_kg : desc.material.density_kg_m3 * solid_volume;
  if (!(mass_kg > 0) || !std::isfinite(mass_kg))
    throw std::runtime_error("object '" + desc.name + "': mass is not positive (is the surface closed and outward?)");
  // The loader bounds given masses and boxes' masses; a tet mesh's comes from its volume only now.
  if (!(mass_kg >= kMinMassKg && mass_kg <= kMaxMassKg))
    throw std::runtime_error("object '" + desc.name + "': mass " + std::to_string(mass_kg) +
                             " kg from its volume is outside [" + std::to_string(kMinMassKg) + ", " +
                             std::to_string(kMaxMassKg) + "] kg: give mass_kg or change the scale or density");
  hand::HandConfig config;
  config.free_body = true;
  config.dt_s = build.dt_s;
  config.gravity_m_s2 = build.gravity_m_s2;
  config.material.youngs_modulus_pa = desc.material.youngs_modulus_pa;
  config.material.poisson_ratio = desc.material.poisson_ratio;
  config.material.density_kg_m3 = mass_kg / mesh_volume;
  config.material.rayleigh_alpha_per_s = desc.material.rayleigh_alpha_per_s;
  config.material.rayleigh_beta_s = desc.material.rayleigh_beta_s;
  try {
    o->model = std::make_unique<hand::HandModel>(o->body.mesh, config);
  } catch (const std::exception& e) {
    throw std::runtime_error("object '" + desc.name + "': " + e.what());
  }
  o->state = make_rest_state(*o->model);
  o->f_hands_W = Eigen::VectorXd::Zero(3 * o->model->num_nodes());
  // Initial velocity: a rigid motion about the centre of mass.
  const Eigen::VectorXd& m = o->model->fem().lumped_mass();
  Eigen::Vector3d com = Eigen::Vector3d::Zero();
  for (int i = 0; i < o->model->num_nodes(); ++i) com += m[i] * o->state.x.segment<3>(3 * i);
  com /= m.sum();
  for (int i = 0; i < o->model->num_nodes(); ++i)
    o->state.v.segment<3>(3 * i) =
        desc.linear_velocity + desc.angular_velocity.cross(Eigen::Vector3d(o->state.x.segment<3>(3 * i)) - com);
  o->solver = make_solver(build.solver);
  if (build.touched_by_hands) {
    // Distances exact within 6 cells (up to 1.8 cm) of the surface, 3 mm cells
    // as for rigid meshes, finer for small objects.
    const Eigen::AlignedBox3d box = [&] {
      Eigen::AlignedBox3d b;
      for (const Eigen::Vector3d& v : o->body.surface.vertices) b.extend(v);
      return b;
    }();
    const double cell = std::clamp(box.sizes().maxCoeff() / 40, 0.001, 0.003);
    o->query = std::make_unique<DeformedMeshQuery>(o->body.mesh, o->body.surface, cell, 6);
    o->query->update(o->state.x);
    o->far_sdf = far_clearance_sdf(o->body.surface);
    o->fit = detail::rigid_fit(*o);
  }
  return o;
}

}  // namespace hapticd::world
