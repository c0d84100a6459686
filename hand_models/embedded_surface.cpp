#include "hand_models/embedded_surface.hpp"

#include <Eigen/Geometry>
#include <Eigen/LU>

#include <algorithm>
#include <array>
#include <cerrno>
#include <charconv>
#include <climits>
#include <cmath>
#include <fstream>
#include <limits>
#include <stdexcept>
#include <string_view>
#include <system_error>
#include <utility>

#include "hand_models/box_mesh.hpp"
#include "hand_models/cell_grid.hpp"
#include "hand_models/mesh_io.hpp"
#include "hand_models/text_reader.hpp"

namespace hapticd::hand {
namespace {

using Eigen::Vector3d;
using Eigen::Vector3i;
using detail::CellGrid;

constexpr double kPi = 3.14159265358979323846;
// Cells are tested slightly enlarged so a surface lying on a grid plane touches the cells on both sides.
constexpr double kCellSlack = 1e-9;
constexpr long long kMaxCells = 1LL << 21;  // grid cells (kept or not): up to 12M tets, several GB to finalize
constexpr double kWeightTolerance = 1e-9;

std::string str(long long v) { return std::to_string(v); }
std::string str(int v) { return std::to_string(v); }
std::string str(std::size_t v) { return std::to_string(v); }

std::string str(double v) {
  char buf[32];
  const auto res = std::to_chars(buf, buf + sizeof buf, v);
  return std::string(buf, res.ptr);
}

std::string str(const Vector3d& p) { return "(" + str(p.x()) + ", " + str(p.y()) + ", " + str(p.z()) + ")"; }

using detail::fail_at;
using detail::parse_int;
using detail::parse_real;
using detail::quote;
using detail::TextReader;

std::ofstream open_for_writing(const std::string& path) {
  errno = 0;
  std::ofstream out(path, std::ios::binary | std::ios::trunc);
  if (!out) {
    const std::string why = errno ? std::error_code(errno, std::generic_category()).message() : "unknown error";
    fail_at(path, 0, "cannot write file: " + why);
  }
  return out;
}

void finish_writing(std::ofstream& out, const std::string& path) {
  out.flush();
  if (!out) fail_at(path, 0, "cannot write file: output error");
}

void check_surface(const SurfaceMesh& s) {
  if (s.triangles.empty()) throw MeshError("surface has no triangles");
  const int n = static_cast<int>(s.vertices.size());
  for (int i = 0; i < n; ++i) {
    if (!s.vertices[i].allFinite()) throw MeshError("surface vertex " + str(i) + " has a non-finite coordinate");
  }
  for (std::size_t t = 0; t < s.triangles.size(); ++t) {
    const Triangle& tri = s.triangles[t];
    for (int k = 0; k < 3; ++k) {
      if (tri[k] < 0 || tri[k] >= n) {
        throw MeshError("surface triangle " + str(t) + " references vertex " + str(tri[k]) +
                        ", outside [0, " + str(n - 1) + "]");
      }
    }
    if (tri[0] == tri[1] || tri[1] == tri[2] || tri[0] == tri[2])
      throw MeshError("surface triangle " + str(t) + " repeats a vertex");
  }
}

std::pair<Vector3d, Vector3d> bounding_box(const SurfaceMesh& s) {
  Vector3d lo = Vector3d::Constant(std::numeric_limits<double>::infinity());
  Vector3d hi = -lo;
  for (const Triangle& t : s.triangles) {
    for (int v : t) {
      lo = lo.cwiseMin(s.vertices[v]);
      hi = hi.cwiseMax(s.vertices[v]);
    }
  }
  return {lo, hi};
}

// The box's low corner sits a fixed, uneven fraction of a cell inside the grid (grid_shift).
CellGrid make_grid(const std::pair<Vector3d, Vector3d>& box, double h) {
  const Vector3d offset = detail::grid_shift(h);
  const Vector3d extent = box.second - box.first + offset;
  CellGrid g;
  g.h = h;
  long long cells = 1;
  for (int a = 0; a < 3; ++a) {
    const double n = std::floor(extent[a] / h) + 1.0;
    if (!(n <= static_cast<double>(kMaxCells))) cells = kMaxCells + 1;
    else cells *= static_cast<long long>(n);
    if (cells > kMaxCells) {
      throw std::invalid_argument("embedded surface: spacing " + str(h) + " m needs more than " + str(kMaxCells) +
                                  " grid cells");
    }
    g.n[a] = static_cast<int>(n);
  }
  g.origin = box.first - offset;
  return g;
}

// Separating-axis test of a triangle (vertices relative to the box centre) against the closed cube [-r, r]^3.
bool triangle_touches_cube(const Vector3d& v0, const Vector3d& v1, const Vector3d& v2, double r) {
  auto separated = [&](const Vector3d& axis) {
    const double p0 = axis.dot(v0), p1 = axis.dot(v1), p2 = axis.dot(v2);
    const double reach = r * axis.cwiseAbs().sum();
    return std::min({p0, p1, p2}) > reach || std::max({p0, p1, p2}) < -reach;
  };
  for (int a = 0; a < 3; ++a) {
    if (std::min({v0[a], v1[a], v2[a]}) > r || std::max({v0[a], v1[a], v2[a]}) < -r) return false;
  }
  const std::array<Vector3d, 3> edges = {v1 - v0, v2 - v1, v0 - v2};
  if (separated(edges[0].cross(edges[1]))) return false;
  for (const Vector3d& e : edges) {
    for (int a = 0; a < 3; ++a) {
      if (separated(e.cross(Vector3d::Unit(a)))) return false;
    }
  }
  return true;
}

// Generalized winding number (sum of signed solid angles / 4 pi): +-1 inside a closed surface, 0 outside.
double winding_number(const SurfaceMesh& s, const Vector3d& p) {
  double sum = 0.0;
  for (const Triangle& t : s.triangles) {
    const Vector3d a = s.vertices[t[0]] - p, b = s.vertices[t[1]] - p, c = s.vertices[t[2]] - p;
    const double la = a.norm(), lb = b.norm(), lc = c.norm();
    const double num = a.dot(b.cross(c));
    const double den = la * lb * lc + a.dot(b) * lc + b.dot(c) * la + c.dot(a) * lb;
    sum += 2.0 * std::atan2(num, den);
  }
  return sum / (4.0 * kPi);
}

// Kept cells: those a triangle touches plus untouched regions inside the solid, reduced to the
// largest face-connected component.
std::vector<char> cover_cells(const SurfaceMesh& s, const CellGrid& g) {
  std::vector<char> keep(g.num_cells(), 0);
  const double r = 0.5 * g.h * (1.0 + 2.0 * kCellSlack);
  for (const Triangle& t : s.triangles) {
    const Vector3d& a = s.vertices[t[0]];
    const Vector3d& b = s.vertices[t[1]];
    const Vector3d& c = s.vertices[t[2]];
    const auto [first, last] = g.cell_range(a.cwiseMin(b).cwiseMin(c), a.cwiseMax(b).cwiseMax(c), kCellSlack);
    for (int k = first.z(); k <= last.z(); ++k) {
      for (int j = first.y(); j <= last.y(); ++j) {
        for (int i = first.x(); i <= last.x(); ++i) {
          const Vector3i cell(i, j, k);
          const int id = g.cell_id(cell);
          if (keep[id]) continue;
          const Vector3d m = g.centre(cell);
          if (triangle_touches_cube(a - m, b - m, c - m, r)) keep[id] = 1;
        }
      }
    }
  }
  // An untouched region lies wholly inside or wholly outside, so one sample decides it; its cells'
  // centres are at least h/2 from the surface, where the winding number is well conditioned.
  std::vector<char> untouched(keep.size());
  for (std::size_t i = 0; i < keep.size(); ++i) untouched[i] = !keep[i];
  std::vector<int> label, sizes;
  const int regions = detail::label_components(g, untouched, label, sizes);
  std::vector<char> inside(regions, 0);
  std::vector<char> decided(regions, 0);
  for (int id = 0; id < g.num_cells(); ++id) {
    const int l = label[id];
    if (l < 0) continue;
    if (!decided[l]) {
      decided[l] = 1;
      inside[l] = std::abs(winding_number(s, g.centre(g.cell_coords(id)))) > 0.5 ? 1 : 0;
    }
    if (inside[l]) keep[id] = 1;
  }
  detail::keep_largest_component(g, keep);
  return keep;
}

Eigen::Vector4d barycentric(const TetMesh& mesh, const Tet& t, const Vector3d& p) {
  const Vector3d& x0 = mesh.X[t[0]];
  Eigen::Matrix3d A;
  A << mesh.X[t[1]] - x0, mesh.X[t[2]] - x0, mesh.X[t[3]] - x0;
  const Vector3d l = A.partialPivLu().solve(p - x0);
  return {1.0 - l.sum(), l[0], l[1], l[2]};
}

EmbeddedBody build_body(const SurfaceMesh& surface, const std::pair<Vector3d, Vector3d>& box, double h) {
  const CellGrid g = make_grid(box, h);
  detail::CellMesh cells = detail::mesh_cells(g, cover_cells(surface, g), kuhn_cube_tets());

  EmbeddedBody body;
  body.surface = surface;
  body.spacing = h;
  body.mesh = std::move(cells.mesh);
  std::vector<int> kept_index(g.num_cells(), -1);
  for (std::size_t i = 0; i < cells.cells.size(); ++i) kept_index[cells.cells[i]] = static_cast<int>(i);

  // A vertex on a cell face may sit in either neighbour: take the tet that contains it most deeply.
  const int nv = static_cast<int>(surface.vertices.size());
  body.surface_tet.resize(nv);
  body.surface_bary.resize(nv);
  for (int v = 0; v < nv; ++v) {
    const Vector3d& p = surface.vertices[v];
    const auto [first, last] = g.cell_range(p, p, kCellSlack);
    double best_min = -std::numeric_limits<double>::infinity();
    for (int k = first.z(); k <= last.z(); ++k) {
      for (int j = first.y(); j <= last.y(); ++j) {
        for (int i = first.x(); i <= last.x(); ++i) {
          const int kc = kept_index[g.cell_id(Vector3i(i, j, k))];
          if (kc < 0) continue;
          for (int e = 6 * kc; e < 6 * kc + 6; ++e) {
            const Eigen::Vector4d w = barycentric(body.mesh, body.mesh.tets[e], p);
            if (w.minCoeff() > best_min) {
              best_min = w.minCoeff();
              body.surface_tet[v] = e;
              body.surface_bary[v] = w;
            }
          }
        }
      }
    }
    if (!(best_min >= -kWeightTolerance)) {
      throw MeshError("surface vertex " + str(v) + " at " + str(p) +
                      " m lies outside the kept cells (surface parts more than a cell apart, or an unused vertex?)");
    }
  }
  return body;
}

int count_tets(const SurfaceMesh& surface, const std::pair<Vector3d, Vector3d>& box, double h) {
  return detail::kept_tet_count(cover_cells(surface, make_grid(box, h)));
}

void check_spacing(double spacing) {
  if (!std::isfinite(spacing) || spacing <= 0.0)
    throw std::invalid_argument("embedded surface: spacing must be finite and positive, got " + str(spacing));
}

}  // namespace

EmbeddedBody embed_surface_with_spacing(const SurfaceMesh& surface, double spacing) {
  check_spacing(spacing);
  check_surface(surface);
  return build_body(surface, bounding_box(surface), spacing);
}

EmbeddedBody embed_surface(const SurfaceMesh& surface, int target_tets) {
  if (target_tets <= 0)
    throw std::invalid_argument("embedded surface: target_tets must be positive, got " + str(target_tets));
  check_surface(surface);
  const auto box = bounding_box(surface);
  const Vector3d extent = box.second - box.first;
  const double size = extent.maxCoeff();
  if (!(size > 0.0)) throw MeshError("surface has zero extent");
  // Finest: 120 cells along the longest axis stays under kMaxCells; coarsest: one cell holds everything.
  const double h_min = size / 120.0;
  const double h_max = size * 2.0;
  // The cover's overhang makes this volume guess low; the box-anchored grid makes the count non-monotone (scan).
  const double volume = std::max(std::abs(enclosed_volume(surface)), 1e-3 * extent.prod());
  const double best_h = detail::spacing_for_tets(target_tets, volume, h_min, h_max, true,
                                                 [&](double h) { return count_tets(surface, box, h); });
  return build_body(surface, box, best_h);
}

double enclosed_volume(const SurfaceMesh& surface) {
  if (surface.vertices.empty()) return 0.0;
  // Tets against a vertex of the surface instead of the origin: no cancellation far from the origin.
  const Vector3d& o = surface.vertices.front();
  double v = 0.0;
  for (const Triangle& t : surface.triangles) {
    v += signed_volume(o, surface.vertices[t[0]], surface.vertices[t[1]], surface.vertices[t[2]]);
  }
  return v;
}

SurfaceMesh load_obj(const std::string& path) {
  TextReader r(path, true);
  SurfaceMesh s;
  std::vector<long long> triangle_line;
  std::vector<int> polygon;
  while (r.next()) {
    const std::string_view key = r[0];
    if (key == "v") {
      if (r.size() < 4) r.fail("vertex needs 3 coordinates, found " + str(r.size() - 1));
      Vector3d p;
      for (int a = 0; a < 3; ++a) p[a] = parse_real(r, r[1 + a], "coordinate");
      for (std::size_t i = 4; i < r.size(); ++i) parse_real(r, r[i], "vertex value");
      if (s.vertices.size() >= static_cast<std::size_t>(INT_MAX)) r.fail("too many vertices");
      s.vertices.push_back(p);
    } else if (key == "f") {
      if (r.size() < 4) {
        r.fail("face needs at least 3 vertices, found " + str(r.size() - 1));
      }
      polygon.clear();
      const long long defined = static_cast<long long>(s.vertices.size());
      for (std::size_t i = 1; i < r.size(); ++i) {
        const std::string_view token = r[i].substr(0, r[i].find('/'));
        const long long index = parse_int(r, token, "vertex index", -defined, INT_MAX);
        // Positive indices may point forward; they are range-checked once every vertex is known.
        if (index == 0) r.fail("vertex index '0' is out of range (OBJ indices start at 1)");
        polygon.push_back(static_cast<int>(index > 0 ? index - 1 : defined + index));
      }
      for (std::size_t i = 1; i + 1 < polygon.size(); ++i) {
        s.triangles.push_back({polygon[0], polygon[i], polygon[i + 1]});
        triangle_line.push_back(r.line());
      }
    }
  }
  if (s.triangles.empty()) r.fail("expected faces ('f' lines), found no faces");
  const int n = static_cast<int>(s.vertices.size());
  for (std::size_t t = 0; t < s.triangles.size(); ++t) {
    const Triangle& tri = s.triangles[t];
    for (int v : tri) {
      if (v >= n) {
        fail_at(path, triangle_line[t],
                "vertex index " + str(v + 1) + " is out of range: the file has " + str(n) + " vertices");
      }
    }
    if (tri[0] == tri[1] || tri[1] == tri[2] || tri[0] == tri[2])
      fail_at(path, triangle_line[t], "face repeats a vertex (degenerate triangle)");
  }
  return s;
}

void save_obj(const std::string& path, const SurfaceMesh& surface) {
  std::ofstream out = open_for_writing(path);
  out << "# " << surface.vertices.size() << " vertices, " << surface.triangles.size() << " triangles\n";
  for (const Vector3d& p : surface.vertices) {
    out << "v " << str(p.x()) << ' ' << str(p.y()) << ' ' << str(p.z()) << '\n';
  }
  for (const Triangle& t : surface.triangles) out << "f " << t[0] + 1 << ' ' << t[1] + 1 << ' ' << t[2] + 1 << '\n';
  finish_writing(out, path);
}

void save_embedding(const std::string& path, const EmbeddedBody& body) {
  const std::size_t nv = body.surface.vertices.size();
  if (body.surface_tet.size() != nv || body.surface_bary.size() != nv)
    throw MeshError(path + ":0: embedding has " + str(body.surface_tet.size()) +
                    " tets and " + str(body.surface_bary.size()) + " weight sets for " +
                    str(nv) + " surface vertices");
  std::ofstream out = open_for_writing(path);
  out << "hapticd-embedding 1\n# surface_vertices tets spacing_m\n"
      << nv << ' ' << body.mesh.num_tets() << ' ' << str(body.spacing) << "\n# tet w0 w1 w2 w3\n";
  for (std::size_t v = 0; v < nv; ++v) {
    const Eigen::Vector4d& w = body.surface_bary[v];
    out << body.surface_tet[v] << ' ' << str(w[0]) << ' ' << str(w[1]) << ' ' << str(w[2]) << ' ' << str(w[3])
        << '\n';
  }
  finish_writing(out, path);
}

EmbeddedBody load_embedding(const std::string& path, TetMesh mesh, SurfaceMesh surface) {
  TextReader r(path, true);
  if (!r.next() || r.size() != 2 || r[0] != "hapticd-embedding" || r[1] != "1")
    r.fail("expected header 'hapticd-embedding 1', found " + r.found());
  if (!r.next()) r.fail("expected '<surface vertices> <tets> <spacing>', found end of file");
  if (r.size() != 3) r.fail("expected '<surface vertices> <tets> <spacing>', found " + r.found());
  const long long nv = parse_int(r, r[0], "surface vertex count", 0, INT_MAX);
  const long long nt = parse_int(r, r[1], "tet count", 1, INT_MAX);
  const double spacing = parse_real(r, r[2], "spacing");
  if (!(spacing > 0.0)) r.fail("spacing " + quote(r[2]) + " is not positive");
  if (nv != static_cast<long long>(surface.vertices.size()))
    r.fail("file is for " + str(nv) + " surface vertices, the surface has " +
           str(surface.vertices.size()));
  if (nt != mesh.num_tets()) r.fail("file is for " + str(nt) + " tets, the mesh has " + str(mesh.num_tets()));

  Vector3d lo = Vector3d::Constant(std::numeric_limits<double>::infinity());
  Vector3d hi = -lo;
  for (const Vector3d& x : mesh.X) {
    lo = lo.cwiseMin(x);
    hi = hi.cwiseMax(x);
  }
  const double tolerance = 1e-6 * (hi - lo).norm();

  EmbeddedBody body;
  body.spacing = spacing;
  body.surface_tet.resize(nv);
  body.surface_bary.resize(nv);
  for (long long v = 0; v < nv; ++v) {
    const std::string expected = "expected '<tet> <w0> <w1> <w2> <w3>' for surface vertex " + str(v) + ", found ";
    if (!r.next()) r.fail(expected + "end of file");
    if (r.size() != 5) r.fail(expected + r.found());
    const int tet = static_cast<int>(parse_int(r, r[0], "tet", 0, nt - 1));
    Eigen::Vector4d w;
    for (int k = 0; k < 4; ++k) {
      w[k] = parse_real(r, r[1 + k], "weight");
      if (w[k] < -kWeightTolerance) r.fail("weight " + quote(r[1 + k]) + " is negative: the vertex is outside its tet");
    }
    if (std::abs(w.sum() - 1.0) > kWeightTolerance) r.fail("weights sum to " + str(w.sum()) + ", not 1");
    Vector3d x = Vector3d::Zero();
    for (int k = 0; k < 4; ++k) x += w[k] * mesh.X[mesh.tets[tet][k]];
    const Vector3d& p = surface.vertices[v];
    if ((x - p).norm() > tolerance) {
      r.fail("weights place surface vertex " + str(v) + " at " + str(x) + ", " + str((x - p).norm()) +
             " m from its position " + str(p) + " (file made for another mesh or surface?)");
    }
    body.surface_tet[v] = tet;
    body.surface_bary[v] = w;
  }
  if (r.next()) r.fail("expected end of file after " + str(nv) + " surface vertices, found " + r.found());
  body.mesh = std::move(mesh);
  body.surface = std::move(surface);
  return body;
}

EmbeddedBody load_embedded_body(const std::string& obj_path, const std::string& mesh_path,
                                const std::string& embed_path) {
  return load_embedding(embed_path, load_tet_mesh(mesh_path), load_obj(obj_path));
}

}  // namespace hapticd::hand
